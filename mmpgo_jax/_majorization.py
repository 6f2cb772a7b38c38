"""Per-robot quantities of the majorization (paper §IV-V, Appendix A, NOTES §3).

All functions here act on ONE robot (its padded incident edges) and are meant to be
``jax.vmap``-ped over the robot axis. A robot reads neighbour poses only at the remote ends of
its inter-robot edges, through a gather from the padded global pose array.

For a robot alpha with local poses Y (slots 0..n_max-1):
  * ``gradient_and_share``: the block grad_alpha F(X) of the Euclidean gradient and the robot's
    share Gbar^alpha = sum(own edges) F_e + 1/2 sum(inter edges) F_e, so that sum_alpha Gbar = F.
  * ``apply_gamma``: V -> Gamma^alpha V with Gamma^alpha = Omega^alpha + xi I (A.15-A.18): the
    Hessian of the robot's own edges plus, for each inter-robot edge, twice the Hessian of the
    edge with the remote end held fixed.
  * ``gamma_diagonal_blocks``: the per-pose (d+1)x(d+1) diagonal blocks of Gamma^alpha, in the
    stacked layout Y_i = [t_i | R_i] (d x (d+1)) on which Gamma acts from the right.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ._partition import RobotEdges
from ._pose_graph import Poses


def _edge_residuals(edges: RobotEdges, Ri, ti, Rj, tj):
    rot = Ri @ edges.R - Rj
    trans = jnp.einsum("eab,eb->ea", Ri, edges.t) + ti - tj
    return rot, trans


def _adjoint_to_slots(edges: RobotEdges, wrot, wtrans, mask_i, mask_j, n_max: int) -> Poses:
    """Scatter weighted residuals back to the local endpoint slots (adjoint of the residual map)."""
    gRi = wrot @ jnp.swapaxes(edges.R, -1, -2) + wtrans[:, :, None] * edges.t[:, None, :]
    mi = mask_i[:, None, None]
    mj = mask_j[:, None, None]
    gR = jax.ops.segment_sum(jnp.where(mi, gRi, 0.0), edges.slot_i, n_max)
    gR = gR - jax.ops.segment_sum(jnp.where(mj, wrot, 0.0), edges.slot_j, n_max)
    gt = jax.ops.segment_sum(jnp.where(mask_i[:, None], wtrans, 0.0), edges.slot_i, n_max)
    gt = gt - jax.ops.segment_sum(jnp.where(mask_j[:, None], wtrans, 0.0), edges.slot_j, n_max)
    return Poses(gR, gt)


def gradient_and_share(edges: RobotEdges, X: Poses, n_max: int):
    """(grad_alpha F(X) over local slots, Gbar^alpha(X), local cost) for one robot.

    The local cost counts every incident edge fully (own and inter-robot): the objective the
    robot would see if its neighbours were fixed.

    ``X`` is the padded GLOBAL pose array (A, n_max, ...): endpoint poses are gathered from it,
    which is exactly the neighbour communication of one iteration.
    """
    Ri, ti = X.R[edges.robot_i, edges.slot_i], X.t[edges.robot_i, edges.slot_i]
    Rj, tj = X.R[edges.robot_j, edges.slot_j], X.t[edges.robot_j, edges.slot_j]
    rot, trans = _edge_residuals(edges, Ri, ti, Rj, tj)
    wrot = edges.kappa[:, None, None] * rot
    wtrans = edges.tau[:, None] * trans
    grad = _adjoint_to_slots(edges, wrot, wtrans, edges.local_i, edges.local_j, n_max)
    edge_F = 0.5 * (jnp.sum(wrot * rot, axis=(-1, -2)) + jnp.sum(wtrans * trans, axis=-1))
    share = jnp.sum(jnp.where(edges.is_inter, 0.5, 1.0) * edge_F)
    return grad, share, jnp.sum(edge_F)


def apply_gamma(edges: RobotEdges, xi, V: Poses) -> Poses:
    """Gamma^alpha V for a local tangent/ambient direction V (n_max slots)."""
    n_max = V.R.shape[0]
    zR = jnp.zeros_like(V.R[edges.slot_i])
    zt = jnp.zeros_like(V.t[edges.slot_i])
    Ri = jnp.where(edges.local_i[:, None, None], V.R[edges.slot_i], zR)
    ti = jnp.where(edges.local_i[:, None], V.t[edges.slot_i], zt)
    Rj = jnp.where(edges.local_j[:, None, None], V.R[edges.slot_j], zR)
    tj = jnp.where(edges.local_j[:, None], V.t[edges.slot_j], zt)
    rot, trans = _edge_residuals(edges, Ri, ti, Rj, tj)
    # Inter-robot edges enter the majorizer with factor 2 on the local end (Eq. (5)).
    w = jnp.where(edges.is_inter, 2.0, 1.0)
    wrot = (w * edges.kappa)[:, None, None] * rot
    wtrans = (w * edges.tau)[:, None] * trans
    out = _adjoint_to_slots(edges, wrot, wtrans, edges.local_i, edges.local_j, n_max)
    return Poses(out.R + xi * V.R, out.t + xi * V.t)


def gamma_diagonal_blocks(edges: RobotEdges, xi, n_max: int):
    """Diagonal blocks (n_max, d+1, d+1) of Gamma^alpha in the layout Y_i = [t_i | R_i]."""
    d = edges.t.shape[-1]
    dt = edges.t.dtype
    w = jnp.where(edges.is_inter, 2.0, 1.0)
    a = jnp.concatenate([jnp.ones(edges.t.shape[:-1] + (1,), dt), edges.t], -1)  # [1; tt]
    rot_block = jnp.diag(jnp.concatenate([jnp.zeros(1, dt), jnp.ones(d, dt)]))
    e0 = jnp.zeros(d + 1, dt).at[0].set(1.0)
    tail = (w * edges.tau)[:, None, None] * a[:, :, None] * a[:, None, :]
    tail = tail + (w * edges.kappa)[:, None, None] * rot_block
    head = (w * edges.tau)[:, None, None] * jnp.outer(e0, e0) + (w * edges.kappa)[:, None, None] * rot_block
    B = jax.ops.segment_sum(jnp.where(edges.local_i[:, None, None], tail, 0.0), edges.slot_i, n_max)
    B = B + jax.ops.segment_sum(jnp.where(edges.local_j[:, None, None], head, 0.0), edges.slot_j, n_max)
    return B + xi * jnp.eye(d + 1, dtype=dt)


def inner(a: Poses, b: Poses):
    """Frobenius inner product of two Poses-shaped pairs."""
    return jnp.sum(a.R * b.R) + jnp.sum(a.t * b.t)


def majorizer_decrease(edges: RobotEdges, xi, D: Poses, grad: Poses):
    """G^alpha(X^alpha + D | X) - Gbar^alpha(X) = 1/2 <Gamma D, D> + <grad_alpha F(X), D>."""
    return 0.5 * inner(apply_gamma(edges, xi, D), D) + inner(grad, D)
