"""RBCD and RBCD++: Riemannian block-coordinate descent on F (Tian, Khosoussi, Rosen, How, "Distributed
certifiably correct pose-graph optimization", T-RO 2021), as a solver of the one solve path.

**Block problem.** A block is one robot's poses. With its neighbours' poses held fixed, F restricted
to robot alpha's poses is exactly the quadratic

    F(Y) = F(X) + <grad_alpha F(X), Y - X_alpha> + 1/2 <Gamma_b (Y - X_alpha), Y - X_alpha>,

Gamma_b = the connection Laplacian of the robot's own edges plus, for each inter-robot edge, the
edge's Hessian at its local end with weight 1 (:func:`~mmpgo_jax._mm.majorization.build_gamma_operator`
with ``inter_weight=1``; MM's majorizer has weight 2 there and a proximal xi). No proximal term is
added by default (``xi=0``): the update is then the exact block minimisation, from the current
iterate, by the robots' own Riemannian trust-region solver
(:func:`~mmpgo_jax._mm.subproblem.solve_subproblem`; preconditioner: the Hessian's block-Jacobi
of Gamma_b, or the two-level one when ``inner`` asks for it). Its accept test never lets the block
value rise, so RBCD's F is non-increasing whatever the inner budget.

**Selection** (one iteration = one block update): "greedy" -- the robot with the largest
Riemannian block-gradient norm (``comm.max``; ties to the lowest robot index); "uniform" -- a robot
drawn uniformly from a key folded from ``seed`` and the iteration number (no key in the state);
"round-robin" -- robot k mod A at iteration k; "parallel" -- the robot adjacency graph is coloured
on the host (networkx, largest-first greedy) and colour class k mod C updates at iteration k, all
its robots at once: robots of one class share no edge, so this equals updating them one after the
other. Every robot evaluates the selection itself from data it has (its block-gradient norm and
one ``comm.max``, or the iteration number), so the step runs sharded over devices unchanged. The
robots not selected keep their poses (masks). For a single selected robot only one lane is solved
per device (its index is found with ``argmax``); "parallel" solves every robot under ``vmap``.

**RBCD++** (``accelerated=True``): the paper's Nesterov scheme, as in the authors' code
(mit-acl/dpgo ``PGOAgent``: ``updateGamma``, ``updateAlpha``, ``updateY``, ``updateV``):
gamma_k = (1 + sqrt(1 + 4 N^2 gamma_{k-1}^2)) / (2N), alpha_k = 1 / (gamma_k N) (N robots),
Y = Proj((1 - alpha) X + alpha V) for every robot, the selected block updated from Y (its
neighbours at Y: one extra pose exchange, and greedy ranks the block gradients at Y), every other
block set to Y, then V = Proj(V + gamma (X^{k+1} - Y)). The restart (``restart``): "adaptive"
(default, the paper's): when f(X^{k+1}) > f(X^k) the iteration is redone as a plain RBCD step from
X^k (its own selection), and gamma = 0, V = X^{k+1}, so F is non-increasing for RBCD++ too;
"fixed" (dpgo's ``restart_interval``, 30 there and here): gamma = 0, V = X^{k+1} after every
``restart_interval``-th iteration and never a redo, so F may rise in between. ``restarted``
records the restarts (every robot's momentum at once: gamma is shared).

**Lifted rank** (``rank=r > d``; dpgo uses r = 5): poses in (St(d, r) x R^r)^n, Y_i = [t_i | R_i]
with r rows and R_i^T R_i = I (:mod:`~mmpgo_jax._baselines.rbcd_lifted`). F is the same quadratic
form (it acts on the right, rows are free), so Gamma_b, the gradients, the tangent projection
Z - Y sym(Y^T Z) and the Weingarten term are those of rank d; the retraction and projection are the
polar factor (no determinant fix), chosen by the blocks' shape in the block solve; its
preconditioner is the lifted block-Jacobi (:class:`~.rbcd_lifted.LiftedPreconditioner`; the
two-level one is refused). The start is lifted by one fixed r x d Stiefel matrix P (seeded random,
as dpgo's ``fixedStiefelVariable``): Y_i = P X_i. F's gradient and the polar retraction keep the
rows in P's span, so from this rank-d start the run optimises over O(d) per block (SO(d) without
the determinant constraint) inside that span. The result's poses are rounded to SE(d) as SE-Sync
and dpgo do (:func:`~.rbcd_lifted.round_lifted`: the top d left singular directions of all poses
side by side, a reflection if most rotation blocks have det < 0, each block projected to SO(d),
translations following); ``stats`` gets ``rbcd_lifted_f`` (f = 2F of the last lifted iterate, the
history's last value) and ``rbcd_rounded_f`` (f of the reported poses; equal to the lifted f up to
the iterates' rounding errors while they keep rank d). ``rank=None`` or d is the SO(d) code,
unchanged bit for bit.

**Communication** (logical volume, what the algorithm needs; :func:`rbcd_poses_sent`): one MM/AMM
iteration sends every robot's boundary poses (:func:`boundary_poses_sent`, summed); one RBCD
iteration the selected robot's only (greedy adds two ``max`` reductions of one number per robot),
"parallel" a colour class's; RBCD++ adds every robot's boundary poses of Y. Poses per iteration,
10 robots (``mm.partition(graph, 10)``), MM / RBCD greedy / RBCD++ greedy / parallel / parallel++:
sphere2500 900 / 90 / 990 / 450 / 1350; M3500 1292 / 129 / 1421 / 258 / 1550; parking-garage
2151 / 215 / 2366 / 430 / 2581; intel 1220 / 122 / 1342 / 244 / 1464. A lifted rank sends r(d+1)
numbers per pose instead of d(d+1). The sharded program itself exchanges every boundary pose each
iteration (the halo exchange does not skip unselected robots).

Not done: robust losses, and certification of the result (see :func:`mmpgo_jax.certify`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import networkx as nx
import numpy as np

from .._core.partition import Partition
from .._core.pose_graph import Poses, cost, host_graph
from .._core.precision import to_device
from .._core.validate import check_choice, check_count, check_flag, check_real
from .._mm.majorization import GammaSoA, build_gamma_operator, host_soa, stack
from .._mm.outer import IterationRecord
from .._mm.preconditioner import NewtonPreconditioner, build_newton_preconditioner
from .._mm.solvers import Solver
from .._mm.subproblem import SubproblemConfig, project_rotations, solve_subproblem, tangent_projection
from .._mm.weighting import LOCAL, Collectives, gradients
from .rbcd_lifted import LiftedPreconditioner, lift_matrix, round_lifted

__all__ = ["RBCD", "SELECTIONS", "RBCDProblem", "RBCDState", "boundary_poses_sent", "rbcd_poses_sent",
           "robot_colouring"]

SELECTIONS = ("greedy", "uniform", "round-robin", "parallel")
RESTARTS = ("adaptive", "fixed")


def default_inner() -> SubproblemConfig:
    """The block solve's settings: block-Jacobi preconditioning (the block Gamma's), and a solve
    close to exact (a block update is the whole work of an iteration, so its accuracy is cheap)."""
    return SubproblemConfig(preconditioner="block-jacobi", gradient_tolerance=1e-2, cg_tolerance=1e-2, max_steps=10)


def robot_colouring(part: Partition) -> np.ndarray:
    """(A,) colour of every robot (-1: a robot without poses) such that robots sharing an edge differ
    (host; networkx's largest-first greedy colouring of the robot adjacency graph)."""
    e = part.edges
    inter = np.asarray(e.local_i) ^ np.asarray(e.local_j)
    ri, rj = np.asarray(e.robot_i)[inter], np.asarray(e.robot_j)[inter]
    real = np.flatnonzero(np.asarray(part.pose_mask).any(axis=1))
    G = nx.Graph()
    G.add_nodes_from(int(a) for a in real)
    G.add_edges_from((int(a), int(b)) for a, b in zip(ri, rj, strict=True) if a != b)
    colour = np.full(part.num_robots, -1, np.int32)
    for robot, c in nx.coloring.greedy_color(G, strategy="largest_first").items():
        colour[robot] = c
    return colour


def boundary_poses_sent(part: Partition) -> np.ndarray:
    """(A,) poses each robot sends in one neighbour exchange: its poses at the ends of inter-robot
    edges, once per neighbour that needs them (host; = :func:`~mmpgo_jax.partition_stats`'s
    ``sent_poses``, read from the partition's own edge lists). One MM/AMM iteration sends their sum."""
    e = part.edges
    local_i = np.asarray(e.local_i)
    inter = local_i ^ np.asarray(e.local_j)  # one end elsewhere: received by the edge list's owner
    owner = np.broadcast_to(np.arange(part.num_robots)[:, None], inter.shape)[inter]
    sender = np.where(local_i, np.asarray(e.robot_j), np.asarray(e.robot_i))[inter]
    pose = np.where(local_i, np.asarray(e.slot_j), np.asarray(e.slot_i))[inter]
    triples = np.unique(np.stack([owner, sender, pose], 1), axis=0)
    return np.bincount(triples[:, 1], minlength=part.num_robots).astype(np.int64)


def rbcd_poses_sent(part: Partition, selection: str = "greedy", accelerated: bool = False) -> float:
    """Poses one RBCD / RBCD++ iteration sends (logical volume, mean over iterations), against
    ``boundary_poses_sent(part).sum()`` for one MM/AMM iteration: the updated robots' boundary poses
    -- one robot's for "greedy", "uniform" and "round-robin" (the mean over robots: exact over a
    round-robin cycle, the expectation for "uniform", an estimate for "greedy", whose choice depends
    on the data), a colour class's for "parallel" (the mean over classes: every robot once per C
    iterations). RBCD++ adds every robot's boundary poses of Y (its neighbours evaluate the selected
    block's problem at Y and set their blocks to Y); an adaptive restart's second pass (rare) sends
    the re-selected block once more and is not counted. Scalars are not counted: greedy's two
    ``max`` reductions of one number per robot, the f of the record (and RBCD++'s restart test)."""
    check_choice("rbcd_poses_sent", "selection", selection, SELECTIONS)
    sent = boundary_poses_sent(part)
    total = float(sent.sum())
    if selection == "parallel":
        per_iteration = total / max(int(robot_colouring(part).max(initial=-1)) + 1, 1)
    else:
        per_iteration = total / max(int(np.asarray(part.pose_mask).any(axis=1).sum()), 1)
    return per_iteration + (total if accelerated else 0.0)


class RBCDProblem(eqx.Module):
    """Constant data of an RBCD run: the block Gamma_b of every robot (structure of arrays), its
    preconditioner data, the fixed-pose mask (None: no pose fixed) and the selection's tables, kept
    per robot (leading axis A) so that a sharded run gives each device its own robots' entries."""

    partition: Partition
    gamma_soa: GammaSoA
    newton: NewtonPreconditioner
    free: jax.Array | None  # (A, n_max) bool
    index: jax.Array  # (A,) int32: the robot's index
    order: jax.Array  # (A,) int32: position among the robots with poses (-1: none)
    colour: jax.Array  # (A,) int32: colour class (-1: no poses)
    robots: jax.Array  # () int32: robots with poses (N)
    colours: jax.Array  # () int32: colour classes (C)
    xi: jax.Array  # () the proximal term in Gamma_b
    lift: jax.Array | None = None  # (A, r, d): the lift of the start, one copy per robot (None: rank d)


class RBCDState(eqx.Module):
    """X^k (stacked, (A, n_max, d, d+1); r rows for a lifted rank r), grad F(X^k) per robot block, the
    objective shares, the iteration count; RBCD++ adds V and gamma (None for RBCD)."""

    X: jax.Array
    grad: jax.Array
    share: jax.Array  # (A,)
    iteration: jax.Array
    V: jax.Array | None = None
    gamma: jax.Array | None = None


def _free_mask(part: Partition, fixed):
    """(A, n_max) bool of the movable slots, as :meth:`MMProblem.build` makes it (None: none fixed)."""
    if fixed is None:
        return None
    mask = fixed.mask(part.num_poses) if hasattr(fixed, "mask") else np.asarray(fixed, dtype=bool)
    if mask.shape != (part.num_poses,):
        raise ValueError(f"fixed mask must have shape ({part.num_poses},), got {mask.shape}")
    free = np.ones(part.pose_mask.shape, dtype=bool)
    free[np.asarray(part.robot_of_pose)[mask], np.asarray(part.slot_of_pose)[mask]] = False
    return to_device(free)


def _block_norms2(problem: RBCDProblem, X, grad):
    """(A,) squared Riemannian block-gradient norms (fixed slots are not variables)."""
    rgrad = tangent_projection(X, grad)
    if problem.free is not None:
        rgrad = jnp.where(problem.free[..., None, None], rgrad, 0.0)
    return jnp.sum(rgrad**2, axis=(1, 2, 3))


def _movable(problem: RBCDProblem):
    """(A, n_max, 1, 1) bool: real, free slots (the ones momentum may move)."""
    m = problem.partition.pose_mask
    if problem.free is not None:
        m = m & problem.free
    return m[..., None, None]


def _project(problem: RBCDProblem, M, keep):
    """M with its rotations projected to SO(d) on the movable slots; ``keep`` elsewhere (bit-exact)."""
    P = M.at[..., 1:].set(project_rotations(M[..., 1:]))
    return jnp.where(_movable(problem), P, keep)


class RBCD(Solver):
    """RBCD / RBCD++ (module docstring). ``selection``: "greedy", "uniform", "round-robin" or
    "parallel"; ``accelerated``: RBCD++ (Nesterov momentum); ``restart``: RBCD++'s momentum restart,
    "adaptive" (default) or "fixed" every ``restart_interval`` iterations (dpgo's rule); ``rank``: None or
    d (SO(d)), or r > d (the lifted rank with rounding; block-Jacobi inner preconditioner); ``inner``: the block solve's
    :class:`~mmpgo_jax.SubproblemConfig` (default :func:`default_inner`); ``xi``: a proximal term in
    the block problem (default 0: exact block minimisation); ``seed``: the "uniform" draws."""

    selection: str = eqx.field(static=True)
    accelerated: bool = eqx.field(static=True)
    rank: int | None = eqx.field(static=True)
    restart: str = eqx.field(static=True)
    restart_interval: int = eqx.field(static=True)
    inner: SubproblemConfig
    xi: float
    seed: int

    def __init__(self, selection: str = "greedy", accelerated: bool = False, rank: int | None = None,
                 inner: SubproblemConfig | None = None, xi: float = 0.0, seed: int = 0, restart: str = "adaptive",
                 restart_interval: int = 30):
        owner = "RBCD"
        check_choice(owner, "selection", selection, SELECTIONS)
        check_flag(owner, "accelerated", accelerated)
        check_choice(owner, "restart", restart, RESTARTS)
        check_count(owner, "restart_interval", restart_interval, 1)
        self.restart, self.restart_interval = restart, int(restart_interval)
        if rank is not None:
            check_count(owner, "rank", rank, 2)
        if inner is not None and not isinstance(inner, SubproblemConfig):
            raise TypeError(f"{owner}.inner must be a SubproblemConfig, got {type(inner).__name__}")
        check_real(owner, "xi", xi, 0.0)
        check_count(owner, "seed", seed, 0)
        self.selection, self.accelerated, self.rank = selection, bool(accelerated), rank
        self.inner = default_inner() if inner is None else inner
        self.xi, self.seed = xi, seed

    @property
    def name(self) -> str:
        return "rbcd++" if self.accelerated else "rbcd"

    # --- host -------------------------------------------------------------------------------

    def build(self, partition: Partition, *, poses, fixed=None, loss=None, min_couplings: int = 0,
              aggregate: int | None = None) -> RBCDProblem:
        if loss is not None:
            raise ValueError("RBCD minimises the least-squares F only: give no loss")
        d = partition.edges.t.shape[-1]
        lifted = self.rank not in (None, d)
        if lifted and self.rank < d:
            raise ValueError(f"RBCD: rank must be None or at least d = {d}, got {self.rank}")
        if lifted and self.inner.preconditioner == "two-level":
            raise ValueError("RBCD with a lifted rank preconditions the block solve by block-Jacobi only: give "
                             "inner=SubproblemConfig(preconditioner='block-jacobi', ...)")
        n_max = partition.max_poses
        gamma = build_gamma_operator(partition.edges, float(self.xi), n_max, min_couplings=min_couplings, host=True,
                                     inter_weight=1.0)
        soa = host_soa(gamma)
        dtype = soa.diag.dtype
        if self.inner.preconditioner == "two-level":
            newton = build_newton_preconditioner(gamma.diag, gamma.band, gamma.src, gamma.dst, gamma.blocks,
                                                 stack(jax.tree.map(np.asarray, poses)), partition.pose_mask, dtype,
                                                 aggregate=aggregate or self.inner.aggregate)
        else:
            newton = build_newton_preconditioner(gamma.diag, dtype=dtype)
        real = np.asarray(partition.pose_mask).any(axis=1)
        order = np.where(real, np.cumsum(real) - 1, -1)
        colour = robot_colouring(partition)
        i32 = np.int32
        lift = np.broadcast_to(lift_matrix(self.rank, d), (partition.num_robots, self.rank, d)) if lifted else None
        return RBCDProblem(partition=partition, gamma_soa=soa, newton=newton, free=_free_mask(partition, fixed),
                           index=to_device(np.arange(partition.num_robots), i32), order=to_device(order, i32),
                           colour=to_device(colour, i32), robots=to_device(max(int(real.sum()), 1), i32),
                           colours=to_device(max(int(colour.max(initial=-1)) + 1, 1), i32),
                           xi=to_device(float(self.xi), dtype), lift=None if lift is None else to_device(lift, dtype))

    def check(self, problem) -> None:
        if not isinstance(problem, RBCDProblem):
            raise TypeError(f"RBCD runs on an RBCDProblem (RBCD().build(...)), got {type(problem).__name__}")
        if self.inner.preconditioner == "two-level" and not problem.newton.has_coarse:
            raise ValueError("this RBCDProblem holds the block-Jacobi preconditioner only: build it with the "
                             "two-level inner config")

    # --- traced -----------------------------------------------------------------------------

    def init(self, problem: RBCDProblem, X0):
        X = stack(X0)
        if problem.lift is not None:  # Y_i = P X_i, P the fixed r x d Stiefel matrix of every robot
            X = jnp.einsum("ard,andc->anrc", problem.lift, X)
        grad, share, _ = gradients(problem, X)
        A = share.shape[0]
        V, gamma = (X, jnp.zeros((), X.dtype)) if self.accelerated else (None, None)
        state = RBCDState(X=X, grad=grad, share=share, iteration=jnp.asarray(0, dtype=int), V=V, gamma=gamma)
        rec = IterationRecord(f=2.0 * jnp.sum(share), grad_norm=jnp.sqrt(jnp.sum(_block_norms2(problem, X, grad))),
                              restarted=jnp.zeros(A, bool), settled=jnp.ones((), bool))
        return state, rec

    def select(self, problem: RBCDProblem, k, norms2, comm: Collectives = LOCAL):
        """(A,) bool: the robots that update at iteration ``k`` (``norms2``: their squared block-gradient
        norms, read by "greedy")."""
        if self.selection == "greedy":
            real = problem.order >= 0
            score = jnp.where(real, norms2, -1.0)
            best = comm.max(score)
            # ties (e.g. all zero at a critical point) go to the lowest index: one robot, never two neighbours
            first = -comm.max(jnp.where(real & (score == best), -problem.index, jnp.iinfo(jnp.int32).min))
            return problem.index == first
        if self.selection == "round-robin":
            return problem.order == k % problem.robots
        if self.selection == "uniform":
            key = jax.random.fold_in(jax.random.PRNGKey(self.seed), k)
            return problem.order == jax.random.randint(key, (), 0, problem.robots)
        return problem.colour == k % problem.colours  # "parallel"

    def block_update(self, problem: RBCDProblem, X, grad, selected):
        """X with every selected robot's block moved to its block minimiser from X (``grad``: grad F(X)
        per block); the other blocks unchanged."""
        g = jnp.where(selected[:, None, None, None], grad, 0.0)  # a zero gradient: the solve returns at once

        def solve(G, P, x, gx, free):
            return solve_subproblem(G, P, x, x, gx, self.inner, free)[0]

        pre = problem.newton if self.inner.preconditioner == "two-level" else problem.newton.without_coarse()
        if problem.lift is not None:
            pre = LiftedPreconditioner(pre, problem.gamma_soa.diag)
        if self.selection == "parallel":
            axis = None if problem.free is None else 0
            Y = jax.vmap(solve, in_axes=(0, 0, 0, 0, axis))(problem.gamma_soa, pre, X, g, problem.free)
            return jnp.where(selected[:, None, None, None], Y, X)
        j = jnp.argmax(selected)  # the one selected robot on this device (if any)

        def lane(tree):
            return jax.tree.map(lambda a: a[j], tree)

        Yj = solve(lane(problem.gamma_soa), lane(pre), X[j], g[j], None if problem.free is None else problem.free[j])
        return X.at[j].set(jnp.where(selected[j], Yj, X[j]))

    def _rbcd(self, problem: RBCDProblem, X, grad, k, comm):
        """One RBCD iteration from X: (X^{k+1}, its gradient, shares)."""
        selected = self.select(problem, k, _block_norms2(problem, X, grad), comm)
        Xn = self.block_update(problem, X, grad, selected)
        gn, sn, _ = gradients(problem, Xn, comm)
        return Xn, gn, sn

    def _adaptive(self, problem: RBCDProblem, state: RBCDState, Y, gY, f_old, k, comm):
        """The paper's adaptive restart: pass 1, the accelerated update from Y; pass 2 (only after an
        increase of f), RBCD from X^k. Returns (X, grad, share, restarted)."""
        def body(carry):
            i, restart, *_ = carry
            first = i == 0
            start, g = jnp.where(first, Y, state.X), jnp.where(first, gY, state.grad)
            Xn, gn, sn = self._rbcd(problem, start, g, k, comm)
            restart = jnp.where(first, 2.0 * comm.sum(sn) > f_old, restart)
            return i + 1, restart, Xn, gn, sn

        def cond(carry):
            i, restart = carry[:2]
            return (i == 0) | ((i == 1) & restart)

        init = (jnp.asarray(0), jnp.zeros((), bool), state.X, state.grad, state.share)
        _, restart, X, grad, share = jax.lax.while_loop(cond, body, init)
        return X, grad, share, restart

    def step(self, problem: RBCDProblem, state: RBCDState, comm: Collectives = LOCAL):
        k = state.iteration
        A = state.share.shape[0]
        if not self.accelerated:
            X, grad, share = self._rbcd(problem, state.X, state.grad, k, comm)
            restart = jnp.zeros((), bool)
            V = gamma = None
        else:
            N = problem.robots.astype(state.X.dtype)
            gamma = (1.0 + jnp.sqrt(1.0 + 4.0 * N**2 * state.gamma**2)) / (2.0 * N)
            alpha = 1.0 / (gamma * N)
            Y = _project(problem, (1.0 - alpha) * state.X + alpha * state.V, state.X)
            gY, _, _ = gradients(problem, Y, comm)  # the neighbours' Y: one more exchange
            if self.restart == "fixed":  # dpgo: no redo, the momentum forgotten every restart_interval iterations
                X, grad, share = self._rbcd(problem, Y, gY, k, comm)
                restart = (k + 1) % self.restart_interval == 0
            else:
                X, grad, share, restart = self._adaptive(problem, state, Y, gY, 2.0 * comm.sum(state.share), k, comm)
            V = jnp.where(restart, X, _project(problem, state.V + gamma * (X - Y), state.V))
            gamma = jnp.where(restart, 0.0, gamma)
        new = RBCDState(X=X, grad=grad, share=share, iteration=k + 1, V=V, gamma=gamma)
        rec = IterationRecord(f=2.0 * comm.sum(share),
                              grad_norm=jnp.sqrt(comm.sum(_block_norms2(problem, X, grad))),
                              restarted=jnp.broadcast_to(restart, (A,)) & (problem.order >= 0),
                              settled=jnp.ones((), bool))
        return new, rec

    def final_poses(self, problem: RBCDProblem, part, X):
        """X itself at rank d; a lifted X rounded to SE(d) (:func:`~.rbcd_lifted.round_lifted`)."""
        if problem.lift is None:
            return X
        free = None if problem.free is None else np.asarray(problem.free)
        return round_lifted(X, np.asarray(part.pose_mask), np.asarray(problem.lift)[0], free)

    def outcome(self, problem: RBCDProblem, graph, part, state: RBCDState, poses, to_host=np.asarray):
        """A lifted run's statistics: ``rbcd_lifted_f`` (f = 2F of the final lifted iterate, the last
        history value) and ``rbcd_rounded_f`` (f of the rounded poses the result reports)."""
        if problem.lift is None:
            return {}, {}
        lifted = 2.0 * float(np.sum(to_host(state.share)))
        rounded = cost(host_graph(graph), Poses(np.asarray(poses.R), np.asarray(poses.t)))
        return {}, dict(rbcd_lifted_f=lifted, rbcd_rounded_f=float(rounded))

    def skipped(self, state: RBCDState) -> IterationRecord:
        nan = jnp.full((), jnp.nan, state.share.dtype)
        return IterationRecord(f=nan, grad_norm=nan, restarted=jnp.zeros(state.share.shape, bool),
                               settled=jnp.ones((), bool))

    def record_structure(self, problem) -> IterationRecord:
        return IterationRecord(f=0.0, grad_norm=0.0, restarted=0.0, settled=0.0)
