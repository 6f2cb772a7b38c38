"""Parameter sweeps: many (graph x robot count) configurations of one method in ONE ``vmap``.

A method is a name of the methods registry (:mod:`~mmpgo_jax._solve.methods`: "mm", "amm",
"rbcd", "rbcd++", "rbcd-parallel", ..., "dgs") or a :class:`~mmpgo_jax.Solver` object; each runs
as its own compiled batch through the same padded layout. RBCD's per-problem scalars (the robot
and colour-class counts its selection reads) are arrays of its problem, so configurations with
different robot counts stack like MM's; under ``vmap`` RBCD++'s redo-after-increase loop runs
until every configuration of the batch is done (results unchanged).

Every configuration (graph, robot count) of a method is built with the library's own padding
(:func:`~mmpgo_jax._partition.partition` with ``min_max_poses`` / ``min_max_edges`` /
``num_robots``, :meth:`MMProblem.build` with ``min_couplings``) to a common shape: the largest
n_max, e_max, loop-closure coupling count and robot count A of the group (padded robots own
nothing; padding never changes a result). The problems and states are stacked along a new leading
*configuration* axis and advanced by one compiled chunk ``jit(vmap(run))`` of ``chunk_size``
outer iterations, so a sweep compiles once per method (``group_by="method"``).

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
the same either way. The default ``group_by="auto"`` is "robots" on a CPU (measured, 3600-pose Cube,
AMM, 300 iterations, robots 5/10/50: 184 s grouped by method, 20 s by robot count) and "method"
on an accelerator, where one large batch fills the device.

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

With several CPU devices (:func:`~mmpgo_jax.use_cpu_cores`, which ``mmpgo sweep`` calls) a group's
batches run one per device at a time, batch b on device b mod D from that device's own thread (XLA
computes with the GIL released, so the devices' cores work at once): a batch is placed on its device
whole, so a configuration's
arithmetic is the one it gets on the default device, and each device compiles the group's program
once. ``groups`` then report ``devices`` and ``wall_seconds`` (the group's wall time; its
``run_seconds`` stay the sum of the batches' own times, which overlap).
"""

from __future__ import annotations

import csv
import dataclasses
import math
import time
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np

from .._core.gauge import FixedPoses
from .._core.partition import SPLITS, partition, split_robots
from .._core.pose_graph import PoseGraph, Poses
from .._core.resources import available_memory_bytes
from .._init.start import initialize_with_weights
from .._io.atomic import atomic_write
from .._mm.driver import RESULTS, Driven, History, NonFiniteError, Termination, compile_once, converged_at, drive
from .._mm.layouts import Padded
from .._mm.majorization import gamma_couplings
from .._mm.outer import MMProblem
from .._mm.preconditioner import aggregate_size
from .._mm.robust import GNC_LOSSES, GNCConfig, RobustLoss, as_loss, loss_code
from .._mm.solvers import AMM, MM, Solver, run_chunk
from .._mm.subproblem import SubproblemConfig
from .._solve.build import finish, prepare, start_for
from .._solve.methods import MAJORIZATION, check_loss, method_name, solver_for
from .._solve.prefilter import PCM, apply_prefilter, as_prefilter
from .._solve.result import SolveResult
from .outliers import outlier_scores

__all__ = ["TRACE_COUNTS", "SweepResult", "default_max_batch_bytes", "reference_optimum", "sweep"]

#: How many times the batched chunk was traced (= compiled: each trace is followed by exactly one
#: compilation), per method (its registry name, :func:`~mmpgo_jax._solve.methods.method_name`).
#: Incremented at trace time only; tests read it.
TRACE_COUNTS: Counter = Counter()


def _sweep_chunk_impl(solver: Solver, problem, state, length: int, limit):
    TRACE_COUNTS[method_name(solver)] += 1  # runs only while tracing
    chunk = run_chunk.__wrapped__
    if jax.tree.leaves(state)[0].shape[0] == 1:
        # A batch of one runs unbatched: under vmap the AMM step's lax.cond (MM fallback only when a
        # robot restarts) would become a select that computes the fallback every iteration.
        def squeeze(tree):
            return jax.tree.map(lambda x: x[0], tree)
        out = chunk(solver, squeeze(problem), squeeze(state), length, limit)
        return jax.tree.map(lambda x: x[None], out)
    return jax.vmap(lambda p, s: chunk(solver, p, s, length, limit))(problem, state)


_sweep_chunk_impl.__name__ = "sweep_chunk"
_sweep_chunk_impl.__qualname__ = "sweep_chunk"
#: ``jit(vmap(run_chunk))`` over the leading configuration axis (name in compile logs: ``sweep_chunk``).
sweep_chunk = jax.jit(_sweep_chunk_impl, static_argnames=("length",))


def default_max_batch_bytes(fraction: float = 0.25) -> int:
    """``fraction`` of MemAvailable (``/proc/meminfo``); 4 GiB where that file is missing."""
    return int(fraction * available_memory_bytes())


def reference_optimum(graph: PoseGraph, *, grad_tol: float = 1e-5, max_iterations: int = 500) -> float:
    """f* for relative gaps: :func:`~mmpgo_jax.centralized_optimum` with a reachable tolerance.

    The library default ``grad_tol=1e-6`` lies below the float64 noise floor of ||grad F|| on large
    problems (3600-pose Cube: f ~ 1.5e4, ||grad F|| stalls at 3e-6 after ~50 iterations while f
    no longer changes in the 16th digit), which turns it into a 5000-iteration run.
    """
    from .._solve.solve import centralized_optimum

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
    results: dict[tuple, SolveResult] = field(repr=False, default_factory=dict)  # key -> SolveResult

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


def sweep(
    graphs,
    robots: Sequence[int] | int = (5, 10, 50),
    methods: Sequence[str | Solver] | Mapping[str, str | Solver] | str | Solver = ("mm", "amm"),
    iterations: int = 1000,
    *,
    init=None,
    xi: float | Sequence[float] | None = None,
    restart: Literal["paper", "adaptive", "average"] | None = None,
    fstar: Mapping[str, float] | Sequence[float] | float | str | None = None,
    max_batch_bytes: int | None = None,
    max_batch_configs: int | None = None,
    ground_truth: Mapping[str, Poses] | Sequence[Poses] | Poses | None = None,
    subproblem: SubproblemConfig | None = None,
    chunk_size: int = 50,
    group_by: Literal["auto", "method", "robots"] = "auto",
    progress=None,
    fixed: Mapping[str, FixedPoses] | Sequence[FixedPoses] | FixedPoses | None = None,
    split="blocks",
    seed: int = 0,
    loss=None,
    loss_scale: float | None = None,
    gnc: GNCConfig | None = None,
    prefilter: str | PCM | None = None,
) -> SweepResult:
    """Run every (graph, robot count) configuration of each method as one batched computation.

    ``methods``: method names of :data:`~mmpgo_jax._solve.methods.METHOD_NAMES` ("mm", "amm",
    "rbcd", "rbcd++", "rbcd-parallel", ..., "dgs") or :class:`~mmpgo_jax.Solver` objects (e.g.
    ``RBCD(selection="uniform", seed=1)``), or a mapping label -> name or solver. Results are keyed
    by the name (a solver's: :func:`~mmpgo_jax._solve.methods.method_name`, e.g. "rbcd++",
    "rbcd-parallel"; or the mapping's label); two methods with one name are refused. Each method is
    its own compiled batch. ``xi``, ``restart`` and ``subproblem`` apply to "mm" and "amm" given by
    name (defaults 1e-3, "adaptive", :class:`~mmpgo_jax.SubproblemConfig`); every other method (and
    a solver object) keeps its own settings, so a sequence of xi with such a method, or a shortcut
    that no method of the sweep takes, is refused (ValueError). RBCD and DGS minimise the
    least-squares F only: a robust ``loss`` with them is refused, naming the method.

    ``graphs``: a PoseGraph, a dataset with ``.graph`` (and ``.ground_truth``, used for ATE/RPE
    unless ``ground_truth`` is given), or a sequence / name-keyed mapping of them (same d; n may
    differ). ``robots``: robot counts (contiguous blocks, as :func:`~mmpgo_jax.solve`).
    ``init``: the start (any :func:`~mmpgo_jax.initialize` method; by default "chordal" for least
    squares and "gnc-chordal" at the loss's scale for a robust kernel; each start is computed once per
    graph). A robust configuration therefore equals ``solve(..., start="gnc-chordal")``, not
    :func:`~mmpgo_jax.solve`'s default, which runs from two starts and keeps the better run (one
    compiled batch runs one start per configuration). ``fstar``: per-graph optimum (mapping or
    sequence), or ``"centralized"`` to compute it with :func:`reference_optimum`; relative gaps need it.
    ``max_batch_bytes``: see the module docstring; ``max_batch_configs`` caps the configurations per
    batch as well (on a CPU, small batches are faster: cache-sized working sets). ``group_by``: "method"
    (one compilation per method, robot axis padded to the largest count), "robots" (one per (method,
    robot count)) or "auto" (default: "robots" on a CPU, "method" on an accelerator; module docstring).
    ``progress(message)`` is called with a line of text after each batch.

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

    ``prefilter``: ``"pcm"`` or a :class:`~mmpgo_jax.PCM`, as :func:`~mmpgo_jax.solve`'s: per (graph,
    robot count), PCM removes the inter-robot loop closures it finds inconsistent (its robot pairs
    depend on the split, so each robot count gets its own filtered graph, partition and start), and
    the configuration runs on the kept edges. Its ``results`` are put back in the graph's edge order
    (``prefiltered`` marks the removed edges, ``inliers`` marks them False, ``weights`` holds 0 for
    them), ``weights`` / ``inliers`` likewise, and ``configs`` gain ``pcm_rejected``; f and the
    history are those of the filtered graph, while ``fstar`` (and so the gaps) stays what was given
    for the whole graph.

    Equivalent, configuration by configuration, to ``solve(graph, robots, method=..., iterations,
    init, xi, restart, subproblem, fixed, loss, loss_scale, gnc, stop_when_stalled=False)`` (for a
    solver object: ``solve(graph, robots, solver=..., ...)``) (for
    ``"l2"`` swept among robust losses: ``loss=RobustLoss("l2", loss_scale)``): a batch runs every
    iteration, since one configuration cannot stop alone (a solver's own stopping rule, such as DGS's
    change rule, holds its configuration's state where it held, and that history ends there, as
    ``solve``'s does). ``results``
    holds each configuration's :class:`~mmpgo_jax.SolveResult` (the fields a ``solve`` returns;
    timings are the configuration's share of its batch).
    """
    if iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {iterations}")
    if group_by not in ("auto", "method", "robots"):
        raise ValueError(f"group_by must be 'auto', 'method' or 'robots', got {group_by!r}")
    if group_by == "auto":
        group_by = "robots" if jax.default_backend() == "cpu" else "method"
    plan = _Plan.make(graphs, robots, iterations, methods=methods, init=init, xi=xi, fstar=fstar,
                      ground_truth=ground_truth, fixed=fixed, split=split, seed=seed, loss=loss, loss_scale=loss_scale,
                      gnc=gnc, chunk_size=chunk_size, subproblem=subproblem, restart=restart,
                      prefilter=as_prefilter(prefilter))
    if max_batch_bytes is None:
        max_batch_bytes = default_max_batch_bytes()
    say = progress or (lambda msg: None)
    out = _Outputs()
    for method in plan.methods:
        keys = [(gi, a, x, li) for a in plan.all_robots for gi in range(len(plan.glist)) if a in plan.robots_of[gi]
                for x in plan.xis for li in range(len(plan.labels))]
        groups = [keys] if group_by == "method" else [[k for k in keys if k[1] == a] for a in plan.all_robots]
        for gkeys in groups:
            _run_group(plan, method, gkeys, out, max_batch_bytes, max_batch_configs, say)
    return out.result(plan, list(plan.methods))


@dataclass
class _Plan:
    """What every configuration of a sweep shares: the normalized inputs, the splits and unpadded
    partitions (each (graph, robots) partitioned once), the starts (each computed once), f*."""

    names: list
    glist: list
    gts: dict
    fixed_of: dict
    corrupt: dict
    loss_of: dict
    labels: list
    methods: dict  # label -> "mm" / "amm" (made per configuration) or the Solver of every configuration
    robots_of: dict
    all_robots: list
    unpadded: dict
    needs: dict
    rops: dict
    fstars: dict
    xis: list
    axes: tuple
    init: object
    iterations: int
    chunk_size: int
    subproblem: SubproblemConfig
    restart: str
    seconds: dict = field(default_factory=dict)  # initialize seconds per (graph, robots[, start])
    starts: dict = field(default_factory=dict)
    filtered: dict = field(default_factory=dict)  # (graph, robots) -> Prefiltered (a prefilter given)

    @staticmethod
    def make(graphs, robots, iterations, *, methods, init, xi, fstar, ground_truth, fixed, split, seed, loss,
             loss_scale, gnc, chunk_size, subproblem, restart, prefilter) -> _Plan:
        names, glist, gts, fixed_of, corrupt = _normalize_graphs(graphs)
        loss_of = _loss_values(loss, loss_scale, gnc)
        labels = list(loss_of)
        xis = _xi_values(1e-3 if xi is None else xi)
        methods = _methods(methods, xi=xi, several_xi=len(xis) > 1, restart=restart, subproblem=subproblem,
                           loss=next((v for v in loss_of.values() if v is not None), None))
        if fixed is not None:
            fixed_of = _per_graph(fixed, names, "fixed")
        for name, g in zip(names, glist, strict=False):
            if fixed_of.get(name) is not None:
                fixed_of[name].check(g.num_poses, g.dim)
        if ground_truth is not None:
            gts = {k: v for k, v in _per_graph(ground_truth, names, "ground_truth").items() if v is not None}
        robots_of, rops = _splits(names, glist, robots, split, seed)
        seconds, unpadded, needs, filtered = {}, {}, {}, {}
        for (gi, a), rop in rops.items():
            t0 = time.perf_counter()
            graph = glist[gi]
            if prefilter is not None:  # PCM's robot pairs depend on the split: one filtered graph per count
                filtered[(gi, a)] = apply_prefilter(graph, rop, prefilter)
                graph = filtered[(gi, a)].graph
            p = partition(graph, rop)
            real = int(np.asarray(p.pose_mask).sum(axis=1).max())
            needs[(gi, a)] = (p.max_poses, p.max_edges, gamma_couplings(p.edges), aggregate_size(real, glist[gi].dim))
            unpadded[(gi, a)] = jax.device_get(p)
            seconds[(gi, a)] = time.perf_counter() - t0
        axes = (("xi",) if len(xis) > 1 else ()) + (("loss",) if len(labels) > 1 else ())
        return _Plan(names=names, glist=glist, gts=gts, fixed_of=fixed_of, corrupt=corrupt, loss_of=loss_of,
                     labels=labels, methods=methods, robots_of=robots_of,
                     all_robots=list(dict.fromkeys(a for gi in range(len(glist)) for a in robots_of[gi])),
                     unpadded=unpadded, needs=needs, rops=rops, fstars=_fstars(fstar, names, glist), xis=xis,
                     axes=axes, init=init, iterations=iterations, chunk_size=chunk_size,
                     subproblem=subproblem or SubproblemConfig(), restart=restart or "adaptive", seconds=seconds,
                     filtered=filtered)

    def graph_of(self, gi: int, a: int) -> PoseGraph:
        """The graph a configuration runs on: the given one, or what the prefilter kept of it."""
        pre = self.filtered.get((gi, a))
        return self.glist[gi] if pre is None else pre.graph

    @property
    def robust(self) -> bool:
        return any(v is not None for v in self.loss_of.values())

    @property
    def any_fixed(self) -> bool:
        return any(v is not None for v in self.fixed_of.values())

    def key_of(self, gi: int, a: int, method: str, x: float, li: int) -> tuple:
        extra = {"xi": (x,), "loss": (self.labels[li],)}
        return (self.names[gi], a, method, *(v for ax in self.axes for v in extra[ax]))

    def solver(self, method: str, xi) -> Solver:
        """The configuration's solver (``xi=None``: the batch's, whose xi each problem carries; a solver
        given as an object is every configuration's)."""
        given = self.methods[method]
        if given == "mm":
            return MM(xi, self.subproblem)
        if given == "amm":
            return AMM(xi, self.restart, self.subproblem)
        return given

    def aggregate(self, method: str) -> int | None:
        """The coarse aggregate size the method's settings fix (None: automatic)."""
        given = self.methods[method]
        if isinstance(given, str):
            sub = self.subproblem
        else:
            config = getattr(given, "config", None)
            sub = getattr(config, "subproblem", None) or getattr(given, "inner", None)
        return getattr(sub, "aggregate", None)

    def _start_key(self, gi: int, a: int, li: int) -> tuple:
        """(cache key, start method, options, whether it depends on the robot count) of a start."""
        method, options = start_for(self.init, self.loss_of[self.labels[li]])
        per_robots = (isinstance(method, str) and method in ("distributed-chordal", "distributed-robust")) or bool(
            self.filtered)  # a prefiltered graph is one per robot count
        key = (gi, a if per_robots else None, str(method) if isinstance(method, str) else id(method),
               tuple(sorted(options.items())))
        return key, method, options, per_robots

    def start_of(self, gi: int, a: int, li: int) -> tuple:
        """(poses, edge weights or None) of the start of (graph, robots, loss), computed once (per robot
        count only when it depends on it); the weights of a start that classifies the edges, which a
        robust configuration holds first as ``solve`` does."""
        fix = self.fixed_of[self.names[gi]]
        key, method, options, per_robots = self._start_key(gi, a, li)
        if key not in self.starts:
            t0 = time.perf_counter()
            robots_kw = {"robots": self.rops[(gi, a)]} if per_robots else {}
            self.starts[key] = initialize_with_weights(self.graph_of(gi, a), method, fixed=fix, **robots_kw, **options)
            self.seconds[("start", key)] = time.perf_counter() - t0
        return self.starts[key]

    def initialize_seconds(self, gi: int, a: int, li: int) -> float:
        """Partition and start seconds of a configuration (a shared start counted whole for each)."""
        key = self._start_key(gi, a, li)[0]
        return self.seconds[(gi, a)] + self.seconds.get(("start", key), 0.0)


def _splits(names, glist, robots, split, seed) -> tuple[dict, dict]:
    """(robot counts per graph, robot-of-pose per (graph, robots)) of ``sweep``'s ``split``."""
    robots = [int(robots)] if np.ndim(robots) == 0 else list(dict.fromkeys(int(a) for a in robots))
    one_array = isinstance(split, np.ndarray) and np.issubdtype(split.dtype, np.integer) and len(names) == 1
    split_of = {n: split for n in names} if isinstance(split, str) or one_array else _per_graph(split, names, "split")
    robots_of: dict[int, list[int]] = {}
    rops: dict[tuple[int, int], np.ndarray] = {}
    for gi, (name, g) in enumerate(zip(names, glist, strict=False)):
        how = split_of[name]
        if isinstance(how, str):
            if how not in SPLITS:
                raise ValueError(f"graph {name!r}: unknown split {how!r} (use {', '.join(SPLITS)} or an array)")
            for a in robots:
                if not 1 <= a <= g.num_poses:
                    raise ValueError(f"graph {name!r} has {g.num_poses} poses: cannot split among {a} robots")
            robots_of[gi] = robots
            for a in robots:
                rops[(gi, a)] = split_robots(g, how, a, seed=seed)
        else:
            given = split_robots(g, how)
            robots_of[gi] = [int(given.max()) + 1]
            rops[(gi, robots_of[gi][0])] = given
    return robots_of, rops


def _fstars(fstar, names, glist) -> dict:
    if isinstance(fstar, str):
        if fstar != "centralized":
            raise ValueError(f"fstar must be a mapping, a sequence, a number, None or 'centralized', got {fstar!r}")
        return {n: reference_optimum(g) for n, g in zip(names, glist, strict=False)}
    return {n: (None if v is None else float(v)) for n, v in _per_graph(fstar, names, "fstar").items()}


@dataclass
class _Outputs:
    """What the groups of a sweep produce, gathered into one :class:`SweepResult`."""

    histories: dict = field(default_factory=dict)
    poses: dict = field(default_factory=dict)
    weights: dict = field(default_factory=dict)
    inliers: dict = field(default_factory=dict)
    results: dict = field(default_factory=dict)
    rows: list = field(default_factory=list)
    groups: list = field(default_factory=list)

    def result(self, plan: _Plan, methods: list) -> SweepResult:
        # order histories as graph-major, then robots, then method (then xi, then loss)
        index_of = {"xi": plan.xis.index, "loss": plan.labels.index}
        order = {k: (plan.names.index(k[0]), plan.all_robots.index(k[1]), methods.index(k[2]),
                     *(index_of[ax](v) for ax, v in zip(plan.axes, k[3:], strict=True)))
                 for k in self.histories}
        histories = dict(sorted(self.histories.items(), key=lambda kv: order[kv[0]]))
        self.rows.sort(key=lambda r: order[r.pop("_key")])
        results = {k: self.results[k] for k in histories}
        return SweepResult(histories=histories, fstar=plan.fstars, configs=self.rows, groups=self.groups,
                           poses=self.poses, iterations=plan.iterations, xi_values=list(plan.xis), axes=plan.axes,
                           loss_values=dict(plan.loss_of), weights=self.weights, inliers=self.inliers, results=results)


def _batchable(problem: MMProblem, n_common: int) -> MMProblem:
    """The problem with its partition's global (n,) arrays padded to ``n_common`` (graphs of a batch
    differ in n; the chunk never reads these arrays, so placeholders of one shape stack)."""
    p = problem.partition
    pad = n_common - p.num_poses
    common = dataclasses.replace(p, robot_of_pose=jnp.pad(p.robot_of_pose, (0, pad)),
                                 slot_of_pose=jnp.pad(p.slot_of_pose, (0, pad)), num_poses=n_common)
    return dataclasses.replace(problem, partition=common)


def _run_group(plan: _Plan, method: str, gkeys: list, out: _Outputs, max_batch_bytes, max_batch_configs, say) -> None:
    """One compiled group: the configurations ``gkeys`` padded to one shape, run in batches."""
    n_max, e_max, kc = (max(plan.needs[k[:2]][i] for k in gkeys) for i in range(3))
    # one coarse aggregate size per batch (a static field): the config's, else the largest automatic one
    agg = plan.aggregate(method) or max(plan.needs[k[:2]][3] for k in gkeys)
    A = max(k[1] for k in gkeys)
    layout = Padded(n_max, e_max, A, couplings=kc, aggregate=agg, mask_fixed=plan.any_fixed)
    termination = Termination(plan.iterations, plan.chunk_size, stop_when_stalled=False)

    def prepared(key):
        """The configuration built by the one builder of every solve (its start computed once per graph)."""
        gi, a, x, li = key
        start, weights = plan.start_of(gi, a, li)
        loss = plan.loss_of[plan.labels[li]]
        run = prepare(plan.graph_of(gi, a), plan.solver(method, x), plan.unpadded[(gi, a)], layout, termination,
                      fixed=plan.fixed_of[plan.names[gi]], loss=loss, given_start=start,
                      start_weights=None if loss is None else weights)
        run.clock.seconds["initialize"] += plan.initialize_seconds(gi, a, li)  # the partition and the start
        return run

    n_common = max(plan.glist[k[0]].num_poses for k in gkeys)
    t_build = time.perf_counter()
    built = {gkeys[0]: prepared(gkeys[0])}  # reused by the first batch
    first = built[gkeys[0]]
    per_config = _tree_bytes(_batchable(first.problem, n_common)) + _tree_bytes(first.state)  # one padded shape
    C = len(gkeys)
    per_batch = max(1, min(C, int(max_batch_bytes // max(per_config, 1)), max_batch_configs or C))
    num_batches = math.ceil(C / per_batch)
    per_batch = math.ceil(C / num_batches)
    group = dict(method=method, robots=sorted({k[1] for k in gkeys}), **({"xi": plan.xis} if "xi" in plan.axes else {}),
                 **({"losses": plan.labels} if "loss" in plan.axes else {}),
                 configs=C, A=A, n_max=n_max, aggregate=agg,
                 e_max=e_max, couplings=kc, bytes_per_config=per_config, batches=num_batches,
                 configs_per_batch=per_batch, compile_seconds=0.0, run_seconds=0.0, setup_seconds=0.0,
                 padding_factor=float(A * n_max * C / sum(plan.glist[k[0]].num_poses for k in gkeys)))
    setup = time.perf_counter() - t_build
    devices = _batch_devices(num_batches)
    group["devices"] = len(devices)
    batches = [gkeys[b * per_batch:(b + 1) * per_batch] for b in range(num_batches)]

    def execute(b, device):
        t0 = time.perf_counter()
        runs = [built.pop(key, None) or prepared(key) for key in batches[b]]
        set_up = time.perf_counter() - t0
        return runs, set_up, _execute_batch(plan, method, batches[b], runs, per_batch, n_common, termination, device)

    def record(b, outcome):
        nonlocal setup
        runs, set_up, (driven, traces) = outcome
        setup += set_up
        if b < len(devices):  # the first batch on each device compiles (then its executable is reused)
            group["compile_seconds"] += driven.compile_seconds
            group["traces"] = group.get("traces", 0) + traces
        _record_batch(plan, method, batches[b], runs, driven, termination, per_config, out, b)
        group["run_seconds"] += driven.solve_seconds
        say(f"{method} robots={group['robots']} batch {b + 1}/{num_batches}: {len(batches[b])} configs, "
            f"{driven.solve_seconds:.1f} s run, {group['compile_seconds']:.1f} s compile")

    t_run = time.perf_counter()
    if len(devices) == 1:
        for b in range(num_batches):
            record(b, execute(b, devices[0]))
    else:  # one thread per CPU device, its batches in order: JAX releases the GIL while a device computes
        from concurrent.futures import ThreadPoolExecutor

        queues = [ThreadPoolExecutor(1) for _ in devices]
        try:
            outcomes = [queues[b % len(devices)].submit(execute, b, devices[b % len(devices)])
                        for b in range(num_batches)]
            for b, future in enumerate(outcomes):
                record(b, future.result())
        finally:
            for queue in queues:
                queue.shutdown(wait=True, cancel_futures=True)
    group["wall_seconds"] = time.perf_counter() - t_run
    group["setup_seconds"] = setup
    out.groups.append(group)


def _batch_devices(num_batches: int) -> list:
    """The devices a group's batches run on: every CPU device (:func:`~mmpgo_jax.use_cpu_cores`) when
    there are several batches on a CPU backend, one batch per device at a time; else [None] (JAX's
    default device, one batch after another)."""
    if num_batches < 2 or jax.default_backend() != "cpu":
        return [None]
    devices = jax.devices("cpu")
    return devices[:num_batches] if len(devices) > 1 else [None]


def _execute_batch(plan: _Plan, method: str, bkeys: list, runs: list, per_batch: int, n_common: int,
                   termination: Termination, device) -> tuple:
    """Run one batch of a group (filled up to ``per_batch`` with discarded copies: one compiled
    shape) on ``device`` (None: the default one); returns (the driven batch, traces it made)."""
    fill = [runs[-1]] * (per_batch - len(runs))
    problem = _stack([_batchable(r.problem, n_common) for r in runs + fill])
    state = _stack([r.state for r in runs + fill])
    if device is not None:
        problem, state = jax.device_put((problem, state), device)
    start = tuple(np.stack([np.asarray(x) for x in column])
                  for column in zip(*(r.placement.start_record(r.start) for r in runs + fill), strict=True))
    solver = plan.solver(method, None)  # xi=None: each problem carries its own xi (an array leaf)

    def compile_chunk(state, length, limit):
        compiled = compile_once(sweep_chunk, solver, problem, state, length, limit, static=(length,))
        return lambda st, lim: compiled(solver, problem, st, lim)

    # sweeps never stop early: the driver keeps the records on the device and fetches f once
    traces = sum(TRACE_COUNTS.values())
    try:
        driven = drive(compile_chunk, state, start, termination, fetch=None)
    except NonFiniteError as err:
        which = ", ".join(f"{plan.names[gi]!r} ({a} robots{f', xi={x:g}' if 'xi' in plan.axes else ''}"
                          f"{f', loss {plan.labels[li]}' if plan.robust else ''})" for gi, a, x, li in bkeys)
        raise NonFiniteError(f"sweep ({method}), in a batch of {which}: {err}") from None
    return driven, sum(TRACE_COUNTS.values()) - traces


def _record_batch(plan: _Plan, method: str, bkeys: list, runs: list, driven: Driven, termination: Termination,
                  per_config: int, out: _Outputs, b: int) -> None:
    """Each configuration's result of a run batch (its row of the batch's records)."""
    real = len(bkeys)
    final = jax.device_get(driven.state)
    for c, (key, run) in enumerate(zip(bkeys, runs, strict=True)):
        state = jax.tree.map(lambda x, c=c: x[c], final)
        # a solver's own stopping rule (DGS's): the configuration's history ends where it held, as solve's
        keep = None if (at := converged_at(state)) is None else at + 1
        one = Driven(state=state, history=History(driven.history.f[c, :keep], driven.history.grad_norm[c, :keep],
                                                  driven.history.restarts[c, :keep]),
                     result=RESULTS.iterations if keep is None else RESULTS.converged,
                     compile_seconds=driven.compile_seconds / real, solve_seconds=driven.solve_seconds / real)
        _record(plan, method, key, run, one, termination, per_config, b, real, out)


def _record(plan: _Plan, method: str, key: tuple, run, driven: Driven, termination: Termination, per_config: int,
            b: int, real: int, out: _Outputs) -> None:
    """One configuration's :class:`SolveResult` (by the one solve path's ``finish``), row, history,
    poses and robust outcome."""
    gi, a, x, li = key
    name, graph, pre = plan.names[gi], plan.graph_of(gi, a), plan.filtered.get((gi, a))
    k = plan.key_of(gi, a, method, x, li)
    result = finish(graph, plan.solver(method, x), run, driven, termination, fixed=plan.fixed_of[name],
                    ground_truth=plan.gts.get(name))
    if pre is not None:  # back in the given graph's edge order, the removed edges marked
        result = pre.report(result)
    result.stats.update(batch=b, batch_size=real)
    out.results[k] = result
    out.histories[k] = f = result.history.f
    out.poses[k] = result.poses
    fs_ = plan.fstars.get(name)
    row = dict(graph=name, robots=a, method=method, **({"xi": x} if "xi" in plan.axes else {}),
               **({"loss": plan.labels[li]} if plan.robust else {}), iterations=plan.iterations,
               f_start=float(f[0]), f=float(f[-1]), gap=None if fs_ is None else float(f[-1] - fs_),
               relative_gap=None if fs_ is None else float((f[-1] - fs_) / fs_), fstar=fs_, bytes=per_config,
               seconds=result.solve_seconds, ms_per_iteration=1e3 * result.solve_seconds / max(plan.iterations, 1),
               batch_ms_per_iteration=1e3 * result.solve_seconds * real / max(plan.iterations, 1), batch=b,
               batch_size=real, _key=k)
    if result.accuracy is not None:
        row["ate"] = result.accuracy.ate
        row["rpe_translation"] = result.accuracy.rpe_translation
        row["rpe_rotation_deg"] = result.accuracy.rpe_rotation_deg
    if name in plan.corrupt:
        row.update(outlier_rate=plan.corrupt[name][1], outliers=int(plan.corrupt[name][0].sum()))
    if pre is not None:
        row["pcm_rejected"] = int(pre.rejected.sum())
    if result.inliers is not None:
        out.inliers[k] = result.inliers
        if result.weights is not None:  # (least squares after a prefilter has inliers but no weights)
            out.weights[k] = result.weights
        row.update(rejected=int((~result.inliers).sum()), weight_updates=result.stats.get("weight_updates"),
                   gnc_stages=result.stats.get("gnc_stages"))
        if name in plan.corrupt:
            scores = outlier_scores(result.inliers, plan.corrupt[name][0])
            row.update(precision=scores.precision, recall=scores.recall)
    out.rows.append(row)


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


def _methods(methods, *, xi, several_xi: bool, restart, subproblem, loss) -> dict:
    """label -> "mm" / "amm" (made per configuration with the sweep's xi, restart and subproblem) or
    the :class:`Solver` of every configuration, of ``sweep``'s ``methods``; a shortcut that no method
    takes, a sequence of xi beside a method with its own settings, a robust ``loss`` (the first
    robust :class:`RobustLoss`, None: none) beside a least-squares method and two methods with one
    label are refused."""
    if isinstance(methods, (str, Solver)):
        items = [(None, methods)]
    elif isinstance(methods, Mapping):
        items = [(str(k), v) for k, v in methods.items()]
    elif isinstance(methods, Sequence):
        items, seen = [], set()
        for m in methods:
            if isinstance(m, str) and m in seen:
                continue  # a name given twice runs once
            seen.add(m if isinstance(m, str) else id(m))
            items.append((None, m))
    else:
        raise TypeError(f"methods: expected method names or solvers (a sequence or a mapping label -> method), got "
                        f"{type(methods).__name__}")
    if not items:
        raise ValueError("methods: give at least one method")
    out: dict = {}
    for label, m in items:
        value = m if isinstance(m, str) and m in MAJORIZATION else solver_for(m)
        label = (m if isinstance(value, str) else method_name(value)) if label is None else label
        if label in out:
            raise ValueError(f"two methods of the sweep are named {label!r} (e.g. two RBCD solvers with other "
                             "settings): give the methods as a mapping label -> method")
        out[label] = value
    by_name = [v for v in out.values() if isinstance(v, str)]
    own = [k for k, v in out.items() if not isinstance(v, str)]
    for option, value, takers in (("xi", xi, MAJORIZATION), ("restart", restart, ("amm",)),
                                  ("subproblem", subproblem, MAJORIZATION)):
        if value is not None and not set(by_name) & set(takers):
            raise ValueError(f"{option} applies to the methods {' and '.join(map(repr, takers))} given by name; no "
                             f"method of this sweep takes it ({', '.join(map(repr, out))})")
    if several_xi and own:
        raise ValueError(f"a sequence of xi sweeps the proximal term of 'mm' / 'amm' given by name; {own[0]!r} keeps "
                         "its own settings: sweep it apart")
    for k in own:
        check_loss(out[k], loss)
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
