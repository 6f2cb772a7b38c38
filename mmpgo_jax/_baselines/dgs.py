"""DGS: distributed Gauss–Seidel pose graph optimization, the baseline "DGS [11]" of the paper's
Tables I/II (Choudhary, Carlone, Nieto, Rogers, Christensen, Dellaert, IJRR 2017).

The rules follow the authors' code, CogRob/distributed-mapper @ a3bbfa9 (``cpp/src/DistributedMapper.cpp``,
``cpp/src/DistributedMapperUtils.h``, ``cpp/src/MultiRobotUtils.cpp``, ``cpp/src/BetweenChordalFactor.h``):

* **Stage 1, rotations** (``DistributedMapper::estimateRotation``, ``optimizeRotation``): the chordal
  relaxation, each R_i an unconstrained d x d block. An intra-robot edge contributes
  w ||R_i R~ - R_j||^2 (linear least squares); an inter-robot edge ("separator") becomes a unary term
  against the neighbour's latest value. Each robot solves its whole local linear system exactly: the
  system matrix does not change between iterations, so it is factored once (dense Cholesky) and every
  iteration is two triangular solves. The blocks are then projected to SO(d)
  (``convertLinearizedRotationToPoses``: ``normalizeRelaxedRotations``).
* **Stage 2, poses** (``estimatePoses``, ``optimizePose``): one Gauss–Newton linearisation of the
  chordal pose cost w_R ||R_i R~ - R_j||^2 + w_t ||R_i t~ + t_i - t_j||^2 (``BetweenChordalFactor``) at
  the stage-1 result, in the increment (omega, dt): R <- R Exp(omega), t <- t + dt
  (``retractPose3Global``), solved by the same block Gauss–Seidel sweeps, then one retraction; no
  relinearisation.
* **Sweeps**: robots update one after another in a fixed order, each reading its neighbours' latest
  values (Gauss–Seidel, their ``incUpdate``); ``jacobi=True`` updates all robots from the previous
  iterate (their ``postUpdate``). Over-relaxation x <- (1 - gamma) x_old + gamma x_new
  (``updateRotation`` / ``updatePoses``, default gamma = 1). One iteration = one sweep over all robots.
* **Order** (``orderRobots``, flagged initialization): robot 0 first; then, round after round, every
  unordered robot adjacent to an ordered one, most adjacent poses first (their code's default
  ``PUSH_SINGLE_SUBGRAPH 0``; ``order="greedy"`` appends one robot per round, ``PUSH_SINGLE_SUBGRAPH 1``).
  In the first sweep of each stage a separator to a robot not yet updated in that stage is ignored.
* **Weights** (``useBetweenNoise``): their default is unit weights, ``weights="unit"``;
  ``weights="information"`` (the default here: it reproduces the paper's DGS column,
  benchmarks/dgs_paper.md) uses the graph's SE-Sync weights kappa, tau, where their code would convert
  g2o covariances to conservative isotropic ones (``convertToChordalNoise``).
* **Stopping** (``optimizeRotation`` / ``optimizePose``, ``USE_STOPPING_CONDITION``): a stage stops after
  a sweep (not the first) in which every robot's estimate moved by at most the threshold (2-norm of the
  robot's stacked relaxed rotations, resp. increments); stage 2 starts when stage 1 stops. Their
  thresholds: 1e-5 / 1e-6 (``distributedOptimizer``, the defaults here), 1e-1 / 1e-1
  (``runDistributedMapper``).
* **Iterations**: one sweep over all robots; ``history`` has one f per sweep, stage 1's (read at the
  projected rotations and the translations stage 2 will linearise at) then stage 2's (read at the
  retraction of the current increments, their ``poseTrace``).

Code: the stages are problems (:class:`~.dgs_solver.DGSStage`) of one solver, :class:`~.dgs_solver.DGS`
(``mmpgo_jax.DGS``), run by the driver of the one solve path: ``solve(graph, robots, solver=DGS())`` runs
stage 2 from solve's start on any layout (one device, sharded), and :func:`dgs` drives stage 1 and then
stage 2 with that same solver, one chunk of sweeps at a time. The stopping rule is the solver's own
(the driver's ``RESULTS.converged``). A sweep is ``lax.scan`` over the robots in the order
(``schedule="sequential"``) or over colour classes of the robot graph, each class under ``vmap``
(``schedule="colours"``; :mod:`~.dgs_kernels`).

Departures (documented where they are made):

* start: the paper (Section VIII.B) starts DGS from the centralized chordal estimate, rotations and
  translations; that is ``start="chordal"`` (default), where the rotation stage is replaced by that
  estimate (``rotation_iterations=0``) and stage 2 linearises at it, so the iterations counted are stage
  2's sweeps (what reproduces the paper's column). ``start="code"`` is their code's own pipeline: stage 1
  from the odometry rotations (their script reads the g2o vertex estimates) until it converges,
  translations 0 at the linearisation point.
* stage 2 linearises every edge at the stage-1 result of both ends; their robots linearise a separator
  at their own copy of the neighbour's relaxed rotation, up to one sweep older (the same once stage 1 has
  converged; no difference for ``start="chordal"``).
* gauge: the first pose of robot 0 is held exactly at its start (the project's anchor), where their code
  puts a prior of variance 1e-12 on it (stage 2) and a unit-weight prior through an anchor key (stage 1);
  ``solve(..., fixed=...)`` holds the fixed poses instead.
* the solver's records also hold ||grad F|| (Riemannian, over the free poses) after every sweep, which
  their code does not compute.
* 2D graphs are solved in 2D (their code is 3D only; a planar problem embedded in 3D decouples, with
  zero out-of-plane increments, so the iterates are the same).
* a robot whose first-sweep system is singular (a local component without any active separator or
  anchor; their code would stop with an indeterminate system; not met on the benchmark files) uses all
  its separators in that sweep.

Every value in ``history`` is the project's f = 2F (SE-Sync weights, :func:`~mmpgo_jax._core.pose_graph.cost`),
whatever weights DGS itself uses.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import numpy as np

from .._core.geometry import mT
from .._core.partition import Partition, partition
from .._core.pose_graph import HostPoses, PoseGraph, Poses, cost, host_view
from .._core.validate import check_choice, check_count
from .._init.start import initialize
from .._mm.driver import RESULTS, Termination, drive
from .._mm.layouts import Placement
from .._mm.majorization import unstack
from .._mm.solvers import start_run
from .dgs_solver import DGS, check_connected, flagged_order, robot_adjacency, robot_order

__all__ = ["DGS", "DGSResult", "dgs", "flagged_order", "robot_adjacency"]

STARTS = ("chordal", "code")
STAGE_START, STAGE_ROTATION, STAGE_POSE = 0, 1, 2
CHUNK = 25  # sweeps per compiled chunk of :func:`dgs`'s stages


@dataclass(frozen=True)
class DGSResult:
    """A DGS run: final ``poses``; ``history`` (K+1,) f = 2F after k iterations (k = 0: the start);
    ``stage`` (K+1,) the stage of each iteration (0 start, 1 rotations, 2 poses); ``stop_reason``
    ("converged": stage 2's change rule; "max_iterations": the budget ran out); ``order`` the robots'
    update order; ``relaxed_rotations`` stage 1's last relaxed (unprojected) blocks (n, d, d), None when
    stage 1 did not run."""

    poses: Poses
    history: np.ndarray
    stage: np.ndarray
    stop_reason: str
    order: np.ndarray
    relaxed_rotations: jax.Array | None = None

    @property
    def iterations(self) -> int:
        return len(self.history) - 1

    @property
    def rotation_iterations(self) -> int:
        return int(np.sum(self.stage == STAGE_ROTATION))

    @property
    def pose_iterations(self) -> int:
        return int(np.sum(self.stage == STAGE_POSE))

    @property
    def f(self) -> float:
        return float(self.history[-1])

    def f_at(self, k: int) -> float:
        """f after ``k`` iterations; the final value when the run stopped earlier (its estimate no longer
        changes)."""
        return float(self.history[min(k, self.iterations)])


def _start(graph: PoseGraph, start) -> tuple[Poses, bool]:
    """(start poses, whether their translations are replaced by 0 at the linearisation point)."""
    if isinstance(start, Poses):
        return initialize(graph, start), False
    check_choice(None, "start", start, STARTS)
    if start == "chordal":
        return initialize(graph, "chordal"), False
    return initialize(graph, "odometry"), True


def _budgets(iterations: int, rotation_iterations, pose_iterations, start) -> tuple[int, int | None]:
    """Stage 1's maximum (None: their code's, the whole budget; 0 for a given start) and stage 2's."""
    check_count(None, "iterations", iterations, 0, scalar=True)
    check_count(None, "rotation_iterations", rotation_iterations, 0, optional=True, scalar=True)
    check_count(None, "pose_iterations", pose_iterations, 0, optional=True, scalar=True)
    if rotation_iterations is None:
        rotation_iterations = iterations if isinstance(start, str) and start == "code" else 0
    return min(int(rotation_iterations), iterations), None if pose_iterations is None else int(pose_iterations)


def _drive_stage(solver: DGS, part: Partition, X0: Poses, budget: int, *, rotation: bool):
    """One stage on the driver from the padded poses ``X0``: (final state, f history, converged)."""
    problem = solver.stage(part, X0, rotation=rotation)
    placement = Placement(part)
    state, start = start_run(solver, problem, X0)
    out = drive(placement.compile_chunk(solver, problem), state, placement.start_record(jax.device_get(start)),
                Termination(budget, CHUNK, stop_when_stalled=False), fetch=placement.fetch)
    return out.state, out.history.f, out.result is RESULTS.converged


def dgs(
    graph: PoseGraph,
    robots: int | np.ndarray | Partition = 10,
    *,
    iterations: int = 1000,
    start="chordal",
    weights: str = "information",
    order="flagged",
    relaxation: float = 1.0,
    rotation_tol: float = 1e-5,
    pose_tol: float = 1e-6,
    jacobi: bool = False,
    rotation_iterations: int | None = None,
    pose_iterations: int | None = None,
) -> DGSResult:
    """Run DGS on ``graph`` split among ``robots`` (a count: contiguous blocks as in the paper; an (n,)
    robot-of-pose array; or a :class:`Partition`). The rules and their sources: the module docstring.
    Stage 2 alone from the chordal start is also ``solve(graph, robots, solver=DGS(...))``, with the
    same history.

    * ``iterations``: the budget of sweeps (one sweep = every robot once), both stages together: the
      x-axis of ``history``. ``rotation_iterations``: stage 1's maximum (default: 0 for ``start="chordal"``
      or a ``Poses`` start, whose rotations are used as they are; the whole budget for ``"code"``).
      ``pose_iterations``: stage 2's maximum (default: what stage 1 left of the budget).
    * ``start``: "chordal" (Section VIII.B: the centralized chordal estimate), "code" (their code: stage 1
      from the odometry rotations, translations 0) or a :class:`Poses`.
    * ``weights``, ``order``, ``relaxation``, ``jacobi``, ``rotation_tol``, ``pose_tol``: the settings of
      :class:`~.dgs_solver.DGS` (their code's thresholds by default, ``distributedOptimizer``'s; their
      script ``runDistributedMapper`` passes 1e-1 for both, which stops stage 2 within a few sweeps).
    """
    solver = DGS(weights=weights, order=order, relaxation=relaxation, rotation_tol=rotation_tol,
                 pose_tol=pose_tol, jacobi=jacobi)
    rot_max, pose_max = _budgets(iterations, rotation_iterations, pose_iterations, start)
    check_connected(graph.num_poses, graph.i, graph.j)
    part = robots if isinstance(robots, Partition) else partition(graph, robots)
    poses, zero_t = _start(graph, start)
    R, t_lin = np.asarray(poses.R), np.asarray(poses.t) * (0.0 if zero_t else 1.0)
    history, stage = [float(cost(host_view(graph), HostPoses(R, t_lin)))], [STAGE_START]
    X0, relaxed = part.scatter(Poses(R, t_lin)), None
    if rot_max > 0:
        state, f, _ = _drive_stage(solver, part, X0, rot_max, rotation=True)
        history, stage = history + f[1:].tolist(), stage + [STAGE_ROTATION] * (len(f) - 1)
        relaxed = mT(state.Z[part.robot_of_pose, part.slot_of_pose])
        X0 = unstack(state.X)
    done = len(history) - 1
    kmax = iterations - done if pose_max is None else min(iterations - done, pose_max)
    converged = False
    if kmax > 0:
        state, f, converged = _drive_stage(solver, part, X0, kmax, rotation=False)
        history, stage = history + f[1:].tolist(), stage + [STAGE_POSE] * (len(f) - 1)
        X0 = unstack(state.X)
    return DGSResult(part.gather(X0), np.asarray(history), np.asarray(stage, np.int8),
                     "converged" if converged else "max_iterations", robot_order(part, solver.order)[0], relaxed)
