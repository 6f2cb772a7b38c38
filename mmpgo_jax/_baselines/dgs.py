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
  puts a prior of variance 1e-12 on it (stage 2) and a unit-weight prior through an anchor key (stage 1).
* 2D graphs are solved in 2D (their code is 3D only; a planar problem embedded in 3D decouples, with
  zero out-of-plane increments, so the iterates are the same).
* a robot whose first-sweep system is singular (a local component without any active separator or
  anchor; their code would stop with an indeterminate system; not met on the benchmark files) uses all
  its separators in that sweep.

Every value in ``history`` is the project's f = 2F (SE-Sync weights, :func:`~mmpgo_jax._core.pose_graph.cost`),
whatever weights DGS itself uses.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.scipy.linalg import cho_solve

from .._core.geometry import mT, project_to_so
from .._core.lie import so
from .._core.partition import Partition, partition
from .._core.pose_graph import HostPoses, PoseGraph, Poses, component_labels, cost, host_view
from .._core.validate import check_choice, check_count, check_real
from .._init.start import initialize

__all__ = ["DGSResult", "dgs", "flagged_order", "robot_adjacency"]

STARTS = ("chordal", "code")
WEIGHTS = ("unit", "information")
ORDERS = ("flagged", "greedy", "natural")
STAGE_START, STAGE_ROTATION, STAGE_POSE = 0, 1, 2


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


# --------------------------------------------------------------------------------------------
# order (host side, once)
# --------------------------------------------------------------------------------------------


def robot_adjacency(graph: PoseGraph, robot_of_pose) -> np.ndarray:
    """(A, A) int: ``adj[a, b]`` = number of distinct poses of robot b sharing an edge with robot a.

    Their ``orderRobots`` counts the keys of robot a's ``neighbors_`` (remote poses, each once), not
    separator edges."""
    rop = np.asarray(robot_of_pose, np.int64)
    A = int(rop.max()) + 1
    gi, gj = np.asarray(graph.i, np.int64), np.asarray(graph.j, np.int64)
    inter = rop[gi] != rop[gj]
    a = np.concatenate([rop[gi[inter]], rop[gj[inter]]])
    remote = np.concatenate([gj[inter], gi[inter]])
    pairs = np.unique(np.stack([a, remote], 1), axis=0)  # (robot, remote pose), each once
    adj = np.zeros((A, A), np.int64)
    np.add.at(adj, (pairs[:, 0], rop[pairs[:, 1]]), 1)
    return adj


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
    rest = [r for r in range(A) if r not in order]  # A == 2: [0, 1], as their code
    return np.asarray(order + rest, np.int32)


# --------------------------------------------------------------------------------------------
# the local quadratic problems (jittable)
# --------------------------------------------------------------------------------------------


class _Edges(NamedTuple):
    """One stage's quadratic per incident edge slot, (A, E, ...): the edge's cost is
    x_i^T H_ii x_i + x_j^T H_jj x_j + 2 x_i^T H_ij x_j + 2 g_i^T x_i + 2 g_j^T x_j + const,
    with x (q, c) per pose; ``unknown_*`` marks an end that is a free unknown of the robot holding the
    slot (a local pose other than the anchor)."""

    H_ii: jax.Array  # (A, E, q, q)
    H_jj: jax.Array
    H_ij: jax.Array
    g_i: jax.Array  # (A, E, q, c)
    g_j: jax.Array
    robot_i: jax.Array  # (A, E) where the ends' current values are read
    slot_i: jax.Array
    robot_j: jax.Array
    slot_j: jax.Array
    unknown_i: jax.Array  # (A, E) bool
    unknown_j: jax.Array


def _unknown_ends(part: Partition, free):
    """Per edge slot: is the tail / head a free unknown of the slot's robot?"""
    e = part.edges
    own_i = jnp.take_along_axis(free, e.slot_i, axis=1)
    own_j = jnp.take_along_axis(free, e.slot_j, axis=1)
    return e.local_i & own_i, e.local_j & own_j


def _edge_weights(part: Partition, unit: bool):
    """(w_R, w_t) per edge slot (A, E): 1 on real edges (their default ``useBetweenNoise=false``) or
    kappa, tau; 0 on padding. Arrays, not a static flag: both weightings share one compilation."""
    e = part.edges
    if not unit:
        return e.kappa, e.tau
    real = (np.asarray(e.local_i) | np.asarray(e.local_j)).astype(e.kappa.dtype)  # host: no dispatch
    return real, real


def _rotation_edges(part: Partition, free, wr) -> _Edges:
    """Stage 1 (``createLinearOrientationGraph``): w ||R_i R~ - R_j||^2 with x_p = R_p^T (d x d, d
    right-hand sides): H_ii = w R~ R~^T, H_jj = w I, H_ij = -w R~, no linear term."""
    e = part.edges
    w = wr[..., None, None]
    d = e.R.shape[-1]
    eye = jnp.eye(d, dtype=e.R.dtype)
    zero = jnp.zeros(e.R.shape, e.R.dtype)
    unknown_i, unknown_j = _unknown_ends(part, free)
    return _Edges(w * (e.R @ mT(e.R)), w * eye, -w * e.R, zero, zero, e.robot_i, e.slot_i, e.robot_j, e.slot_j,
                  unknown_i, unknown_j)


def _pose_jacobians(Ri, ti, Rj, tj, Rm, tm, wr, wt):
    """Whitened residual r0 = [sqrt(w_R) vec(R_i R~ - R_j); sqrt(w_t) (R_i t~ + t_i - t_j)] and its
    Jacobians J_i, J_j ((d^2 + d) x p, columns (omega, dt)) in the increment R Exp(omega), t + dt
    (``BetweenChordalFactor::evaluateError`` with ``retractPose3Global``)."""
    d = Ri.shape[-1]
    G = jnp.asarray(so(d).generators(), Ri.dtype)  # [omega]_x = sum_k omega_k G_k
    lead = Ri.shape[:-2]
    sr, st = jnp.sqrt(wr)[..., None, None], jnp.sqrt(wt)[..., None, None]
    dEi = jnp.einsum("...ab,kbc,...cd->...kad", Ri, G, Rm).reshape(*lead, -1, d * d)  # (.., k, d^2)
    dEj = -jnp.einsum("...ab,kbc->...kac", Rj, G).reshape(*lead, -1, d * d)
    dti = jnp.einsum("...ab,kbc,...c->...ka", Ri, G, tm)  # (.., k, d)
    eye = jnp.broadcast_to(jnp.eye(d, dtype=Ri.dtype), (*lead, d, d))
    zr = jnp.zeros((*lead, d, d * d), Ri.dtype)
    zt = jnp.zeros(dti.shape, Ri.dtype)
    # rows of the transposed Jacobians: one per increment component (omega_k, then dt_a)
    Ji_T = jnp.concatenate([jnp.concatenate([sr * dEi, st * dti], -1), jnp.concatenate([zr, st * eye], -1)], -2)
    Jj_T = jnp.concatenate([jnp.concatenate([sr * dEj, zt], -1), jnp.concatenate([zr, -st * eye], -1)], -2)
    rot = (Ri @ Rm - Rj).reshape(*lead, d * d)
    trans = jnp.einsum("...ab,...b->...a", Ri, tm) + ti - tj
    r0 = jnp.concatenate([sr[..., 0] * rot, st[..., 0] * trans], -1)
    return mT(Ji_T), mT(Jj_T), r0


def _pose_edges(part: Partition, free, lin: Poses, wr, wt) -> _Edges:
    """Stage 2: the Gauss–Newton model of every edge at the padded linearisation point ``lin``
    (A, n_max, ...): H = J^T J, g = J^T r0 (one right-hand side)."""
    e = part.edges
    Ji, Jj, r0 = _pose_jacobians(lin.R[e.robot_i, e.slot_i], lin.t[e.robot_i, e.slot_i], lin.R[e.robot_j, e.slot_j],
                                 lin.t[e.robot_j, e.slot_j], e.R, e.t, wr, wt)
    unknown_i, unknown_j = _unknown_ends(part, free)
    g_i = jnp.einsum("...ra,...r->...a", Ji, r0)[..., None]
    g_j = jnp.einsum("...ra,...r->...a", Jj, r0)[..., None]
    return _Edges(mT(Ji) @ Ji, mT(Jj) @ Jj, mT(Ji) @ Jj, g_i, g_j, e.robot_i, e.slot_i, e.robot_j, e.slot_j,
                  unknown_i, unknown_j)


def _local_matrix(edges: _Edges, free, active):
    """One robot's dense system matrix (n_max q square): its active edges' blocks on its free unknowns;
    identity rows on the anchor and padding slots (their values are held)."""
    n_max, q = free.shape[0], edges.H_ii.shape[-1]
    on_i = (edges.unknown_i & active)[:, None, None]
    on_j = (edges.unknown_j & active)[:, None, None]
    on_ij = on_i & on_j
    M = jnp.zeros((n_max, n_max, q, q), edges.H_ii.dtype)
    M = M.at[edges.slot_i, edges.slot_i].add(jnp.where(on_i, edges.H_ii, 0.0))
    M = M.at[edges.slot_j, edges.slot_j].add(jnp.where(on_j, edges.H_jj, 0.0))
    M = M.at[edges.slot_i, edges.slot_j].add(jnp.where(on_ij, edges.H_ij, 0.0))
    M = M.at[edges.slot_j, edges.slot_i].add(jnp.where(on_ij, mT(edges.H_ij), 0.0))
    held = jnp.where(free[:, None, None], 0.0, jnp.eye(q, dtype=M.dtype))
    M = M.at[jnp.arange(n_max), jnp.arange(n_max)].add(held)
    return M.transpose(0, 2, 1, 3).reshape(n_max * q, n_max * q)


def _factors(edges: _Edges, free, actives):
    """Cholesky factors (A, S, N, N) of every robot's local matrix for each of the S edge selections
    ``actives`` (S, A, E), one robot at a time (``lax.map``: the peak memory is one dense assembly).

    Selection 0 is the first sweep's (flagged separators dropped); a robot whose reduced system there
    is singular keeps all its separators (the last selection's factor)."""

    def robot(args):
        edges, free, actives = args
        chol = jnp.stack([jnp.linalg.cholesky(_local_matrix(edges, free, active)) for active in actives])
        ok = jnp.all(jnp.isfinite(chol), axis=(1, 2))[:, None, None]
        return jnp.where(ok, chol, chol[-1])

    return lax.map(robot, (edges, free, jnp.swapaxes(actives, 0, 1)))


def _local_solve(X, own, edges: _Edges, free, chol, active):
    """One robot's exact local solve: its free unknowns given the latest values ``X`` (A, n_max, q, c)
    of everything else (separator ends and the anchor); ``own`` (n_max, q, c) its current values."""
    x_i = X[edges.robot_i, edges.slot_i]
    x_j = X[edges.robot_j, edges.slot_j]
    col = (slice(None), None, None)
    c_i = -(edges.g_i + jnp.where(edges.unknown_j[col], 0.0, edges.H_ij @ x_j))
    c_j = -(edges.g_j + jnp.where(edges.unknown_i[col], 0.0, mT(edges.H_ij) @ x_i))
    c_i = jnp.where((edges.unknown_i & active)[col], c_i, 0.0)
    c_j = jnp.where((edges.unknown_j & active)[col], c_j, 0.0)
    b = jnp.zeros(own.shape, own.dtype).at[edges.slot_i].add(c_i).at[edges.slot_j].add(c_j)
    b = jnp.where(free[col], b, own)
    n_max, q, c = own.shape
    return cho_solve((chol, True), b.reshape(n_max * q, c)).reshape(own.shape)


def _robot(tree, alpha):
    return jax.tree_util.tree_map(lambda a: a[alpha], tree)


def _gauss_seidel_sweep(X, edges: _Edges, free, chols, s, active, order, gamma):
    """Robots one after another in ``order`` (``lax.scan``), each reading the others' latest values
    (their ``incUpdate``), with the factors ``chols[:, s]``; returns the new iterate and each robot's
    change ||x_new - x_old||."""

    def step(X, alpha):
        own = X[alpha]
        new = _local_solve(X, own, _robot(edges, alpha), free[alpha], chols[alpha, s], active[alpha])
        return X.at[alpha].set((1.0 - gamma) * own + gamma * new), jnp.linalg.norm(new - own)

    return lax.scan(step, X, order)


def _jacobi_sweep(X, edges: _Edges, free, chols, s, active, order, gamma):
    """All robots from the previous iterate at once (``vmap``; their ``postUpdate``)."""
    del order
    robots = jnp.arange(X.shape[0])
    new = jax.vmap(lambda a, e, fr, L, ac: _local_solve(X, X[a], e, fr, L, ac))(robots, edges, free, chols[:, s],
                                                                                 active)
    change = jnp.sqrt(jnp.sum((new - X) ** 2, axis=(1, 2, 3)))
    return (1.0 - gamma) * X + gamma * new, change


def _iterate(X, edges, free, chols, actives, order, value, *, size, kmax, tol, gamma, jacobi):
    """Up to ``kmax`` sweeps of a stage: the first with the edge selection ``actives[0]`` and its factors
    (flagged separators dropped), the others with the last; stops after a sweep (not the first) where
    every robot changed by <= ``tol`` (``optimizeRotation`` / ``optimizePose``). Returns the number of
    sweeps, the iterate, f after each sweep (``size``, NaN past the end) and whether the change rule
    stopped it."""
    sweep = functools.partial(_jacobi_sweep if jacobi else _gauss_seidel_sweep, edges=edges, free=free,
                              chols=chols, order=order, gamma=gamma)

    def body(carry):
        k, X, history, _ = carry
        s = jnp.minimum(k, len(actives) - 1)
        X, change = sweep(X, s=s, active=actives[s])
        return k + 1, X, history.at[k].set(value(X)), (k > 0) & jnp.all(change <= tol)

    carry = (jnp.asarray(0), X, jnp.full(size, jnp.nan, X.dtype), jnp.asarray(False))
    return lax.while_loop(lambda c: (c[0] < kmax) & ~c[3], body, carry)


def _selections(part: Partition, active_first, flagged: bool):
    """(S, A, E) edge selections: the flagged first sweep's and all real edges (S = 2), or just the latter."""
    active = part.edges.local_i | part.edges.local_j
    return jnp.stack([active_first, active]) if flagged else active[None]


def _global(part: Partition, X):
    """Padded per-robot values (A, n_max, ...) -> global (n, ...)."""
    return X[part.robot_of_pose, part.slot_of_pose]


@functools.partial(jax.jit, static_argnames=("size", "jacobi", "flagged"))
def _rotation_stage(graph, part, X, t, weights, free, active_first, order, kmax, tol, gamma, *, size, jacobi,
                    flagged):
    """Stage 1 from the relaxed blocks X (A, n_max, d, d) = R^T per slot; f is read at the projected
    rotations and the translations ``t`` (n, d) that stage 2 will linearise at."""
    edges = _rotation_edges(part, free, weights[0])
    actives = _selections(part, active_first, flagged)

    def value(X):
        return cost(graph, Poses(project_to_so(mT(_global(part, X))), t))

    k, X, history, _ = _iterate(X, edges, free, _factors(edges, free, actives), actives, order, value, size=size,
                                kmax=kmax, tol=tol, gamma=gamma, jacobi=jacobi)
    relaxed = mT(_global(part, X))
    return k, relaxed, project_to_so(relaxed), history


def _retract(lin: Poses, delta, d: int) -> Poses:
    """R Exp(omega), t + dt for increments ``delta`` (..., p, 1) (``retractPose3Global``)."""
    delta = delta[..., 0]
    group = so(d)
    k = group.tangent_dim
    return Poses(lin.R @ group.exp(delta[..., :k]), lin.t + delta[..., k:])


@functools.partial(jax.jit, static_argnames=("size", "jacobi", "flagged"))
def _pose_stage(graph, part, lin, weights, free, active_first, order, kmax, tol, gamma, *, size, jacobi, flagged):
    """Stage 2: block Gauss–Seidel on the Gauss–Newton system at the padded point ``lin``, increments
    from 0; f is read at the retraction of the current increments (their ``poseTrace``)."""
    d = lin.R.shape[-1]
    edges = _pose_edges(part, free, lin, *weights)
    actives = _selections(part, active_first, flagged)
    p = edges.H_ii.shape[-1]
    X = jnp.zeros((*free.shape, p, 1), lin.R.dtype)
    lin_global = Poses(_global(part, lin.R), _global(part, lin.t))

    def value(X):
        return cost(graph, _retract(lin_global, _global(part, X), d))

    k, X, history, converged = _iterate(X, edges, free, _factors(edges, free, actives), actives, order, value,
                                        size=size, kmax=kmax, tol=tol, gamma=gamma, jacobi=jacobi)
    return k, _retract(lin_global, _global(part, X), d), history, converged


# --------------------------------------------------------------------------------------------
# driver
# --------------------------------------------------------------------------------------------


def _robot_order(graph: PoseGraph, part: Partition, order) -> tuple[np.ndarray, bool]:
    """(update order, whether the first sweep drops separators to robots not yet updated): the flagged
    orders drop them (their ``useFlaggedInit``), a natural or given order does not."""
    A = part.num_robots
    if isinstance(order, str):
        check_choice(None, "order", order, ORDERS)
        if order == "natural":
            return np.arange(A, dtype=np.int32), False
        adj = robot_adjacency(graph, np.asarray(part.robot_of_pose))
        return flagged_order(adj, single=order == "greedy"), True
    order = np.asarray(order, np.int32)
    if sorted(order.tolist()) != list(range(A)):
        raise ValueError(f"order must be a permutation of the {A} robots, got {order.tolist()}")
    return order, False


def _first_sweep_active(part: Partition, order: np.ndarray, flagged: bool) -> np.ndarray:
    """(A, E) bool: the edge slots a robot uses in a stage's first sweep: with flagged initialization,
    intra-robot edges and separators to robots earlier in the order (``neighboringRobotsInitialized_``)."""
    e = part.edges
    local_i, local_j = np.asarray(e.local_i), np.asarray(e.local_j)
    real = local_i | local_j
    if not flagged:
        return real
    position = np.empty(len(order), np.int64)
    position[order] = np.arange(len(order))
    other = np.where(local_i, np.asarray(e.robot_j), np.asarray(e.robot_i))
    earlier = position[other] < position[np.arange(part.num_robots)][:, None]
    return real & ((local_i & local_j) | earlier)


def _free_slots(part: Partition) -> tuple[np.ndarray, int]:
    """(A, n_max) bool free unknowns (real slots other than the anchor) and the anchor pose: robot 0's
    first pose (their code's prior on ``KeyVector(initial.keys()).at(0)`` of robot 0)."""
    free = np.asarray(part.pose_mask).copy()
    free[0, 0] = False
    return free, int(np.asarray(part.pose_index)[0, 0])


def _start(graph: PoseGraph, start) -> tuple[Poses, bool]:
    """(start poses, whether their translations are replaced by 0 at the linearisation point)."""
    if isinstance(start, Poses):
        return initialize(graph, start), False
    check_choice(None, "start", start, STARTS)
    if start == "chordal":
        return initialize(graph, "chordal"), False
    return initialize(graph, "odometry"), True


def _check_connected(graph: PoseGraph) -> None:
    _, sizes, _ = component_labels(graph.num_poses, np.asarray(graph.i), np.asarray(graph.j))
    if len(sizes) > 1:
        raise ValueError(f"DGS needs a connected measurement graph (one anchor); this one has {len(sizes)} "
                         "components")


def _budgets(iterations: int, rotation_iterations, pose_iterations, start) -> tuple[int, int | None]:
    """Stage 1's maximum (None: their code's, the whole budget; 0 for a given start) and stage 2's."""
    check_count(None, "iterations", iterations, 0, scalar=True)
    check_count(None, "rotation_iterations", rotation_iterations, 0, optional=True, scalar=True)
    check_count(None, "pose_iterations", pose_iterations, 0, optional=True, scalar=True)
    if rotation_iterations is None:
        rotation_iterations = iterations if isinstance(start, str) and start == "code" else 0
    return min(int(rotation_iterations), iterations), None if pose_iterations is None else int(pose_iterations)


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

    * ``iterations``: the budget of sweeps (one sweep = every robot once), both stages together: the
      x-axis of ``history``. ``rotation_iterations``: stage 1's maximum (default: 0 for ``start="chordal"``
      or a ``Poses`` start, whose rotations are used as they are; the whole budget for ``"code"``).
      ``pose_iterations``: stage 2's maximum (default: what stage 1 left of the budget).
    * ``start``: "chordal" (Section VIII.B: the centralized chordal estimate), "code" (their code: stage 1
      from the odometry rotations, translations 0) or a :class:`Poses`.
    * ``weights``: "information" (kappa, tau: reproduces the paper's DGS column, benchmarks/dgs_paper.md)
      or "unit" (their code's default).
    * ``order``: "flagged" (their default), "greedy", "natural" (0..A-1, no flagged first sweep) or a
      permutation of the robots. ``jacobi``: all robots at once. ``relaxation``: their gamma.
    * ``rotation_tol`` / ``pose_tol``: their change thresholds (defaults: ``distributedOptimizer``'s; their
      script ``runDistributedMapper`` passes 1e-1 for both, which stops stage 2 within a few sweeps).
    """
    check_choice(None, "weights", weights, WEIGHTS)
    check_real(None, "relaxation", relaxation, 0.0, low_open=True, scalar=True)
    rot_max, pose_max = _budgets(iterations, rotation_iterations, pose_iterations, start)
    _check_connected(graph)
    part = robots if isinstance(robots, Partition) else partition(graph, robots)
    robot_order, flagged = _robot_order(graph, part, order)
    poses, zero_t = _start(graph, start)
    R, t_lin = np.asarray(poses.R), np.asarray(poses.t) * (0.0 if zero_t else 1.0)
    dtype = R.dtype.type
    # host arrays go to the jitted stages as they are (no eager JAX op: each would compile a program);
    # the history buffers hold the whole budget, so runs with the same budget share one compilation
    common = dict(weights=_edge_weights(part, weights == "unit"), free=_free_slots(part)[0],
                  active_first=_first_sweep_active(part, robot_order, flagged), order=robot_order,
                  gamma=dtype(relaxation), jacobi=bool(jacobi), flagged=flagged, size=iterations)
    run = _Run([float(cost(host_view(graph), HostPoses(R, t_lin)))], [STAGE_START])
    relaxed, R = run.rotations(graph, part, R, t_lin, rot_max, dtype(rotation_tol), common)
    kmax = iterations - run.done if pose_max is None else min(iterations - run.done, pose_max)
    final, reason = run.poses(graph, part, Poses(R, t_lin), kmax, dtype(pose_tol), common)
    return DGSResult(final, np.asarray(run.history), np.asarray(run.stage, np.int8), reason, robot_order, relaxed)


@dataclass
class _Run:
    """The host side of a run: the stages in turn, their f and stage labels appended."""

    history: list
    stage: list

    @property
    def done(self) -> int:
        return len(self.history) - 1

    def _record(self, k, hist, label) -> None:
        k = int(k)
        self.history += np.asarray(hist)[:k].tolist()  # sliced on the host: no program per k
        self.stage += [label] * k

    def rotations(self, graph, part, R, t_lin, kmax, tol, common):
        """Stage 1 for up to ``kmax`` sweeps: (relaxed blocks (n, d, d), their projections), or (None, R)
        when ``kmax`` is 0."""
        if kmax == 0:
            return None, R
        X0 = part.scatter(Poses(np.swapaxes(R, 1, 2), t_lin)).R
        k, relaxed, R, hist = _rotation_stage(graph, part, X0, t_lin, kmax=kmax, tol=tol, **common)
        self._record(k, hist, STAGE_ROTATION)
        return relaxed, R

    def poses(self, graph, part, lin: Poses, kmax, tol, common) -> tuple[Poses, str]:
        """Stage 2 at ``lin`` for up to ``kmax`` sweeps: (poses, stop reason)."""
        if kmax == 0:  # no stage 2: the linearisation point, on the device like every other result
            return Poses(jax.device_put(np.asarray(lin.R)), jax.device_put(np.asarray(lin.t))), "max_iterations"
        k, final, hist, converged = _pose_stage(graph, part, part.scatter(lin), kmax=kmax, tol=tol, **common)
        self._record(k, hist, STAGE_POSE)
        return final, "converged" if bool(converged) else "max_iterations"
