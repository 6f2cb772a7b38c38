"""The one solve path: ``solve(graph, robots, solver=AMM(), start=..., termination=Termination(...),
layout=OneDevice())``, and its front-ends ``solve_sharded`` and ``centralized_optimum``.

Every run — any solver (:mod:`~mmpgo_jax._mm.solvers`), any layout (one device, a sharded mesh) —
is the same three steps: :func:`~mmpgo_jax._solve.build.prepare` (split, start, ``solver.build``,
``solver.init``, placement), :func:`~mmpgo_jax._mm.driver.drive` (compiled chunks until the
budget or a stopping rule) and :func:`~mmpgo_jax._solve.build.finish` (the :class:`SolveResult`).
"""

from __future__ import annotations

import dataclasses
import functools
import os
import time
from collections.abc import Callable, Sequence
from typing import Literal

import jax
import numpy as np

from .._core.gauge import FixedPoses
from .._core.partition import Partition, partition
from .._core.pose_graph import HostPoses, PoseGraph, Poses, connected_subgraph, host_edge_costs
from .._core.precision import float64_enabled
from .._init.start import initialize
from .._mm.centralized import NewtonConfig, newton_optimum
from .._mm.checkpoint import DEFAULT_EVERY
from .._mm.driver import RESULTS, History, Monitor, NonFiniteError, Termination, drive
from .._mm.robust import L2, GNCConfig, RobustLoss, as_loss, robust_objective
from .._mm.solvers import MM, Solver, as_solver
from .._mm.subproblem import SubproblemConfig
from .._robust.release import move_changes, removal_changes
from .build import ROBUST_START, ROBUST_STARTS, Clock, NamedStart, as_termination, finish, prepare
from .devices import auto_layout
from .methods import check_loss, solver_for
from .prefilter import PCM, apply_prefilter
from .result import SolveResult, output_frame

__all__ = ["DISTRIBUTED_ROBUST_START", "RESULTS", "ROBUST_START", "ROBUST_STARTS", "History", "NonFiniteError",
           "SolveResult", "centralized_optimum", "output_frame", "solve", "solve_sharded"]


def solve(
    graph: PoseGraph,
    robots: int | np.ndarray | Partition = 10,
    *,
    solver: Solver | None = None,
    start=None,
    termination: Termination | None = None,
    layout=None,
    method: str | None = None,
    iterations: int | None = None,
    init=None,
    initial: Poses | None = None,
    xi: float | None = None,
    restart: Literal["paper", "adaptive", "average"] | None = None,
    subproblem: SubproblemConfig | None = None,
    chunk_size: int | None = None,
    grad_tol: float | None = None,
    f_target: float | None = None,
    rel_decrease_tol: float | None = None,
    stop_when_stalled: bool | None = None,
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
    prefilter: str | PCM | None = None,
    distributed: bool = False,
    start_weights=None,
    readmit: bool = False,
) -> SolveResult:
    """Run ``solver`` on ``graph`` split among ``robots``, laid out by ``layout``.

    ``solver``: a :class:`~mmpgo_jax.Solver`, e.g. :class:`~mmpgo_jax.AMM` (default),
    :class:`~mmpgo_jax.MM` or ``RBCD(...)``, which owns its settings (xi, restart rule, subproblem);
    the shortcuts ``method``, ``xi``, ``restart``, ``subproblem`` make one (not beside ``solver``).
    ``method``: a name of :data:`~mmpgo_jax._solve.methods.METHOD_NAMES` ("mm", "amm", "rbcd",
    "rbcd++", "rbcd-parallel", "rbcd++-parallel", ..., "dgs"; :func:`~mmpgo_jax._solve.methods.solver_for`);
    ``xi``, ``restart`` and ``subproblem`` apply to "mm" and "amm" only (ValueError with another
    method: its settings are its solver object's). RBCD and DGS minimise the least-squares F only:
    a robust ``loss`` with them is a ValueError naming the method.
    ``termination``: a :class:`~mmpgo_jax.Termination`; the shortcuts ``iterations`` (default 1000),
    ``chunk_size`` (50), ``grad_tol``, ``f_target``, ``rel_decrease_tol``, ``stop_when_stalled`` make
    one (not beside ``termination``). ``layout``: :class:`~mmpgo_jax.OneDevice` or
    :class:`~mmpgo_jax.sharding.Sharded` (robots over a device mesh; :func:`solve_sharded`); by
    default one device, or, when the process has several CPU devices (:func:`~mmpgo_jax.use_cpu_cores`)
    and the graph has 1000 poses or more, the robots split over them, as ``mmpgo solve`` does. The
    result has the same fields either way. ``start`` (alias ``init``): the start, see below.

    ``robots``: a count (contiguous blocks, as in the paper), an (n,) robot-of-pose array, or a
    prepared :class:`Partition`. ``start``: see :func:`mmpgo_jax.initialize` (default ``"chordal"``,
    the paper's start; for a robust loss :data:`ROBUST_STARTS`, below), or a :class:`~mmpgo_jax.NamedStart`:
    a start by name with options of its own (``NamedStart("distributed-robust", {"team_check": True})``:
    the distributed robust start's accepted closures checked at the team's chordal map,
    :func:`~mmpgo_jax._init.robust_distributed.distributed_robust_initialization`); ``initial`` holds the file's
    VERTEX estimates for ``init="vertices"``. A sequence of starts runs the whole solve from each and
    returns the run of lowest final objective (f, or for a robust loss 2 F_rho recomputed at each
    run's poses); ``stats["starts"]`` lists each start's f, iterations, rejected edges and seconds
    and which was kept (the other stats are the kept run's); ``callback`` and ``monitor`` see each
    run in turn (k counts from 0 again). Not with ``checkpoint`` / ``resume``.
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
    kernel runs by default from both :data:`ROBUST_STARTS`, ``"gnc-chordal"`` (GNC-TLS with chordal +
    Newton stages of the whole graph, at the loss's scale) and ``"distributed-robust"`` (each robot's
    own GNC, then the robots' frames from their inter-robot closures), and keeps the lower robust
    objective: each start wins on other graphs (benchmarks/robust_distributed_files_findings.md);
    a run from the distributed robust start that overrules it is revisited, closures it doubted
    are re-admitted and accepted closures that strain their robots' maps are left out while the
    objective falls (docs/conventions.md §10; ``stats["starts"][k]``'s ``revisits``, ``readmissions``
    and ``removals``); one start when given, with one robot, with ``start_weights``,
    ``checkpoint`` or ``resume`` (then ``"gnc-chordal"``). ``gnc``: a :class:`~mmpgo_jax.GNCConfig`
    (tls, geman-mcclure) runs GNC stages in the distributed solver instead, from the chordal start.
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

    ``prefilter``: ``"pcm"`` or a :class:`~mmpgo_jax.PCM` removes the inter-robot loop closures that
    PCM finds inconsistent before the start and the solve (:mod:`~mmpgo_jax._solve.prefilter`); f,
    the history and ``partition`` are then those of the graph without them, ``result.prefiltered``
    (m,) marks them, ``result.inliers`` marks them False (for least squares too, where it is then
    ``~prefiltered``), ``result.weights`` holds 0 for them and ``stats["pcm_rejected"]`` counts them.

    ``distributed=True``: refuse every step that gathers the whole graph in one place (the starts
    "chordal", "gnc-chordal" and "odometry": ValueError naming it); the start is by default
    "distributed-chordal" (§VII's stages, distributed) for least squares and, for a robust loss,
    :data:`DISTRIBUTED_ROBUST_START`: the distributed robust start (each robot's own GNC, then the
    robots' frames from their inter-robot closures) with its accepted inter-robot closures checked at
    the team's distributed chordal map (:mod:`~mmpgo_jax._init.closure_check`; without the check, on
    long noisy robot chains, the wrong closures the frame test passes wreck the team's map:
    benchmarks/robust_teams.md); ``start="distributed-robust"`` is that start without the check. PCM
    is a per-robot-pair test and stays allowed.

    ``start_weights``: (m,) robust weights in [0, 1], in the graph's edge order, that the robust run
    holds as its first stage (the weighted least squares of that classification, until the weighted
    objective stalls by :class:`~mmpgo_jax.GNCConfig`'s stage rule), before the kernel's own
    weights take over (:func:`~mmpgo_jax._mm.robust.next_weights`). A robust run from
    ``start="distributed-robust"`` takes that start's classification by default: its maps are
    rigid, so correct inter-robot closures start with residuals far above c^2 and TLS weights
    rho'(s) at the start would drop them all. Refused beside least squares.

    ``readmit=True`` (a robust loss; not with ``distributed=True``): after the run, the loop closures
    it rejected (PCM's removals included) are re-admitted one at a time while the optimum of the kept
    edges has a lower robust objective (:func:`~mmpgo_jax.readmit_loop_closures`: one centralized
    Newton solve per rejected closure per round; for tens to hundreds of rejected closures, e.g.
    robot teams after ``prefilter="pcm"``), then a run from that optimum on the whole graph is
    returned when its objective is lower; ``stats["readmission"]`` says what was re-admitted.

    Raises :class:`NonFiniteError` when f or its gradient stops being finite (data whose weights or
    residuals float arithmetic cannot represent). Numbers are checked (ValueError naming the
    parameter). A second call with the same shapes and configuration structure does not compile
    again (:func:`~mmpgo_jax._mm.driver.compile_once`).
    """
    if init is not None and start is not None:
        raise ValueError("give start= (or its older name init=), not both")
    start = start if init is None else init
    if distributed:
        start, gnc = _distributed_defaults(start, loss, gnc)
        if readmit:
            raise ValueError("distributed=True: readmit=True re-solves the kept edges with Newton of the whole "
                             "graph in one place")
    full_graph, full_robots = graph, robots
    pre = apply_prefilter(graph, robots, prefilter)
    if pre is not None:  # the solve runs on the kept edges; report() restores the original edge order
        graph, robots = pre.graph, pre.robot_of_pose
    if solver is not None or method is None:
        solver = as_solver(solver, method=method, xi=xi, restart=restart, subproblem=subproblem)
    else:  # by name: MM / AMM exactly as as_solver makes them, the other methods from the registry
        solver = solver_for(method, xi=xi, restart=restart, subproblem=subproblem)
    loss = as_loss(loss, loss_scale, gnc)
    check_loss(solver, loss)
    if readmit and (loss is None or int(np.asarray(loss.kernel)) == L2):
        raise ValueError("readmit=True re-admits loop closures a robust loss rejected: give a robust loss "
                         "(e.g. loss='tls')")
    if readmit and (checkpoint is not None or resume is not None):
        raise ValueError("readmit=True may run a second solve: not with checkpoint= / resume=")
    termination = as_termination(termination, iterations=iterations, chunk_size=chunk_size, grad_tol=grad_tol,
                                 f_target=f_target, rel_decrease_tol=rel_decrease_tol,
                                 stop_when_stalled=stop_when_stalled)
    monitor = monitor or Monitor()
    if layout is None:
        layout = auto_layout(graph.num_poses, _robot_count(robots))
    if pre is not None and start_weights is not None and np.shape(start_weights) == pre.rejected.shape:
        start_weights = np.asarray(start_weights)[~pre.rejected]  # the given weights of the kept edges

    def run_from(begin, monitor: Monitor = monitor, on=None, weights=None) -> SolveResult:
        # on: (graph, robots) of a run on the given graph after a prefilter (re-admission), from poses;
        # weights: start weights held first in place of the solve's (a re-admission trial)
        g, rb = (graph, robots) if on is None else on
        weights = weights if weights is not None else (start_weights if on is None else None)
        run = prepare(g, solver, rb, layout, termination, start=begin,
                      initial=initial, fixed=fixed, loss=loss, monitor=monitor,
                      checkpoint=checkpoint, checkpoint_every=checkpoint_every, resume=resume,
                      start_weights=weights)
        placement = run.placement
        out = drive(placement.compile_chunk(solver, run.problem), run.state, placement.start_record(run.start),
                    termination, fetch=placement.fetch, callback=callback, agree=placement.agree, monitor=monitor,
                    checkpoint=run.saver, history=None if run.snapshot is None else run.snapshot.history)
        return finish(g, solver, run, out, termination, fixed=fixed, frame=frame, ground_truth=ground_truth)

    starts = _starts(start, loss, robots, start_weights=start_weights, checkpoint=checkpoint, resume=resume)
    finish_kept = _kept_edges_finish(loss, distributed, len(starts), robots, fixed)
    # the default's distributed robust row, finished and searched as distributed=True, ends where its last
    # run's budget ran out (teams at 50 % wrong closures, every edge right: 1e-4 to 1e-2 from the
    # outlier-free optimum on maps ~20 across); so it goes on once from the optimum of the edges it keeps,
    # kept where that lowers F_rho, as the GNC start's row ends at an optimum
    polish = functools.partial(_kept_edges_optimum, fixed=fixed) if finish_kept is not None and not distributed \
        else None
    revisit = _revisits(loss, start_weights, checkpoint, resume)
    if len(starts) == 1 and finish_kept is None and not (revisit and _start_name(starts[0]) == "distributed-robust"):
        result = run_from(starts[0])
    else:
        result = _best_of(starts, run_from, graph, monitor, finish_kept, revisit, polish)
    result = result if pre is None else pre.report(result)
    if readmit:
        again = functools.partial(run_from, monitor=_FromStart(monitor, "after re-admission"),
                                  on=(full_graph, full_robots))
        result = _readmitted(full_graph, result, again, fixed)
    return result


def _readmitted(graph: PoseGraph, result: SolveResult, run_from: Callable, fixed) -> SolveResult:
    """``readmit=True``: the rejected loop closures re-admitted greedily while that lowers the robust
    objective (:func:`~mmpgo_jax._robust.readmit.readmit_loop_closures`), then a run from the
    optimum of the edges kept, returned when its objective is lower. ``stats["readmission"]``: the
    edges re-admitted (graph order), f before and after the search, the Newton solves, seconds and
    whether the second run was kept (it then carries the first run's ``pcm_*`` stats)."""
    from .._robust.readmit import readmit_loop_closures

    t = time.perf_counter()
    found = readmit_loop_closures(graph, result.inliers, result.poses, result.loss, fixed=fixed)
    info = dict(readmitted=found.readmitted.tolist(), f_before=found.f_before, f_after=found.f,
                solves=found.solves, kept=False)
    if found.readmitted.size:
        again = run_from(Poses(found.poses.R, found.poses.t))
        if _objective(again, graph) < _objective(result, graph):
            # what a prefilter removed stays reported (its removals may have been re-admitted since)
            again.stats.update({k: v for k, v in result.stats.items() if k.startswith("pcm_")})
            result, info["kept"] = again, True
    info["seconds"] = time.perf_counter() - t
    result.stats["readmission"] = info
    return result


def _revisits(loss, start_weights, checkpoint, resume) -> bool:
    """Whether a run from the distributed robust start that overrules it is revisited
    (:func:`_revisited`): robust losses, the start's own weights, one run per checkpoint."""
    robust = loss is not None and int(np.asarray(loss.kernel)) != L2
    return robust and start_weights is None and checkpoint is None and resume is None


def _objective(run: SolveResult, graph: PoseGraph) -> float:
    return run.f if run.loss is None else robust_objective(run.loss, graph, run.poses)


def _kept_edges_finish(loss, distributed: bool, start_count: int, robots, fixed) -> Callable | None:
    """``finish_for(start name)``: how a robust run from that start that used its whole iteration
    budget is finished (:func:`_best_of`), or None: from the distributed chordal start of the edges
    it keeps in every ``distributed=True`` run and for the distributed robust start's runs of the
    default (so that the default's run and search from that start are those of the fully distributed
    pipeline, with the other starts' runs as evidence in its revisits), at the optimum of those
    edges (centralized Newton) for the other starts of a run from several starts; None otherwise.
    The optimum is no finish for a search: a TLS run from the optimum of its own kept edges stays
    there (10 x 500-pose team at 50 % wrong inter-robot closures, seed 3, benchmarks/robust_teams.md:
    f = 846.3 from the optimum, whether Newton started from the run's poses or from the chordal start
    of those edges; 570.7 from their distributed chordal start, whose rougher poses let TLS's weights
    sort the closures again, and 556.4, the outlier-free classification, after its search)."""
    if loss is None or int(np.asarray(loss.kernel)) == L2:
        return None
    chordal = functools.partial(_kept_edges_chordal, robots=robots, fixed=fixed)
    if distributed:
        return lambda name: chordal
    if start_count < 2:
        return None
    optimum = functools.partial(_kept_edges_optimum, fixed=fixed)
    return lambda name: chordal if name == "distributed-robust" else optimum


def _kept_edges_optimum(graph: PoseGraph, run: SolveResult, fixed=None) -> tuple[Poses, dict] | None:
    """The optimum of the edges a robust run keeps, by centralized Newton from its poses: what the
    GNC-chordal start ends with, for a run whose iterations had not converged (a distributed robust
    start's rigid maps take thousands of iterations to bend into the optimum)."""
    kept = connected_subgraph(graph, run.inliers)
    if kept is None:
        return None
    return centralized_optimum(kept, init=run.poses, fixed=fixed, frame="raw").poses, dict(by="optimum")


def _kept_edges_chordal(graph: PoseGraph, run: SolveResult, robots, fixed=None) -> tuple[Poses, dict] | None:
    """The distributed chordal start (neighbour exchanges only) of the edges a robust run keeps, and
    its CG iterations per stage: the distributed counterpart of :func:`_kept_edges_optimum`. A
    distributed robust run starts from rigid robot maps, whose bending into the optimum is the slow
    part of AMM's iterations (M3500 with 50 % wrong inter-robot closures, every outlier rejected:
    1.5 % of the map's extent from the optimum after 1000 iterations, 0.46 % after a second run from
    this start; least squares without the outliers from the chordal start: 0.45 %)."""
    from .._init.distributed_chordal import distributed_chordal_initialization

    kept = connected_subgraph(graph, run.inliers)
    if kept is None:
        return None
    poses, info = distributed_chordal_initialization(kept, robots, fixed=fixed)
    return poses, dict(by="distributed-chordal", rotation_iterations=int(info.rotation_iterations),
                       translation_iterations=int(info.translation_iterations))


class _FromStart(Monitor):
    """``monitor`` for one of several runs: the phases before the iterations carry the start's label
    ("initializing, start 1 of 2, gnc-chordal")."""

    def __init__(self, inner: Monitor, label: str):
        self.inner, self.label = inner, label

    def phase(self, name: str) -> None:
        self.inner.phase(name if name in ("iterating", "finishing") else f"{name}, {self.label}")

    def chunk(self, done: int, f: np.ndarray, grad_norm: np.ndarray) -> None:
        self.inner.chunk(done, f, grad_norm)

    def note(self, text: str) -> None:
        self.inner.note(text)


def _starts(start, loss: RobustLoss | None, robots, *, start_weights, checkpoint, resume) -> tuple:
    """The starts a run goes from: ``start`` (one, or a sequence of them), or by default for a robust
    loss (without GNC in the solver, given weights, a checkpoint or a resume, and with two robots or
    more) :data:`ROBUST_STARTS`; None: the solver's default start."""
    if isinstance(start, (tuple, list)):
        if not start:
            raise ValueError("start: an empty sequence of starts")
        if len(start) > 1 and (checkpoint is not None or resume is not None):
            raise ValueError("checkpoint= / resume= run from one start: give one start, not a sequence")
        return tuple(start)
    robust = loss is not None and int(np.asarray(loss.kernel)) != L2 and not bool(np.asarray(loss.use_gnc))
    if (start is None and robust and start_weights is None and checkpoint is None and resume is None
            and _robot_count(robots) > 1):
        return ROBUST_STARTS
    return (start,)


def _best_of(starts: tuple, run_from: Callable, graph: PoseGraph, monitor: Monitor,
             finish: Callable | None = None, revisit: bool = False, polish: Callable | None = None) -> SolveResult:
    """Run from each start and keep the run whose final objective is lowest (f, or for a robust loss
    2 F_rho recomputed at the final poses on the host, so that each run is judged by the same
    number: a sum over the edges). ``finish(start name)``: how a run from that start that used its
    whole iteration budget (not 0: that asks for the start alone) is finished, a start from the edges
    it keeps (:func:`_kept_edges_finish`; or None), from which a second run goes on; kept when its
    objective is lower. ``revisit``: a run from the distributed robust start that rejected closures
    the start had accepted goes on from that start without them (:func:`_revisited`). ``polish(graph,
    run)``: a start from the edges a run keeps, from which a last run goes on after a distributed
    robust start's search when that search's run used its budget, kept when its objective is lower
    (``polished``: the f before; the default: the optimum of the kept edges).
    ``stats["starts"]``: per start its name, f, iterations (of every run from it: a second run's and
    the revisits' added), rejected edges, seconds (and those of the start itself,
    ``start_seconds``), whether its run held given weights first (``held``), whether a second run
    went on (``finished_by``: how its start was made, with the distributed chordal start's CG
    iterations) and was kept (``finished``: the f before), the revisits (``revisits``: per round
    the edge left out, f, iterations, kept), the re-admissions (``readmissions``,
    :func:`_readmitted_to_start`) and the removals (``removals``, :func:`_removed_from_run`); the kept
    run's own timings stay its own."""
    runs, firsts, rows = [], [], []
    for k, begin in enumerate(starts):
        name = _start_name(begin)
        label = f"start {k + 1} of {len(starts)}, {name}"
        t = time.perf_counter()
        first, run, f, iterations, before, finished_by = _run_finished(begin, label, run_from, graph, monitor,
                                                                       _finish_for(finish, name))
        rejected = None if run.inliers is None else int((~np.asarray(run.inliers, bool)).sum())
        rows.append(dict(start=name, f=f, iterations=iterations, rejected=rejected, finished=before,
                         finished_by=finished_by, held=bool(first.stats.get("start_weights_given", False)),
                         start_seconds=float(first.stats.get("initialize_seconds", 0.0)),
                         team_check=first.stats.get("team_check"), revisits=[],
                         readmissions=[], removals=[], exchanges=[], seconds=time.perf_counter() - t))
        runs.append(run)
        firsts.append(first)
    for k, row in enumerate(rows):  # after every start ran: the other starts' runs are evidence too
        label = f"start {k + 1} of {len(starts)}, {row['start']}"
        if revisit and row["start"] == "distributed-robust" and firsts[k].iterations > 0:  # 0: the start alone
            t = time.perf_counter()
            others = [run.inliers for j, run in enumerate(runs) if j != k]
            row_finish = _finish_for(finish, row["start"])
            options = starts[k].options if isinstance(starts[k], NamedStart) else {}
            runs[k], row["f"], row["revisits"], first = _revisited(
                firsts[k], runs[k], row["f"], others, label, run_from, graph, monitor, row_finish, options)
            exchanges = _ExchangeMemory()  # each move tried once in this search
            while True:  # a closure left out may let a rejected one back in: again until none is left out
                runs[k], row["f"], rounds = _readmitted_to_start(first, runs[k], row["f"], label, run_from, graph,
                                                                 monitor, row_finish)
                row["readmissions"] += rounds
                runs[k], row["f"], rounds = _removed_from_run(first, runs[k], row["f"], label, run_from, graph,
                                                              monitor, row_finish)
                row["removals"] += rounds
                if any(r["kept"] for r in rounds):
                    continue
                runs[k], row["f"], rounds = _exchanged_in_run(first, runs[k], row["f"], label, run_from, graph,
                                                              monitor, row_finish, exchanges)
                row["exchanges"] += rounds
                if not any(r["kept"] for r in rounds):
                    break
            rounds = (*row["revisits"], *row["readmissions"], *row["removals"], *row["exchanges"])
            row["iterations"] += sum(r["iterations"] for r in rounds)
            row["polished"] = None
            if polish is not None and runs[k].result is RESULTS.iterations:
                runs[k], row["f"], row["polished"], iterations, _ = _went_on(
                    runs[k], row["f"], polish, f"{label}, at its kept edges' optimum", run_from, graph, monitor)
                row["iterations"] += iterations
            row["rejected"] = int((~np.asarray(runs[k].inliers, bool)).sum())
            row["seconds"] += time.perf_counter() - t
    best = int(np.argmin([row["f"] for row in rows]))  # the first of equal ones
    for k, row in enumerate(rows):
        row["kept"] = k == best
    runs[best].stats["starts"] = rows
    return runs[best]


def _went_on(run: SolveResult, f: float, make_start: Callable, label: str, run_from: Callable, graph: PoseGraph,
             monitor: Monitor) -> tuple[SolveResult, float, float | None, int, dict | None]:
    """(run, f, f before or None, iterations, how the start was made or None): a run from the start
    ``make_start(graph, run)`` makes of ``run``'s kept edges (None: nothing goes on), kept when its
    robust objective is lower (a finish, :func:`_run_finished`, or the default's last run from the
    kept edges' optimum after a distributed robust start's search, :func:`_best_of`)."""
    made = make_start(graph, run)
    if made is None:
        return run, f, None, 0, None
    begin, made_by = made
    again = run_from(begin, _FromStart(monitor, label))
    f_again = _objective(again, graph)
    if f_again < f:
        return again, f_again, f, again.iterations, made_by
    return run, f, None, again.iterations, made_by


def _finish_for(finish_for: Callable | None, name: str) -> Callable | None:
    return None if finish_for is None else finish_for(name)


def _start_name(begin) -> str:
    if isinstance(begin, NamedStart):
        return begin.name
    return begin if isinstance(begin, str) else type(begin).__name__


def _run_finished(begin, label: str, run_from: Callable, graph: PoseGraph, monitor: Monitor,
                  finish: Callable | None, keeps=None, weights: np.ndarray | None = None) -> tuple:
    """(first run, kept run, f, iterations, f before the finish or None, how it was finished or None):
    a run from ``begin`` and, when it used its budget, the second run from its kept edges (kept when
    lower, :func:`_best_of`). ``keeps``: an edge (or a list of edges) the run is made to try (a
    re-admission, an exchange); a run that rejected one again is not finished (the kept edges are
    those the trial was to change).
    ``weights``: start weights the first run holds (the second run's come from its own start)."""
    first = run = run_from(begin, _FromStart(monitor, label), weights=weights)
    f, before, iterations, finished_by = _objective(run, graph), None, run.iterations, None
    tried = keeps is None or run.inliers is None or bool(np.all(run.inliers[keeps]))
    if finish is not None and tried and run.result is RESULTS.iterations and run.iterations > 0:
        run, f, before, more, finished_by = _went_on(run, f, finish, f"{label}, finished from its kept edges",
                                                     run_from, graph, monitor)
        iterations += more
    return first, run, f, iterations, before, finished_by


def _overruled(start_weights, run: SolveResult, others=()) -> np.ndarray:
    """(m,) bool: edges the start accepted (``start_weights``, held at 1) and the run rejected, or
    any of ``others`` (the inliers of the runs from the other starts) did."""
    if start_weights is None:
        return np.zeros(0 if run.inliers is None else len(run.inliers), bool)
    accepted = np.asarray(start_weights) > 0.5
    rejected = np.zeros_like(accepted)
    for inliers in (run.inliers, *others):
        if inliers is not None:
            rejected |= ~np.asarray(inliers, bool)
    return accepted & rejected


def _revisited(first: SolveResult, run: SolveResult, f: float, others: list, label: str, run_from: Callable,
               graph: PoseGraph, monitor: Monitor, finish: Callable | None, options=None) -> tuple:
    """A robust run that rejected edges its distributed robust start had accepted says the start was
    wrong: an outlier its frame search accepted holds the maps bent while it is held, and the run
    then rejects it *and* correct closures near it. So the start is made again without the overruled
    edge of largest residual at the run's result (the outlier, where one bends the map: its residual
    is orders of magnitude above the collateral ones), and a run (finished as the first) goes on from
    it, kept when its robust objective is lower; repeated while it is and the run overrules the start.
    With several starts, an edge the other starts' runs (``others``: their inliers) rejected counts as
    overruled too (the GNC-chordal start's run, on 10 x 500-pose teams at 50 % wrong inter-robot
    closures: the distributed start's run kept the outlier it accepted, the GNC run rejected it, and
    the start without it led to the outlier-free optimum).
    Even one overruled edge is worth it: the map it bent while held converges more slowly (M3500, 50 %
    wrong inter-robot closures, seed 2: ATE 0.46 % -> 0.21 % of the extent, same classification).
    Measured on 10 x 500-pose teams (benchmarks/robust_teams.md) and files
    (benchmarks/robust_distributed_files.md). ``first``: the first run from the start (its
    ``start_weights``: the start's classification). Returns (run, f, rounds, the first run from the
    kept run's start). ``options``: the start's own (a :class:`NamedStart`'s), kept by the starts made again."""
    excluded = np.zeros(graph.num_edges, bool)
    rounds = []
    while True:
        over = _overruled(first.start_weights, run, others) & ~excluded
        if not over.any():
            break
        residual = host_edge_costs(graph, run.poses)
        edge = int(np.flatnonzero(over)[np.argmax(residual[over])])
        excluded[edge] = True
        begin = NamedStart("distributed-robust", {**(options or {}), "excluded": excluded.copy()})
        again_label = f"{label}, without {int(excluded.sum())} overruled"
        first_again, again, f_again, iterations, _, _ = _run_finished(begin, again_label, run_from, graph, monitor,
                                                                      finish)
        kept = f_again < f
        rounds.append(dict(excluded=edge, f=f_again, iterations=iterations, kept=kept))
        if not kept:
            break
        run, f, first = again, f_again, first_again
    return run, f, rounds, first


def _readmitted_to_start(first: SolveResult, run: SolveResult, f: float, label: str, run_from: Callable,
                         graph: PoseGraph, monitor: Monitor,
                         finish: Callable | None) -> tuple[SolveResult, float, list]:
    """The converse of :func:`_revisited`: an inter-robot loop closure the run rejected may be correct,
    whether the distributed robust start rejected it too or accepted it. The frame test sees the robots' maps as
    rigid, with their drift only as a variance, and a correct closure far along two long chains can
    fail it (MIT without outliers: robots 0 and 3's only closure, 0.8 rad off at the maps' frames,
    cost 0.10 at the optimum; the run without it ends 11 % above the optimum with its residual at
    52 c^2, where no weight update of TLS takes it back). So a run goes on from the run's own result
    with its classification held first and that closure accepted, kept when its robust objective
    (every edge: the number the runs are compared by) is lower by more than (1 - v) c^2, v the maps'
    variance factor (``first.stats["start_variance_factor"]``, at most 1): the closure's cost judged
    at the noise level the robots' own edges show, not the one their information matrices claim
    (M3500's overstate it ~30x, v = 0.036: wrong closures lowered f by less than 0.1 % of c^2 and
    were admitted without the margin; MIT's v = 1). The trial goes on from the run's result, not
    from a start made again with the closure accepted: the result's maps are already bent by every
    other closure, so the trial moves only what that closure moves (10 x 500-pose team, seed 3, 50 %
    wrong inter-robot closures: a remade start led to f = 600.5 against the run's 570.7, the run's
    result with the closure held to 564.8, in 11 s against 25 s; MIT: 4.4 s, the same optimum).
    Candidates: the inter-robot closures the run rejected (not the consecutive-pose edges between
    robots, which the start trusts), also those the start accepted (the run overruled it; until
    2026-12-06 only those the start rejected too: on a 10 x 500-pose team with the Cube's noise, 13
    wrong inter-robot closures, seed 1, benchmarks/robust_teams.md, the run rejected a correct closure
    its start accepted, the revisit without it was not kept, and a run from the result with it
    accepted lowers F_rho from 356.3 to 352.7; it is the rejected closure of smallest residual there,
    6063 c^2 against 25085 c^2 and more for the wrong ones), whatever the other starts' runs did (until
    2026-12-06 only those another start's run accepted: the 10 x 500-pose team of seed 3 at 30 %
    wrong closures then missed its correct closure, which the GNC start's run rejected too; dropping
    that rule changed no file's result, measured on MIT, intel, M3500, city10000 and kitti_00 at
    10-70 %, one more trial, not kept, on about half of them). In batches by residual at the current
    run's result, smallest first: a round admits the ``size`` cheapest open closures at once (its run
    finished as the first, unless it rejected one of them again: then the round is not kept), kept when
    its run keeps every one and f falls by more than the margin per closure; ``size`` starts at 1,
    doubles after a kept round and halves after one not kept, and the search ends at a round of one
    closure that is not kept. A search that admits many closures takes fewer rounds (the 15 000-pose
    long-chain graph with 73 wrong inter-robot closures, distributed: 15 rounds of about a minute, 29
    closures admitted, against 27 rounds and 26 closures one at a time until 2026-12-07), and one whose
    first candidate is wrong ends after the same single round as before. A batch holding a wrong
    closure fails as a whole (TLS rejects it, or f does not fall enough), and the halving then admits
    the correct ones before it; each failed batch is a round more than one closure at a time would
    take there (the doubling after a kept round can reach the wrong closure again: 8 of the 15 rounds
    above were not kept). The run's result, which every edge shaped,
    ranks them better than the frame test's rigid maps: MIT with 10 %
    wrong loop closures (seed 1) has a wrong closure at 3.7 c^2 of the frame test and the correct one
    at 3.8 c^2, at the result 2905 c^2 against 52 c^2; on MIT at 50 % the correct one is again first
    by residual (52 against 217-8359 c^2) and third by frame cost. A correct closure can fail the
    frame test by far (10 x 500-pose team, seed 3, 10 % and 30 % wrong closures: 14.3 c^2 there, 2789
    c^2 at the result, the wrong ones from 8307 c^2), so no bound of the frame test limits the
    candidates (until 2026-12-05 those within chi^2_p(1 - 1e-6) only: that team's correct closure
    was never tried). Stopping at the first round of one closure not kept bounds the cost (city10000
    at 10 %: 23 candidates within that bound, none kept, 6 s each). Returns (run, f, rounds: per round
    the edges admitted (a list, cheapest first), f before and after, iterations, kept, seconds)."""
    margin = _admission_margin(first, run)
    if first.start_weights is None:
        return run, f, []
    doubted = np.flatnonzero(_inter_robot_closures(run, graph))  # those the run rejects are open
    rounds, size = [], 1
    while run.inliers is not None:  # a kept round accepted its closures, so they are not open again
        open_ = doubted[~np.asarray(run.inliers, bool)[doubted]]
        if not len(open_):
            break
        residual = host_edge_costs(graph, run.poses)
        batch = [int(e) for e in open_[np.argsort(residual[open_], kind="stable")[:size]]]
        again, f_again, iterations, seconds = _trial(
            run, batch, 1.0, f"{label}, {len(batch)} rejected closure(s) admitted", run_from, graph, monitor,
            finish, keeps=batch)
        # a trial that rejected a closure again is not kept even where its f is lower: the run it went
        # on from had used its budget, and more iterations lower f without admitting anything
        kept = bool(np.all(again.inliers[batch])) and f_again < f - margin * len(batch)
        rounds.append(dict(admitted=batch, f_before=f, f=f_again, iterations=iterations, kept=kept, seconds=seconds))
        if kept:
            run, f, size = again, f_again, 2 * len(batch)
        elif len(batch) > 1:
            size = len(batch) // 2
        else:
            break
    return run, f, rounds


def _admission_margin(first: SolveResult, run: SolveResult) -> float:
    """How much a trial that admits a closure must lower 2 F_rho to be kept: (1 - v) c^2, v the
    maps' variance factor at the start (at most 1; :func:`_readmitted_to_start`)."""
    factor = min(float(first.stats.get("start_variance_factor", 1.0)), 1.0)
    return 0.0 if factor == 1.0 else (1.0 - factor) * float(np.asarray(run.loss.scale)) ** 2


def _trial(run: SolveResult, edge, weight, label: str, run_from: Callable, graph: PoseGraph,
           monitor: Monitor, finish: Callable | None, keeps=None) -> tuple:
    """One round of the re-admissions, removals or exchanges: a run (finished as the first) from
    ``run``'s result holding its classification with the weight of ``edge`` (an index, or a list of
    them) set to ``weight`` (one value, or one per edge). Returns (the run, its objective,
    iterations, seconds)."""
    weights = np.asarray(run.inliers, np.float64)
    weights[np.atleast_1d(edge)] = weight
    t = time.perf_counter()
    _, again, f_again, iterations, _, _ = _run_finished(run.poses, label, run_from, graph, monitor, finish,
                                                        keeps=keeps, weights=weights)
    return again, f_again, iterations, time.perf_counter() - t


def _loop_closures(graph: PoseGraph) -> np.ndarray:
    """(m,) bool: the edges not between consecutive poses (those the distributed robust start trusts
    as odometry)."""
    return np.abs(np.asarray(graph.i) - np.asarray(graph.j)) != 1


def _inter_robot_closures(run: SolveResult, graph: PoseGraph) -> np.ndarray:
    """(m,) bool: the loop closures (:func:`_loop_closures`) between two robots of ``run``'s split."""
    robot = np.asarray(run.partition.robot_of_pose)
    return (robot[np.asarray(graph.i)] != robot[np.asarray(graph.j)]) & _loop_closures(graph)


def _closures_their_pair_cannot_outvote(run: SolveResult, graph: PoseGraph) -> np.ndarray:
    """(m,) bool: the inter-robot loop closures ``run`` accepted (not the trusted consecutive-pose
    edges) whose robot pair holds at most two accepted closures: a pair of three or more outvotes a
    wrong one of them (its residual at the pair's frame stays large, and TLS drops it), one of one or
    two it cannot (one closure alone, or two that disagree without telling which is wrong)."""
    robot = np.asarray(run.partition.robot_of_pose)
    a, b = robot[np.asarray(graph.i)], robot[np.asarray(graph.j)]
    accepted = np.asarray(run.inliers, bool) & _inter_robot_closures(run, graph)
    count = int(robot.max()) + 1
    pair = np.minimum(a, b) * count + np.maximum(a, b)
    held = np.bincount(pair[accepted], minlength=count * count)
    return accepted & (held[pair] <= 2)


def _removed_from_run(first: SolveResult, run: SolveResult, f: float, label: str, run_from: Callable,
                      graph: PoseGraph, monitor: Monitor, finish: Callable | None) -> tuple[SolveResult, float, list]:
    """An inter-robot loop closure the start accepted wrongly may fit the run's result (it bent the
    maps to itself), so neither the run nor :func:`_revisited` nor :func:`_readmitted_to_start` ever
    looks at it. What it leaves is strain in its robots' other edges (MIT with 50 % wrong
    inter-robot closures, seed 1: robot 8's only accepted closure is wrong, cost 0.05 c^2 at the
    result; robot 8's odometry costs 19.5 there against 2.2 at the outlier-free classification's
    result). Candidates: the accepted closures their own robot pair cannot outvote
    (:func:`_closures_their_pair_cannot_outvote`); per candidate the change of the objective its removal is
    predicted to bring, its two robots' maps re-optimized with and without it, the neighbours held
    (:func:`~mmpgo_jax._robust.release.removal_changes`). Until 2026-12-06 the prediction was the
    robots' strain shared among the closures touching them, which on a 10 x 500-pose team with the
    Cube's noise (seed 1, 13 wrong inter-robot closures; benchmarks/robust_teams.md) left the one
    wrong closure the run kept untried: its robots' share 3.58 against c^2 less its cost, 11.0, while
    its predicted change is -6.4 and every correct one's of its kind above +6 (the wrong one first).
    One per round, the most negative prediction first: a run goes on from the result with the run's
    classification held and that closure rejected, kept when its robust objective is lower (MIT 50 %:
    346.6 -> 322.1, the outlier-free classification), until a round is not kept or no prediction is
    negative. Each closure is tried once. Returns (run, f, rounds: per round the edge removed, its
    predicted change, f before and after, iterations, kept, seconds)."""
    if run.inliers is None or first.start_weights is None:
        return run, f, []
    c2 = float(np.asarray(run.loss.scale)) ** 2
    tried = np.zeros(graph.num_edges, bool)
    rounds = []
    while True:
        candidates = np.flatnonzero(_closures_their_pair_cannot_outvote(run, graph) & ~tried)
        if not candidates.size:
            break
        change = removal_changes(graph, run.partition.robot_of_pose, run.poses, run.inliers, candidates, c2)
        if not (change < 0).any():
            break
        edge = int(candidates[np.argmin(change)])
        tried[edge] = True
        again, f_again, iterations, seconds = _trial(run, edge, 0.0, f"{label}, {len(rounds) + 1} accepted closure(s) "
                                                     "left out", run_from, graph, monitor, finish)
        kept = f_again < f
        rounds.append(dict(removed=edge, predicted=float(change.min()), f_before=f, f=f_again, iterations=iterations,
                           kept=kept, seconds=seconds))
        if not kept:
            break
        run, f = again, f_again
    return run, f, rounds


@dataclasses.dataclass
class _ExchangeMemory:
    """What the exchange rounds of one search carry from call to call (:func:`_exchanged_in_run`):
    the moves tried, each move's last predicting solve (``move_changes``'s ``warm``), and the
    closures a kept exchange left out."""

    tried: set = dataclasses.field(default_factory=set)
    warm: dict = dataclasses.field(default_factory=dict)
    left: set = dataclasses.field(default_factory=set)


def _exchanged_in_run(first: SolveResult, run: SolveResult, f: float, label: str, run_from: Callable,
                      graph: PoseGraph, monitor: Monitor, finish: Callable | None,
                      memory: _ExchangeMemory | None = None) -> tuple[SolveResult, float, list]:
    """What the re-admissions and removals cannot do one closure at a time: a wrong closure that bent
    its robots' maps keeps a correct one out, and neither leaving out the wrong one (the correct one
    does not fit yet) nor admitting the correct one (the wrong one holds the maps away) lowers the
    objective alone. Candidates: the loop closures the start accepted and the run rejected
    (:func:`_overruled`: the two pieces of evidence disagree), each admitted alone or exchanged with an
    accepted inter-robot closure of one of its robots whose pair cannot outvote it
    (:func:`_closures_their_pair_cannot_outvote`). Intra-robot closures too: a run that rejected one
    early can fold its robot's map away from it, beyond any weight update of TLS (the same team: a
    closure of robot 1 at 1.1e4 c^2 at the result, 1.4e-4 c^2 at the outlier-free optimum, its
    admission predicted at -9.3). Each move's change of the objective is predicted
    with the robots it touches re-optimized, the other robots held
    (:func:`~mmpgo_jax._robust.release.move_changes`); a whole run moves those too and can only
    release more, so a move predicted below c^2 (less than one closure's share of the objective) is
    worth a trial: on a 10 x 500-pose team with the Cube's noise (seed 2, 13 wrong inter-robot
    closures; benchmarks/robust_teams.md) the exchange the outlier-free classification needs is
    predicted at +0.27 with its three robots free and -0.79 with their neighbours free too, the wrong
    closures' moves at +36.8 or more. Per round, the move of lowest prediction and with it every
    other move predicted below 0 on robots none of the chosen moves touch
    (:func:`_moves_on_disjoint_robots`): a run goes on from the result with the run's classification
    held and the moves made, kept when its robust objective is lower by more than the re-admissions'
    margin per admitted closure and every admitted closure stays accepted; a batch of several not kept
    is followed by its first move alone (the same team, seed 2: two correct closures made together,
    the same result in 856 s against 989 s one move at a time; seed 0: a batch of seven admitted two
    wrong closures with five correct ones, predicted like them, and that search ends wrong). Until a
    round of one move is not kept or no move is predicted below c^2. Each move is tried once in a
    search (alone or in a kept batch; ``memory`` carries the moves tried from call to call), and a
    closure a kept exchange left out is not admitted again. Returns (run, f, rounds: per round the
    moves (admitted, left out or None), their predictions, f before and after, iterations, kept,
    seconds)."""
    if run.inliers is None or first.start_weights is None:
        return run, f, []
    c2 = float(np.asarray(run.loss.scale)) ** 2
    margin = _admission_margin(first, run)
    robot = np.asarray(run.partition.robot_of_pose)
    i, j = np.asarray(graph.i), np.asarray(graph.j)
    memory = _ExchangeMemory() if memory is None else memory
    tried, rounds = memory.tried, []
    while True:  # a closure a kept exchange left out is not admitted again (no undoing)
        left = np.isin(np.arange(graph.num_edges), list(memory.left))
        overruled = np.flatnonzero(_overruled(first.start_weights, run) & _loop_closures(graph) & ~left)
        partners = np.flatnonzero(_closures_their_pair_cannot_outvote(run, graph))
        moves = [m for e in overruled.tolist()
                 for m in [((e,), ()), *[((e,), (a,)) for a in partners.tolist()
                                         if {robot[i[e]], robot[j[e]]} & {robot[i[a]], robot[j[a]]}]]
                 if m not in tried]
        if not moves:
            break
        change = move_changes(graph, robot, run.poses, run.inliers, moves, c2, warm=memory.warm)
        if change.min() >= c2:
            break
        together = _moves_on_disjoint_robots(moves, change, robot, i, j)
        batches = [together, together[:1]] if len(together) > 1 else [together]
        for batch in batches:  # a batch not kept: its first move alone, as one move per round would
            chosen = [moves[k] for k in batch]
            admitted = [e for (e,), _ in chosen]
            left_out = [a for _, out in chosen for a in out]
            again, f_again, iterations, seconds = _trial(
                run, admitted + left_out, [1.0] * len(admitted) + [0.0] * len(left_out),
                f"{label}, {len(rounds) + 1} exchange trial(s)", run_from, graph, monitor, finish,
                keeps=admitted)
            kept = bool(np.all(again.inliers[admitted])) and f_again < f - margin * len(admitted)
            rounds.append(dict(moves=[(e, out[0] if out else None) for (e,), out in chosen],
                               predicted=[float(change[k]) for k in batch], f_before=f, f=f_again,
                               iterations=iterations, kept=kept, seconds=seconds))
            if kept or len(batch) == 1:
                tried.update(chosen)
            if kept:
                run, f = again, f_again
                memory.left.update(left_out)
                break
        if not kept:
            break
    return run, f, rounds


def _moves_on_disjoint_robots(moves: list, change: np.ndarray, robot: np.ndarray, i: np.ndarray,
                              j: np.ndarray) -> list[int]:
    """Indices of ``moves`` to try together: the one of lowest predicted ``change``, then, lowest
    first, each further move predicted to lower the objective (below 0) whose robots share none with
    a move already chosen. Each prediction holds every robot its move does not touch, so on disjoint
    robots the predictions add up to first order, and one run tries them all (on a team whose run
    rejected tens of correct closures each kept move costs a trial and a pass of predictions)."""
    order = np.argsort(change, kind="stable")
    chosen, busy = [], set()
    for k in order.tolist():
        if chosen and change[k] >= 0.0:
            break
        (e,), out = moves[k]
        robots = {int(robot[i[x]]) for x in (e, *out)} | {int(robot[j[x]]) for x in (e, *out)}
        if chosen and robots & busy:
            continue
        chosen.append(k)
        busy |= robots
    return chosen


#: the start of a robust ``distributed=True`` run by default: the distributed robust start with its
#: accepted inter-robot closures checked at the team's map (``solve``'s docstring)
DISTRIBUTED_ROBUST_START = NamedStart("distributed-robust", {"team_check": True})

#: starts that need the whole graph in one place, and why (refused by ``distributed=True``)
CENTRALIZED_STARTS = {
    "chordal": "solves the chordal relaxation of the whole graph in one place",
    "gnc-chordal": "runs GNC with chordal and Newton solves of the whole graph in one place",
    "odometry": "composes a spanning tree of the whole graph in one place",
}


def _distributed_defaults(start, loss, gnc):
    """(start, gnc) of a ``distributed=True`` run: a centralized start refused with its name; by
    default the distributed chordal start for least squares and :data:`DISTRIBUTED_ROBUST_START` for a
    robust loss (its weights held as the first stage, then the kernel's own)."""
    for one in start if isinstance(start, (tuple, list)) else (start,):
        if isinstance(one, str) and one in CENTRALIZED_STARTS:
            raise ValueError(f"distributed=True: the start {one!r} {CENTRALIZED_STARTS[one]}; "
                             "use start='distributed-chordal' or 'distributed-robust'")
    robust = isinstance(loss, RobustLoss) or (loss is not None and loss != "l2") or gnc is not None
    if start is None:
        start = DISTRIBUTED_ROBUST_START if robust else "distributed-chordal"
    return start, gnc


def _robot_count(robots) -> int:
    if isinstance(robots, Partition):
        return robots.num_robots
    return int(np.max(robots)) + 1 if np.ndim(robots) else int(robots)


def solve_sharded(
    graph: PoseGraph,
    robots: int | np.ndarray | Partition = 10,
    *,
    mesh=None,
    devices: int | Sequence | None = None,
    reorder: bool | None = None,
    exchange: Literal["halo", "all_gather"] = "halo",
    **options,
) -> SolveResult:
    """:func:`solve` with ``layout=Sharded(mesh, devices, exchange, reorder)``: the robots sharded over
    the devices of a 1-D mesh.

    ``mesh`` (a ``Mesh`` with one axis named ``"robots"``) or ``devices`` (a device list, a count, or
    None for all devices, of every process), ``reorder`` (see :func:`~mmpgo_jax.sharding.plan_shards`)
    and ``exchange``: "halo" (default) sends each device only the neighbour poses its robots read (one
    ``all_to_all`` per iteration), "all_gather" every pose. Every other argument is :func:`solve`'s;
    the result has its fields. ``result.partition`` is the user's partition (robot indices as given);
    ``result.stats`` also holds the mesh size, the shard plan and the sharded (renumbered, padded)
    partition. A second call with the same shapes and configuration structure does not compile again.
    In a multi-process run every process must call this with the same arguments; the callback's stop
    decision is taken from process 0.

    ``checkpoint`` / ``checkpoint_every`` / ``resume``: as for :func:`solve`; the state is saved in the
    sharded layout, so a checkpoint resumes only on the same number of devices with the same
    ``exchange`` (and is refused otherwise). In a multi-process run every process gathers the state for
    a checkpoint and process 0 writes it; to resume, every process reads the file (on several hosts it
    must be readable on each, e.g. a shared file system).
    """
    from .._distributed.layout import Sharded  # the sharded machinery loads only when asked for

    if options.get("layout") is not None:
        raise ValueError("solve_sharded lays the robots out itself: call solve(..., layout=...) instead")
    options.pop("layout", None)
    return solve(graph, robots, layout=Sharded(mesh=mesh, devices=devices, exchange=exchange, reorder=reorder),
                 **options)


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
    # a run to grad_tol: no stop at 1e-8 of F left to gain, which would slow the last digits
    sub = subproblem or SubproblemConfig(max_steps=4, gradient_tolerance=0.1, cg_iterations=1000, cg_tolerance=tol,
                                         decrease_tolerance=0.0)
    # float32 stalls far above grad_tol: stop once a chunk no longer lowers f
    termination = Termination(max_iterations, chunk_size, grad_tol,
                              rel_decrease_tol=None if float64_enabled() else 1e-7)
    return solve(
        graph,
        1,
        solver=MM(xi, sub),
        termination=termination,
        start=init,
        initial=initial,
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
    clock = Clock()
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
