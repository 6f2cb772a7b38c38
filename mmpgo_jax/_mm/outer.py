"""MM-PGO (Algorithm 1) and AMM-PGO (Algorithm 2), all robots at once.

One outer iteration = one ``vmap`` over robots of the subproblem solver, then one ``vmap`` of the
gradient/objective-share evaluation (which gathers neighbour poses). Outer iterations run in
``lax.scan``; per-robot momentum s, gamma and restarts live in the scan carry. ``run`` is jitted
with a static chunk length, so running 1000 iterations as 10 chunks of 100 compiles once.
"""

from __future__ import annotations

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._core.partition import Partition
from .._core.pose_graph import Poses
from .._core.precision import to_device
from .._core.validate import check_choice, check_count, check_real, concrete_value
from .majorization import (
    GammaOperator,
    GammaSoA,
    build_gamma_operator,
    gamma_layout,
    host_soa,
    soa_to_gamma,
    stack,
)
from .preconditioner import NewtonPreconditioner, build_coarse_parts, build_newton_preconditioner
from .robust import RobustLoss, robust_edges
from .subproblem import (
    PRECONDITIONERS,
    SubproblemConfig,
    majorizer_value,
    project_rotations,
    solve_subproblem,
    tangent_projection,
)
from .weighting import LOCAL, Collectives, LeastSquares, NoWeights, Reweighted, Weighting, WeightState

METHODS = ("mm", "amm")
RESTARTS = ("paper", "adaptive", "average")


class MMConfig(eqx.Module):
    """Outer-loop settings.

    method: "mm" (Algorithm 1) or "amm" (Algorithm 2).
    restart: "paper" is exactly the test of Algorithm 2 line 15 (G^alpha(Z|X^k) > Gbar^alpha(k)),
      which keeps F non-increasing (Proposition 3). "adaptive" is the same test with a vanishing
      per-robot slack: a robot keeps its momentum step Z unless G^alpha(Z|X^k) - Gbar^alpha(k)
      exceeds slack^alpha_k = slack_scale * (robot's initial local cost) * (1 - slack_decay)^k.
      Since the slacks are summable, F(X^k) stays below F(X^0) + sum_k slack_k (bounded), and
      the rule turns into Algorithm 2's test as k grows. The robot's shares move between robots
      through inter-robot edges, so a test against the robot's own share history (docs/conventions.md §7) would
      keep restarting robots whose share legitimately grows; the slack avoids that.
      "average" tests against moving averages of each robot's own objective share, in the spirit
      of the authors' later code (docs/conventions.md §7): a hard restart (MM fallback, momentum reset) when
      G^alpha(Z|X^k) exceeds the slow average (rate ``average_rates[0]``) or when its increase over
      Gbar^alpha(k) exceeds the vanishing slack above (which keeps F bounded and the rule tending to
      Algorithm 2's); a soft restart (momentum reset only, Z kept) after ``soft_restart_hits``
      consecutive iterations in which G^alpha(Z|X^k) exceeds the fast average (rate
      ``average_rates[1]``). Measured against "adaptive" in benchmarks/restart_rules.md.
    rise_limit: AMM's guard against momentum that runs away (every restart rule). Let F_best be the
      lowest value of the objective the MM step minimises (F; with a robust loss F_rho, or the
      weighted objective while its weights are held fixed, ``Weighting.minimised``) since the start
      or since that objective last changed (a GNC stage), and F_start its value there. When it rises
      above F_best by more than ``rise_limit`` times the decrease F_start - F_best made since then,
      every robot's momentum restarts (s = 1: the next iteration is an MM step) and the slack of the
      adaptive and average tests is halved (repeated, they become Algorithm 2's test). It needs F
      summed over the robots, which the history and the stopping rules already sum at every
      iteration. On the benchmark files AMM's F never rises above its lowest value by more than 1e-4
      of it, far below a tenth of the decrease made, so the guard never acts there; on graphs whose
      measurement weights spread over many orders of magnitude the slack alone let F climb to
      up to 4.6x its start (benchmarks/restart_rules.md). ``inf`` turns it off.
    xi: the proximal term of Eq. (13), >= 0, or None: "the xi the MMProblem was built with".
      Gamma^alpha (and its preconditioners) contain xi, so the xi of a run is the problem's
      (``MMProblem.xi``). The rule: ``MMProblem.build(partition, config=config)`` takes xi from
      the config; ``init_state`` / ``run`` raise a ValueError when the config's xi and the problem's
      are both concrete and differ (so the two can never silently disagree); ``xi=None`` defers to
      the problem (e.g. for a batch of problems with different xi).

    Static fields (their values select the compiled code): ``method``, ``restart`` and the
    subproblem's ``preconditioner`` and loop caps. Everything else is an ordinary (traced) field:
    ``xi``, ``slack_scale`` (>= 0), ``slack_decay`` (in [0, 1]), ``average_rates`` (two rates in
    [0, 1]: slow, fast), ``soft_restart_hits`` (integer >= 1) and the subproblem's ``gradient_tolerance`` and
    ``cg_tolerance``;
    a run with other values of these reuses the compiled code. Every field is checked when the
    config is built (ValueError naming the field and its range); values that are traced at that
    point (configs built under ``jit`` / ``vmap``) are not.
    """

    method: Literal["mm", "amm"] = eqx.field(static=True, default="amm")
    restart: Literal["paper", "adaptive", "average"] = eqx.field(static=True, default="adaptive")
    xi: float | None = 1e-3
    subproblem: SubproblemConfig = SubproblemConfig()
    slack_scale: float = 1.0
    slack_decay: float = 5e-4
    average_rates: tuple[float, float] = (5e-4, 2.5e-2)
    soft_restart_hits: int = 25
    rise_limit: float = 0.1

    def __check_init__(self):
        owner = "MMConfig"
        check_choice(owner, "method", self.method, METHODS)
        check_choice(owner, "restart", self.restart, RESTARTS)
        if self.xi is not None:
            check_real(owner, "xi", self.xi, 0.0)
        if not isinstance(self.subproblem, SubproblemConfig):
            raise TypeError(f"{owner}.subproblem must be a SubproblemConfig, got {type(self.subproblem).__name__}")
        check_real(owner, "slack_scale", self.slack_scale, 0.0)
        check_real(owner, "slack_decay", self.slack_decay, 0.0, 1.0)
        rates = self.average_rates
        if not isinstance(rates, (tuple, list)) or len(rates) != 2:
            raise ValueError(f"{owner}.average_rates must be a pair (slow, fast) of rates in [0, 1], got {rates!r}")
        check_real(owner, "average_rates[0]", rates[0], 0.0, 1.0)
        check_real(owner, "average_rates[1]", rates[1], 0.0, 1.0)
        check_count(owner, "soft_restart_hits", self.soft_restart_hits, 1)
        if not (isinstance(self.rise_limit, (int, float)) and self.rise_limit == float("inf")):  # inf: no guard
            check_real(owner, "rise_limit", self.rise_limit, 0.0)


def check_consistent(problem: MMProblem, config: MMConfig) -> None:
    """ValueError when ``config`` cannot run on ``problem``: its xi (when set and concrete) differs
    from the xi Gamma was built with, or its preconditioner was not built (see ``MMProblem.build``)."""
    check_xi(problem, config)
    check_preconditioner(problem, config)


def check_preconditioner(problem: MMProblem, config: MMConfig) -> None:
    """ValueError when the config asks for a preconditioner the problem was not built for."""
    kind = config.subproblem.preconditioner
    if kind not in problem.preconditioners:
        held = " and ".join(problem.preconditioners) or "no"
        poses = ", poses=partition.scatter(X0)" if kind == "two-level" else ""
        raise ValueError(
            f"this MMProblem holds {held} preconditioner, the config asks for {kind!r}: build it with "
            f"MMProblem.build(..., config=config{poses}) (or preconditioner={kind!r})"
        )


def check_xi(problem: MMProblem, config: MMConfig) -> None:
    """ValueError when the config's xi and the problem's are both concrete and differ."""
    if config.xi is not None:
        cx, px = concrete_value(config.xi), concrete_value(problem.xi)
        if cx is not None and px is not None and np.any(cx.astype(px.dtype) != px):
            raise ValueError(
                f"MMConfig.xi = {config.xi!r} differs from the xi the MMProblem was built with ({px.tolist()!r}): "
                "build the problem with MMProblem.build(partition, config=config), or give MMConfig(xi=None) "
                "to use the problem's"
            )


class MMProblem(eqx.Module):
    """Constant data of a run: the partition, Gamma^alpha of every robot and the constant part of
    the subproblem's preconditioner (built once).

    Only what the solver reads is stored: Gamma^alpha in the solver's structure-of-arrays layout
    (``gamma_soa``; ``gamma`` is the stacked-layout view, computed on access) and the
    :class:`~mmpgo_jax._mm.preconditioner.NewtonPreconditioner` data (``newton``: its block-Jacobi
    level always, its coarse level when the problem was built for "two-level"). ``xi`` (a 0-d array,
    traced like the other leaves) is the xi Gamma was built with.

    ``free`` (A, n_max) bool marks the slots the solver may move: all but the fixed poses (g2o FIX;
    see :class:`~mmpgo_jax.FixedPoses`), which keep their value in X^0; None when no pose is fixed
    (``build(..., fixed=mask)`` with an all-False mask gives an all-True array, e.g. to batch
    problems with and without fixed poses).

    ``weighting`` is the edge-weighting strategy (:mod:`~mmpgo_jax._mm.weighting`):
    :class:`~mmpgo_jax._mm.weighting.LeastSquares` (``loss`` "l2": the program of a plain run) or
    :class:`~mmpgo_jax._mm.weighting.Reweighted` (a robust kernel), whose Gamma and preconditioner
    depend on the edge weights and live in the state (:class:`MMState`); ``gamma_soa`` and
    ``newton`` then hold those of unit weights, from which the loop-closure list and the coarse
    space are read.
    """

    partition: Partition
    gamma_soa: GammaSoA  # batched over robots, structure-of-arrays (the solver's layout)
    newton: NewtonPreconditioner  # batched over robots: the subproblem's preconditioner data
    free: jax.Array | None  # (A, n_max) bool, or None when no pose is fixed
    xi: jax.Array  # () the xi of Gamma
    weighting: Weighting = LeastSquares()

    @property
    def gamma(self) -> GammaOperator:
        """Gamma^alpha in the stacked layout (a view of ``gamma_soa``, computed on access)."""
        return soa_to_gamma(self.gamma_soa)

    @property
    def preconditioners(self) -> tuple[str, ...]:
        """The preconditioner kinds this problem can run (a config asking for another one fails)."""
        return PRECONDITIONERS if self.newton.has_coarse else ("block-jacobi",)

    def preconditioner(self, config: MMConfig) -> NewtonPreconditioner:
        """The configured preconditioner's data (batched over robots), for ``solve_subproblem``."""
        check_preconditioner(self, config)
        return self.newton if config.subproblem.preconditioner == "two-level" else self.newton.without_coarse()

    @staticmethod
    def build(partition: Partition, xi: float | None = None, *, config: MMConfig | None = None,
              preconditioner: str | None = None, min_couplings: int = 0, fixed=None,
              poses=None, aggregate: int | None = None, loss: RobustLoss | None = None,
              start_weights=None) -> MMProblem:
        """Gamma^alpha of every robot, its preconditioner data and the fixed-pose mask (host, once).

        ``xi``: the proximal term; default ``config.xi`` (1e-3 without a config). Given both and
        different: ValueError. ``preconditioner``: "two-level" or "block-jacobi" (default: the
        config's, else "two-level" when ``poses`` are given and "block-jacobi" otherwise).
        ``poses``: the start X^0 (``partition.scatter(poses)``), which the two-level coarse space is
        made of; needed for "two-level" (the default). ``aggregate``: slots per coarse aggregate
        (default the config's ``subproblem.aggregate``, else chosen from the robots' size; one value
        for problems batched together).
        ``min_couplings`` pads Gamma's loop-closure list (to batch problems of one shape);
        ``fixed``: a :class:`~mmpgo_jax.FixedPoses` (or (n,) bool mask) of poses that never move.
        ``loss``: a :class:`~mmpgo_jax.RobustLoss` (None: least squares). ``start_weights``: (A, e_max)
        weights of the incident-edge slots given with the start (e.g. the distributed robust start's
        classification), held as a first stage of the robust run (robust losses only)."""
        if config is not None and config.xi is not None:
            if xi is None:
                xi = config.xi
            elif concrete_value(xi) is not None and concrete_value(config.xi) is not None and \
                    float(xi) != float(config.xi):
                raise ValueError(f"MMProblem.build: xi = {xi!r} differs from config.xi = {config.xi!r}")
        if xi is None:
            xi = 1e-3
        check_real("MMProblem.build", "xi", xi, 0.0)
        xi = float(xi)
        if preconditioner is None:
            if config is not None:
                preconditioner = config.subproblem.preconditioner
            else:
                preconditioner = "two-level" if poses is not None else "block-jacobi"
        check_choice("MMProblem.build", "preconditioner", preconditioner, PRECONDITIONERS)
        if preconditioner == "two-level" and poses is None:
            raise ValueError("MMProblem.build: the two-level preconditioner is made of the start poses: "
                             "give poses=partition.scatter(X0) (or preconditioner='block-jacobi')")
        gamma = build_gamma_operator(partition.edges, xi, partition.max_poses, min_couplings=min_couplings, host=True)
        soa = host_soa(gamma)
        dtype = soa.diag.dtype
        if aggregate is None and config is not None:
            aggregate = config.subproblem.aggregate
        if preconditioner == "two-level":
            newton = build_newton_preconditioner(gamma.diag, gamma.band, gamma.src, gamma.dst, gamma.blocks,
                                                 stack(jax.tree.map(np.asarray, poses)), partition.pose_mask, dtype,
                                                 aggregate=aggregate)
        else:
            newton = build_newton_preconditioner(gamma.diag, dtype=dtype)
        weighting = LeastSquares()
        if start_weights is not None and loss is None:
            raise ValueError("MMProblem.build: start_weights apply to a robust loss; least squares has no weights")
        if loss is not None:
            n_max = partition.max_poses
            coarse = build_coarse_parts(partition.edges, newton, n_max) if newton.has_coarse else None
            e = partition.edges
            index = np.asarray(partition.pose_index)
            gi = index[np.asarray(e.robot_i), np.asarray(e.slot_i)]
            gj = index[np.asarray(e.robot_j), np.asarray(e.slot_j)]
            mask = robust_edges(loss, gi.reshape(-1), gj.reshape(-1)).reshape(gi.shape)
            given = np.ones(gi.shape, dtype) if start_weights is None else np.asarray(start_weights, dtype)
            if given.shape != gi.shape or not np.all((given >= 0) & (given <= 1)):
                raise ValueError(f"MMProblem.build: start_weights must be {gi.shape} values in [0, 1]")
            weighting = Reweighted(loss=loss.with_defaults(e.t.shape[-1]),
                                   layout=gamma_layout(e, n_max, min_couplings=min_couplings), coarse=coarse,
                                   robust_edge=to_device(mask), given=to_device(given),
                                   use_given=to_device(np.asarray(start_weights is not None)))
        del gamma  # the stacked-layout copy is not kept: the solver reads gamma_soa
        free = None  # no fixed pose: the solver runs without a mask (same compiled code as ever)
        if fixed is not None:
            mask = fixed.mask(partition.num_poses) if hasattr(fixed, "mask") else np.asarray(fixed, dtype=bool)
            if mask.shape != (partition.num_poses,):
                raise ValueError(f"fixed mask must have shape ({partition.num_poses},), got {mask.shape}")
            # padding slots count as free: they have no edges and never move anyway
            free = np.ones(partition.pose_mask.shape, dtype=bool)
            free[np.asarray(partition.robot_of_pose)[mask], np.asarray(partition.slot_of_pose)[mask]] = False
            free = to_device(free)
        return MMProblem(partition=partition, gamma_soa=soa, newton=newton, free=free, xi=to_device(xi, dtype),
                         weighting=weighting)


class MMState(eqx.Module):
    """Outer-loop state; poses in the stacked layout (A, n_max, d, d+1) = [t | R] per slot."""

    X: jax.Array  # current iterate X^k
    grad: jax.Array  # grad F(X^k), per robot block
    share: jax.Array  # (A,) Gbar^alpha(k)
    X_prev: jax.Array  # X^{k-1}
    grad_prev: jax.Array
    s: jax.Array  # (A,) Nesterov sequence
    slack: jax.Array  # (A,) allowed increase of G^alpha over Gbar^alpha (adaptive restart)
    iteration: jax.Array
    share_slow: jax.Array  # (A,) slow moving average of Gbar^alpha ("average" restart)
    share_fast: jax.Array  # (A,) fast moving average of Gbar^alpha
    soft_hits: jax.Array  # (A,) consecutive iterations above the fast average
    f_start: jax.Array  # () the minimised objective at the start, or where it last changed (rise_limit)
    f_best: jax.Array  # () its lowest value since then
    resets: jax.Array  # () int32: momentum restarts of every robot by rise_limit
    weighting: NoWeights | WeightState  # the state of the problem's weighting strategy


class IterationRecord(eqx.Module):
    f: jax.Array  # 2F(X^{k+1}) (the tables' convention)
    grad_norm: jax.Array  # ||grad F(X^{k+1})|| (Riemannian, of F)
    restarted: jax.Array  # (A,) bool: robot took the MM fallback this iteration
    settled: jax.Array  # () bool: the stopping rules may apply (a robust run's GNC has ended; always True otherwise)


def _riemannian_grad_norm(X, grad, free, comm: Collectives = LOCAL):
    """||grad F|| over the free poses (the fixed ones are not variables)."""
    rgrad = tangent_projection(X, grad)
    if free is not None:
        rgrad = jnp.where(free[..., None, None], rgrad, 0.0)
    return jnp.sqrt(comm.sum(jnp.sum(rgrad**2, axis=(1, 2, 3))))


def init_state(problem: MMProblem, X0: Poses, config: MMConfig = None) -> MMState:
    """State at X^0 (padded per-robot poses, e.g. ``partition.scatter(poses)``); Alg. 2 lines 3-8.

    Without ``config``: the default config with the problem's xi. ValueError when the config's xi
    and the problem's are concrete and differ (see :class:`MMConfig`)."""
    if config is None:
        config = MMConfig(xi=None)
    else:
        check_xi(problem, config)
    X0 = stack(X0)
    grad, share, local, weighting = problem.weighting.start(problem, config, X0)
    A = share.shape[0]
    f0 = problem.weighting.minimised(weighting, jnp.sum(share))
    return MMState(
        X=X0,
        grad=grad,
        share=share,
        X_prev=X0,
        grad_prev=grad,
        s=jnp.ones(A, share.dtype),
        slack=config.slack_scale * local,
        iteration=jnp.asarray(0, dtype=int),  # not weakly typed: the same as a deserialized program returns
        share_slow=share,
        share_fast=share,
        soft_hits=jnp.zeros(A, jnp.int32),
        f_start=f0,
        f_best=f0,
        resets=jnp.zeros((), jnp.int32),
        weighting=weighting,
    )


def _mm_update(problem: MMProblem, config: MMConfig, X, grad, gamma=None, pre=None, share=None):
    """X^{alpha,k+1} = argmin G^alpha(. | X^k) for every robot (Algorithm 1 line 6); ``gamma``,
    ``pre``: the majorizer's Gamma^alpha and preconditioner (default: the problem's)."""
    def solve(G, P, x, g, free, scale):
        return solve_subproblem(G, P, x, x, g, config.subproblem, free, scale)[0]
    if gamma is None:
        gamma, pre = problem.gamma_soa, problem.preconditioner(config)
    return jax.vmap(solve, in_axes=(0, 0, 0, 0, _free_axis(problem), None if share is None else 0))(
        gamma, pre, X, grad, problem.free, share)


def _free_axis(problem: MMProblem):
    return None if problem.free is None else 0


def momentum_point(problem: MMProblem, st: MMState):
    """Algorithm 2 lines 11-13: (s^{k+1}, the momentum point Y, its extrapolated gradient, and Y with
    its rotations projected to SO(d), where the robots' subproblems start)."""
    s_next = 0.5 * (jnp.sqrt(4.0 * st.s**2 + 1.0) + 1.0)
    gamma = ((st.s - 1.0) / s_next)[:, None, None, None]
    Y = st.X + gamma * (st.X - st.X_prev)
    gY = st.grad + gamma * (st.grad - st.grad_prev)
    start = Y.at[..., 1:].set(project_rotations(Y[..., 1:]))
    if problem.free is not None:  # fixed slots have Y = X exactly; unprojected, they stay bit-exact
        start = jnp.where(problem.free[..., None, None], start, Y)
    return s_next, Y, gY, start


def _amm_update(problem: MMProblem, config: MMConfig, st: MMState, gamma_soa, pre):
    """Algorithm 2 lines 11-20 (per robot) with the configured restart test, for the majorizer with
    Gamma^alpha ``gamma_soa`` and preconditioner ``pre``."""
    s_next, Y, gY, start = momentum_point(problem, st)

    def solve(G, P, x0, c, g, free, scale):
        return solve_subproblem(G, P, x0, c, g, config.subproblem, free, scale)[0]

    def restart_test(Z):
        # G^alpha(Z | X^k) - Gbar^alpha(k): no objective evaluation needed (paper Eq. (19); docs/conventions.md §3).
        decrease = jax.vmap(majorizer_value)(gamma_soa, Z, st.X, st.grad)
        soft_hits = st.soft_hits
        soft = jnp.zeros_like(decrease, dtype=bool)
        if config.restart == "paper":
            restart = decrease > 0
        elif config.restart == "adaptive":
            # Algorithm 2's test with a vanishing slack: G^alpha(Z|X^k) may exceed Gbar^alpha(k) by
            # at most slack^alpha_k = slack^alpha_0 (1 - slack_decay)^k, which is summable over k.
            restart = decrease > st.slack
        elif config.restart == "average":
            value = st.share + decrease  # G^alpha(Z | X^k)
            restart = (value > st.share_slow) | (decrease > st.slack)
            above = (value > st.share_fast) & ~restart
            soft_hits = jnp.where(above, soft_hits + 1, 0)
            soft = soft_hits >= config.soft_restart_hits
            soft_hits = jnp.where(soft, 0, soft_hits)
        else:
            raise ValueError(f"unknown restart rule {config.restart!r}: use 'adaptive', 'average' or 'paper'")
        return restart, soft, soft_hits

    # Pass 1 solves every robot's subproblem from the momentum point Y; pass 2, only in iterations
    # where some robot restarts, the MM subproblem at X^k for those robots (the others repeat pass 1
    # bit for bit). A loop of at most two passes keeps one copy of the solver in the compiled program
    # (half the compile time of a separate fallback branch).
    def body(carry):
        k, restart, soft, soft_hits, _ = carry
        r = restart[:, None, None, None]
        Z = jax.vmap(solve, in_axes=(0, 0, 0, 0, 0, _free_axis(problem), 0))(
            gamma_soa, pre, jnp.where(r, st.X, start), jnp.where(r, st.X, Y), jnp.where(r, st.grad, gY),
            problem.free, st.share)
        first = k == 0
        tested = restart_test(Z)
        restart, soft, soft_hits = (jnp.where(first, new, old) for new, old in zip(tested, (restart, soft, soft_hits),
                                                                                      strict=True))
        return k + 1, restart, soft, soft_hits, Z

    def cond(carry):
        k, restart = carry[:2]
        return (k == 0) | ((k == 1) & jnp.any(restart))

    no = jnp.zeros_like(st.s, dtype=bool)
    _, restart, soft, soft_hits, X_new = jax.lax.while_loop(cond, body, (0, no, no, st.soft_hits, start))
    s_new = jnp.where(restart, jnp.maximum(0.5 * s_next, 1.0), s_next)
    s_new = jnp.where(soft, 1.0, s_new)
    return X_new, s_new, restart, soft_hits


def step(problem: MMProblem, config: MMConfig, st: MMState, comm: Collectives = LOCAL):
    """One outer iteration; returns (new state, record). With a robust loss the weights of the next
    majorizer are set at the new iterate when their schedule says so (:func:`~mmpgo_jax._mm.robust.next_weights`)."""
    gamma, pre, weighting = problem.weighting.operators(problem, config, st.weighting)
    if config.method == "mm":
        X_new = _mm_update(problem, config, st.X, st.grad, gamma, pre, st.share)
        s_new = st.s
        restart = jnp.zeros_like(st.s, dtype=bool)
        soft_hits = st.soft_hits
    elif config.method == "amm":
        X_new, s_new, restart, soft_hits = _amm_update(problem, config, st, gamma, pre)
    else:
        raise ValueError(f"unknown method {config.method!r}: use 'mm' or 'amm'")
    grad, share, renewed, weighting, settled = problem.weighting.update(problem, config, weighting, X_new, comm)
    f_new = comm.sum(share)
    watched = problem.weighting.minimised(weighting, f_new)
    fresh = renewed | problem.weighting.switched(st.weighting, weighting)  # a new objective: its own reference
    runaway = jnp.zeros((), bool)  # MM has no momentum to run away
    if config.method == "amm":
        # momentum that gave back more than rise_limit of the decrease made since the reference restarts
        # everywhere; a run that starts at a minimum has nothing to give back: rises at the rounding level
        # (below sqrt(eps) of F) do not count
        floor = jnp.sqrt(jnp.finfo(f_new.dtype).eps) * jnp.abs(st.f_best)
        runaway = (watched - st.f_best > jnp.maximum(config.rise_limit * (st.f_start - st.f_best), floor)) & ~fresh
    s_new = jnp.where(renewed | runaway, 1.0, s_new)  # a new objective (GNC stage) or a runaway: no momentum
    new = MMState(
        X=X_new,
        grad=grad,
        share=share,
        X_prev=st.X,
        grad_prev=st.grad,
        s=s_new,
        # and a runaway halves the slack of the adaptive and average tests: repeated, it leaves Algorithm 2's test
        slack=jnp.where(runaway, 0.5, 1.0 - config.slack_decay) * st.slack,
        iteration=st.iteration + 1,
        share_slow=st.share_slow + config.average_rates[0] * (share - st.share_slow),
        share_fast=st.share_fast + config.average_rates[1] * (share - st.share_fast),
        soft_hits=soft_hits,
        f_start=jnp.where(fresh, watched, st.f_start),
        f_best=jnp.where(fresh, watched, jnp.minimum(st.f_best, watched)),
        resets=st.resets + runaway.astype(jnp.int32),
        weighting=weighting,
    )
    rec = IterationRecord(
        f=2.0 * f_new, grad_norm=_riemannian_grad_norm(X_new, grad, problem.free, comm), restarted=restart,
        settled=settled,
    )
    return new, rec


def scan_with_budget(advance, skipped, iteration, state, length: int, limit=None):
    """``length`` applications of ``advance(state) -> (state, record)`` in one ``lax.scan``; with a
    traced ``limit``, those at ``iteration(state) >= limit`` give ``(state, skipped(state))`` instead,
    so a budget that is not a multiple of ``length`` reuses the same compiled chunk. The one loop body
    of every compiled run (``run`` here, every solver's ``run_chunk``)."""
    def body(st, _):
        if limit is None:
            return advance(st)
        return jax.lax.cond(iteration(st) >= limit, lambda s: (s, skipped(s)), advance, st)

    return jax.lax.scan(body, state, None, length=length)


def _run(problem: MMProblem, config: MMConfig, state: MMState, length: int, limit=None):
    return scan_with_budget(lambda s: step(problem, config, s), skipped_record, lambda s: s.iteration, state,
                            length, limit)


_run.__name__ = _run.__qualname__ = "run"  # the name in compile logs


class _CheckedJit:
    """``jax.jit(run, static_argnames="length")`` that first checks the config against the problem
    (:func:`check_consistent`; on concrete values only, so also when called inside another jit)."""

    def __init__(self, fn, doc: str):
        self._jit = jax.jit(fn, static_argnames=("length",))
        self.__doc__ = doc
        self.__name__ = self.__qualname__ = "run"
        self.__module__ = __name__
        self.__wrapped__ = fn

    def __call__(self, problem: MMProblem, config: MMConfig, state: MMState, length: int, limit=None):
        check_consistent(problem, config)
        return self._jit(problem, config, state, length, limit)

    def lower(self, problem: MMProblem, config: MMConfig, state: MMState, length: int, limit=None):
        check_consistent(problem, config)
        return self._jit.lower(problem, config, state, length, limit)

    def __getattr__(self, name):  # trace, eval_shape, clear_cache, ... of the jitted function
        return getattr(self._jit, name)


run = _CheckedJit(_run, """``length`` outer iterations in one ``lax.scan``; returns (state, records).

    Jitted with a static ``length``: the config's traced fields (xi, the inner tolerances, restart
    constants) and the problem's arrays are arguments, so runs that differ only in those values
    share one compilation. ValueError when the config's xi differs from the problem's, or asks for a
    preconditioner the problem does not hold (checked before tracing, on concrete values).

    Iterations at or beyond ``limit`` (a traced count of total iterations, e.g. the user's budget
    when it is not a multiple of the chunk length) leave the state unchanged and record NaN, so
    every chunk of a run uses the same compiled code.
    """)


def skipped_record(st: MMState) -> IterationRecord:
    nan = jnp.full((), jnp.nan, st.share.dtype)
    return IterationRecord(f=nan, grad_norm=nan, restarted=jnp.zeros_like(st.s, dtype=bool), settled=jnp.ones((), bool))


def evaluate(problem: MMProblem, state: MMState) -> IterationRecord:
    """The record (f, gradient norm) of the state itself, e.g. at X^0."""
    return IterationRecord(
        f=2.0 * jnp.sum(state.share),
        grad_norm=_riemannian_grad_norm(state.X, state.grad, problem.free),
        restarted=jnp.zeros_like(state.s, dtype=bool),
        settled=jnp.ones((), bool),
    )


@jax.jit
def start_state(problem: MMProblem, X0: Poses, config: MMConfig) -> tuple[MMState, IterationRecord]:
    """``init_state`` and its ``evaluate`` record in one compiled call (op by op, the gradient
    evaluation would dispatch and compile every primitive separately: seconds on any graph).
    The config's xi is not checked against the problem's here (traced): see :func:`init_state`."""
    state = init_state(problem, X0, config)
    return state, evaluate(problem, state)
