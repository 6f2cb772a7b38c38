"""Parameter sweeps: many (graph x robot count) configurations of one method in ONE ``vmap``.

Every configuration (graph, robot count) of a method is built with the library's own padding
(:func:`~mmpgo_jax._partition.partition` with ``min_max_poses`` / ``min_max_edges`` /
``num_robots``, :meth:`MMProblem.build` with ``min_couplings``) to a common shape: the largest
n_max, e_max, loop-closure coupling count and robot count A of the group (padded robots own
nothing; padding never changes a result). The problems and states are stacked along a new leading
*configuration* axis and advanced by one compiled chunk ``jit(vmap(run))`` of ``chunk_size``
outer iterations, so a sweep compiles once per method (``group_by="method"``, the default).

Padding the robot axis has a price: a 5-robot configuration padded to 50 robots carries 10x the
slots of the real problem (measured on the 3600-pose Cube: about 20x the time per iteration).
``group_by="robots"`` stacks only the configurations that share a robot count (for example the
same robot count on many datasets), at one compilation per (method, robot count); the results are
the same either way.

Under ``vmap`` the ``lax.cond`` inside the AMM step (the MM fallback, computed only when some robot
restarts) becomes a ``select`` that evaluates both branches: results are unchanged, but AMM costs
more per iteration than in :func:`~mmpgo_jax.solve`. A batch of one configuration (the CPU default
of ``benchmarks/fig1.py``) is therefore run without ``vmap`` and keeps the real ``cond``.

When the stacked batch (bytes of the problem and state pytrees, times the number of
configurations) would exceed ``max_batch_bytes`` (default: a quarter of ``MemAvailable`` from
``/proc/meminfo``), the configurations are split into several batches of equal size (the last one
filled up with copies that are discarded), which reuse the same compiled executable.
``max_batch_configs`` caps the batch size directly. On a CPU a large batch is not faster per
configuration than a small one (measured, 3600-pose Cube, MM with 5 robots: 32.7 ms per
configuration and iteration with 7 configurations per batch, 16.8 ms with 1: the working set
leaves the cache); on an accelerator, larger batches fill the device.
"""

from __future__ import annotations

import csv
import math
import time
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np

from .._core.gauge import FixedPoses
from .._core.partition import Partition, partition
from .._core.pose_graph import PoseGraph, Poses
from .._init.chordal import initialize
from .._mm.majorization import build_gamma_operator, stack, unstack
from .._mm.outer import MMConfig, MMProblem, evaluate, init_state, run
from .._mm.solve import NonFiniteError, output_frame
from .._mm.subproblem import SubproblemConfig
from .metrics import absolute_trajectory_error, relative_pose_error

__all__ = ["sweep", "SweepResult", "reference_optimum", "TRACE_COUNTS", "default_max_batch_bytes"]

#: How many times the batched chunk was traced (= compiled: each trace is followed by exactly one
#: compilation), per method. Incremented at trace time only; tests read it.
TRACE_COUNTS: Counter = Counter()


def _sweep_chunk_impl(problem: MMProblem, config: MMConfig, state, length: int, limit):
    TRACE_COUNTS[config.method] += 1  # runs only while tracing
    if state.s.shape[0] == 1:
        # A batch of one runs unbatched: under vmap the AMM step's lax.cond (MM fallback only when a
        # robot restarts) would become a select that computes the fallback every iteration.
        squeeze = lambda tree: jax.tree.map(lambda x: x[0], tree)
        out = run(squeeze(problem), config, squeeze(state), length, limit)
        return jax.tree.map(lambda x: x[None], out)
    return jax.vmap(lambda p, s: run(p, config, s, length, limit))(problem, state)


_sweep_chunk_impl.__name__ = "sweep_chunk"
_sweep_chunk_impl.__qualname__ = "sweep_chunk"
#: ``jit(vmap(run))`` over the leading configuration axis (name in compile logs: ``sweep_chunk``).
sweep_chunk = jax.jit(_sweep_chunk_impl, static_argnames=("length",))


@partial(jax.jit)
def _batched_start(problem: MMProblem, config: MMConfig, X0):
    def one(p, x):
        st = init_state(p, unstack(x), config)
        return st, evaluate(p, st)

    return jax.vmap(one)(problem, X0)


def default_max_batch_bytes(fraction: float = 0.25) -> int:
    """``fraction`` of MemAvailable (``/proc/meminfo``); 4 GiB where that file is missing."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(fraction * int(line.split()[1]) * 1024)
    except OSError:
        pass
    return int(fraction * (16 << 30))


def reference_optimum(graph: PoseGraph, *, grad_tol: float = 1e-5, max_iterations: int = 500) -> float:
    """f* for relative gaps: :func:`~mmpgo_jax.centralized_optimum` with a reachable tolerance.

    The library default ``grad_tol=1e-6`` lies below the float64 noise floor of ||grad F|| on large
    problems (3600-pose Cube: f ~ 1.5e4, ||grad F|| stalls at 3e-6 after ~50 iterations while f
    no longer changes in the 16th digit), which turns it into a 5000-iteration run.
    """
    from .._mm.solve import centralized_optimum

    return float(centralized_optimum(graph, grad_tol=grad_tol, max_iterations=max_iterations).f)


def _tree_bytes(tree) -> int:
    """Bytes of the array leaves of a pytree (arrays or ShapeDtypeStructs)."""
    return int(sum(math.prod(x.shape) * np.dtype(x.dtype).itemsize for x in jax.tree.leaves(tree)))


def _stack(trees):
    return jax.tree.map(lambda *xs: jnp.stack(xs), *trees)


# ----------------------------------------------------------------------------------------------
# result
# ----------------------------------------------------------------------------------------------

_HISTORY_COLUMNS = ("graph", "robots", "method", "iteration", "f", "gap", "relative_gap")


@dataclass
class SweepResult:
    """Tidy results of a sweep.

    ``rows``: one dict per (graph, robots, method, iteration) with f = 2F and, when f* is known,
    ``gap`` = f - f* and ``relative_gap`` = (f - f*)/f* (else None). ``configs``: one dict per
    configuration (final f and gap, ``bytes`` of its problem + state pytrees as run (padded),
    ``seconds`` (its share of the batch's run time, compilation excluded), batch index, and, with a
    ground truth, ``ate`` / ``rpe_translation`` / ``rpe_rotation_deg``). ``groups``: one dict per
    compiled group (shape, compile seconds, batches).
    """

    histories: dict[tuple[str, int, str], np.ndarray]  # (graph, robots, method) -> f (K+1,)
    fstar: dict[str, float | None]
    configs: list[dict]
    groups: list[dict]
    poses: dict[tuple[str, int, str], Poses] = field(repr=False, default_factory=dict)
    iterations: int = 0

    def history(self, graph: str, robots: int, method: str) -> np.ndarray:
        return self.histories[(graph, int(robots), method)]

    def relative_gap(self, graph: str, robots: int, method: str) -> np.ndarray:
        fs = self.fstar.get(graph)
        if fs is None:
            raise ValueError(f"no f* for graph {graph!r}")
        return (self.history(graph, robots, method) - fs) / fs

    @property
    def graphs(self) -> list[str]:
        return list(dict.fromkeys(k[0] for k in self.histories))

    @property
    def robots(self) -> list[int]:
        return sorted({k[1] for k in self.histories})

    @property
    def methods(self) -> list[str]:
        return list(dict.fromkeys(k[2] for k in self.histories))

    @property
    def rows(self) -> list[dict]:
        out = []
        for (g, a, m), f in self.histories.items():
            fs = self.fstar.get(g)
            for k, v in enumerate(f):
                v = float(v)
                gap = None if fs is None else v - fs
                out.append(dict(graph=g, robots=a, method=m, iteration=k, f=v, gap=gap,
                                relative_gap=None if fs is None else gap / fs))
        return out

    def to_csv(self, path) -> None:
        """The per-iteration table (columns: graph, robots, method, iteration, f, gap, relative_gap)."""
        _write_csv(path, _HISTORY_COLUMNS, self.rows)

    def configs_to_csv(self, path) -> None:
        """The per-configuration table."""
        cols = list(dict.fromkeys(k for row in self.configs for k in row))
        _write_csv(path, cols, self.configs)

    def stack(self, method: str, robots: int, graphs: Sequence[str] | None = None, relative: bool = True):
        """(graphs, K+1) array of relative gaps (or f when ``relative=False``) for one (method, robots)."""
        graphs = self.graphs if graphs is None else list(graphs)
        if relative:
            return np.stack([self.relative_gap(g, robots, method) for g in graphs])
        return np.stack([self.history(g, robots, method) for g in graphs])


def _write_csv(path, columns, rows) -> None:
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=list(columns), extrasaction="ignore")
        w.writeheader()
        for row in rows:
            w.writerow({k: ("" if row.get(k) is None else row.get(k)) for k in columns})


# ----------------------------------------------------------------------------------------------
# inputs
# ----------------------------------------------------------------------------------------------


def _normalize_graphs(graphs) -> tuple[list[str], list[PoseGraph], dict[str, Poses], dict[str, FixedPoses | None]]:
    """-> names, graphs, ground truths and fixed poses found on dataset-like inputs."""
    if isinstance(graphs, Mapping):
        items = list(graphs.items())
    else:
        if isinstance(graphs, PoseGraph) or hasattr(graphs, "graph"):
            graphs = [graphs]
        items = []
        for k, g in enumerate(graphs):
            items.append((getattr(g, "name", None) or f"graph{k}", g))
    names, out, gts, fixed = [], [], {}, {}
    for name, g in items:
        name = str(name)
        if name in names:
            raise ValueError(f"duplicate graph name {name!r}")
        fixed[name] = None
        if hasattr(g, "graph") and isinstance(g.graph, PoseGraph):
            if getattr(g, "ground_truth", None) is not None:
                gts[name] = g.ground_truth
            fixed[name] = getattr(g, "fixed_poses", None)
            g = g.graph
        if not isinstance(g, PoseGraph):
            raise TypeError(f"graph {name!r}: expected a PoseGraph (or a dataset with .graph), got {type(g).__name__}")
        names.append(name)
        out.append(g)
    if not out:
        raise ValueError("no graphs given")
    dims = {g.dim for g in out}
    if len(dims) > 1:
        raise ValueError(f"all graphs of a sweep must have the same dimension d, got {sorted(dims)}")
    return names, out, gts, fixed


def _per_graph(value, names, what):
    """None | scalar (one graph) | mapping name -> v | sequence aligned with the graphs."""
    if value is None:
        return {n: None for n in names}
    if isinstance(value, Mapping):
        unknown = set(map(str, value)) - set(names)
        if unknown:
            raise ValueError(f"{what} given for unknown graphs {sorted(unknown)}")
        return {n: value.get(n) for n in names}
    if isinstance(value, (Sequence, np.ndarray)) and not isinstance(value, (str, Poses)):
        if len(value) != len(names):
            raise ValueError(f"{what}: expected {len(names)} values, got {len(value)}")
        return dict(zip(names, value))
    if len(names) == 1:
        return {names[0]: value}
    raise ValueError(f"{what}: give a mapping graph name -> value for several graphs")


# ----------------------------------------------------------------------------------------------
# the sweep
# ----------------------------------------------------------------------------------------------


@dataclass
class _Config:
    index: int
    name: str
    graph: PoseGraph
    robots: int
    method: str
    n_max: int = 0
    e_max: int = 0
    couplings: int = 0


def sweep(
    graphs,
    robots: Sequence[int] | int = (5, 10, 50),
    methods: Sequence[str] | str = ("mm", "amm"),
    iterations: int = 1000,
    *,
    init="chordal",
    xi: float = 1e-3,
    restart: Literal["paper", "adaptive", "average"] = "adaptive",
    fstar: Mapping[str, float] | Sequence[float] | float | str | None = None,
    max_batch_bytes: int | None = None,
    max_batch_configs: int | None = None,
    ground_truth: Mapping[str, Poses] | Sequence[Poses] | Poses | None = None,
    subproblem: SubproblemConfig | None = None,
    chunk_size: int = 50,
    group_by: Literal["method", "robots"] = "method",
    progress=None,
    fixed: Mapping[str, FixedPoses] | Sequence[FixedPoses] | FixedPoses | None = None,
) -> SweepResult:
    """Run every (graph, robot count) configuration of each method as one batched computation.

    ``graphs``: a PoseGraph, a dataset with ``.graph`` (and ``.ground_truth``, used for ATE/RPE
    unless ``ground_truth`` is given), or a sequence / name-keyed mapping of them (same d; n may
    differ). ``robots``: robot counts (contiguous blocks, as :func:`~mmpgo_jax.solve`).
    ``init``: the start (any :func:`~mmpgo_jax.initialize` method; "chordal" is computed once per
    graph). ``fstar``: per-graph optimum (mapping or sequence), or ``"centralized"`` to compute it
    with :func:`reference_optimum`; relative gaps need it. ``max_batch_bytes``: see the module
    docstring; ``max_batch_configs`` caps the configurations per batch as well (on a CPU, small
    batches are faster: cache-sized working sets). ``group_by``: "method" (one compilation per method, robot axis padded to the largest
    count) or "robots" (one per (method, robot count)). ``progress(message)`` is called with a
    line of text after each batch.

    ``fixed``: per-graph :class:`~mmpgo_jax.FixedPoses` held by the start and every iteration
    (default: a dataset's own ``fixed_poses``, e.g. a :class:`~mmpgo_jax.G2OFile`'s FIX lines).
    Final poses are in the frame :func:`~mmpgo_jax.solve` reports by default.

    Equivalent, configuration by configuration, to ``solve(graph, robots, method=..., iterations,
    init, xi, restart, subproblem, fixed)``.
    """
    if iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {iterations}")
    if group_by not in ("method", "robots"):
        raise ValueError(f"group_by must be 'method' or 'robots', got {group_by!r}")
    names, glist, gts, fixed_of = _normalize_graphs(graphs)
    if fixed is not None:
        fixed_of = _per_graph(fixed, names, "fixed")
    for name, g in zip(names, glist):
        if fixed_of.get(name) is not None:
            fixed_of[name].check(g.num_poses, g.dim)
    any_fixed = any(v is not None for v in fixed_of.values())
    d = glist[0].dim
    robots = [int(robots)] if np.ndim(robots) == 0 else list(dict.fromkeys(int(a) for a in robots))
    methods = [methods] if isinstance(methods, str) else list(dict.fromkeys(methods))
    for m in methods:
        if m not in ("mm", "amm"):
            raise ValueError(f"unknown method {m!r}: use 'mm' or 'amm'")
    for name, g in zip(names, glist):
        for a in robots:
            if not 1 <= a <= g.num_poses:
                raise ValueError(f"graph {name!r} has {g.num_poses} poses: cannot split among {a} robots")
    if ground_truth is not None:
        gts = {k: v for k, v in _per_graph(ground_truth, names, "ground_truth").items() if v is not None}
    if isinstance(fstar, str):
        if fstar != "centralized":
            raise ValueError(f"fstar must be a mapping, a sequence, a number, None or 'centralized', got {fstar!r}")
        fstars = {n: reference_optimum(g) for n, g in zip(names, glist)}
    else:
        fstars = {n: (None if v is None else float(v)) for n, v in _per_graph(fstar, names, "fstar").items()}
    if max_batch_bytes is None:
        max_batch_bytes = default_max_batch_bytes()
    sub = subproblem or SubproblemConfig()
    say = progress or (lambda msg: None)

    # Shape needs of every (graph, robots): n_max, e_max and couplings of the unpadded layout.
    needs: dict[tuple[int, int], tuple[int, int, int]] = {}
    for gi, g in enumerate(glist):
        for a in robots:
            p = partition(g, a)
            k = int(build_gamma_operator(p.edges, xi, p.max_poses).src.shape[-1])
            needs[(gi, a)] = (p.max_poses, p.max_edges, k)

    starts: dict[int, Poses] = {}

    def start_of(gi: int, a: int) -> Poses:
        fix = fixed_of[names[gi]]
        if isinstance(init, str) and init == "distributed-chordal":
            return initialize(glist[gi], init, robots=a, fixed=fix)
        if gi not in starts:
            starts[gi] = initialize(glist[gi], init, fixed=fix)
        return starts[gi]

    histories: dict[tuple[str, int, str], np.ndarray] = {}
    final_poses: dict[tuple[str, int, str], Poses] = {}
    config_rows: list[dict] = []
    group_rows: list[dict] = []

    for method in methods:
        config = MMConfig(method=method, restart=restart, xi=xi, subproblem=sub)
        keys = [(gi, a) for a in robots for gi in range(len(glist))]
        groups = [keys] if group_by == "method" else [[k for k in keys if k[1] == a] for a in robots]
        for gkeys in groups:
            n_max = max(needs[k][0] for k in gkeys)
            e_max = max(needs[k][1] for k in gkeys)
            kc = max(needs[k][2] for k in gkeys)
            A = max(k[1] for k in gkeys)

            def build(gi: int, a: int):
                g = glist[gi]
                part = partition(g, a, min_max_poses=n_max, min_max_edges=e_max, num_robots=A)
                fix = fixed_of[names[gi]]
                if fix is None and any_fixed:  # one pytree structure per batch: an all-free mask
                    fix = np.zeros(g.num_poses, dtype=bool)
                problem = MMProblem.build(part, xi, min_couplings=kc, fixed=fix)
                return part, problem

            def batchable(problem: MMProblem, n_common: int) -> MMProblem:
                # robot_of_pose / slot_of_pose (n,) and the static num_poses differ between graphs;
                # run() never reads them, so the stacked copy carries common-shaped placeholders.
                p = problem.partition
                pad = n_common - p.num_poses
                common = Partition(
                    pose_index=p.pose_index,
                    pose_mask=p.pose_mask,
                    edges=p.edges,
                    robot_of_pose=jnp.pad(p.robot_of_pose, (0, pad)),
                    slot_of_pose=jnp.pad(p.slot_of_pose, (0, pad)),
                    num_poses=n_common,
                )
                return MMProblem(common, problem.gamma, problem.chain, problem.block_jacobi,
                                 problem.gamma_soa, problem.block_jacobi_soa, problem.free, problem.xi)

            n_common = max(glist[k[0]].num_poses for k in gkeys)
            # bytes of one configuration (all have the same padded shape)
            t_build = time.perf_counter()
            built = {gkeys[0]: build(*gkeys[0])}  # reused by the first batch
            prob0 = batchable(built[gkeys[0]][1], n_common)
            st_shape = jax.eval_shape(lambda p, x: init_state(p, unstack(x), config), prob0,
                                      jax.ShapeDtypeStruct((A, n_max, d, d + 1), prob0.gamma.diag.dtype))
            per_config = _tree_bytes(prob0) + _tree_bytes(st_shape)
            del prob0
            C = len(gkeys)
            per_batch = max(1, min(C, int(max_batch_bytes // max(per_config, 1)), max_batch_configs or C))
            num_batches = math.ceil(C / per_batch)
            per_batch = math.ceil(C / num_batches)
            group = dict(method=method, robots=sorted({k[1] for k in gkeys}), configs=C, A=A, n_max=n_max,
                         e_max=e_max, couplings=kc, bytes_per_config=per_config, batches=num_batches,
                         configs_per_batch=per_batch, compile_seconds=0.0, run_seconds=0.0,
                         setup_seconds=0.0,
                         padding_factor=float(A * n_max * C / sum(glist[gi].num_poses for gi, _ in gkeys)))
            compiled = None
            length = max(1, min(chunk_size, iterations)) if iterations > 0 else 0
            limit = jnp.asarray(iterations)
            setup = time.perf_counter() - t_build
            for b in range(num_batches):
                t0 = time.perf_counter()
                bkeys = gkeys[b * per_batch:(b + 1) * per_batch]
                real = len(bkeys)
                bkeys = bkeys + [bkeys[-1]] * (per_batch - real)  # same compiled shape
                parts, probs, X0s = [], [], []
                for (gi, a) in bkeys[:real]:
                    part, prob = built.pop((gi, a), None) or build(gi, a)
                    parts.append(part)
                    probs.append(batchable(prob, n_common))
                    X0s.append(stack(part.scatter(start_of(gi, a))))
                probs += [probs[-1]] * (per_batch - real)
                X0s += [X0s[-1]] * (per_batch - real)
                problem = _stack(probs)
                del probs
                state, rec0 = _batched_start(problem, config, jnp.stack(X0s))
                fs = [np.asarray(rec0.f)[:, None]]
                setup += time.perf_counter() - t0
                run_s = 0.0
                if iterations > 0:
                    if compiled is None:
                        t, traces = time.perf_counter(), TRACE_COUNTS[method]
                        compiled = sweep_chunk.lower(problem, config, state, length, limit).compile()
                        group["compile_seconds"] = time.perf_counter() - t
                        group["traces"] = TRACE_COUNTS[method] - traces  # 1 (0: jax's trace cache hit)
                    done = 0
                    t = time.perf_counter()
                    while done < iterations:
                        state, rec = compiled(problem, config, state, limit)
                        take = min(length, iterations - done)
                        fs.append(np.asarray(rec.f)[:, :take])
                        done += take
                    jax.block_until_ready(state)
                    run_s = time.perf_counter() - t
                f_all = np.concatenate(fs, axis=1)
                X_final = np.asarray(state.X)
                del problem, state
                for c, (gi, a) in enumerate(bkeys[:real]):
                    name = names[gi]
                    key = (name, a, method)
                    f = f_all[c]
                    if not np.isfinite(f).all():
                        raise NonFiniteError(f"sweep: f became non-finite for graph {name!r}, {a} robots, {method} "
                                             f"(after iteration {int(np.flatnonzero(~np.isfinite(f))[0])})")
                    histories[key] = f
                    Xc = unstack(jnp.asarray(X_final[c]))
                    poses = output_frame(parts[c].gather(Xc), fixed_of[name], None)
                    final_poses[key] = poses
                    fs_ = fstars.get(name)
                    row = dict(graph=name, robots=a, method=method, iterations=iterations,
                               f_start=float(f[0]), f=float(f[-1]),
                               gap=None if fs_ is None else float(f[-1] - fs_),
                               relative_gap=None if fs_ is None else float((f[-1] - fs_) / fs_),
                               fstar=fs_, bytes=per_config, seconds=run_s / real,
                               ms_per_iteration=1e3 * run_s / real / max(iterations, 1), batch=b,
                               batch_size=real)
                    if name in gts:
                        row["ate"] = absolute_trajectory_error(poses, gts[name])
                        rpe = relative_pose_error(poses, gts[name])
                        row["rpe_translation"] = rpe.translation
                        row["rpe_rotation_deg"] = rpe.rotation_deg
                    config_rows.append(row)
                group["run_seconds"] += run_s
                say(f"{method} robots={group['robots']} batch {b + 1}/{num_batches}: {real} configs, "
                    f"{run_s:.1f} s run, {group['compile_seconds']:.1f} s compile")
            group["setup_seconds"] = setup
            group_rows.append(group)

    # order histories as graph-major, then robots, then method
    order = {(n, a, m): (names.index(n), robots.index(a), methods.index(m)) for (n, a, m) in histories}
    histories = dict(sorted(histories.items(), key=lambda kv: order[kv[0]]))
    config_rows.sort(key=lambda r: order[(r["graph"], r["robots"], r["method"])])
    return SweepResult(histories=histories, fstar=fstars, configs=config_rows, groups=group_rows,
                       poses=final_poses, iterations=iterations)
