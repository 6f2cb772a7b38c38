"""DGS as a solver of the one solve path: :class:`DGS` (settings, ``build`` / ``init`` / ``step``), its
problem :class:`DGSStage` (one stage's constant data) and state, and the host set-up they need (the
robot order, colour classes, first-sweep edge selections, held poses). The rules and their sources:
:mod:`mmpgo_jax._baselines.dgs`.

One iteration of the driver = one sweep over all robots (:func:`~.dgs_kernels.sweep`); f = 2F at the
retraction of the current increments. Their stopping rule (every robot's change <= the stage's
tolerance after a sweep, not the first) sets the state's ``converged_at``: the driver then stops
(``RESULTS.converged``) and the state no longer changes.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._core.geometry import mT, project_to_so
from .._core.partition import Partition
from .._core.pose_graph import Poses, component_labels
from .._core.validate import check_choice, check_flag, check_real
from .._mm.majorization import stack, unstack
from .._mm.outer import IterationRecord, _riemannian_grad_norm
from .._mm.solvers import Solver
from .._mm.weighting import LOCAL, Collectives, gradients
from .dgs_kernels import factors, pose_edges, retract, rotation_edges, sweep

__all__ = ["DGS", "DGSStage", "DGSState", "flagged_order", "robot_adjacency"]

WEIGHTS = ("information", "unit")
ORDERS = ("flagged", "greedy", "natural")
SCHEDULES = ("sequential", "colours")


# --------------------------------------------------------------------------------------------
# host set-up (once per run)
# --------------------------------------------------------------------------------------------


def _adjacency(i, j, rop, num_robots: int) -> np.ndarray:
    """(A, A) int: ``adj[a, b]`` = number of distinct poses of robot b sharing an edge with robot a."""
    rop, i, j = (np.asarray(x, np.int64) for x in (rop, i, j))
    inter = rop[i] != rop[j]
    a = np.concatenate([rop[i[inter]], rop[j[inter]]])
    remote = np.concatenate([j[inter], i[inter]])
    pairs = np.unique(np.stack([a, remote], 1), axis=0)  # (robot, remote pose), each once
    adj = np.zeros((num_robots, num_robots), np.int64)
    np.add.at(adj, (pairs[:, 0], rop[pairs[:, 1]]), 1)
    return adj


def robot_adjacency(graph, robot_of_pose) -> np.ndarray:
    """(A, A) int: ``adj[a, b]`` = number of distinct poses of robot b sharing an edge with robot a.

    Their ``orderRobots`` counts the keys of robot a's ``neighbors_`` (remote poses, each once), not
    separator edges."""
    rop = np.asarray(robot_of_pose)
    return _adjacency(graph.i, graph.j, rop, int(rop.max()) + 1)


def flagged_order(adjacency, *, single: bool = False) -> np.ndarray:
    """The flagged-initialization order of ``orderRobots`` (DistributedMapperUtils.h).

    Robot 0 first (it holds the anchor); then in rounds: each unordered robot's count of adjacent
    poses in already ordered robots; every robot with a nonzero count is appended, largest count first
    (``single=True``: only the first, their ``PUSH_SINGLE_SUBGRAPH 1``). Ties go to the larger robot
    index (their ``std::multimap`` read from its end). Robots never reached are appended in index
    order. A host-side set-up loop over rounds (at most A of them).
    """
    adj = np.asarray(adjacency)
    A = adj.shape[0]
    order = [0]
    placed = np.zeros(A, bool)
    placed[0] = True
    while A > 2:
        counts = np.where(placed, 0, adj[:, placed].sum(1))
        cand = np.flatnonzero(counts > 0)
        if cand.size == 0:
            break
        ranked = cand[np.lexsort((-cand, -counts[cand]))]
        ranked = ranked[:1] if single else ranked
        order.extend(ranked.tolist())
        placed[ranked] = True
    rest = np.flatnonzero(~np.isin(np.arange(A), order))  # A == 2: [0, 1], as their code
    return np.concatenate([np.asarray(order, np.int64), rest]).astype(np.int32)


def edge_ends(part: Partition) -> tuple[np.ndarray, np.ndarray]:
    """(i, j) global pose indices of every real edge, once (the copy in its tail's robot)."""
    e = part.edges
    tail = np.asarray(e.local_i)
    index = np.asarray(part.pose_index)
    ri, si, rj, sj = (np.asarray(x)[tail] for x in (e.robot_i, e.slot_i, e.robot_j, e.slot_j))
    return index[ri, si], index[rj, sj]


def check_connected(num_poses: int, i, j) -> None:
    _, sizes, _ = component_labels(num_poses, np.asarray(i), np.asarray(j))
    if len(sizes) > 1:
        raise ValueError(f"DGS needs a connected measurement graph (one anchor); this one has {len(sizes)} "
                         "components")


def robot_order(part: Partition, order) -> tuple[np.ndarray, bool]:
    """(update order, whether the first sweep drops separators to robots not yet updated): the flagged
    orders drop them (their ``useFlaggedInit``), a natural or given order does not."""
    A = part.num_robots
    if isinstance(order, str):
        if order == "natural":
            return np.arange(A, dtype=np.int32), False
        i, j = edge_ends(part)
        return flagged_order(_adjacency(i, j, part.robot_of_pose, A), single=order == "greedy"), True
    if len(order) != A:
        raise ValueError(f"order must be a permutation of the {A} robots, got {list(order)}")
    return np.asarray(order, np.int32), False


def colour_classes(part: Partition, order: np.ndarray) -> np.ndarray:
    """(A,) colour class of every robot (-1: a robot without poses): greedy colouring along ``order``
    (each robot the smallest class none of its neighbours earlier in the order has; networkx), so
    robots of one class share no edge and a class can update at once."""
    import networkx as nx

    e = part.edges
    inter = np.asarray(e.local_i) ^ np.asarray(e.local_j)
    pairs = np.unique(np.stack([np.asarray(e.robot_i)[inter], np.asarray(e.robot_j)[inter]], 1), axis=0)
    real = np.asarray(part.pose_mask).any(axis=1)
    G = nx.Graph()
    G.add_nodes_from(np.flatnonzero(real).tolist())
    G.add_edges_from(pairs.tolist())
    along = order[real[order]].tolist()
    classes = nx.coloring.greedy_color(G, strategy=lambda graph, colours: iter(along))
    colour = np.full(part.num_robots, -1, np.int32)
    colour[np.fromiter(classes.keys(), np.int64, len(classes))] = np.fromiter(classes.values(), np.int32, len(classes))
    return colour


def first_sweep_active(part: Partition, position: np.ndarray, flagged: bool) -> np.ndarray:
    """(A, E) bool: the edge slots a robot uses in a stage's first sweep: with flagged initialization,
    intra-robot edges and separators to robots updated earlier in the sweep (``neighboringRobotsInitialized_``)."""
    e = part.edges
    local_i, local_j = np.asarray(e.local_i), np.asarray(e.local_j)
    real = local_i | local_j
    if not flagged:
        return real
    other = np.where(local_i, np.asarray(e.robot_j), np.asarray(e.robot_i))
    earlier = position[other] < position[:, None]
    return real & ((local_i & local_j) | earlier)


def free_slots(part: Partition, fixed=None) -> np.ndarray:
    """(A, n_max) bool free unknowns: real slots other than the held poses, the ``fixed`` ones when
    given, else robot 0's first pose (their code's prior on ``KeyVector(initial.keys()).at(0)``)."""
    free = np.asarray(part.pose_mask).copy()
    if fixed is None:
        free[0, 0] = False
        return free
    mask = fixed.mask(part.num_poses) if hasattr(fixed, "mask") else np.asarray(fixed, dtype=bool)
    free[np.asarray(part.robot_of_pose)[mask], np.asarray(part.slot_of_pose)[mask]] = False
    return free


def edge_weights(part: Partition, unit: bool):
    """(w_R, w_t) per edge slot (A, E): 1 on real edges (their default ``useBetweenNoise=false``) or
    kappa, tau; 0 on padding (host arrays)."""
    e = part.edges
    if not unit:
        return np.asarray(e.kappa), np.asarray(e.tau)
    real = (np.asarray(e.local_i) | np.asarray(e.local_j)).astype(np.asarray(e.kappa).dtype)
    return real, real


# --------------------------------------------------------------------------------------------
# the problem and the state
# --------------------------------------------------------------------------------------------


class DGSStage(eqx.Module):
    """One DGS stage's constant data, per robot (leading axis A; a sharded run gives each device its
    robots'): the quadratic per edge slot, the free unknowns, the dense local factors of the S edge
    selections (the flagged first sweep's, then all edges), the step of the sweep at which each robot
    updates (``position``, -1: never) and ``base``, what the unknowns are read against: stage 2 the
    linearisation point (stacked poses), stage 1 the translations f is read with."""

    partition: Partition
    edges: object
    free: jax.Array  # (A, n_max) bool
    chols: jax.Array  # (A, S, N, N)
    active: jax.Array  # (A, S, E) bool
    position: jax.Array  # (A,) int32
    base: jax.Array
    steps: int = eqx.field(static=True)  # steps of one sweep
    rotation: bool = eqx.field(static=True)  # stage 1 (relaxed rotations) or stage 2 (increments)

    def unknowns(self, X0: Poses):
        """The stage's unknowns at the start: R^T (stage 1) or zero increments (stage 2)."""
        if self.rotation:
            return mT(X0.R)
        d = X0.R.shape[-1]
        return jnp.zeros((*X0.R.shape[:-2], d * (d - 1) // 2 + d, 1), X0.R.dtype)

    def poses(self, Z):
        """Stacked poses of the unknowns: projected rotations with ``base``'s translations (stage 1), or
        the retraction of the increments at ``base`` (stage 2, their ``poseTrace``)."""
        if self.rotation:
            return stack(Poses(project_to_so(mT(Z)), self.base))
        return stack(retract(unstack(self.base), Z))


@functools.partial(jax.jit, static_argnames=("rotation",))
def _stage_system(part, free, poses, weights, active, *, rotation: bool):
    """(edges, factors, base) of a stage, in one compiled call (op by op each would compile)."""
    edges = rotation_edges(part, free, weights[0]) if rotation else pose_edges(part, free, poses, *weights)
    return edges, factors(edges, free, active), poses.t if rotation else stack(poses)


class DGSState(eqx.Module):
    """The stacked poses X (what the result reads), the stage's unknowns Z, f and ||grad F|| at X, the
    sweeps done, and the sweep after which the stopping rule held (-1: not yet)."""

    X: jax.Array
    Z: jax.Array
    f: jax.Array
    grad_norm: jax.Array
    iteration: jax.Array
    converged_at: jax.Array


def _evaluate(stage: DGSStage, X, comm: Collectives):
    """(f = 2F, ||grad F|| over the free poses) at the stacked poses X."""
    grad, share, _ = gradients(stage, X, comm)
    return 2.0 * comm.sum(share), _riemannian_grad_norm(X, grad, stage.free, comm)


# --------------------------------------------------------------------------------------------
# the solver
# --------------------------------------------------------------------------------------------


class DGS(Solver):
    """Distributed Gauss–Seidel (Choudhary et al. 2017; rules and sources: :mod:`mmpgo_jax._baselines.dgs`)
    as a solver: stage 2 (one Gauss–Newton linearisation of the chordal pose cost at the start, block
    Gauss–Seidel sweeps over the robots) from the start ``solve`` gives it (chordal by default: the
    paper's setting). One iteration = one sweep; f = 2F at the retraction of the increments.

    ``weights``: "information" (kappa, tau; reproduces the paper's DGS column) or "unit" (their
    code's default). ``order``: "flagged" (their default: robot 0, then by adjacency; the first sweep
    ignores separators to robots not yet updated), "greedy" (one robot per round), "natural" (0..A-1)
    or a permutation of the robots. ``schedule``: "sequential" (one robot after another in the order,
    ``lax.scan``: their Gauss–Seidel) or "colours" (colour classes of the robot graph, greedily coloured
    along the order, one class after another, its robots at once under ``vmap``: the Gauss–Seidel
    iterate of the order sorted by class, a different but legitimate one). ``jacobi``: every robot from
    the previous sweep (their ``postUpdate``). ``relaxation``: their over-relaxation gamma.
    ``pose_tol`` / ``rotation_tol``: their change thresholds; the run stops after a sweep (not the
    first) in which every robot's increments moved by at most ``pose_tol`` (``RESULTS.converged``).
    ``rotations``: their stage 1 (chordal rotations, ``start="code"``) is not a stage of
    ``solve``; True is refused (:func:`~mmpgo_jax.dgs` runs it, with this solver, before stage 2).

    With a sharded layout that renumbers robots (``Sharded(reorder=...)``) the order and the held
    pose follow the renumbered robots; robots given as a count are not renumbered.
    """

    weights: str = eqx.field(static=True)
    order: str | tuple = eqx.field(static=True)
    schedule: str = eqx.field(static=True)
    jacobi: bool = eqx.field(static=True)
    relaxation: float
    pose_tol: float
    rotation_tol: float

    def __init__(self, weights: str = "information", order="flagged", schedule: str = "sequential",
                 jacobi: bool = False, relaxation: float = 1.0, pose_tol: float = 1e-6, rotation_tol: float = 1e-5,
                 rotations: bool = False):
        owner = "DGS"
        check_choice(owner, "weights", weights, WEIGHTS)
        check_choice(owner, "schedule", schedule, SCHEDULES)
        check_flag(owner, "jacobi", jacobi)
        check_flag(owner, "rotations", rotations)
        check_real(owner, "relaxation", relaxation, 0.0, low_open=True, scalar=True)
        check_real(owner, "pose_tol", pose_tol, 0.0, scalar=True)
        check_real(owner, "rotation_tol", rotation_tol, 0.0, scalar=True)
        if rotations:
            raise ValueError("DGS(rotations=True): the rotation stage (their start='code' pipeline) is not a stage "
                             "of solve(); DGS runs stage 2 from solve's start (chordal by default, the paper's "
                             "setting); mmpgo_jax.dgs(graph, robots, start='code') runs both stages")
        if jacobi and schedule != "sequential":
            raise ValueError("DGS: jacobi=True updates every robot at once; give schedule='sequential'")
        self.weights, self.order, self.schedule, self.jacobi = weights, _checked_order(order), schedule, jacobi
        self.relaxation, self.pose_tol, self.rotation_tol = relaxation, pose_tol, rotation_tol

    @property
    def name(self) -> str:
        return "dgs"

    # --- host -------------------------------------------------------------------------------

    def build(self, partition: Partition, *, poses, fixed=None, loss=None, min_couplings: int = 0,
              aggregate: int | None = None) -> DGSStage:
        """Stage 2 at the start ``poses`` (padded per robot)."""
        if loss is not None:
            raise ValueError("DGS minimises the least-squares F only: give no loss")
        return self.stage(partition, poses, fixed, rotation=False)

    def stage(self, part: Partition, poses: Poses, fixed=None, *, rotation: bool) -> DGSStage:
        """A stage's :class:`DGSStage` at the padded ``poses`` (stage 1: their rotations are the start of
        the relaxed blocks, their translations those f is read with)."""
        check_connected(part.num_poses, *edge_ends(part))
        order, flagged = robot_order(part, self.order)
        rank = np.empty(len(order), np.int32)
        rank[order] = np.arange(len(order), dtype=np.int32)
        position, steps = (rank, len(order)) if not self.jacobi else (np.zeros_like(rank), 1)
        if self.schedule == "colours":
            position = colour_classes(part, order)
            steps = max(int(position.max(initial=-1)) + 1, 1)
        free = free_slots(part, fixed)
        first = first_sweep_active(part, rank if self.jacobi else position, flagged)
        real = np.asarray(part.edges.local_i) | np.asarray(part.edges.local_j)
        active = np.stack([first, real], 1) if flagged else real[:, None]
        edges, chols, base = _stage_system(part, free, poses, edge_weights(part, self.weights == "unit"), active,
                                           rotation=rotation)
        return DGSStage(part, edges, jnp.asarray(free), chols, jnp.asarray(active), jnp.asarray(position), base,
                        steps, rotation)

    def check(self, problem) -> None:
        if not isinstance(problem, DGSStage):
            raise TypeError(f"DGS runs on a DGSStage (DGS().build(...)), got {type(problem).__name__}")

    # --- traced -----------------------------------------------------------------------------

    def init(self, problem: DGSStage, X0):
        Z = problem.unknowns(X0)
        X = problem.poses(Z)
        f, g = _evaluate(problem, X, LOCAL)
        state = DGSState(X, Z, f, g, jnp.asarray(0, jnp.int32), jnp.asarray(-1, jnp.int32))
        return state, self._record(state)

    def step(self, problem: DGSStage, state: DGSState, comm: Collectives = LOCAL):
        def one_sweep(st: DGSState) -> DGSState:
            s = jnp.minimum(st.iteration, problem.active.shape[1] - 1)  # the flagged first sweep's selection
            one_lane = self.schedule == "sequential" and not self.jacobi
            Z, change = sweep(problem, st.Z, s, jnp.asarray(self.relaxation, st.Z.dtype), comm, one_lane=one_lane)
            tol = self.rotation_tol if problem.rotation else self.pose_tol
            k = st.iteration + 1
            done = (st.iteration > 0) & (comm.max(change) <= tol)
            X = problem.poses(Z)
            f, g = _evaluate(problem, X, comm)
            return DGSState(X, Z, f, g, k, jnp.where(done, k, -1).astype(jnp.int32))

        # after the stopping rule held the state stays as it is (the driver cuts the history there)
        state = lax.cond(state.converged_at >= 0, lambda st: st, one_sweep, state)
        return state, self._record(state)

    def skipped(self, state: DGSState) -> IterationRecord:
        nan = jnp.full((), jnp.nan, state.f.dtype)
        return IterationRecord(f=nan, grad_norm=nan, restarted=jnp.zeros(state.Z.shape[:1], bool),
                               settled=jnp.ones((), bool))

    def record_structure(self, problem) -> IterationRecord:
        return IterationRecord(f=0.0, grad_norm=0.0, restarted=0.0, settled=0.0)

    def start_structure(self, problem):
        leaf = 0.0
        return DGSState(leaf, leaf, leaf, leaf, leaf, leaf), self.record_structure(problem)

    @staticmethod
    def _record(state: DGSState) -> IterationRecord:
        return IterationRecord(f=state.f, grad_norm=state.grad_norm, restarted=jnp.zeros(state.Z.shape[:1], bool),
                               settled=jnp.ones((), bool))


def _checked_order(order):
    """``order`` as a static value: one of :data:`ORDERS`, or a permutation as a tuple of ints."""
    if isinstance(order, str):
        check_choice("DGS", "order", order, ORDERS)
        return order
    perm = np.asarray(order)
    if perm.ndim != 1 or perm.dtype.kind not in "iu" or not np.array_equal(np.sort(perm), np.arange(len(perm))):
        raise ValueError(f"DGS.order must be 'flagged', 'greedy', 'natural' or a permutation of the robots, "
                         f"got {np.asarray(order).tolist()}")
    return tuple(perm.tolist())
