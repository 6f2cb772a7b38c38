"""DGS's traced pieces (:mod:`mmpgo_jax._baselines.dgs`): each stage's quadratic per incident edge
slot, the robots' dense local factors, their exact local solves and one sweep over the robots.

A sweep is ``lax.scan`` over its steps; at step k the robots whose ``position`` is k solve their local
problems from the latest values of everything else, read through the layout's
:class:`~mmpgo_jax._mm.weighting.Collectives` (one device: the iterate itself; sharded: the neighbour
poses). Sequential Gauss–Seidel has one robot per step (only its lane is solved), a colour class of
the robot graph many (no two of them neighbours: ``vmap``, the same as one after the other), Jacobi
all robots in one step.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax
from jax.scipy.linalg import cho_solve

from .._core.geometry import mT
from .._core.lie import so
from .._core.partition import Partition
from .._core.pose_graph import Poses


class Edges(NamedTuple):
    """One stage's quadratic per incident edge slot, (A, E, ...): the edge's cost is
    x_i^T H_ii x_i + x_j^T H_jj x_j + 2 x_i^T H_ij x_j + 2 g_i^T x_i + 2 g_j^T x_j + const,
    with x (q, c) per pose; ``unknown_*`` marks an end that is a free unknown of the robot holding the
    slot (a local pose that is not held)."""

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


def rotation_edges(part: Partition, free, wr) -> Edges:
    """Stage 1 (``createLinearOrientationGraph``): w ||R_i R~ - R_j||^2 with x_p = R_p^T (d x d, d
    right-hand sides): H_ii = w R~ R~^T, H_jj = w I, H_ij = -w R~, no linear term."""
    e = part.edges
    w = wr[..., None, None]
    d = e.R.shape[-1]
    eye = jnp.eye(d, dtype=e.R.dtype)
    zero = jnp.zeros(e.R.shape, e.R.dtype)
    unknown_i, unknown_j = _unknown_ends(part, free)
    return Edges(w * (e.R @ mT(e.R)), w * eye, -w * e.R, zero, zero, e.robot_i, e.slot_i, e.robot_j, e.slot_j,
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


def pose_edges(part: Partition, free, lin: Poses, wr, wt) -> Edges:
    """Stage 2: the Gauss–Newton model of every edge at the padded linearisation point ``lin``
    (A, n_max, ...): H = J^T J, g = J^T r0 (one right-hand side)."""
    e = part.edges
    Ji, Jj, r0 = _pose_jacobians(lin.R[e.robot_i, e.slot_i], lin.t[e.robot_i, e.slot_i], lin.R[e.robot_j, e.slot_j],
                                 lin.t[e.robot_j, e.slot_j], e.R, e.t, wr, wt)
    unknown_i, unknown_j = _unknown_ends(part, free)
    g_i = jnp.einsum("...ra,...r->...a", Ji, r0)[..., None]
    g_j = jnp.einsum("...ra,...r->...a", Jj, r0)[..., None]
    return Edges(mT(Ji) @ Ji, mT(Jj) @ Jj, mT(Ji) @ Jj, g_i, g_j, e.robot_i, e.slot_i, e.robot_j, e.slot_j,
                 unknown_i, unknown_j)


def _local_matrix(edges: Edges, free, active):
    """One robot's dense system matrix (n_max q square): its active edges' blocks on its free unknowns;
    identity rows on held and padding slots (their values are kept)."""
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


def factors(edges: Edges, free, actives):
    """Cholesky factors (A, S, N, N) of every robot's local matrix for each of its S edge selections
    ``actives`` (A, S, E), one robot at a time (``lax.map``: the peak memory is one dense assembly).

    Selection 0 is the first sweep's (flagged separators dropped); a robot whose reduced system there
    is singular keeps all its separators (the last selection's factor)."""

    def robot(args):
        edges, free, actives = args
        chol = jnp.stack([jnp.linalg.cholesky(_local_matrix(edges, free, active)) for active in actives])
        ok = jnp.all(jnp.isfinite(chol), axis=(1, 2))[:, None, None]
        return jnp.where(ok, chol, chol[-1])

    return lax.map(robot, (edges, free, actives))


def _local_solve(X, own, edges: Edges, free, chol, active):
    """One robot's exact local solve: its free unknowns given the latest values ``X`` (A, n_max, q, c)
    of everything else (separator ends and held poses); ``own`` (n_max, q, c) its current values."""
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


def _lane(tree, j):
    return jax.tree_util.tree_map(lambda a: a[j], tree)


def sweep(stage, Z, s, gamma, comm, *, one_lane: bool):
    """One sweep of ``stage`` (its ``edges``, ``free``, ``chols``, ``active``, ``position``, ``steps``)
    from the unknowns Z (A_local, n_max, q, c) with the edge selection ``s``: (Z, each robot's change
    ||x_new - x_old|| (0 where it did not update)). Over-relaxation x <- (1 - gamma) x + gamma x_new.
    ``one_lane``: at most one robot per step on this device (sequential Gauss–Seidel: only its lane
    is solved)."""
    chol, active = stage.chols[:, s], stage.active[:, s]

    def step(carry, k):
        Z, change = carry
        full = comm.gather_poses(Z)  # the latest values: robots earlier in the sweep have updated
        mine = stage.position == k
        if one_lane:
            j = jnp.argmax(mine)
            own = Z[j]
            new = _local_solve(full, own, _lane(stage.edges, j), stage.free[j], chol[j], active[j])
            Z = Z.at[j].set(jnp.where(mine[j], (1.0 - gamma) * own + gamma * new, own))
            return (Z, change.at[j].set(jnp.where(mine[j], jnp.linalg.norm(new - own), change[j]))), None
        new = jax.vmap(_local_solve, in_axes=(None, 0, 0, 0, 0, 0))(full, Z, stage.edges, stage.free, chol, active)
        change = jnp.where(mine, jnp.sqrt(jnp.sum((new - Z) ** 2, axis=(1, 2, 3))), change)
        return (jnp.where(mine[:, None, None, None], (1.0 - gamma) * Z + gamma * new, Z), change), None

    (Z, change), _ = lax.scan(step, (Z, jnp.zeros(Z.shape[:1], Z.dtype)), jnp.arange(stage.steps))
    return Z, change


def retract(lin: Poses, delta) -> Poses:
    """R Exp(omega), t + dt for increments ``delta`` (..., p, 1) (``retractPose3Global``)."""
    delta = delta[..., 0]
    group = so(lin.R.shape[-1])
    k = group.tangent_dim
    return Poses(lin.R @ group.exp(delta[..., :k]), lin.t + delta[..., k:])
