"""How edges are weighted in the majorizer: a strategy of the MM step with its own state.

:class:`LeastSquares` is the trivial weighting (every edge weight 1, Γ^α and its preconditioner
constant, no state: the program of a plain run). :class:`Reweighted` is a robust kernel's
iteratively reweighted majorizer (Eq. (13) with w_ij = ρ'(s_ij), the GNC schedule of
:mod:`~mmpgo_jax._mm.robust`): its state (:class:`WeightState`) holds the edge weights, the Γ^α
and preconditioner of those weights and where the weight updates stand. The outer step
(:mod:`~mmpgo_jax._mm.outer`) asks the strategy for the current operators and, at the new
iterate, for the gradient, the objective shares and whether the majorizer changed; it never asks
which strategy it has.

Also here: :class:`Collectives`, how robots exchange data in one iteration (the strategies read
neighbour poses through it).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .majorization import (
    GammaLayout,
    GammaSoA,
    assemble_gamma,
    gamma_to_soa,
    gradient_and_share,
    incident_residuals,
    robot_share,
    weighted_gradient,
)
from .preconditioner import CoarseParts, NewtonPreconditioner, newton_from_gamma
from .robust import (
    RobustLoss,
    WeightSchedule,
    initial_schedule,
    next_weights,
    robust_cost,
    robust_outcome,
    start_weights,
)

__all__ = ["LOCAL", "Collectives", "LeastSquares", "NoWeights", "Reweighted", "WeightState", "Weighting"]


class Collectives(eqx.Module):
    """How robots exchange data in one iteration.

    The default is a single device holding every robot. A sharded run (robots split over devices,
    see ``mmpgo_jax.sharding``) replaces these with collectives over its mesh axis.
    """

    def gather_poses(self, X):
        """All robots' poses (A, n_max, d, d+1) from this device's block of robots."""
        return X

    def sum(self, x):
        """Sum over all robots of a per-robot quantity (A_local,) -> scalar."""
        return jnp.sum(x)

    def max(self, x):
        """Maximum over all robots of a per-robot array (A_local, ...) -> scalar."""
        return jnp.max(x)


LOCAL = Collectives()


def gradients(problem, X, comm: Collectives = LOCAL):
    """(grad F(X) blocks (stacked), shares, local costs) for stacked padded poses X.

    Endpoint poses are gathered from all robots' poses: this is the neighbour exchange.
    """
    part = problem.partition
    Xg = comm.gather_poses(X)
    return jax.vmap(lambda e: gradient_and_share(e, Xg, part.max_poses))(part.edges)


class NoWeights(eqx.Module):
    """The state of :class:`LeastSquares`: nothing."""


class WeightState(eqx.Module):
    """The state of :class:`Reweighted`: the edge weights of the current majorizer, its Γ^α and
    preconditioner, and where the weight updates stand."""

    weights: jax.Array  # (A, e_max) per incident edge
    gamma: GammaSoA
    newton: NewtonPreconditioner
    schedule: WeightSchedule
    rebuilds: jax.Array  # () int32: times Γ^α and the preconditioner were rebuilt after the start
    gamma_weights: jax.Array  # (A, e_max) the weights Γ^α was built with (>= weights, see GAMMA_SLACK)
    coarse_weights: jax.Array  # (A, e_max) the weights the preconditioner's coarse level was built with
    coarse_rebuilds: jax.Array  # () int32: times that coarse level was rebuilt after the start
    # Γ^α and the preconditioner are rebuilt from gamma_weights when the next step asks for them
    # (:meth:`Reweighted.operators`), the coarse level too with ``refresh``: one copy of the assembly
    # in the compiled loop, none in the start's program (whose operators are placeholders, pending)
    pending: jax.Array  # () bool
    refresh: jax.Array  # () bool


class Weighting(eqx.Module):
    """The strategy interface (see the module docstring)."""

    stateless = True  # whether the state is NoWeights (its structure is then known without tracing)

    def start(self, problem, config, X0):
        """At X^0: (gradient, shares, local costs, state)."""
        raise NotImplementedError

    def operators(self, problem, config, state):
        """(Γ^α, preconditioner) of the current majorizer, and the state that holds them."""
        raise NotImplementedError

    def update(self, problem, config, state, X, comm: Collectives):
        """At the new iterate X: (gradient, shares, whether the objective changed (AMM's momentum then
        starts afresh), state, whether the stopping rules may apply yet)."""
        raise NotImplementedError

    def outcome(self, graph, part, state, poses, to_host=np.asarray) -> tuple[dict, dict]:
        """The run's robust outcome for ``SolveResult`` (loss, weights, inliers) and its statistics."""
        return {}, {}

    def minimised(self, state, f):
        """The objective the MM step currently minimises, given F (the sum of the shares): what AMM's
        momentum guard watches (``MMConfig.rise_limit``)."""
        return f

    def switched(self, old, new):
        """Whether :meth:`minimised` measures another objective in state ``new`` than in ``old``
        without a renewal (the guard then takes a new reference)."""
        return jnp.zeros((), bool)


class LeastSquares(Weighting):
    """Every edge weight 1: Γ^α and the preconditioner are the problem's, built once."""

    def start(self, problem, config, X0):
        grad, share, local = gradients(problem, X0)
        return grad, share, local, NoWeights()

    def operators(self, problem, config, state):
        return problem.gamma_soa, problem.preconditioner(config), state

    def update(self, problem, config, state, X, comm: Collectives):
        grad, share, _ = gradients(problem, X, comm)
        return grad, share, False, state, jnp.ones((), bool)


#: Γ^α is built with the edge weights times 1 + GAMMA_SLACK (at most 1) and rebuilt only when a weight
#: rises above its Γ weight or falls below it / (1 + GAMMA_SLACK)^2. A Γ^α of larger weights still
#: majorizes (each edge's block is positive semidefinite), so MM's guarantee holds with a slightly
#: looser majorizer, and kernels whose weights move a little at every iteration (Huber, Cauchy, ...)
#: rebuild at a fraction of the iterations. TLS's weights are 0 or 1: unaffected.
GAMMA_SLACK = 0.05
#: A rebuild of Γ^α keeps the two-level preconditioner's coarse level (the pseudo-inverse of
#: B^T Γ B, the costly part of a rebuild) until, for some robot, the weights changed since it was built
#: by more than COARSE_DRIFT of that robot's total weight (sum of |change| over its incident edges).
#: The preconditioner only sets how fast the inner CG converges: a coarse level of older weights is
#: still symmetric positive semidefinite, and the fine level and Γ^α (the majorizer) are always current.
COARSE_DRIFT = 0.05


class Reweighted(Weighting):
    """A robust kernel's reweighted majorizer: the loss (its numbers filled in,
    :meth:`RobustLoss.with_defaults`), where each edge goes in Γ^α, each edge's contribution to the
    coarse matrix of the two-level preconditioner (None with block-Jacobi alone), the incident
    edges the loss applies to (the others keep weight 1) and the weights that came with the start
    (``given``, used where ``use_given``: held as a first stage, :func:`~mmpgo_jax._mm.robust.next_weights`;
    always an array, so that runs with and without them share one compiled program)."""

    loss: RobustLoss
    layout: GammaLayout
    coarse: CoarseParts | None
    robust_edge: jax.Array  # (A, e_max) bool
    given: jax.Array  # (A, e_max) start weights (1 where none were given)
    use_given: jax.Array  # () bool
    stateless = False

    def _residuals(self, problem, X, comm: Collectives = LOCAL):
        Xg = comm.gather_poses(X)
        return jax.vmap(lambda e: incident_residuals(e, Xg))(problem.partition.edges)

    def _gradients(self, problem, E, s, weights):
        """(grad of 1/2 sum w s (stacked), robust shares of F_rho, shares of 1/2 sum w s) per robot."""
        part = problem.partition
        grad = jax.vmap(lambda e, r, w: weighted_gradient(e, r, w, part.max_poses))(part.edges, E, weights)
        share = jax.vmap(robot_share)(part.edges, robust_cost(self.loss, s, self.robust_edge))
        weighted = jax.vmap(robot_share)(part.edges, weights * s)
        return grad, share, weighted

    def _operators_of(self, problem, config, weights, coarse_inverse=None, refresh=None):
        """Γ^α (structure of arrays) and the preconditioner of every robot for edge ``weights``,
        assembled in the compiled step; the coarse level only when the config uses it, and then
        ``coarse_inverse`` (A, ...) kept as it is when given, unless the traced flag ``refresh``
        holds (:data:`COARSE_DRIFT`)."""
        block_jacobi = config.subproblem.preconditioner == "block-jacobi"
        base = problem.newton.without_coarse() if block_jacobi else problem.newton
        n_max = problem.partition.max_poses

        def one(edges, layout, w, base_a, parts_a, kept_a):
            gamma, empty = assemble_gamma(edges, layout, w, problem.xi, n_max)
            slot_weight = jnp.where(empty, 1.0, problem.xi).astype(w.dtype)
            return gamma_to_soa(gamma), newton_from_gamma(gamma.diag, base_a, parts_a, w, slot_weight, kept_a,
                                                          refresh)

        parts = self.coarse if base.has_coarse else None
        kept = coarse_inverse if base.has_coarse else None
        return jax.vmap(one)(problem.partition.edges, self.layout, weights, base, parts, kept)

    def _inflated(self, weights):
        """The weights Γ^α is built with (:data:`GAMMA_SLACK`)."""
        return jnp.where(self.robust_edge, jnp.minimum(weights * (1.0 + GAMMA_SLACK), 1.0), weights)

    def start(self, problem, config, X0):
        E, s = self._residuals(problem, X0)
        weights = start_weights(self.loss, s, self.robust_edge, self.given, self.use_given)
        gamma_weights = self._inflated(weights)
        shapes = jax.eval_shape(lambda: self._operators_of(problem, config, gamma_weights))
        gamma, newton = jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), shapes)  # pending: built in step 1
        grad, share, weighted = self._gradients(problem, E, s, weights)
        local = 0.5 * jnp.sum(robust_cost(self.loss, s, self.robust_edge), axis=-1)
        schedule = initial_schedule(self.loss, 2.0 * jnp.sum(weighted), self.use_given)
        zero, yes = jnp.zeros((), jnp.int32), jnp.ones((), bool)
        return grad, share, local, WeightState(weights, gamma, newton, schedule, zero, gamma_weights, gamma_weights,
                                               zero, pending=yes, refresh=yes)

    def operators(self, problem, config, state: WeightState):
        """Γ^α and the preconditioner, rebuilt first when the last update (or the start) left them
        pending (the coarse level's pseudo-inverse only where refreshed)."""
        problem.preconditioner(config)  # checks that the config's preconditioner was built
        has_coarse = state.newton.coarse_inverse is not None  # the config's preconditioner has that level

        def rebuilt():
            kept = state.newton.coarse_inverse if has_coarse else None
            return self._operators_of(problem, config, state.gamma_weights, kept,
                                      refresh=state.refresh if has_coarse else None)

        gamma, newton = jax.lax.cond(state.pending, rebuilt, lambda: (state.gamma, state.newton))
        no = jnp.zeros((), bool)
        state = eqx.tree_at(lambda st: (st.gamma, st.newton, st.pending, st.refresh), state, (gamma, newton, no, no))
        block_jacobi = config.subproblem.preconditioner == "block-jacobi"
        return gamma, newton.without_coarse() if block_jacobi else newton, state

    def update(self, problem, config, state: WeightState, X, comm: Collectives):
        """The weights (updated when the schedule says so, and Γ^α with its preconditioner left to
        rebuild then only, by the next :meth:`operators`), the gradient of the new majorizer, the
        robust shares."""
        E, s = self._residuals(problem, X, comm)
        weighted_f = 2.0 * comm.sum(jax.vmap(robot_share)(problem.partition.edges, state.weights * s))
        s_max = comm.max(jnp.where(self.robust_edge, s, 0.0))
        update, weights, schedule = next_weights(self.loss, state.schedule, s, state.weights, weighted_f, s_max,
                                                 comm.sum, self.robust_edge)
        # an update that changes no weight (TLS's binary weights, mostly) leaves the majorizer as it is
        # (and AMM's momentum); Γ^α and the preconditioner are rebuilt only when a weight of some robot
        # left the band its Γ weight allows (GAMMA_SLACK)
        def anywhere(flags):
            return comm.sum(jnp.sum(flags, axis=tuple(range(1, flags.ndim)))) > 0

        update = update & anywhere(weights != state.weights)
        stale = (weights > state.gamma_weights) | (weights * (1.0 + GAMMA_SLACK) ** 2 < state.gamma_weights)
        rebuild = update & anywhere(stale)
        gamma_weights = jnp.where(rebuild, self._inflated(weights), state.gamma_weights)
        # the coarse level too when some robot's weights drifted from the ones it was built with
        drift = jnp.sum(jnp.abs(gamma_weights - state.coarse_weights), axis=-1)
        has_coarse = state.newton.coarse_inverse is not None  # the config's preconditioner has that level
        # the robot's total weight over its real incident edges: padding slots (weight 1) would make the
        # rule depend on how far the arrays were padded (a sweep's batch against a plain solve)
        edges = problem.partition.edges
        total = jnp.sum(jnp.where(edges.local_i | edges.local_j, state.coarse_weights, 0.0), axis=-1)
        coarse = rebuild & anywhere(drift > COARSE_DRIFT * total) & has_coarse
        coarse_weights = jnp.where(coarse, gamma_weights, state.coarse_weights)

        grad, share, weighted = self._gradients(problem, E, s, weights)
        schedule = eqx.tree_at(lambda sc: sc.weighted_f, schedule, 2.0 * comm.sum(weighted))
        # AMM's momentum is dropped only when the objective changes: at a GNC stage (mu moves) or at the
        # end of the held start weights. An M-estimator's reweighting keeps F_rho and only tightens its
        # majorizer; dropping the momentum there made AMM an MM method whenever weights moved at every
        # iteration (Huber on city10000: f after 300 iterations 1.0 % higher; benchmarks/robust_cost.md)
        renewed = update & (jnp.asarray(self.loss.use_gnc) | state.schedule.held)
        settled = (schedule.done | ~jnp.asarray(self.loss.use_gnc)) & ~schedule.held
        rebuilds = state.rebuilds + rebuild.astype(jnp.int32)
        coarse_rebuilds = state.coarse_rebuilds + coarse.astype(jnp.int32)
        return grad, share, renewed, WeightState(weights, state.gamma, state.newton, schedule, rebuilds, gamma_weights,
                                                coarse_weights, coarse_rebuilds, pending=rebuild,
                                                refresh=coarse), settled

    def minimised(self, state: WeightState, f):
        """F_rho for an M-estimator's reweighting (its majorizer majorizes F_rho); while the weights are
        held fixed (a GNC stage, the start's held weights) the weighted objective 1/2 sum w s."""
        fixed = jnp.asarray(self.loss.use_gnc) | state.schedule.held
        return jnp.where(fixed, 0.5 * state.schedule.weighted_f, f)

    def switched(self, old: WeightState, new: WeightState):
        """The end of the held start weights: from there an M-estimator's step minimises F_rho (an
        update that changed no weight ends the stage without renewing the majorizer)."""
        return old.schedule.held & ~new.schedule.held

    def outcome(self, graph, part, state: WeightState, poses, to_host=np.asarray) -> tuple[dict, dict]:
        loss = jax.device_get(self.loss)
        weights, inliers = robust_outcome(loss, graph, part, to_host(state.weights), poses)
        sched = jax.device_get(jax.tree.map(to_host, state.schedule))
        stats = dict(weight_updates=int(sched.updates), operator_rebuilds=int(to_host(state.rebuilds)),
                     coarse_rebuilds=int(to_host(state.coarse_rebuilds)),
                     gnc_stages=int(sched.stage), gnc_mu=float(sched.mu),
                     weights_final=bool(sched.done), start_weights_given=bool(to_host(self.use_given)),
                     start_weights_held=bool(sched.held))
        return dict(loss=loss, weights=weights, inliers=inliers), stats
