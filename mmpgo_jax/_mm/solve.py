"""The friendly entry point: ``solve(graph, robots=10, method="amm", ...)``.

Builds the partition and the constant majorization data once, then hands the start state and one
compiled chunk of the outer loop to the shared driver (:mod:`._mm.driver`: progress callbacks and
stopping tolerances are checked between chunks on the host; the compiled code is the same for
every chunk and every call with the same shapes).
"""

from __future__ import annotations

import dataclasses
import functools
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import jax
import numpy as np

from .._core.gauge import FixedPoses, express_in_frame
from .._core.partition import Partition, partition
from .._core.pose_graph import HostPoses, PoseGraph, Poses
from .._core.precision import float64_enabled
from .._core.metrics import TrajectoryAccuracy, trajectory_accuracy
from .._init.start import initialize
from .centralized import NewtonConfig, newton_optimum
from .checkpoint import DEFAULT_EVERY, Checkpointer, identity, restore_state
from .checkpoint import load as load_checkpoint
from .driver import RESULTS, History, Monitor, NonFiniteError, Termination, compile_once, drive
from .majorization import unstack
from .outer import IterationRecord, MMConfig, MMProblem, MMState, check_consistent, run, start_state
from .robust import L2, GNCConfig, RobustLoss, as_loss, robust_outcome
from .subproblem import SubproblemConfig

__all__ = ["RESULTS", "ROBUST_START", "History", "NonFiniteError", "SolveResult", "centralized_optimum", "output_frame",
           "solve"]


@dataclass(frozen=True)
class SolveResult:
    """A solve's outcome, in the spirit of optimistix's ``Solution(value, result, stats)``: the
    final poses (global order, in the requested frame), the history, why it stopped (``result``, a
    :class:`RESULTS`; ``stop_reason`` is its short name) and ``stats`` (timings in seconds:
    ``initialize_seconds`` (partition and start), ``build_seconds`` (Gamma, preconditioner, state at
    X^0), ``init_seconds`` (their sum), ``compile_seconds``, ``solve_seconds`` = the compiled
    iterations alone; a sharded run adds its mesh size, plan and exchange). ``partition`` is the
    split the run used (one robot for the centralized Newton solver, built when first read)."""

    poses: Poses
    history: History
    _partition: Partition | Callable[[], Partition] = field(repr=False)
    config: MMConfig | None  # None for the centralized Newton solver
    result: RESULTS
    stats: dict = field(default_factory=dict)
    accuracy: TrajectoryAccuracy | None = None  # against ``ground_truth`` when one was given
    termination: Termination | None = None
    loss: RobustLoss | None = None  # the robust loss (its numbers filled in), None for least squares
    weights: np.ndarray | None = None  # (m,) final edge weights (robust losses), graph edge order
    inliers: np.ndarray | None = None  # (m,) bool: final residual within the scale (robust losses)
    start: Poses | None = None  # the start X^0 in the frame of ``poses`` (None for the centralized solver)

    @property
    def partition(self) -> Partition:
        if not isinstance(self._partition, Partition):  # built on first use
            object.__setattr__(self, "_partition", self._partition())
        return self._partition

    @property
    def f(self) -> float:
        return float(self.history.f[-1])

    @property
    def iterations(self) -> int:
        return self.history.iterations

    @property
    def stop_reason(self) -> str:
        return self.result.value

    @property
    def stop_description(self) -> str:
        """Why the run stopped, in words (e.g. "budget of 1000 iterations reached")."""
        return self.result.describe(self.termination) if self.termination is not None else self.result.value

    @property
    def init_seconds(self) -> float:
        return float(self.stats.get("init_seconds", 0.0))

    @property
    def initialize_seconds(self) -> float:
        return float(self.stats.get("initialize_seconds", 0.0))

    @property
    def build_seconds(self) -> float:
        return float(self.stats.get("build_seconds", 0.0))

    @property
    def compile_seconds(self) -> float:
        return float(self.stats.get("compile_seconds", 0.0))

    @property
    def solve_seconds(self) -> float:
        return float(self.stats.get("solve_seconds", 0.0))

    @property
    def extra(self) -> dict:
        """``stats`` (the name of earlier versions)."""
        return self.stats

    @property
    def ms_per_iteration(self) -> float:
        return 1e3 * self.solve_seconds / max(self.iterations, 1)

    @property
    def outliers(self) -> np.ndarray | None:
        """(m,) bool: the edges a robust run rejects (``~inliers``); None for least squares."""
        return None if self.inliers is None else ~self.inliers


def start_for(init, loss: RobustLoss | None) -> tuple:
    """(start, options) of a run: ``init`` as given, or by default the chordal start for least
    squares and for GNC run by the distributed solver, and :data:`ROBUST_START` (with the loss's
    scale) for a robust loss otherwise (measured in benchmarks/robust.md)."""
    if init is not None:
        return init, {}
    if loss is None or bool(np.asarray(loss.use_gnc)) or int(np.asarray(loss.kernel)) == L2:
        return "chordal", {}
    scale = None if loss.scale is None else float(np.asarray(loss.scale))
    return ROBUST_START, dict(scale=scale, trust_odometry=loss.trust_odometry)


ROBUST_START = "gnc-chordal"  # the default start of robust runs (benchmarks/robust.md)


def robust_fields(problem: MMProblem, graph: PoseGraph, part: Partition, state, poses) -> dict:
    """The robust outcome of a run for :class:`SolveResult` (``loss``, ``weights``, ``inliers``) and
    its statistics (weight updates, GNC stages, final mu); empty for least squares."""
    if problem.robust is None:
        return {}, {}
    loss = jax.device_get(problem.robust.loss)
    weights, inliers = robust_outcome(loss, graph, part, state.weights, poses)
    sched = jax.device_get(state.schedule)
    stats = dict(weight_updates=int(sched.updates), gnc_stages=int(sched.stage), gnc_mu=float(sched.mu),
                 weights_final=bool(sched.done))
    return dict(loss=loss, weights=weights, inliers=inliers), stats


def solve(
    graph: PoseGraph,
    robots: int | np.ndarray | Partition = 10,
    *,
    method: Literal["mm", "amm"] = "amm",
    iterations: int = 1000,
    init=None,
    initial: Poses | None = None,
    xi: float = 1e-3,
    restart: Literal["paper", "adaptive", "average"] = "adaptive",
    subproblem: SubproblemConfig | None = None,
    chunk_size: int = 50,
    grad_tol: float | None = None,
    f_target: float | None = None,
    rel_decrease_tol: float | None = None,
    stop_when_stalled: bool = True,
    callback: Callable[[int, np.ndarray], bool | None] | None = None,
    ground_truth: Poses | None = None,
    fixed: FixedPoses | None = None,
    frame: FixedPoses | Literal["raw"] | None = None,
    monitor: Monitor | None = None,
    loss: str | RobustLoss = "l2",
    loss_scale: float | None = None,
    gnc: GNCConfig | None = None,
    checkpoint: str | os.PathLike | None = None,
    checkpoint_every: int = DEFAULT_EVERY,
    resume: str | os.PathLike | None = None,
) -> SolveResult:
    """Run MM-PGO (``method="mm"``) or AMM-PGO (``"amm"``) on ``graph`` split among ``robots``.

    ``robots``: a count (contiguous blocks, as in the paper), an (n,) robot-of-pose array, or a
    prepared :class:`Partition`. ``init``: see :func:`mmpgo_jax.initialize` (default ``"chordal"``,
    the paper's start; for a robust loss :data:`ROBUST_START`); ``initial`` holds the file's VERTEX
    estimates for ``init="vertices"``.
    ``restart``: AMM's restart rule, ``"adaptive"`` (default), ``"average"`` or ``"paper"`` (see
    :class:`MMConfig`; measured in benchmarks/restart_rules.md). Stops after ``iterations`` or,
    checked after each chunk of ``chunk_size`` iterations, when
    ||grad F|| <= ``grad_tol``, f <= ``f_target``, the relative decrease of f over the last chunk
    is below ``rel_decrease_tol``, or (``stop_when_stalled``, default) f moved only by rounding over
    the last chunk (:class:`~mmpgo_jax._mm.driver.Termination`): ``iterations`` is an upper bound,
    ``stop_when_stalled=False`` runs all of them (fixed-length histories). ``callback(k, f_chunk)``
    is called after each chunk (k = total iterations so far); returning True stops the run.
    ``monitor`` (a :class:`Monitor`, e.g. a progress bar) is told when each phase begins and of
    every chunk's f and ||grad F||. With ``ground_truth`` (synthetic data), the result's
    ``accuracy`` holds ATE / RPE of the final
    estimate after rigid alignment.

    ``fixed`` (e.g. :attr:`G2OFile.fixed_poses`): poses held at their values by the start and by
    every iteration. ``frame``: the frame of ``result.poses`` (see :func:`output_frame`): by
    default the fixed poses' frame when there are fixed poses, else pose 0 at the identity; a
    :class:`FixedPoses` (e.g. :attr:`G2OFile.frame`: the file's first pose at its VERTEX value)
    moves the result rigidly so that its first pose takes that value; ``"raw"`` keeps the solver's
    own gauge. f and the history do not depend on it.

    ``loss``: the kernel of the robust objective F_rho = 1/2 sum rho_c(s_ij) (docs/conventions.md
    §10): "l2" (least squares, the default), "huber", "cauchy", "geman-mcclure", "welsch" or
    "tls" (truncated least squares), or a :class:`~mmpgo_jax.RobustLoss` with its weight-update
    options; ``loss_scale``: c in residual units (default :func:`~mmpgo_jax.chi2_scale`). A robust
    kernel starts by default from ``init="gnc-chordal"`` (GNC-TLS with chordal + Newton stages, at
    the loss's scale); ``gnc``: a :class:`~mmpgo_jax.GNCConfig` (tls, geman-mcclure) runs GNC stages
    in the distributed solver instead, from the chordal start.
    f and the history are then f = 2 F_rho, and the result holds the final edge ``weights`` and the
    ``inliers`` (edges whose final residual is within the scale).

    ``checkpoint``: a file to which the state, the history so far and the start are written
    (atomically: the file is always a whole checkpoint) after every ``checkpoint_every``-th chunk
    the run goes on from (:mod:`~mmpgo_jax._mm.checkpoint`). ``resume``: such a file; the run
    continues from it exactly as the interrupted run would have (same f history and poses, bit for
    bit on the same machine), with the same other arguments except ``iterations`` (which may be
    larger); a checkpoint of another problem (graph, robots, start, method, settings, loss, fixed
    poses, chunk size, precision) is refused with a :class:`~mmpgo_jax._mm.checkpoint.CheckpointError`
    naming what differs. Both may name the same file.

    Raises :class:`NonFiniteError` when f or its gradient stops being finite (data whose weights or
    residuals float arithmetic cannot represent). Numbers are checked (ValueError naming the
    parameter). A second call with the same shapes and configuration structure does not compile
    again (:func:`~mmpgo_jax._mm.driver.compile_once`).
    """
    termination = Termination(iterations, chunk_size, grad_tol, f_target, rel_decrease_tol, stop_when_stalled)
    config = MMConfig(method=method, restart=restart, xi=xi, subproblem=subproblem or SubproblemConfig())
    robust = as_loss(loss, loss_scale, gnc)
    monitor = monitor or Monitor()
    clock = _Clock()
    monitor.phase("initializing")
    part = robots if isinstance(robots, Partition) else partition(graph, robots)
    start_method, start_options = start_for(init, robust)
    key = snapshot = None
    if checkpoint is not None or resume is not None:
        key = run_identity(graph, part, (start_method, start_options, initial), config, robust, fixed, chunk_size,
                           "one device")
    if resume is not None:
        snapshot = load_checkpoint(resume)
        snapshot.check(key, iterations)
        X0 = Poses(*snapshot.X0)  # the start the checkpointed run was built from
    else:
        X0 = initialize(graph, start_method, initial=initial, robots=part, fixed=fixed, **start_options)
    saver = None if checkpoint is None else Checkpointer(checkpoint, checkpoint_every, key, jax.device_get(X0),
                                                         chunk_size=chunk_size)
    start_poses = X0
    X0 = jax.block_until_ready(part.scatter(X0))
    clock.lap("initialize")
    monitor.phase("building")
    problem = jax.block_until_ready(MMProblem.build(part, xi, config=config, fixed=fixed, poses=X0, loss=robust))
    clock.lap("build")
    monitor.phase("compiling")
    start_fn = compile_once(start_state, problem, X0, config, exported=_start_export(problem))
    clock.lap("compile")
    monitor.phase("building")
    state, start = start_fn(problem, X0, config)
    start = jax.device_get(start)
    if snapshot is not None:  # the checkpoint's state, placed as the fresh one
        state = jax.tree.map(lambda a, b: jax.device_put(a, b.sharding), restore_state(snapshot, state), state)
    clock.lap("build")

    check_consistent(problem, config)  # (the exported program below skips run()'s own check)

    def compile_chunk(state, length, limit):
        settled = None if problem.robust is None else 0.0
        out = (state, IterationRecord(f=0.0, grad_norm=0.0, restarted=0.0, settled=settled))  # run's result structure
        compiled = compile_once(run, problem, config, state, length, limit, static=(length,),
                                exported=(run.__wrapped__, (3,), out))
        return lambda st, lim: compiled(problem, config, st, lim)

    def fetch(rec):  # robust runs add whether GNC has ended (the stopping rules wait for it)
        extra = () if problem.robust is None else (rec.settled,)
        return jax.device_get((rec.f, rec.grad_norm, rec.restarted, *extra))

    out = drive(compile_chunk, state, (start.f, start.grad_norm, start.restarted), termination, fetch=fetch,
                callback=callback, monitor=monitor, checkpoint=saver,
                history=None if snapshot is None else snapshot.history)
    poses = output_frame(part.gather(unstack(np.asarray(out.state.X))), fixed, frame)  # sliced on the host
    outcome, robust_stats = robust_fields(problem, graph, part, out.state, poses)
    return SolveResult(
        poses=poses,
        history=out.history,
        _partition=part,
        config=config,
        result=out.result,
        stats={**clock.stats(out), **robust_stats},
        accuracy=None if ground_truth is None else trajectory_accuracy(poses, ground_truth),
        termination=termination,
        start=output_frame(start_poses, fixed, frame),
        **outcome,
    )


def run_identity(graph: PoseGraph, part: Partition, start, config: MMConfig, loss, fixed, chunk_size: int,
                 layout) -> dict:
    """The :func:`~mmpgo_jax._mm.checkpoint.identity` of a run (what a resume must match)."""
    return identity(graph=graph, robot_of_pose=part.robot_of_pose, num_robots=part.num_robots, start=start,
                    config=config, loss=loss, fixed=fixed, chunk_size=chunk_size, precision=graph.R.dtype,
                    layout=layout)


def _start_export(problem: MMProblem):
    """``compile_once``'s ``exported`` for :func:`start_state` (kept in the persistent cache, so a
    warm process does not trace it again): its output structure, known without tracing for least
    squares (robust states hold the weighted operators; those are compiled as usual)."""
    if problem.robust is not None:
        return None
    leaf = 0.0
    state = MMState(**{f.name: leaf for f in dataclasses.fields(MMState) if f.default is dataclasses.MISSING})
    return start_state.__wrapped__, (), (state, IterationRecord(f=leaf, grad_norm=leaf, restarted=leaf))


class _Clock:
    """Seconds per phase of a solve (``initialize``: partition and start; ``build``: Gamma, its
    preconditioner and the state at X^0; ``compile``), for ``SolveResult.stats``."""

    def __init__(self):
        self.seconds = {"initialize": 0.0, "build": 0.0, "compile": 0.0}
        self._t = time.perf_counter()

    def lap(self, phase: str) -> None:
        now = time.perf_counter()
        self.seconds[phase] += now - self._t
        self._t = now

    def stats(self, driven) -> dict:
        s = self.seconds
        return dict(initialize_seconds=s["initialize"], build_seconds=s["build"],
                    init_seconds=s["initialize"] + s["build"], compile_seconds=s["compile"] + driven.compile_seconds,
                    solve_seconds=driven.solve_seconds)


def output_frame(poses: Poses, fixed: FixedPoses | None, frame) -> Poses:
    """The frame a result is reported in (see :func:`solve`)."""
    if isinstance(frame, str):
        if frame != "raw":
            raise ValueError(f"frame must be a FixedPoses, 'raw' or None, got {frame!r}")
        return poses
    if frame is None:
        if fixed is not None:
            return poses  # the fixed poses hold the gauge
        frame = FixedPoses.identity([0], poses.R.shape[-1])
    return express_in_frame(poses, frame)


def centralized_optimum(
    graph: PoseGraph,
    *,
    init="chordal",
    initial: Poses | None = None,
    grad_tol: float = 1e-6,
    max_iterations: int = 5000,
    xi: float | None = None,
    subproblem: SubproblemConfig | None = None,
    fixed: FixedPoses | None = None,
    frame: FixedPoses | Literal["raw"] | None = None,
    callback: Callable[[int, np.ndarray], bool | None] | None = None,
    monitor: Monitor | None = None,
    chunk_size: int = 25,
    method: Literal["newton", "mm"] = "newton",
) -> SolveResult:
    """The centralized optimum: one robot, run to ||grad F|| <= ``grad_tol`` (f* of every reported gap).

    ``method="newton"`` (default): Riemannian Newton steps with Levenberg–Marquardt damping and a
    sparse direct solve per step, on the host in float64 (:mod:`~mmpgo_jax._mm.centralized`);
    ``xi`` is the initial damping (default 0: the first step is Gauss–Newton, whose matrix is
    positive definite). It converges quadratically near the optimum: 2–16 iterations
    on the benchmark files (benchmarks/centralized.md compares it with GTSAM's Levenberg–Marquardt
    on the same objective). The stopping rules are checked, and ``callback(k, f)`` /
    ``monitor`` told, after every iteration; ``result.config`` is None.

    ``method="mm"``: MM with A = 1 (:func:`solve`), where the majorizer is F plus the proximal term
    xi/2 ||X - X^k||^2 (``xi`` default 1e-6), so each outer iteration is a damped Riemannian
    Newton step solved by truncated CG (``subproblem``; default near exact: CG to a relative
    residual 1e-8 in float64, 1e-4 in float32, at most 1000 iterations); checked every ``chunk_size`` iterations, and in
    float32, which stalls far above ``grad_tol``, also stopped once a chunk lowers f by less than
    a relative 1e-7.

    Check a result with :func:`~mmpgo_jax.certify`. ``init`` / ``initial`` / ``fixed`` /
    ``frame`` / ``callback`` / ``monitor``: as for :func:`solve` (with two or more fixed poses the
    optimum is a constrained one, which the certificate does not cover).
    """
    if method == "newton":
        return _newton_optimum(graph, init, initial, grad_tol, max_iterations, xi, fixed, frame, callback, monitor)
    if method != "mm":
        raise ValueError(f"method must be 'newton' or 'mm', got {method!r}")
    xi = 1e-6 if xi is None else xi
    # float32 cannot resolve a 1e-8 residual: CG would always run to its cap
    tol = 1e-8 if float64_enabled() else 1e-4
    sub = subproblem or SubproblemConfig(max_steps=4, gradient_tolerance=0.1, cg_iterations=1000, cg_tolerance=tol)
    return solve(
        graph,
        1,
        method="mm",
        iterations=max_iterations,
        init=init,
        initial=initial,
        xi=xi,
        subproblem=sub,
        chunk_size=chunk_size,
        grad_tol=grad_tol,
        # float32 stalls far above grad_tol: stop once a chunk no longer lowers f
        rel_decrease_tol=None if float64_enabled() else 1e-7,
        fixed=fixed,
        frame=frame,
        callback=callback,
        monitor=monitor,
    )


def _newton_optimum(graph, init, initial, grad_tol, max_iterations, xi, fixed, frame, callback, monitor) -> SolveResult:
    """:func:`centralized_optimum` by the host Newton solver."""
    # Newton's own rule: ||grad F|| <= grad_tol or the cap (the certificate needs a critical point)
    termination = Termination(max_iterations, 1, grad_tol, stop_when_stalled=False)
    config = NewtonConfig() if xi is None else NewtonConfig(initial_damping=xi)
    monitor = monitor or Monitor()
    clock = _Clock()
    monitor.phase("initializing")
    X0 = initialize(graph, init, initial=initial, fixed=fixed, host=True)
    clock.lap("initialize")
    monitor.phase("building")
    R, t, history, result, stats = newton_optimum(graph, X0.R, X0.t, termination, fixed=fixed,
                                                  config=config, callback=callback, monitor=monitor)
    dt = X0.R.dtype
    out = output_frame(HostPoses(R.astype(dt), t.astype(dt)), fixed, frame)  # the frame on the host
    # one transfer of both (jnp.asarray would be cheaper per call but compiles a conversion per
    # new shape: ~15 ms on the first call for a graph, which is the call that matters)
    poses = Poses(*jax.device_put((out.R, out.t)))
    seconds = clock.seconds
    return SolveResult(
        poses=poses,
        history=history,
        _partition=functools.partial(partition, graph, 1),  # device arrays only when asked for
        config=None,
        result=result,
        stats=dict(initialize_seconds=seconds["initialize"], build_seconds=stats["build_seconds"],
                   init_seconds=seconds["initialize"] + stats["build_seconds"], compile_seconds=0.0,
                   solve_seconds=stats["solve_seconds"], factorizations=stats["factorizations"]),
        termination=termination,
    )
