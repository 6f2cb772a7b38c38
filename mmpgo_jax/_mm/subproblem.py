"""The robot subproblem: minimise G^alpha(Y | C) over R^{d x n} x SO(d)^n (paper Eq. (21)).

G^alpha(Y | C) = 1/2 <Gamma (Y - C), Y - C> + <g, Y - C> + const is a quadratic with a constant
Gamma^alpha, restricted to the product manifold. Poses are in the stacked layout
Y_i = [t_i | R_i] (n, d, d+1), on which Gamma acts from the right. We use a Riemannian
truncated-Newton method:

  1. at the current Y, the Riemannian gradient and the Riemannian Hessian of G^alpha
     (Gamma projected to the tangent space, plus the Weingarten term of SO(d));
  2. the Newton system is solved by truncated preconditioned CG (Steihaug-Toint: it stops at
     negative curvature or at a relative residual ``cg_tolerance``), preconditioned by the
     inverses of Gamma's per-pose diagonal blocks (``preconditioner="block-jacobi"``, the default)
     or by the exact inverse of its block-tridiagonal (chain) part (``preconditioner="chain"``);
     both are factored once, since Gamma is constant;
  3. the step is retracted (rotations projected back to SO(d)) and accepted only if G^alpha
     decreases, else halved (``max_backtracks`` times) and finally rejected.

Why this choice: a warm-started Newton step on a quadratic is near exact when rotations move
little, which is the regime of every MM iteration after the first few; measured on the benchmark
files, one Newton step with up to 20 CG iterations reproduces the per-iteration progress of the
authors' code (more inner work does not change f after 100/250/1000 iterations in the 4th digit).
The accept/reject test guarantees G^alpha never increases (Assumption 1's first half) at any
inner budget, so the outer MM/AMM guarantees on F hold for every budget. Everything is
fixed-shape and ``vmap``-able; Gamma is applied as a block-sparse operator (band + loop closures).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._core.geometry import bmm, mT, nearest_rotations, sym
from .majorization import (
    GammaOperator,
    GammaSoA,
    from_soa,
    gamma_to_soa,
    preconditioner_to_soa,
    soa_bmm,
    soa_T,
    to_soa,
)

# --- config validation (shared with MMConfig) ------------------------------------------------


def concrete_value(x):
    """``x`` as a numpy array, or None when it is traced (under jit / vmap: not checkable)."""
    try:
        return np.asarray(x)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return None


def check_choice(owner: str, name: str, value, allowed) -> None:
    if not isinstance(value, str) or value not in allowed:
        options = " or ".join(repr(a) for a in allowed)
        raise ValueError(f"{owner}.{name}: unknown {name} {value!r}: use {options}")


def check_count(owner: str, name: str, value, low: int) -> None:
    """A Python (or numpy) integer >= low; traced values are accepted unchecked."""
    v = concrete_value(value)
    if v is None:
        return
    if isinstance(value, bool) or v.dtype.kind not in "iu" or v.size == 0 or np.any(v < low):
        raise ValueError(f"{owner}.{name} must be an integer >= {low}, got {value!r}")


def check_real(owner: str, name: str, value, low: float, high: float | None = None, *,
               low_open: bool = False) -> None:
    """A finite real number in [low, high] ((low, high] with ``low_open``); arrays are checked
    elementwise; traced values (under jit / vmap) are accepted unchecked."""
    v = concrete_value(value)
    if v is None:
        return
    ok = not isinstance(value, bool) and v.dtype.kind in "iuf" and v.size > 0
    if ok:
        v = v.astype(np.float64)
        ok = bool(np.all(np.isfinite(v)) and np.all(v > low if low_open else v >= low))
        ok = ok and (high is None or bool(np.all(v <= high)))
    if not ok:
        lo = "(" if low_open else "["
        rng = f"in {lo}{low:g}, {high:g}]" if high is not None else (f"> {low:g}" if low_open else f">= {low:g}")
        raise ValueError(f"{owner}.{name} must be a finite number {rng}, got {value!r}")


PRECONDITIONERS = ("block-jacobi", "chain")


class SubproblemConfig(eqx.Module):
    """Inner-solver budget, per robot and outer iteration.

    Static (part of the compiled structure): ``preconditioner`` ("block-jacobi" or "chain") and
    the loop budgets ``newton_steps`` (>= 1), ``cg_iterations`` (>= 1) and ``max_backtracks``
    (>= 0; 0 tries the full step only). Traced (a new value reuses the compiled code, and a
    batch of values can be ``vmap``-ped): ``cg_tolerance`` in (0, 1], CG's relative residual
    (preconditioned norm) at which it stops. Every field is checked when the config is built
    (ValueError naming the field and its range); traced values (e.g. under ``vmap``) are not.

    The budgets stay static on purpose: they set the kind of loop XLA compiles (a fixed-length
    ``fori_loop`` for the Newton steps), they are integers that nobody sweeps within one run, and a
    batched budget under ``vmap`` would run every lane to the largest one anyway.
    """

    newton_steps: int = eqx.field(static=True, default=1)
    preconditioner: str = eqx.field(static=True, default="block-jacobi")
    cg_iterations: int = eqx.field(static=True, default=20)
    cg_tolerance: float = 1e-2
    max_backtracks: int = eqx.field(static=True, default=4)

    def __check_init__(self):
        owner = "SubproblemConfig"
        check_count(owner, "newton_steps", self.newton_steps, 1)
        check_choice(owner, "preconditioner", self.preconditioner, PRECONDITIONERS)
        check_count(owner, "cg_iterations", self.cg_iterations, 1)
        check_real(owner, "cg_tolerance", self.cg_tolerance, 0.0, 1.0, low_open=True)
        check_count(owner, "max_backtracks", self.max_backtracks, 0)


def project_rotations(M):
    """Nearest rotation to each block (..., d, d): closed form (d = 2), Newton polar (d = 3), SVD
    otherwise -- :func:`~mmpgo_jax._core.geometry.nearest_rotations` with ``method="fast"``."""
    return nearest_rotations(M, method="fast")


def tangent_projection(Y, V):
    """Orthogonal projection of an ambient direction V onto T_Y (stacked layout (..., n, d, d+1))."""
    R, VR = Y[..., 1:], V[..., 1:]
    return V.at[..., 1:].add(-bmm(R, sym(bmm(mT(R), VR))))


# --- the solver works in the structure-of-arrays layout: Y (d, d+1, n_max) -------------------


def _sym0(M):
    return 0.5 * (M + soa_T(M))


def _tangent_soa(Y, V):
    R = Y[:, 1:]
    return V.at[:, 1:].add(-soa_bmm(R, _sym0(soa_bmm(soa_T(R), V[:, 1:]))))


def _project_soa(M):
    """Nearest rotations for blocks stored as (d, d, n) (the same projection, entries first)."""
    return nearest_rotations(M, method="fast", layout="blocks-first")


def _retract_soa(Y, V):
    return jnp.concatenate([Y[:, :1] + V[:, :1], _project_soa(Y[:, 1:] + V[:, 1:])], axis=1)


def _inner(a, b):
    return jnp.sum(a * b)


def _value_soa(gamma: GammaSoA, Y, center, g):
    D = Y - center
    return 0.5 * _inner(gamma(D), D) + _inner(g, D)


def majorizer_value(gamma, Y, center, g):
    """G^alpha(Y | center) minus its constant term (stacked layout)."""
    D = Y - center
    if isinstance(gamma, GammaSoA):
        Dsoa = to_soa(D)
        return 0.5 * _inner(gamma(Dsoa), Dsoa) + _inner(g, D)
    return 0.5 * _inner(gamma(D), D) + _inner(g, D)


def _truncated_cg(hess, precond, grad, config: SubproblemConfig):
    """Steihaug-Toint truncated PCG for hess(v) = -grad (no trust radius: negative curvature stops)."""
    r = -grad
    z = precond(r)
    rz = _inner(r, z)
    stop_at = (config.cg_tolerance**2) * rz

    def cond(state):
        k, *_, active = state
        return (k < config.cg_iterations) & active

    def body(state):
        k, v, r, z, p, rz_k, _ = state
        Hp = hess(p)
        pHp = _inner(p, Hp)
        negative = pHp <= 0
        alpha = rz_k / jnp.where(negative, 1.0, pHp)
        # On negative curvature keep v (at the first step: the preconditioned gradient).
        v_new = jnp.where(negative, jnp.where(k == 0, z, v), v + alpha * p)
        r_new = r - alpha * Hp
        z_new = precond(r_new)
        rz_new = _inner(r_new, z_new)
        p_new = z_new + (rz_new / jnp.where(rz_k > 0, rz_k, 1.0)) * p
        return k + 1, v_new, r_new, z_new, p_new, rz_new, (~negative) & (rz_new > stop_at)

    state = (jnp.asarray(0), jnp.zeros_like(grad), r, z, z, rz, rz > 0)
    return jax.lax.while_loop(cond, body, state)[1]


def solve_subproblem(gamma, preconditioner, start, center, g, config: SubproblemConfig, free=None):
    """Decrease G^alpha(. | center) from ``start`` (on the manifold). Returns (Y, G(Y) - const).

    ``free`` (n,) bool, optional: slots that may move; the others (fixed poses) keep their value
    in ``start`` exactly (their tangent space is {0}, so the Newton system is solved on the free
    slots only and the step is zero elsewhere).

    Pose arrays are stacked (n, d, d+1); ``g`` is the (possibly extrapolated) Euclidean gradient
    of F at ``center``; ``gamma`` is Gamma^alpha (``GammaOperator`` or its ``GammaSoA`` form) and
    ``preconditioner`` approximates its inverse (``BlockJacobi``, ``ChainPreconditioner`` or their
    structure-of-arrays forms). The returned value never exceeds the value at ``start``.
    Internally everything runs in the structure-of-arrays layout (d, d+1, n).
    """
    if isinstance(gamma, GammaOperator):
        gamma = gamma_to_soa(gamma)
    precond_soa = preconditioner_to_soa(preconditioner)
    center, g = to_soa(center), to_soa(g)

    def newton_step(_, carry):
        Y, G_Y = carry
        egrad = gamma(Y - center) + g

        def tangent(V):
            return _tangent_soa(Y, V) if free is None else jnp.where(free, _tangent_soa(Y, V), 0.0)

        rgrad = tangent(egrad)
        weingarten = _sym0(soa_bmm(soa_T(Y[:, 1:]), egrad[:, 1:]))

        def hess(V):
            HV = gamma(V)
            return tangent(HV.at[:, 1:].add(-soa_bmm(V[:, 1:], weingarten)))

        def precond(V):
            return tangent(precond_soa(V))

        V = _truncated_cg(hess, precond, rgrad, config)

        def bt_cond(state):
            k, _, _, accepted = state
            return (k <= config.max_backtracks) & ~accepted

        def bt_body(state):
            k, Ybest, Gbest, _ = state
            Yc = _retract_soa(Y, (0.5**k) * V)
            if free is not None:  # re-projecting a fixed rotation would change its last bits
                Yc = jnp.where(free, Yc, Y)
            Gc = _value_soa(gamma, Yc, center, g)
            ok = Gc <= G_Y
            return k + 1, jnp.where(ok, Yc, Ybest), jnp.where(ok, Gc, Gbest), ok

        init = (jnp.asarray(0), Y, G_Y, jnp.asarray(False))
        _, Y_new, G_new, _ = jax.lax.while_loop(bt_cond, bt_body, init)
        return Y_new, G_new

    start = to_soa(start)
    G0 = _value_soa(gamma, start, center, g)
    Y, G = jax.lax.fori_loop(0, config.newton_steps, newton_step, (start, G0))
    return from_soa(Y), G
