"""The robot subproblem: minimise G^alpha(Y | C) over R^{d x n} x SO(d)^n (paper Eq. (21)).

G^alpha(Y | C) = 1/2 <Gamma (Y - C), Y - C> + <g, Y - C> + const is a quadratic with a constant
Gamma^alpha, restricted to the product manifold. Poses are in the stacked layout
Y_i = [t_i | R_i] (n, d, d+1), on which Gamma acts from the right. We use a Riemannian
trust-region Newton method (Absil, Baker & Gallivan 2007), stopped on accuracy:

  1. at the current Y, the Riemannian gradient and the Riemannian Hessian of G^alpha
     (Gamma projected to the tangent space, plus the Weingarten term of SO(d));
  2. the trust-region model is minimised by truncated preconditioned CG (Steihaug-Toint, in the
     preconditioner's norm: it stops at the relative residual ``cg_tolerance``, at the boundary or
     at negative curvature), preconditioned by the inverses of the Hessian's own per-pose
     diagonal blocks (Weingarten term included, rebuilt at each step from constants of Gamma)
     plus a coarse correction on the rigid motions of aggregates of consecutive poses
     (``preconditioner="two-level"``, the default), or by the diagonal blocks alone
     (``"block-jacobi"``); see :mod:`~mmpgo_jax._mm.preconditioner`;
  3. the step is retracted (rotations projected back to SO(d)) and accepted when G^alpha's actual
     decrease is at least a tenth of the model's; the radius (infinite at first: a plain truncated
     Newton step) shrinks to a quarter of a rejected step and doubles after a good boundary step;
  4. it stops when ||grad G^alpha|| has fallen to ``gradient_tolerance`` times its value at the
     start, or -- given the robot's share of the objective -- once the decrease still to gain is
     at most ``decrease_tolerance`` of that share (CG stops on the same test), or after
     ``max_steps`` steps (a safety cap) -- but not before a step was accepted
     (up to 30 more rejected steps, each shrinking the radius 4-fold: returning the start would
     make the next outer iteration repeat the same rejected steps forever); and once a step's
     predicted decrease is within the rounding level of G^alpha's evaluation (below), where no
     further step can be told from noise. That is the gradient's floor in float32: at coordinates
     far from the origin the gradient cannot be evaluated below their rounding, the start's own
     gradient is near that floor late in a run, and the gradient criterion was out of reach (every
     robot ran ``max_steps`` steps: twice the time per iteration on kitti_00 and M3500). In float64
     the rule acts only at rounding level.

Why this choice (measured, benchmarks/inner_solver.md): one Newton step with a budget of CG
iterations was accurate on the benchmark files it was tuned on and 1-2 % off on long odometry
chains, where a full step along the chain's weakly curved directions overshoots; halving that step
does not change its direction, a trust region does. The gradient criterion makes the accuracy of
the inner solve the same on every graph instead of the work; the two-level preconditioner keeps
the work of reaching it small on long chains and on graphs whose rotation curvature dominates
(benchmarks/profile_step.md). The accept test guarantees G^alpha never increases beyond the
rounding of its evaluation (Assumption 1's first half) for any settings, so the outer MM/AMM
guarantees on F hold; letting steps through at that rounding level (a regularized ratio, as in
Manopt's trust regions) is what lets a near-exact inner solve (one robot, A = 1) keep converging
instead of stalling on noise. Everything is fixed-shape and ``vmap``-able (robots that have met
the criterion wait, masked, for the others); Gamma is applied as a block-sparse operator (band +
loop closures).

Lifted poses (RBCD's rank r > d, :mod:`~mmpgo_jax._baselines.rbcd`): Y_i = [t_i | R_i] with r rows,
R_i on the Stiefel manifold St(d, r). Gamma acts from the right, so the value, the gradients, the
tangent projection and the Weingarten term read the same; only the retraction (the polar factor)
depends on the row count, chosen by shape, and the preconditioner is the caller's (anything with
``at``). Square blocks compile to the same code as before.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .._core.geometry import bmm, mT, nearest_rotations, sym
from .._core.lie import so, stiefel_polar
from .._core.validate import check_choice, check_count, check_real
from .majorization import (
    GammaOperator,
    GammaSoA,
    from_soa,
    gamma_to_soa,
    soa_bmm,
    soa_T,
    sym0,
    tangent_soa,
    to_soa,
)

PRECONDITIONERS = ("two-level", "block-jacobi")


class SubproblemConfig(eqx.Module):
    """The robot subproblem's stopping criteria and safety caps, per robot and outer iteration.

    The solver stops on accuracy: when the Riemannian gradient of G^alpha has fallen to
    ``gradient_tolerance`` times its value at the start (for MM: times the robot's block of
    grad F(X^k)), or once a step's predicted decrease is at the rounding level of G^alpha (in
    float32 the gradient's floor can lie above that target); each trust-region step's CG stops at
    the relative residual ``cg_tolerance`` (preconditioned norm). ``max_steps`` (trust-region
    steps) and ``cg_iterations`` (per step) are safety caps that bound the work of one outer
    iteration (benchmarks/profile_step.md counts how often they are reached;
    benchmarks/inner_solver.md compares the result with subproblems solved to convergence).

    The work follows the need (``decrease_tolerance``): the outer loop passes each robot's share of
    the objective, Gbar^alpha(k), and CG stops once the model decrease still to gain, estimated by
    1/2 <r, P r> (r CG's residual, P the preconditioner; exact for P = H^-1), is at most
    ``decrease_tolerance`` times that share; the trust-region loop then stops too if the step was
    accepted and its model predicted the actual decrease to within the same amount (so the new point
    has about twice that left at most; no further evaluation needed). Early in a run an outer
    iteration lowers F by 1e-4-1e-2 of its value and this rule does not act; late in an AMM run,
    where an iteration gains 1e-8 of F or less, a step of one or two CG iterations is enough and is
    all it takes. Default 1e-8, chosen in benchmarks/inner_tolerances.md (1e-7 left a long-chain
    graph at 6.6e-4 of converged inner solves, 1e-6 missed the 0.1 % on kitti_00) and checked in
    benchmarks/inner_solver.md (the 0.1 % criterion at 100/250/1000 iterations on every file).
    The price: once less than 1e-8 of F is left to gain in an outer iteration, every robot takes one
    preconditioned step per iteration, so a run to a tight ``grad_tol`` (with one robot, a run to a
    critical point) reaches its last digits in more (if cheaper) iterations -- set 0 there, as
    ``centralized_optimum(method="mm")`` does. Callers without a share (RBCD's block solves) never
    use the rule.

    Defaults (0.2 and 0.03, chosen by measurement: benchmarks/inner_tolerances.md): most robots
    take one trust-region step per outer iteration, whose CG stops at 3 % of its starting
    residual. The earlier defaults (0.1 and 1e-2) took 1.03-1.53x (AMM) and 1.08-1.46x (MM) more
    time per iteration, for f within 8e-6 of converged inner solves instead of 8.3e-5 (1.5e-5 on
    every benchmark file). Looser CG tolerances (0.05, 0.1) were faster still but let MM fall behind
    on long odometry chains: 2.3e-4 and 8.3e-4 above converged inner solves on a 15 000-pose chain
    graph.

    Static (part of the compiled structure): ``preconditioner`` ("two-level" or "block-jacobi"),
    the caps ``max_steps`` (>= 1) and ``cg_iterations`` (>= 1), and ``aggregate``, the slots per
    coarse aggregate of the two-level preconditioner (None: chosen from the robots' size by
    :func:`~mmpgo_jax._mm.preconditioner.aggregate_size`; a sweep that batches robot counts uses
    the largest size of the batch unless one is given here). Traced (a new value reuses the
    compiled code, and a batch of values can be ``vmap``-ped): ``gradient_tolerance`` in [0, 1)
    (0: run to the caps), ``cg_tolerance`` in (0, 1] and ``decrease_tolerance`` in [0, 1). Every
    field is checked when the config is built (ValueError naming the field and its range); traced
    values (e.g. under ``vmap``) are not.

    The caps stay static on purpose: they bound ``while_loop``s whose trip count is data dependent,
    they are integers nobody sweeps within one run, and under ``vmap`` every lane runs to the
    largest trip count anyway.
    """

    preconditioner: str = eqx.field(static=True, default="two-level")
    gradient_tolerance: float = 0.2
    cg_tolerance: float = 0.03
    decrease_tolerance: float = 1e-8
    max_steps: int = eqx.field(static=True, default=3)
    cg_iterations: int = eqx.field(static=True, default=50)
    aggregate: int | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        owner = "SubproblemConfig"
        check_choice(owner, "preconditioner", self.preconditioner, PRECONDITIONERS)
        # 1 or more would hold at the start: the robot would never move
        check_real(owner, "gradient_tolerance", self.gradient_tolerance, 0.0, 1.0, high_open=True)
        check_real(owner, "cg_tolerance", self.cg_tolerance, 0.0, 1.0, low_open=True)
        check_real(owner, "decrease_tolerance", self.decrease_tolerance, 0.0, 1.0, high_open=True)
        check_count(owner, "max_steps", self.max_steps, 1)
        check_count(owner, "cg_iterations", self.cg_iterations, 1)
        if self.aggregate is not None:
            check_count(owner, "aggregate", self.aggregate, 1)


def project_rotations(M):
    """Nearest rotation to each block (..., d, d): closed form (d = 2), Newton polar (d = 3), SVD
    otherwise -- :func:`~mmpgo_jax._core.geometry.nearest_rotations` with ``method="fast"``. Tall
    blocks (..., r, d), r > d (a lifted rank): the nearest point of the Stiefel manifold, the polar
    factor (:func:`~mmpgo_jax._core.lie.stiefel_polar`)."""
    if M.shape[-2] > M.shape[-1]:
        return jnp.moveaxis(stiefel_polar(jnp.moveaxis(M, (-2, -1), (0, 1))), (0, 1), (-2, -1))
    return nearest_rotations(M, method="fast")


def tangent_projection(Y, V):
    """Orthogonal projection of an ambient direction V onto T_Y (stacked layout (..., n, d, d+1)):
    B - R sym(R^T B) on the rotation columns, for SO(d) and, with r rows (..., n, r, d+1), the
    Stiefel manifold St(d, r) alike."""
    R, VR = Y[..., 1:], V[..., 1:]
    return V.at[..., 1:].add(-bmm(R, sym(bmm(mT(R), VR))))


# --- the solver works in the structure-of-arrays layout: Y (d, d+1, n_max) -------------------


_sym0 = sym0
_tangent_soa = tangent_soa


def _project_soa(M):
    """Nearest rotations for blocks stored as (d, d, n) (the same projection, entries first)."""
    return nearest_rotations(M, method="fast", layout="blocks-first")


def _retract_soa(Y, V):
    """Y + V with the rotations projected back to SO(d) (V tangent at Y): the polar retraction; tall
    rotation blocks (r > d rows, a lifted rank) are projected to the Stiefel manifold."""
    R, B = Y[:, 1:], V[:, 1:]
    r, d = R.shape[:2]
    rotations = stiefel_polar(R + B) if r > d else so(d).retract(R, B)
    return jnp.concatenate([Y[:, :1] + V[:, :1], rotations], axis=1)


def _inner(a, b):
    return jnp.sum(a * b)


def _norm(a):
    return jnp.sqrt(_inner(a, a))


def majorizer_value(gamma, Y, center, g):
    """G^alpha(Y | center) minus its constant term (stacked layout)."""
    D = Y - center
    if isinstance(gamma, GammaSoA):
        Dsoa = to_soa(D)
        return 0.5 * _inner(gamma(Dsoa), Dsoa) + _inner(g, D)
    return 0.5 * _inner(gamma(D), D) + _inner(g, D)


# The scalar state of truncated CG, packed in one vector so that the loop carries (and copies) one
# small array instead of eight: every carried array costs XLA a separate buffer copy per iteration.
_K, _RZ, _VMV, _VMP, _PMP, _OUT, _ACTIVE = range(7)


def _truncated_cg(hess, precond, grad, radius, config: SubproblemConfig, enough=None):
    """Steihaug-Toint truncated PCG for the trust-region model m(v) = <grad, v> + 1/2 <v, H v>.

    The region is ||v||_M <= radius in the norm of M = precond^{-1} (Conn, Gould & Toint, Alg.
    7.5.1), whose value is tracked by recurrences (no application of M). CG stops at the relative
    residual ``cg_tolerance``, at ``cg_iterations``, at the boundary or at negative curvature (there
    it moves to the boundary; with an infinite radius it keeps v, at the first iteration the
    preconditioned gradient), and -- with ``enough`` -- once the model decrease still to gain,
    estimated by 1/2 <r, M^-1 r> (exact for M = H), is at most ``enough`` (after one iteration at
    least). Returns (v, ||v||_M, m(v), hit the boundary, CG iterations, whether ``enough`` was
    reached inside the region).
    """
    r = -grad  # residual of H v = -grad at v = 0
    z = precond(r)
    rz = _inner(r, z)
    stop_at = (config.cg_tolerance**2) * rz
    if enough is not None:  # one test: rz above both thresholds keeps CG going
        stop_at = jnp.maximum(stop_at, 2.0 * enough)
    finite = jnp.isfinite(radius)
    radius2 = jnp.where(finite, radius**2, 0.0)

    def cond(state):
        s = state[-1]
        return (s[_K] < config.cg_iterations) & (s[_ACTIVE] > 0)

    def body(state):
        v, r, p, s = state
        k, rz_k, vMv, vMp, pMp = s[_K], s[_RZ], s[_VMV], s[_VMP], s[_PMP]
        Hp = hess(p)
        pHp = _inner(p, Hp)
        curved = pHp > 0
        alpha = rz_k / jnp.where(curved, pHp, 1.0)
        vMv_cg = vMv + 2.0 * alpha * vMp + alpha**2 * pMp
        outside = (~curved) | (finite & (vMv_cg >= radius2))
        # the step to the boundary along p: ||v + tau p||_M = radius, tau >= 0
        tau = (-vMp + jnp.sqrt(jnp.maximum(vMp**2 + pMp * (radius2 - vMv), 0.0))) / jnp.where(pMp > 0, pMp, 1.0)
        # an infinite radius and negative curvature: keep v (at k = 0 take the preconditioned gradient)
        tau = jnp.where(finite, tau, jnp.where(k == 0, 1.0, 0.0))
        step = jnp.where(outside, tau, alpha)
        v_new = v + step * p
        r_new = r - step * Hp
        z_new = precond(r_new)
        rz_new = _inner(r_new, z_new)
        beta = rz_new / jnp.where(rz_k > 0, rz_k, 1.0)
        p_new = z_new + beta * p
        vp = vMp + step * pMp
        s_new = jnp.stack([
            k + 1.0,
            rz_new,
            vMv + 2.0 * step * vMp + step**2 * pMp,
            beta * vp,
            rz_new + beta**2 * pMp,
            outside.astype(rz.dtype),
            ((~outside) & (rz_new > stop_at)).astype(rz.dtype),
        ])
        return v_new, r_new, p_new, s_new

    zero = jnp.zeros_like(rz)
    s0 = jnp.stack([zero, rz, zero, zero, rz, zero, (rz > 0).astype(rz.dtype)])
    v, r, _, s = jax.lax.while_loop(cond, body, (jnp.zeros_like(grad), r, z, s0))
    model = 0.5 * (_inner(grad, v) - _inner(v, r))  # = <grad, v> + 1/2 <v, H v>, as r = -grad - H v
    small = False if enough is None else (s[_OUT] == 0) & (s[_RZ] <= 2.0 * enough)
    return v, jnp.sqrt(s[_VMV]), model, s[_OUT] > 0, s[_K].astype(jnp.int32), small


class _TrustRegionState(eqx.Module):
    steps: jax.Array
    cg: jax.Array  # CG iterations so far
    Y: jax.Array
    egrad: jax.Array  # Euclidean gradient of G^alpha at Y
    value: jax.Array  # G^alpha(Y) - const
    gnorm: jax.Array  # ||grad G^alpha(Y)|| (Riemannian)
    radius: jax.Array
    moved: jax.Array  # a step has been accepted, or none can be: its predicted decrease is at rounding level
    flat: jax.Array  # the last step's predicted decrease was within the rounding level of G^alpha: stop
    enough: jax.Array  # the last step left at most ~2 ``enough`` to gain (CG's estimate, an accurate model): stop


# Trust-region steps allowed beyond ``max_steps`` while none has been accepted: each rejection
# shrinks the radius at least 4-fold, so 30 cover any scale of a first (infinite-radius) step that
# overshoots (4^-30 ~ 1e-18). Without them a subproblem that rejects ``max_steps`` steps returns its
# start, and the next outer iteration, from the same point and radius, repeats them forever. Steps
# whose predicted decrease is itself at the rounding level of G (a converged robot) end the extra
# steps at once: nothing measurable is left to gain.
EXTRA_REJECTED_STEPS = 30


def _solve(gamma, preconditioner, start, center, g, config: SubproblemConfig, free=None, enough=None):
    """The trust-region loop in the structure-of-arrays layout; returns its final state."""
    def masked(V):  # fixed slots have the tangent space {0}
        return V if free is None else jnp.where(free, V, 0.0)

    def tangent(Y, V):
        return masked(_tangent_soa(Y, V))

    def evaluate(Y):
        D = Y - center
        GD = gamma(D)
        return GD + g, 0.5 * _inner(GD, D) + _inner(g, D)

    def cond(st):
        cap = jnp.where(st.moved, config.max_steps, config.max_steps + EXTRA_REJECTED_STEPS)
        return (st.steps < cap) & (st.gnorm > stop_at) & ~st.flat & ~st.enough

    def body(st):
        Y, egrad = st.Y, st.egrad
        rgrad = tangent(Y, egrad)
        weingarten = _sym0(soa_bmm(soa_T(Y[:, 1:]), egrad[:, 1:]))

        def hess(V):
            GV = gamma(V)
            return tangent(Y, jnp.concatenate([GV[:, :1], GV[:, 1:] - soa_bmm(V[:, 1:], weingarten)], axis=1))

        precond = preconditioner.at(Y, weingarten)
        V, vnorm, model, boundary, cg, small = _truncated_cg(hess, lambda V: masked(precond(V)), rgrad, st.radius,
                                                             config, enough)
        Yc = _retract_soa(Y, V)
        if free is not None:  # re-projecting a fixed rotation would change its last bits
            Yc = jnp.where(free, Yc, Y)
        egrad_c, value_c = evaluate(Yc)
        predicted = -model
        # Near a critical point both decreases fall to the rounding of G^alpha's evaluation (mostly
        # that of the retracted rotations, ~ eps sum |egrad * Y|); regularizing the ratio by that
        # level (as Manopt's trustregions does) accepts such steps instead of stalling on noise.
        noise = 100.0 * jnp.finfo(Y.dtype).eps * jnp.sum(jnp.abs(egrad * Y))
        rho = jnp.where(predicted > 0, (st.value - value_c + noise) / jnp.where(predicted > 0, predicted + noise, 1.0),
                        -jnp.inf)
        accept = (rho > 0.1) & (value_c <= st.value + noise)
        radius = jnp.where(rho < 0.25, 0.25 * vnorm, jnp.where((rho > 0.75) & boundary, 2.0 * st.radius, st.radius))
        Y_new = jnp.where(accept, Yc, Y)
        egrad_new = jnp.where(accept, egrad_c, egrad)
        rgrad_new = tangent(Y_new, egrad_new)
        # CG left at most ``enough`` of the model to gain, and the model predicted this step's decrease
        # to within ``enough``: to that accuracy the new point has at most about 2 ``enough`` left
        done = st.enough if enough is None else accept & small & (jnp.abs(st.value - value_c - predicted) <= enough)
        return _TrustRegionState(
            steps=st.steps + 1, cg=st.cg + cg, Y=Y_new, egrad=egrad_new,
            value=jnp.where(accept, value_c, st.value),
            gnorm=jnp.where(accept, _norm(rgrad_new), st.gnorm),
            radius=radius, moved=st.moved | accept | (predicted <= noise),
            flat=predicted <= noise,
            enough=done,
        )

    egrad, value = evaluate(start)
    gnorm = _norm(tangent(start, egrad))
    stop_at = config.gradient_tolerance * gnorm
    # The counters start as int32, the type the body returns (weakly typed ones made while_loop
    # trace the whole body again with the promoted types), and counters, radius and flag are
    # computed from gnorm so that under vmap (the robots) every carry is batched from the start
    # (else the body, CG loop included, is batched a second time; jnp.zeros_like is not batched).
    # Measured: 30-45 % less tracing of the chunk program, every result the same.
    zero = jnp.where(gnorm == gnorm, 0, 0).astype(jnp.int32)
    init = _TrustRegionState(steps=zero, cg=zero, Y=start, egrad=egrad, value=value, gnorm=gnorm,
                             radius=jnp.where(gnorm == gnorm, jnp.inf, jnp.inf).astype(value.dtype), moved=zero > 0,
                             flat=zero > 0, enough=zero > 0)
    return jax.lax.while_loop(cond, body, init)


def solve_subproblem(gamma, preconditioner, start, center, g, config: SubproblemConfig, free=None, scale=None):
    """Decrease G^alpha(. | center) from ``start`` (on the manifold). Returns (Y, G(Y) - const).

    ``free`` (n,) bool, optional: slots that may move; the others (fixed poses) keep their value
    in ``start`` exactly (their tangent space is {0}, so the model is minimised over the free
    slots only and the step is zero elsewhere).

    Pose arrays are stacked (n, d, d+1); ``g`` is the (possibly extrapolated) Euclidean gradient
    of F at ``center``; ``gamma`` is Gamma^alpha (``GammaOperator`` or its ``GammaSoA`` form) and
    ``preconditioner`` the data of the Newton system's preconditioner
    (:class:`~mmpgo_jax._mm.preconditioner.NewtonPreconditioner`: anything with ``at(Y, W)``
    giving a tangent-space operator). The returned value never exceeds the value at ``start`` by
    more than the rounding of its evaluation.

    ``scale`` (scalar, optional): the robot's share of the objective (the outer loop passes
    Gbar^alpha(k)); with it, the solve also stops once a step leaves about
    ``config.decrease_tolerance * scale`` of decrease to gain (see
    :class:`SubproblemConfig`). Without it only the gradient criterion stops the solve.
    Internally everything runs in the structure-of-arrays layout (d, d+1, n).
    """
    st = subproblem_steps(gamma, preconditioner, start, center, g, config, free, scale)
    return from_soa(st.Y), st.value


def subproblem_steps(gamma, preconditioner, start, center, g, config: SubproblemConfig, free=None, scale=None):
    """:func:`solve_subproblem`'s final trust-region state (structure-of-arrays ``Y``, ``value``,
    ``gnorm``, ``radius``, and the ``steps`` and ``cg`` iteration counts it took)."""
    if isinstance(gamma, GammaOperator):
        gamma = gamma_to_soa(gamma)
    enough = None if scale is None else config.decrease_tolerance * jnp.abs(scale)
    return _solve(gamma, preconditioner, to_soa(start), to_soa(center), to_soa(g), config, free, enough)
