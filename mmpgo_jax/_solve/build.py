"""The one builder of a run, shared by every entry point and layout.

``prepare`` does, for any :class:`~mmpgo_jax._mm.solvers.Solver` and any layout: the split (the
layout's placement), the start (or a checkpoint's), ``solver.build`` (the constant data),
``solver.init`` (the state at X^0, compiled once per shape) and the placement on devices, timing
each phase. ``finish`` turns the driver's outcome into a :class:`SolveResult` with the same fields
whatever the layout. ``solve``, ``solve_sharded`` and ``sweep`` all go through these two.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from .._core.compile_mode import code_generation, program_slots
from .._core.metrics import trajectory_accuracy
from .._core.pose_graph import PoseGraph, Poses
from .._init.start import initial_classified
from .._mm.checkpoint import Checkpointer, identity, restore_state
from .._mm.checkpoint import load as load_checkpoint
from .._mm.driver import Monitor, Termination, compile_once
from .._mm.majorization import unstack
from .._mm.robust import L2, RobustLoss, incident_edge_index
from .._mm.solvers import Solver, start_run
from .result import SolveResult, output_frame

__all__ = ["ROBUST_START", "ROBUST_STARTS", "Clock", "NamedStart", "Prepared", "as_termination", "check_start_weights",
           "finish", "prepare", "slot_weights", "start_for"]

ROBUST_START = "gnc-chordal"  # the start of a robust run from one start (benchmarks/robust.md)
#: the default starts of a robust run: the run from each, the lower robust objective kept
#: (benchmarks/robust_distributed_files_findings.md: each start wins on other graphs)
ROBUST_STARTS = ("gnc-chordal", "distributed-robust")


@dataclass(frozen=True)
class NamedStart:
    """A start by name with options of its own, added to those :func:`start_for` gives the name: the
    user's (``NamedStart("distributed-robust", {"team_check": True})``, the options of
    :func:`~mmpgo_jax._init.robust_distributed.distributed_robust_initialization`), or the search's
    (the distributed robust start without the closures a run overruled: ``options=dict(excluded=...)``,
    added to the user's)."""

    name: str
    options: dict = field(default_factory=dict)


def start_for(init, loss: RobustLoss | None) -> tuple:
    """(start, options) of a run: ``init`` as given, or by default the chordal start for least
    squares and for GNC run by the distributed solver, and :data:`ROBUST_START` (with the loss's
    scale) for a robust loss otherwise (measured in benchmarks/robust.md). The robust starts by name
    ("gnc-chordal", "distributed-robust") take the loss's scale and ``trust_odometry``."""
    if isinstance(init, NamedStart):
        method, options = start_for(init.name, loss)
        return method, {**options, **init.options}
    robust = loss is not None and int(np.asarray(loss.kernel)) != L2
    if init is None:
        if not robust or bool(np.asarray(loss.use_gnc)):
            return "chordal", {}
        init = ROBUST_START
    if robust and isinstance(init, str) and init in ("gnc-chordal", "distributed-robust"):
        scale = None if loss.scale is None else float(np.asarray(loss.scale))
        return init, dict(scale=scale, trust_odometry=loss.trust_odometry)
    return init, {}


def as_termination(termination: Termination | None = None, **shortcuts) -> Termination:
    """``termination``, or one made of the shortcut arguments (``iterations``, ``chunk_size``,
    ``grad_tol``, ``f_target``, ``rel_decrease_tol``, ``stop_when_stalled``; None = default); a
    shortcut beside a Termination is refused (the number would have two owners)."""
    given = {k: v for k, v in shortcuts.items() if v is not None}
    if termination is not None:
        if given:
            raise ValueError(f"give {', '.join(given)} inside the Termination, not beside termination=")
        if not isinstance(termination, Termination):
            raise TypeError(f"termination must be a Termination, got {type(termination).__name__}")
        return termination
    return Termination(given.pop("iterations", 1000), **given)


class Clock:
    """Seconds per phase of a run (``initialize``: partition and start; ``build``: the solver's
    constant data, its state at X^0 and their placement; ``compile``), for ``SolveResult.stats``."""

    def __init__(self):
        self.seconds = {"initialize": 0.0, "build": 0.0, "compile": 0.0}
        self._t = time.perf_counter()

    def lap(self, phase: str) -> None:
        now = time.perf_counter()
        self.seconds[phase] += now - self._t
        self._t = now

    def stats(self, compile_seconds: float, solve_seconds: float) -> dict:
        s = self.seconds
        return dict(initialize_seconds=s["initialize"], build_seconds=s["build"],
                    init_seconds=s["initialize"] + s["build"], compile_seconds=s["compile"] + compile_seconds,
                    solve_seconds=solve_seconds)


@dataclass
class Prepared:
    """A run ready for the driver: the layout's placement, the start (global, as computed), the
    placed problem and state, the start's record (host), a resumed checkpoint and the checkpointer."""

    placement: object
    start_poses: Poses
    problem: object
    state: object
    start: object
    snapshot: object
    saver: Checkpointer | None
    clock: Clock
    start_weights: np.ndarray | None = None  # (m,) held as the robust run's first stage, graph order
    start_info: dict | None = None  # what the start reported (initial_classified's info)


def prepare(graph: PoseGraph, solver: Solver, robots, layout, termination: Termination, *, start=None, initial=None,
            fixed=None, loss: RobustLoss | None = None, monitor: Monitor | None = None,
            checkpoint: str | os.PathLike | None = None, checkpoint_every: int = 1,
            resume: str | os.PathLike | None = None, given_start: Poses | None = None,
            start_weights=None) -> Prepared:
    """Everything before the iterations (see the module docstring). ``given_start``: a start already
    computed for this graph (a sweep computes each graph's start once for all its configurations).
    ``start_weights``: (m,) robust weights in the graph's edge order held as the robust run's first
    stage; by default a robust run takes the weights of a start that classifies the edges (the
    distributed robust start), and a least-squares run has none (given ones: ValueError)."""
    monitor = monitor or Monitor()
    clock = Clock()
    monitor.phase("initializing")
    placement = layout.setup(graph, robots)
    start_method, start_options = start_for(start, loss)
    weights = check_start_weights(graph, start_weights, loss)
    with placement.building():
        key = snapshot = saver = start_info = None
        if checkpoint is not None or resume is not None:
            key = identity(graph=graph, robot_of_pose=placement.user_part.robot_of_pose,
                           num_robots=placement.user_part.num_robots,
                           start=(start_method, start_options, initial, weights),
                           config=solver, loss=loss, fixed=fixed, chunk_size=termination.chunk_size,
                           precision=graph.R.dtype, layout=placement.identity())
        if given_start is not None:
            X0 = given_start
        elif resume is not None:  # every process reads the file: the same start everywhere
            snapshot = load_checkpoint(resume)
            snapshot.check(key, termination.iterations)
            X0 = Poses(*(jnp.asarray(x) for x in snapshot.X0))  # the start the checkpointed run was built from
        else:
            if isinstance(start_method, str) and start_method == "gnc-chordal":  # minutes on some graphs: its stages
                start_options = dict(start_options, progress=monitor.note)
            X0, from_start, start_info = initial_classified(graph, start_method, initial=initial,
                                                            robots=placement.user_part, fixed=fixed, **start_options)
            X0 = placement.share_start(X0)
            if weights is None and loss is not None:
                weights = from_start
            elif start_info is not None:  # given weights: the start's maps are not the run's classification's
                start_info = {k: v for k, v in start_info.items() if k != "variance_factor"} or None
        if checkpoint is not None:
            saver = Checkpointer(checkpoint, checkpoint_every, key, jax.device_get(X0),
                                 chunk_size=termination.chunk_size, **placement.checkpoint_options())
        start_poses = X0
        X0 = jax.block_until_ready(placement.part.scatter(X0))
        clock.lap("initialize")
        monitor.phase("building")
        extra = {} if weights is None else dict(start_weights=slot_weights(graph, placement.part, weights))
        problem = jax.block_until_ready(solver.build(placement.part, poses=X0, loss=loss, **extra,
                                                     **placement.build_options(graph, fixed)))
        clock.lap("build")
        monitor.phase("compiling")
        structure = solver.start_structure(problem)
        start_fn = compile_once(start_run, solver, problem, X0, once=True,
                                exported=None if structure is None else (start_run.__wrapped__, (), structure))
        clock.lap("compile")
        monitor.phase("building")
        state, record = start_fn(solver, problem, X0)
        record = jax.device_get(record)
        if snapshot is not None:  # the checkpoint's state, placed as the fresh one
            state = jax.tree.map(lambda a, b: jax.device_put(a, b.sharding), restore_state(snapshot, state), state)
    problem, state = placement.place(problem, state)
    clock.lap("build")
    held = None if weights is None else np.asarray(weights, np.float64)
    return Prepared(placement, start_poses, problem, state, record, snapshot, saver, clock, held, start_info)


def check_start_weights(graph: PoseGraph, weights, loss: RobustLoss | None):
    """``start_weights`` as (m,) float64 in [0, 1], or None; refused beside least squares."""
    if weights is None:
        return None
    if loss is None:
        raise ValueError("start_weights apply to a robust loss (loss='tls', ...); least squares has no weights")
    w = np.asarray(weights, np.float64)
    if w.shape != (graph.num_edges,):
        raise ValueError(f"start_weights must have one value per edge, shape ({graph.num_edges},), got {w.shape}")
    if not np.all((w >= 0.0) & (w <= 1.0)):
        raise ValueError("start_weights must lie in [0, 1]")
    return w


def slot_weights(graph: PoseGraph, part, weights) -> np.ndarray:
    """(A, e_max) per incident-edge slot of ``part`` from (m,) per-edge ``weights`` (1 on padding)."""
    index = incident_edge_index(graph.i, graph.j, part.robot_of_pose, part.num_robots, part.max_edges)
    return np.where(index >= 0, np.asarray(weights, np.float64)[np.maximum(index, 0)], 1.0)


def finish(graph: PoseGraph, solver: Solver, run: Prepared, driven, termination: Termination, *, fixed=None,
           frame=None, ground_truth=None) -> SolveResult:
    """The :class:`SolveResult` of a driven run (poses and start in the requested frame)."""
    placement = run.placement
    X = solver.final_poses(run.problem, placement.part, placement.to_host(driven.state.X))
    poses = output_frame(placement.part.gather(unstack(X)), fixed, frame)  # sliced on the host
    outcome, robust_stats = solver.outcome(run.problem, graph, placement.part, driven.state, poses, placement.to_host)
    return SolveResult(
        poses=poses,
        history=driven.history,
        _partition=placement.user_part,
        config=getattr(solver, "config", None),
        result=driven.result,
        stats={**run.clock.stats(driven.compile_seconds, driven.solve_seconds), **placement.stats(), **robust_stats,
               "compile_mode": code_generation(program_slots((run.problem,))), **_start_stats(run)},
        accuracy=None if ground_truth is None else trajectory_accuracy(poses, ground_truth),
        termination=termination,
        start=output_frame(run.start_poses, fixed, frame),
        solver=solver,
        start_weights=run.start_weights,
        **outcome,
    )


def _start_stats(run: Prepared) -> dict:
    """``stats["start_variance_factor"]``: the distributed robust start's maps' variance factor;
    ``stats["distributed_chordal"]``: the distributed chordal start's CG iterations per stage and how
    each stage applied Gamma; ``stats["team_check"]``: what the distributed robust start's team check
    did (the closures it dropped, its rounds, its chordal solves and their CG iterations) (no entry
    for other starts)."""
    info = run.start_info or {}
    stats = {"start_variance_factor": float(info["variance_factor"])} if "variance_factor" in info else {}
    for key in ("distributed_chordal", "team_check"):
        if key in info:
            stats[key] = info[key]
    return stats
