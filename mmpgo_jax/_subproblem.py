"""The robot subproblem: minimise G^alpha(Y | center) over R^{d x n} x SO(d)^n (paper Eq. (21)).

G^alpha(Y | C) = 1/2 <Gamma (Y - C), Y - C> + <g, Y - C> + const is a quadratic with a constant
Gamma^alpha, restricted to the product manifold. We use a Riemannian truncated-Newton method:

  1. at the current Y, the Riemannian gradient and the Riemannian Hessian of G^alpha
     (Euclidean Hessian Gamma projected to the tangent space, plus the Weingarten term of SO(d));
  2. the Newton system is solved by truncated preconditioned CG (Steihaug-Toint: it stops at
     negative curvature or at a relative residual ``cg_tolerance``), preconditioned by the inverse
     of Gamma's per-pose (d+1)x(d+1) diagonal blocks (computed once: Gamma is constant);
  3. the step is retracted (rotations by SVD/closed-form projection to SO(d)) and accepted only if
     G^alpha decreases, else it is halved (``max_backtracks`` times) and finally rejected.

Why this choice: a warm-started Newton step on a quadratic is near exact when rotations move
little, which is the regime of every MM iteration after the first few; the accept/reject test
guarantees G^alpha never increases (Assumption 1's first half) at any inner budget, so the outer
MM/AMM guarantees hold for every setting of the budget. Everything is fixed-shape and ``vmap``-able.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ._geometry import project_to_so, sym
from ._majorization import apply_gamma, gamma_diagonal_blocks, inner
from ._partition import RobotEdges
from ._pose_graph import Poses


class SubproblemConfig(eqx.Module):
    """Inner-solver budget, per robot and outer iteration."""

    newton_steps: int = eqx.field(static=True, default=1)
    cg_iterations: int = eqx.field(static=True, default=20)
    cg_tolerance: float = eqx.field(static=True, default=1e-2)
    max_backtracks: int = eqx.field(static=True, default=4)


def project_rotations(M):
    """Nearest rotation to each block; closed form for d = 2, SVD otherwise."""
    if M.shape[-1] == 2:
        a = M[..., 0, 0] + M[..., 1, 1]
        b = M[..., 1, 0] - M[..., 0, 1]
        r = jnp.sqrt(a * a + b * b)
        safe = r > 0
        c = jnp.where(safe, a / jnp.where(safe, r, 1.0), 1.0)
        s = jnp.where(safe, b / jnp.where(safe, r, 1.0), 0.0)
        return jnp.stack([jnp.stack([c, -s], -1), jnp.stack([s, c], -1)], -2)
    return project_to_so(M)


def tangent_projection(R, V: Poses) -> Poses:
    """Orthogonal projection of an ambient direction onto T_Y (R^{d x n} x SO(d)^n)."""
    return Poses(V.R - R @ sym(jnp.swapaxes(R, -1, -2) @ V.R), V.t)


def retract(Y: Poses, V: Poses) -> Poses:
    return Poses(project_rotations(Y.R + V.R), Y.t + V.t)


def block_preconditioner(edges: RobotEdges, xi, n_max: int):
    """Inverses of Gamma's per-pose diagonal blocks (n_max, d+1, d+1); constant over iterations."""
    return jnp.linalg.inv(gamma_diagonal_blocks(edges, xi, n_max))


def _apply_block_inverse(Binv, V: Poses) -> Poses:
    # Gamma acts from the right on Y_i = [t_i | R_i]; so does its block inverse.
    Y = jnp.concatenate([V.t[..., None], V.R], axis=-1)
    Z = Y @ Binv
    return Poses(Z[..., 1:], Z[..., 0])


def majorizer_value(edges: RobotEdges, xi, Y: Poses, center: Poses, g: Poses):
    """G^alpha(Y | center) minus its constant term."""
    D = Y - center
    return 0.5 * inner(apply_gamma(edges, xi, D), D) + inner(g, D)


def _truncated_cg(hess, precond, grad: Poses, config: SubproblemConfig) -> Poses:
    """Steihaug-Toint truncated PCG for hess(v) = -grad (no trust radius: negative curvature stops)."""
    zero = jax.tree.map(jnp.zeros_like, grad)
    r = jax.tree.map(jnp.negative, grad)
    z = precond(r)
    rz = inner(r, z)
    stop_at = (config.cg_tolerance**2) * rz

    def cond(state):
        k, _, _, _, _, rz_k, active = state
        return (k < config.cg_iterations) & active

    def body(state):
        k, v, r, z, p, rz_k, active = state
        Hp = hess(p)
        pHp = inner(p, Hp)
        negative = pHp <= 0
        # On negative curvature at the first step fall back to the preconditioned gradient.
        first = k == 0
        alpha = rz_k / jnp.where(negative, 1.0, pHp)
        v_step = jax.tree.map(lambda v_, p_: v_ + alpha * p_, v, p)
        v_new = jax.tree.map(
            lambda vs, v_, z_: jnp.where(negative, jnp.where(first, z_, v_), vs), v_step, v, z
        )
        r_new = jax.tree.map(lambda r_, h_: r_ - alpha * h_, r, Hp)
        z_new = precond(r_new)
        rz_new = inner(r_new, z_new)
        beta = rz_new / jnp.where(rz_k > 0, rz_k, 1.0)
        p_new = jax.tree.map(lambda z_, p_: z_ + beta * p_, z_new, p)
        still = (~negative) & (rz_new > stop_at)
        return k + 1, v_new, r_new, z_new, p_new, rz_new, still

    state = (jnp.asarray(0), zero, r, z, z, rz, rz > 0)
    _, v, *_ = jax.lax.while_loop(cond, body, state)
    return v


def solve_subproblem(
    edges: RobotEdges,
    xi,
    block_inverse,
    start: Poses,
    center: Poses,
    g: Poses,
    config: SubproblemConfig,
):
    """Decrease G^alpha(. | center) from ``start`` (on the manifold). Returns (Y, G(Y) - const).

    ``g`` is the (possibly extrapolated) gradient at ``center``; ``block_inverse`` from
    :func:`block_preconditioner`. The returned value never exceeds the value at ``start``.
    """

    def value(Y):
        return majorizer_value(edges, xi, Y, center, g)

    def newton_step(_, carry):
        Y, G_Y = carry
        egrad = apply_gamma(edges, xi, Y - center) + g
        rgrad = tangent_projection(Y.R, egrad)
        weingarten = sym(jnp.swapaxes(Y.R, -1, -2) @ egrad.R)

        def hess(V):
            HV = apply_gamma(edges, xi, V)
            return tangent_projection(Y.R, Poses(HV.R - V.R @ weingarten, HV.t))

        def precond(V):
            return tangent_projection(Y.R, _apply_block_inverse(block_inverse, V))

        V = _truncated_cg(hess, precond, rgrad, config)

        def bt_cond(state):
            k, _, _, accepted = state
            return (k <= config.max_backtracks) & ~accepted

        def bt_body(state):
            k, Ybest, Gbest, _ = state
            step = 0.5**k
            Yc = retract(Y, V.scale(step))
            Gc = value(Yc)
            ok = Gc <= G_Y
            Ybest = jax.tree.map(lambda a, b: jnp.where(ok, b, a), Ybest, Yc)
            return k + 1, Ybest, jnp.where(ok, Gc, Gbest), ok

        _, Y_new, G_new, _ = jax.lax.while_loop(bt_cond, bt_body, (jnp.asarray(0), Y, G_Y, jnp.asarray(False)))
        return Y_new, G_new

    G0 = value(start)
    return jax.lax.fori_loop(0, config.newton_steps, newton_step, (start, G0))
