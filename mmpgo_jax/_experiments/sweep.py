"""Parameter sweeps: many (graph x robot count) configurations of one method in ONE ``vmap``.

Every configuration (graph, robot count) of a method is built with the library's own padding
(:func:`~mmpgo_jax._partition.partition` with ``min_max_poses`` / ``min_max_edges`` /
``num_robots``, :meth:`MMProblem.build` with ``min_couplings``) to a common shape: the largest
n_max, e_max, loop-closure coupling count and robot count A of the group (padded robots own
nothing; padding never changes a result). The problems and states are stacked along a new leading
*configuration* axis and advanced by one compiled chunk ``jit(vmap(run))`` of ``chunk_size``
outer iterations, so a sweep compiles once per method (``group_by="method"``, the default).

A sequence of proximal terms (``xi=[1e-3, 1e-2, ...]``) adds an axis: every (graph, robot count,
xi) is one configuration. xi lives in the problems' arrays (Gamma^alpha and its preconditioner
contain it; ``MMProblem.xi`` is an ordinary leaf), so the configurations with different xi stack
and share the method's one compilation as well.

A sequence of robust losses (``loss=["huber", "cauchy", "tls"]``, kernel names or
:class:`~mmpgo_jax.RobustLoss` values, or a mapping label -> loss) adds another axis: the kernel is
an integer code, a traced leaf of the problem like its scale and GNC options, so every kernel runs
in the method's one compilation. With robust losses every configuration runs the weighted program
(``"l2"`` among them as ``RobustLoss("l2")``: least squares through the weighted machinery, equal to
the plain program to rounding), and the results hold each configuration's final edge weights and
inlier mask, as :func:`~mmpgo_jax.solve`'s. Graphs with different numbers of edges (one graph at
several outlier rates, :func:`~mmpgo_jax._experiments.outliers.add_outliers`) are padded to the
group's common shape like graphs of different sizes; a
:class:`~mmpgo_jax._experiments.outliers.CorruptedGraph` given as a graph brings its true outlier
mask and rate, and the configurations then report ``outlier_rate``, ``precision`` and ``recall``.

Every partition and Gamma^alpha is built once: the unpadded partition of each (graph, robot count)
gives the group's common shape and is then padded to it (no second partitioning), and Gamma^alpha
of each configuration is built once, on the padded partition. Sweeps never stop early, so the
per-chunk records stay on the device and f is fetched once per batch.

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
from .._core.partition import SPLITS, Partition, RobotEdges, partition, split_robots
from .._core.pose_graph import PoseGraph, Poses
from .._core.resources import available_memory_bytes
from .._init.start import initialize
from .._io.atomic import atomic_write
from .._mm.driver import NonFiniteError, Termination, compile_once, drive
from .._mm.majorization import gamma_couplings, stack, unstack
from .._mm.outer import MMConfig, MMProblem, evaluate, init_state, run
from .._mm.preconditioner import aggregate_size
from .._mm.robust import GNC_LOSSES, GNCConfig, RobustLoss, as_loss, loss_code, robust_outcome
from .._mm.solve import output_frame, start_for
from .._mm.subproblem import SubproblemConfig
from .._core.metrics import absolute_trajectory_error, relative_pose_error
from .outliers import outlier_scores

__all__ = ["TRACE_COUNTS", "SweepResult", "default_max_batch_bytes", "reference_optimum", "sweep"]

#: How many times the batched chunk was traced (= compiled: each trace is followed by exactly one
#: compilation), per method. Incremented at trace time only; tests read it.
TRACE_COUNTS: Counter = Counter()


def _sweep_chunk_impl(problem: MMProblem, config: MMConfig, state, length: int, limit):
    TRACE_COUNTS[config.method] += 1  # runs only while tracing
    if state.s.shape[0] == 1:
        # A batch of one runs unbatched: under vmap the AMM step's lax.cond (MM fallback only when a
        # robot restarts) would become a select that computes the fallback every iteration.
        def squeeze(tree):
            return jax.tree.map(lambda x: x[0], tree)
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
    return int(fraction * available_memory_bytes())


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
    return int(sum(math.prod(np.shape(x)) * np.dtype(getattr(x, "dtype", None) or np.asarray(x).dtype).itemsize
                   for x in jax.tree.leaves(tree)))  # (Python scalars: a RobustLoss's numbers)


def _stack(trees):
    return jax.tree.map(lambda *xs: jnp.stack(xs), *trees)


# ----------------------------------------------------------------------------------------------
# result
# ----------------------------------------------------------------------------------------------

_HISTORY_COLUMNS = ("graph", "robots", "method", "iteration", "f", "gap", "relative_gap")
_AXES = ("xi", "loss")  # optional key components after (graph, robots, method), in this order


@dataclass
class SweepResult:
    """Tidy results of a sweep.

    ``rows``: one dict per (graph, robots, method, iteration) with f = 2F (2F_rho for a robust
    loss) and, when f* is known, ``gap`` = f - f* and ``relative_gap`` = (f - f*)/f* (else None).
    A sweep over several xi (``xi=[...]``) keys everything by (graph, robots, method, xi) instead
    and adds an ``xi`` column to ``rows`` and ``configs`` (and to the CSV files); a sweep over
    several losses appends the loss label the same way: (graph, robots, method[, xi], loss).
    ``axes`` names the optional components the keys have (``()``, ``("xi",)``, ``("loss",)`` or
    ``("xi", "loss")``); with one xi and one loss, keys and columns are (graph, robots, method).
    ``configs``: one dict per configuration (final f and gap, ``bytes`` of its problem + state
    pytrees as run (padded), ``seconds`` and ``ms_per_iteration`` (its share of the batch's run time,
    compilation excluded), ``batch_ms_per_iteration`` (the whole batch's, ``batch_size`` configurations), the
    batch index, and, with a ground truth, ``ate`` / ``rpe_translation`` / ``rpe_rotation_deg``;
    with a robust loss ``loss``, ``rejected`` (edges outside the inlier mask), ``weight_updates``,
    ``gnc_stages``, and for a graph with a known outlier mask ``outlier_rate``, ``precision`` and
    ``recall`` (:func:`~mmpgo_jax._experiments.outliers.outlier_scores`)). ``groups``: one dict per
    compiled group (shape, compile seconds, batches). ``weights`` / ``inliers``: per key, the final
    (m,) edge weights and inlier mask in the graph's edge order (robust losses only, as
    :class:`~mmpgo_jax.SolveResult`'s).
    """

    histories: dict[tuple, np.ndarray]  # (graph, robots, method[, xi][, loss]) -> f (K+1,)
    fstar: dict[str, float | None]
    configs: list[dict]
    groups: list[dict]
    poses: dict[tuple, Poses] = field(repr=False, default_factory=dict)
    iterations: int = 0
    xi_values: list[float] = field(default_factory=list)  # the sweep's xi, in the given order
    axes: tuple[str, ...] | None = None  # optional key components; None: inferred (xi when keys have 4)
    loss_values: dict[str, object] = field(default_factory=dict)  # label -> RobustLoss (None: least squares)
    weights: dict[tuple, np.ndarray] = field(repr=False, default_factory=dict)
    inliers: dict[tuple, np.ndarray] = field(repr=False, default_factory=dict)

    def __post_init__(self):
        if self.axes is None:
            self.axes = ("xi",) if any(len(k) == 4 for k in self.histories) else ()
        self.axes = tuple(self.axes)

    @property
    def keyed_by_xi(self) -> bool:
        """True when several xi were swept: keys are (graph, robots, method, xi[, loss])."""
        return "xi" in self.axes

    @property
    def keyed_by_loss(self) -> bool:
        """True when several losses were swept: keys end with the loss label."""
        return "loss" in self.axes

    def key(self, graph: str, robots: int, method: str, xi: float | None = None, loss: str | None = None) -> tuple:
        """The key of one configuration in ``histories`` / ``poses`` / ``weights`` / ``inliers``
        (``xi`` / ``loss`` needed when several were swept)."""
        key = [graph, int(robots), method]
        if not self.keyed_by_xi:
            if xi is not None and self.xi_values and float(xi) != self.xi_values[0]:
                raise KeyError(f"this sweep ran xi = {self.xi_values[0]:g} only, not {xi!r}")
        elif xi is None:
            raise ValueError(f"this sweep ran several xi {self.xi_values}: give xi=")
        else:
            key.append(float(xi))
        labels = list(self.loss_values)
        if not self.keyed_by_loss:
            if loss is not None and labels and loss != labels[0]:
                raise KeyError(f"this sweep ran loss {labels[0]!r} only, not {loss!r}")
        elif loss is None:
            raise ValueError(f"this sweep ran several losses {labels}: give loss=")
        else:
            key.append(str(loss))
        return tuple(key)

    @property
    def xis(self) -> list[float]:
        return list(self.xi_values)

    @property
    def losses(self) -> list[str]:
        """The loss labels, in the given order."""
        return list(self.loss_values)

    def history(self, graph: str, robots: int, method: str, xi: float | None = None,
                loss: str | None = None) -> np.ndarray:
        return self.histories[self.key(graph, robots, method, xi, loss)]

    def relative_gap(self, graph: str, robots: int, method: str, xi: float | None = None,
                     loss: str | None = None) -> np.ndarray:
        fs = self.fstar.get(graph)
        if fs is None:
            raise ValueError(f"no f* for graph {graph!r}")
        return (self.history(graph, robots, method, xi, loss) - fs) / fs

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
        for key, f in self.histories.items():
            g, a, m = key[:3]
            extra = dict(zip(self.axes, key[3:], strict=True))
            fs = self.fstar.get(g)
            for k, v in enumerate(f):
                v = float(v)
                gap = None if fs is None else v - fs
                out.append(dict(graph=g, robots=a, method=m, **extra, iteration=k, f=v, gap=gap,
                                relative_gap=None if fs is None else gap / fs))
        return out

    def to_csv(self, path) -> None:
        """The per-iteration table (columns: graph, robots, method[, xi][, loss], iteration, f, gap, relative_gap)."""
        cols = (*_HISTORY_COLUMNS[:3], *self.axes, *_HISTORY_COLUMNS[3:])
        _write_csv(path, cols, self.rows)

    def configs_to_csv(self, path) -> None:
        """The per-configuration table."""
        cols = list(dict.fromkeys(k for row in self.configs for k in row))
        _write_csv(path, cols, self.configs)

    def stack(self, method: str, robots: int, graphs: Sequence[str] | None = None, relative: bool = True,
              xi: float | None = None, loss: str | None = None):
        """(graphs, K+1) array of relative gaps (or f when ``relative=False``) for one
        (method, robots[, xi][, loss])."""
        graphs = self.graphs if graphs is None else list(graphs)
        if relative:
            return np.stack([self.relative_gap(g, robots, method, xi, loss) for g in graphs])
        return np.stack([self.history(g, robots, method, xi, loss) for g in graphs])


def _write_csv(path, columns, rows) -> None:
    with atomic_write(path, newline="") as fh:  # all or nothing
        w = csv.DictWriter(fh, fieldnames=list(columns), extrasaction="ignore")
        w.writeheader()
        for row in rows:
            w.writerow({k: ("" if row.get(k) is None else row.get(k)) for k in columns})


# ----------------------------------------------------------------------------------------------
# inputs
# ----------------------------------------------------------------------------------------------


def _normalize_graphs(graphs) -> tuple[list[str], list[PoseGraph], dict[str, Poses], dict[str, FixedPoses | None],
                                       dict[str, tuple[np.ndarray, float | None]]]:
    """-> names, graphs, ground truths, fixed poses and (true outlier mask, rate) found on
    dataset-like inputs (a CorruptedGraph's ``outlier`` / ``rate``)."""
    if isinstance(graphs, Mapping):
        items = list(graphs.items())
    else:
        if isinstance(graphs, PoseGraph) or hasattr(graphs, "graph"):
            graphs = [graphs]
        items = []
        for k, g in enumerate(graphs):
            items.append((getattr(g, "name", None) or f"graph{k}", g))
    names, out, gts, fixed, corrupt = [], [], {}, {}, {}
    for name, g in items:
        name = str(name)
        if name in names:
            raise ValueError(f"duplicate graph name {name!r}")
        fixed[name] = None
        if hasattr(g, "graph") and isinstance(g.graph, PoseGraph):
            if getattr(g, "ground_truth", None) is not None:
                gts[name] = g.ground_truth
            fixed[name] = getattr(g, "fixed_poses", None)
            if getattr(g, "outlier", None) is not None:
                mask = np.asarray(g.outlier, bool)
                if mask.shape != (g.graph.num_edges,):
                    raise ValueError(f"graph {name!r}: outlier mask of shape {mask.shape}, expected "
                                     f"({g.graph.num_edges},)")
                rate = getattr(g, "rate", None)
                corrupt[name] = (mask, None if rate is None else float(rate))
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
    return names, out, gts, fixed, corrupt


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
        return dict(zip(names, value, strict=False))
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
    init=None,
    xi: float | Sequence[float] = 1e-3,
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
    split="blocks",
    seed: int = 0,
    loss=None,
    loss_scale: float | None = None,
    gnc: GNCConfig | None = None,
) -> SweepResult:
    """Run every (graph, robot count) configuration of each method as one batched computation.

    ``graphs``: a PoseGraph, a dataset with ``.graph`` (and ``.ground_truth``, used for ATE/RPE
    unless ``ground_truth`` is given), or a sequence / name-keyed mapping of them (same d; n may
    differ). ``robots``: robot counts (contiguous blocks, as :func:`~mmpgo_jax.solve`).
    ``init``: the start (any :func:`~mmpgo_jax.initialize` method; by default, as in
    :func:`~mmpgo_jax.solve`, "chordal" for least squares and "gnc-chordal" at the loss's scale for a
    robust kernel; each start is computed once per graph). ``fstar``: per-graph optimum (mapping or
    sequence), or ``"centralized"`` to compute it with :func:`reference_optimum`; relative gaps need it.
    ``max_batch_bytes``: see the module docstring; ``max_batch_configs`` caps the configurations per
    batch as well (on a CPU, small batches are faster: cache-sized working sets). ``group_by``: "method"
    (one compilation per method, robot axis padded to the largest count) or "robots" (one per (method,
    robot count)). ``progress(message)`` is called with a line of text after each batch.

    ``fixed``: per-graph :class:`~mmpgo_jax.FixedPoses` held by the start and every iteration
    (default: a dataset's own ``fixed_poses``, e.g. a :class:`~mmpgo_jax.G2OFile`'s FIX lines).
    Final poses are in the frame :func:`~mmpgo_jax.solve` reports by default.

    ``xi``: the proximal term, or a sequence of them: each value is one more configuration per
    (graph, robot count), run in the same compilation; results are then keyed by (graph, robots,
    method, xi) and ``rows`` / ``configs`` get an ``xi`` column (see :class:`SweepResult`). A
    single value (a number, or a one-element sequence) keeps the (graph, robots, method) keys.

    ``split``: how each graph is split among its robot counts: ``"blocks"`` (default, the paper's
    contiguous blocks), ``"metis"`` or ``"random"`` (see :func:`~mmpgo_jax.split_robots`,
    ``seed``), or an (n,) robot-of-pose array (robots read from the data); one value for every
    graph, or a mapping graph name -> value / a sequence aligned with the graphs. A graph with an
    array runs with its own robot count only. To compare splits of one graph in one sweep, pass
    it under several names (``{"M3500 blocks": g, "M3500 metis": g}``) with a split per name: the
    configurations then share the compilations.

    ``loss``: the robust kernel (a name of :data:`~mmpgo_jax._mm.robust.LOSSES` or a
    :class:`~mmpgo_jax.RobustLoss`; default least squares), or a sequence of them (labels: the
    kernel names) or a mapping label -> loss: each is one more configuration per (graph, robot
    count[, xi]), run in the same compilation; results are then keyed by (graph, robots, method[,
    xi], loss label) and get a ``loss`` column. ``loss_scale`` and ``gnc`` apply to the losses given
    by name as :func:`~mmpgo_jax.solve`'s do (``gnc`` to the kernels that take one: tls,
    geman-mcclure). Robust configurations report their final ``weights`` and ``inliers``.

    Equivalent, configuration by configuration, to ``solve(graph, robots, method=..., iterations,
    init, xi, restart, subproblem, fixed, loss, loss_scale, gnc, stop_when_stalled=False)`` (for
    ``"l2"`` swept among robust losses: ``loss=RobustLoss("l2", loss_scale)``): a batch runs every
    iteration, since one configuration cannot stop alone.
    """
    if iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {iterations}")
    if group_by not in ("method", "robots"):
        raise ValueError(f"group_by must be 'method' or 'robots', got {group_by!r}")
    names, glist, gts, fixed_of, corrupt = _normalize_graphs(graphs)
    loss_of = _loss_values(loss, loss_scale, gnc)
    labels = list(loss_of)
    robust = any(v is not None for v in loss_of.values())
    by_loss = len(labels) > 1
    if fixed is not None:
        fixed_of = _per_graph(fixed, names, "fixed")
    for name, g in zip(names, glist, strict=False):
        if fixed_of.get(name) is not None:
            fixed_of[name].check(g.num_poses, g.dim)
    any_fixed = any(v is not None for v in fixed_of.values())
    d = glist[0].dim
    robots = [int(robots)] if np.ndim(robots) == 0 else list(dict.fromkeys(int(a) for a in robots))
    methods = [methods] if isinstance(methods, str) else list(dict.fromkeys(methods))
    for m in methods:
        if m not in ("mm", "amm"):
            raise ValueError(f"unknown method {m!r}: use 'mm' or 'amm'")
    one_array = isinstance(split, np.ndarray) and np.issubdtype(split.dtype, np.integer) and len(names) == 1
    split_of = {n: split for n in names} if isinstance(split, str) or one_array else _per_graph(split, names, "split")
    robots_of: dict[int, list[int]] = {}  # robot counts run per graph
    given: dict[int, np.ndarray] = {}  # robot-of-pose arrays given per graph
    for gi, (name, g) in enumerate(zip(names, glist, strict=False)):
        how = split_of[name]
        if isinstance(how, str):
            if how not in SPLITS:
                raise ValueError(f"graph {name!r}: unknown split {how!r} (use {', '.join(SPLITS)} or an array)")
            for a in robots:
                if not 1 <= a <= g.num_poses:
                    raise ValueError(f"graph {name!r} has {g.num_poses} poses: cannot split among {a} robots")
            robots_of[gi] = robots
        else:
            given[gi] = split_robots(g, how)
            robots_of[gi] = [int(given[gi].max()) + 1]
    all_robots = list(dict.fromkeys(a for gi in range(len(glist)) for a in robots_of[gi]))

    def robot_of_pose(gi: int, a: int) -> np.ndarray:
        how = split_of[names[gi]]
        return given[gi] if gi in given else split_robots(glist[gi], how, a, seed=seed)
    if ground_truth is not None:
        gts = {k: v for k, v in _per_graph(ground_truth, names, "ground_truth").items() if v is not None}
    if isinstance(fstar, str):
        if fstar != "centralized":
            raise ValueError(f"fstar must be a mapping, a sequence, a number, None or 'centralized', got {fstar!r}")
        fstars = {n: reference_optimum(g) for n, g in zip(names, glist, strict=False)}
    else:
        fstars = {n: (None if v is None else float(v)) for n, v in _per_graph(fstar, names, "fstar").items()}
    if max_batch_bytes is None:
        max_batch_bytes = default_max_batch_bytes()
    xis = _xi_values(xi)
    by_xi = len(xis) > 1  # several xi: results keyed (graph, robots, method, xi)
    sub = subproblem or SubproblemConfig()
    say = progress or (lambda msg: None)

    axes = (("xi",) if by_xi else ()) + (("loss",) if by_loss else ())

    def key_of(name: str, a: int, method: str, x: float, label: str) -> tuple:
        return (name, a, method) + ((x,) if by_xi else ()) + ((label,) if by_loss else ())

    # Every (graph, robots) is partitioned once: the unpadded partition gives the shape needs
    # (n_max, e_max, loop-closure couplings) and is kept on the host, to be padded to its group's
    # common shape (exactly the arrays of a padded partition(...) call) when it is built.
    unpadded: dict[tuple[int, int], Partition] = {}
    needs: dict[tuple[int, int], tuple[int, int, int, int]] = {}
    rops: dict[tuple[int, int], np.ndarray] = {}
    for gi, g in enumerate(glist):
        for a in robots_of[gi]:
            rops[(gi, a)] = robot_of_pose(gi, a)
            p = partition(g, rops[(gi, a)])
            real = int(np.asarray(p.pose_mask).sum(axis=1).max())
            needs[(gi, a)] = (p.max_poses, p.max_edges, gamma_couplings(p.edges), aggregate_size(real, g.dim))
            unpadded[(gi, a)] = jax.device_get(p)

    starts: dict = {}

    def start_of(gi: int, a: int, li: int) -> Poses:
        fix = fixed_of[names[gi]]
        method, options = start_for(init, loss_of[labels[li]])
        per_robots = isinstance(method, str) and method == "distributed-chordal"
        key = (gi, a) if per_robots else (gi, str(method) if isinstance(method, str) else id(method),
                                          tuple(sorted(options.items())))
        if key not in starts:
            robots_kw = {"robots": rops[(gi, a)]} if per_robots else {}
            starts[key] = initialize(glist[gi], method, fixed=fix, **robots_kw, **options)
        return starts[key]

    histories: dict[tuple, np.ndarray] = {}
    final_poses: dict[tuple, Poses] = {}
    final_weights: dict[tuple, np.ndarray] = {}
    final_inliers: dict[tuple, np.ndarray] = {}
    config_rows: list[dict] = []
    group_rows: list[dict] = []

    for method in methods:
        # xi=None: each problem carries its own xi (an array leaf), so one config serves them all
        config = MMConfig(method=method, restart=restart, xi=None, subproblem=sub)
        keys = [(gi, a, x, li) for a in all_robots for gi in range(len(glist)) if a in robots_of[gi] for x in xis
                for li in range(len(labels))]
        groups = [keys] if group_by == "method" else [[k for k in keys if k[1] == a] for a in all_robots]
        for gkeys in groups:
            n_max = max(needs[k[:2]][0] for k in gkeys)
            e_max = max(needs[k[:2]][1] for k in gkeys)
            kc = max(needs[k[:2]][2] for k in gkeys)
            # one coarse aggregate size per batch (a static field): the config's, else the largest automatic one
            agg = sub.aggregate or max(needs[k[:2]][3] for k in gkeys)
            A = max(k[1] for k in gkeys)

            def build(gi: int, a: int, x: float, li: int, n_max=n_max, e_max=e_max, A=A, kc=kc, agg=agg,
                      config=config):
                g = glist[gi]
                part = _pad_partition(unpadded[(gi, a)], n_max, e_max, A)
                fix = fixed_of[names[gi]]
                if fix is None and any_fixed:  # one pytree structure per batch: an all-free mask
                    fix = np.zeros(g.num_poses, dtype=bool)
                problem = MMProblem.build(part, x, config=config, min_couplings=kc, fixed=fix, aggregate=agg,
                                          poses=part.scatter(start_of(gi, a, li)), loss=loss_of[labels[li]])
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
                return MMProblem(partition=common, gamma_soa=problem.gamma_soa, newton=problem.newton,
                                 free=problem.free, xi=problem.xi, robust=problem.robust)

            n_common = max(glist[k[0]].num_poses for k in gkeys)
            # bytes of one configuration (all have the same padded shape)
            t_build = time.perf_counter()
            built = {gkeys[0]: build(*gkeys[0])}  # reused by the first batch
            prob0 = batchable(built[gkeys[0]][1], n_common)
            st_shape = jax.eval_shape(lambda p, x, config=config: init_state(p, unstack(x), config), prob0,
                                      jax.ShapeDtypeStruct((A, n_max, d, d + 1), prob0.gamma_soa.diag.dtype))
            per_config = _tree_bytes(prob0) + _tree_bytes(st_shape)
            del prob0
            C = len(gkeys)
            per_batch = max(1, min(C, int(max_batch_bytes // max(per_config, 1)), max_batch_configs or C))
            num_batches = math.ceil(C / per_batch)
            per_batch = math.ceil(C / num_batches)
            group = dict(method=method, robots=sorted({k[1] for k in gkeys}), **({"xi": xis} if by_xi else {}),
                         **({"losses": labels} if by_loss else {}),
                         configs=C, A=A, n_max=n_max, aggregate=agg,
                         e_max=e_max, couplings=kc, bytes_per_config=per_config, batches=num_batches,
                         configs_per_batch=per_batch, compile_seconds=0.0, run_seconds=0.0,
                         setup_seconds=0.0,
                         padding_factor=float(A * n_max * C / sum(glist[k[0]].num_poses for k in gkeys)))
            setup = time.perf_counter() - t_build
            for b in range(num_batches):
                t0 = time.perf_counter()
                bkeys = gkeys[b * per_batch:(b + 1) * per_batch]
                real = len(bkeys)
                bkeys = bkeys + [bkeys[-1]] * (per_batch - real)  # same compiled shape
                parts, probs, X0s, blosses = [], [], [], []
                for (gi, a, x, li) in bkeys[:real]:
                    part, prob = built.pop((gi, a, x, li), None) or build(gi, a, x, li)
                    parts.append(part)
                    blosses.append(None if prob.robust is None else jax.device_get(prob.robust.loss))
                    probs.append(batchable(prob, n_common))
                    X0s.append(stack(part.scatter(start_of(gi, a, li))))
                probs += [probs[-1]] * (per_batch - real)
                X0s += [X0s[-1]] * (per_batch - real)
                problem = _stack(probs)
                del probs
                state, rec0 = _batched_start(problem, config, jnp.stack(X0s))
                setup += time.perf_counter() - t0

                def compile_chunk(state, length, limit, problem=problem, config=config):
                    compiled = compile_once(sweep_chunk, problem, config, state, length, limit, static=(length,))
                    return lambda st, lim: compiled(problem, config, st, lim)

                # sweeps never stop early: the driver keeps the records on the device and fetches f once
                traces = TRACE_COUNTS[method]
                try:
                    out = drive(compile_chunk, state, (rec0.f, rec0.grad_norm, rec0.restarted),
                                Termination(iterations, chunk_size), fetch=None)
                except NonFiniteError as err:
                    which = ", ".join(f"{names[gi]!r} ({a} robots{f', xi={x:g}' if by_xi else ''}"
                                      f"{f', loss {labels[li]}' if robust else ''})"
                                      for gi, a, x, li in bkeys[:real])
                    raise NonFiniteError(f"sweep ({method}), in a batch of {which}: {err}") from None
                if b == 0:
                    group["compile_seconds"] = out.compile_seconds
                    group["traces"] = TRACE_COUNTS[method] - traces  # 1 (0: jax's trace cache hit)
                f_all, run_s, state = out.history.f, out.solve_seconds, out.state
                X_final = np.asarray(state.X)
                if robust:
                    W_final, sched = jax.device_get((state.weights, state.schedule))
                del problem, state
                for c, (gi, a, x, li) in enumerate(bkeys[:real]):
                    name = names[gi]
                    key = key_of(name, a, method, x, labels[li])
                    f = f_all[c]
                    histories[key] = f
                    Xc = unstack(jnp.asarray(X_final[c]))
                    poses = output_frame(parts[c].gather(Xc), fixed_of[name], None)
                    final_poses[key] = poses
                    fs_ = fstars.get(name)
                    row = dict(graph=name, robots=a, method=method, **({"xi": x} if by_xi else {}),
                               **({"loss": labels[li]} if robust else {}),
                               iterations=iterations,
                               f_start=float(f[0]), f=float(f[-1]),
                               gap=None if fs_ is None else float(f[-1] - fs_),
                               relative_gap=None if fs_ is None else float((f[-1] - fs_) / fs_),
                               fstar=fs_, bytes=per_config, seconds=run_s / real,
                               ms_per_iteration=1e3 * run_s / real / max(iterations, 1),
                               batch_ms_per_iteration=1e3 * run_s / max(iterations, 1), batch=b,
                               batch_size=real)
                    if name in gts:
                        row["ate"] = absolute_trajectory_error(poses, gts[name])
                        rpe = relative_pose_error(poses, gts[name])
                        row["rpe_translation"] = rpe.translation
                        row["rpe_rotation_deg"] = rpe.rotation_deg
                    if name in corrupt:
                        row.update(outlier_rate=corrupt[name][1], outliers=int(corrupt[name][0].sum()))
                    if robust:
                        w, inl = robust_outcome(blosses[c], glist[gi], parts[c], W_final[c], poses)
                        final_weights[key], final_inliers[key] = w, inl
                        row.update(rejected=int((~inl).sum()), weight_updates=int(sched.updates[c]),
                                   gnc_stages=int(sched.stage[c]))
                        if name in corrupt:
                            scores = outlier_scores(inl, corrupt[name][0])
                            row.update(precision=scores.precision, recall=scores.recall)
                    config_rows.append(row)
                group["run_seconds"] += run_s
                say(f"{method} robots={group['robots']} batch {b + 1}/{num_batches}: {real} configs, "
                    f"{run_s:.1f} s run, {group['compile_seconds']:.1f} s compile")
            group["setup_seconds"] = setup
            group_rows.append(group)

    # order histories as graph-major, then robots, then method (then xi, then loss)
    index_of = {"xi": xis.index, "loss": labels.index}
    order = {k: (names.index(k[0]), all_robots.index(k[1]), methods.index(k[2]),
                 *(index_of[ax](v) for ax, v in zip(axes, k[3:], strict=True)))
             for k in histories}
    histories = dict(sorted(histories.items(), key=lambda kv: order[kv[0]]))
    config_rows.sort(key=lambda r: order[key_of(r["graph"], r["robots"], r["method"], r.get("xi"), r.get("loss"))])
    return SweepResult(histories=histories, fstar=fstars, configs=config_rows, groups=group_rows,
                       poses=final_poses, iterations=iterations, xi_values=list(xis), axes=axes,
                       loss_values=dict(loss_of), weights=final_weights, inliers=final_inliers)


def _loss_values(loss, scale, gnc) -> dict[str, RobustLoss | None]:
    """label -> RobustLoss (None: the plain least-squares program) of ``sweep``'s ``loss``.

    A name goes through :func:`~mmpgo_jax._mm.robust.as_loss` with ``scale`` and (for the kernels
    that take one) ``gnc``; with any robust loss in the sweep, "l2" becomes ``RobustLoss("l2",
    scale)`` so that every configuration shares the weighted program's pytree structure."""
    if loss is None or isinstance(loss, (str, RobustLoss)):
        items = [(None, loss if loss is not None else "l2")]
    elif isinstance(loss, Mapping):
        items = [(str(k), v) for k, v in loss.items()]
    elif isinstance(loss, Sequence):
        items = [(None, v) for v in loss]
    else:
        raise TypeError(f"loss: expected a kernel name, a RobustLoss, a sequence or a mapping of them, got "
                        f"{type(loss).__name__}")
    if not items:
        raise ValueError("loss: give at least one loss")
    out: dict[str, RobustLoss | None] = {}
    for label, v in items:
        if isinstance(v, RobustLoss):
            if scale is not None or gnc is not None:
                raise ValueError("loss_scale / gnc apply to losses given by name; give them inside a RobustLoss")
            value, name = v, v.name
        elif isinstance(v, str):
            loss_code(v)  # unknown names: one-line ValueError
            value, name = as_loss(v, scale, gnc if v in GNC_LOSSES else None), v
        else:
            raise TypeError(f"loss: expected a kernel name or a RobustLoss, got {type(v).__name__}")
        label = name if label is None else label
        if label in out:
            raise ValueError(f"loss {label!r} given twice (label the losses with a mapping label -> loss)")
        out[label] = value
    if any(v is not None for v in out.values()):
        out = {k: (RobustLoss("l2", scale) if v is None else v) for k, v in out.items()}
        trust = {v.trust_odometry for v in out.values()}
        if len(trust) > 1:
            raise ValueError("the losses of one sweep must agree on trust_odometry (a static setting)")
    return out


def _xi_values(xi) -> list[float]:
    """A number or a sequence of numbers (finite, >= 0), de-duplicated in the given order."""
    values = [xi] if np.ndim(xi) == 0 else list(np.asarray(xi).reshape(-1)) if isinstance(xi, np.ndarray) else list(xi)
    out = []
    for v in values:
        ok = isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))
        if not ok or not np.isfinite(v) or v < 0:
            raise ValueError(f"xi must be a finite number >= 0 or a sequence of them, got {xi!r}")
        out.append(float(v))
    if not out:
        raise ValueError("xi: give at least one value")
    return list(dict.fromkeys(out))


def _pad_partition(p: Partition, n_max: int, e_max: int, num_robots: int) -> Partition:
    """``partition(graph, robots, min_max_poses=n_max, min_max_edges=e_max, num_robots=...)`` from the
    unpadded partition ``p`` (host arrays): the same arrays, without partitioning the graph again."""
    A0, n0 = np.shape(p.pose_mask)
    e0 = np.shape(p.edges.kappa)[1]
    A, n_max, e_max = max(num_robots, A0), max(n_max, n0), max(e_max, e0)

    def pad(x, lead, fill=0):
        x = np.asarray(x)
        out = np.full(lead + x.shape[2:], fill, dtype=x.dtype)
        out[: x.shape[0], : x.shape[1]] = x
        return jnp.asarray(out)

    e = p.edges
    d = np.shape(e.t)[-1]
    R = np.broadcast_to(np.eye(d, dtype=np.asarray(e.R).dtype), (A, e_max, d, d)).copy()
    R[:A0, :e0] = np.asarray(e.R)
    E = (A, e_max)
    edges = RobotEdges(
        robot_i=pad(e.robot_i, E), slot_i=pad(e.slot_i, E), robot_j=pad(e.robot_j, E), slot_j=pad(e.slot_j, E),
        local_i=pad(e.local_i, E, False), local_j=pad(e.local_j, E, False), R=jnp.asarray(R), t=pad(e.t, E),
        kappa=pad(e.kappa, E), tau=pad(e.tau, E),
    )
    return Partition(pose_index=pad(p.pose_index, (A, n_max)), pose_mask=pad(p.pose_mask, (A, n_max), False),
                     edges=edges, robot_of_pose=jnp.asarray(p.robot_of_pose), slot_of_pose=jnp.asarray(p.slot_of_pose),
                     num_poses=p.num_poses)
