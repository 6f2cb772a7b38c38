"""Distributed chordal initialization by accelerated majorization minimization (paper §VII).

Rotations (Algorithm 3, "AMM-Chordal"). The relaxed problem (22) min F_R(R) over R in
R^{d x dn} with R_0 = I is split among the robots of a :class:`~._partition.Partition`. Eq. (24)
majorizes every inter-robot term 1/2 kappa ||R_i Rt - R_j||^2 by kappa ||R_i Rt - P||^2 +
kappa ||R_j - P||^2 around the midpoint P of the current iterate, plus a proximal term
xi/2 ||R - R^k||^2. As a function of robot alpha's own blocks the majorizer is the quadratic

    G_R^alpha(Z | Y) = 1/2 <Gamma_R^alpha (Z - Y), Z - Y> + <grad_alpha F_R(Y), Z - Y> + const,

    Gamma_R^alpha = (kappa-connection Laplacian of the robot's own edges)
                    + sum over its inter-robot edges of 2 kappa Rt Rt^T (tail) or 2 kappa I (head)
                      on the local pose's diagonal block
                    + xi I,

which is constant over the iterations. Its exact minimiser is Z = Y - grad_alpha F_R(Y)
(Gamma_R^alpha)^{-1} (acting from the right on the d x dn block row). Algorithm 3 adds
Nesterov momentum: s_{k+1} = (sqrt(4 s_k^2 + 1) + 1) / 2, gamma_k = (s_k - 1) / s_{k+1},
Y^k = R^k + gamma_k (R^k - R^{k-1}) and, since grad F_R is affine,
grad F_R(Y^k) = grad F_R(R^k) + gamma_k (grad F_R(R^k) - grad F_R(R^{k-1})) exactly (line 13),
so each iteration evaluates one gradient (at the new iterate) and exchanges each robot's poses at
the ends of its inter-robot edges once.

Translations. With the projected rotations fixed, the translation problem (25)-(26) is the same
kind of quadratic with the tau-weighted graph Laplacian (a scalar n_alpha x n_alpha Gamma_t^alpha,
2 tau on inter-robot edge ends, + xi I), solved by the identical accelerated scheme, t_0 = 0.

Anchoring. As in the centralized version (:func:`~._initialization.anchor_poses`) the first pose
of every connected component of the measurement graph is held at R = I, t = 0 (pose 0 of robot 0
for a connected graph with the contiguous partition). It is eliminated from the robot's
subproblem by zeroing its gradient and its rows/columns of Gamma (identity on the diagonal), so
its value never moves.

Solves. Gamma^alpha is factored once, on the host: it is sparse, so each robot's inverse is
computed by a sparse LU (SuperLU) solve against the identity and stored densely, padded to
n_max slots (identity on padding slots). The iteration then applies all robots' inverses by one
batched matrix product, (A, N, N) x (A, N, d). Measured on this 2-core CPU for A = 10,
N = n_max d = 2000, d = 2 right-hand sides: batched product 29-34 ms per application, vmapped
``jax.scipy.linalg.cho_solve`` with the dense Cholesky factor 840 ms (XLA's CPU triangular solve
is not blocked for few right-hand sides), so the explicit inverse is used. Memory:
A N^2 float64 (320 MB for city10000 with 10 robots).

Proximal weight xi (default 1e-3, the value used for the paper's experiments; see NOTES §3).
It only keeps Gamma positive definite in degenerate cases (zero-weight edges); with the
component anchoring Gamma is already positive definite for xi = 0, and because xi is tiny next
to the measurement weights it does not change the iteration counts measurably.

Stopping. ``tol`` (relative) stops a stage at the first iteration k with
  <grad F(Y^k), (Gamma)^{-1} grad F(Y^k)> <= tol * f(R^{k+1}),
i.e. when the decrease that the exact majorizer step from Y^k promises is a relative ``tol`` of
the (relaxed, 2F-convention) objective; it costs nothing extra (both factors are computed by the
step anyway). The loop is a ``lax.while_loop`` over ``lax.scan`` chunks of the same jitted step
with the state frozen once converged, so ``tol`` and the iteration budget are traced values: no
recompilation, and the reported iteration count is exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ._geometry import project_to_so
from ._initialization import anchor_poses
from ._partition import Partition, partition as make_partition
from ._pose_graph import PoseGraph, Poses

__all__ = [
    "DEFAULT_ROTATION_ITERATIONS",
    "DEFAULT_TRANSLATION_ITERATIONS",
    "DistributedChordalInfo",
    "distributed_chordal_initialization",
    "distributed_relaxed_rotations",
    "distributed_translations",
]

DEFAULT_ROTATION_ITERATIONS = 500
DEFAULT_TRANSLATION_ITERATIONS = 500
DEFAULT_XI = 1e-3
_CHUNK = 10  # iterations per lax.scan chunk between convergence checks of the while loop


# --------------------------------------------------------------------------------------------
# host-side set-up: Gamma^alpha and its inverse
# --------------------------------------------------------------------------------------------


def _padded_anchor_mask(part: Partition, anchors: np.ndarray) -> np.ndarray:
    mask = np.zeros(part.pose_mask.shape, dtype=bool)
    rob = np.asarray(part.robot_of_pose)[anchors]
    slot = np.asarray(part.slot_of_pose)[anchors]
    mask[rob, slot] = True
    return mask


def _gamma_inverses(part: Partition, anchor_mask: np.ndarray, xi: float, d: int, rotation: bool) -> np.ndarray:
    """(A, N, N) dense inverses of Gamma_R^alpha (N = n_max d) or Gamma_t^alpha (N = n_max).

    Rotation layout: row/column ``slot*d + a`` acts on the transposed block R_slot^T.
    """
    e = part.edges
    A, n_max = part.pose_mask.shape
    b = d if rotation else 1
    N = n_max * b
    loc_i = np.asarray(e.local_i)
    loc_j = np.asarray(e.local_j)
    si = np.asarray(e.slot_i, dtype=np.int64)
    sj = np.asarray(e.slot_j, dtype=np.int64)
    w = np.asarray(e.kappa if rotation else e.tau, dtype=np.float64)
    Rm = np.asarray(e.R, dtype=np.float64)
    pose_mask = np.asarray(part.pose_mask)
    ar = np.arange(b)
    out = np.empty((A, N, N))
    for a in range(A):  # host-side set-up only; the iteration itself is vmapped
        own = loc_i[a] & loc_j[a]
        tail = loc_i[a] & ~loc_j[a]
        head = loc_j[a] & ~loc_i[a]
        rows, cols, vals = [], [], []

        def add(r_slots, c_slots, blocks):
            if len(r_slots) == 0:
                return
            r = (b * r_slots[:, None] + ar)[:, :, None]
            c = (b * c_slots[:, None] + ar)[:, None, :]
            rows.append(np.broadcast_to(r, blocks.shape).ravel())
            cols.append(np.broadcast_to(c, blocks.shape).ravel())
            vals.append(blocks.ravel())

        if rotation:
            R = Rm[a]
            RRt = R @ np.swapaxes(R, 1, 2)
            eye = np.broadcast_to(np.eye(d), R.shape)
            k = w[a][:, None, None]
            add(si[a][own], si[a][own], (k * RRt)[own])
            add(sj[a][own], sj[a][own], (k * eye)[own])
            add(si[a][own], sj[a][own], (-k * R)[own])
            add(sj[a][own], si[a][own], (-k * np.swapaxes(R, 1, 2))[own])
            add(si[a][tail], si[a][tail], (2 * k * RRt)[tail])
            add(sj[a][head], sj[a][head], (2 * k * eye)[head])
        else:
            k = w[a][:, None, None]
            one = np.ones((e.kappa.shape[1], 1, 1))
            add(si[a][own], si[a][own], (k * one)[own])
            add(sj[a][own], sj[a][own], (k * one)[own])
            add(si[a][own], sj[a][own], (-k * one)[own])
            add(sj[a][own], si[a][own], (-k * one)[own])
            add(si[a][tail], si[a][tail], (2 * k * one)[tail])
            add(sj[a][head], sj[a][head], (2 * k * one)[head])
        diag = np.where(np.repeat(pose_mask[a], b), xi, 1.0)
        rows.append(np.arange(N))
        cols.append(np.arange(N))
        vals.append(diag)
        G = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(N, N)).tocsr()
        # eliminate anchor poses: zero rows/columns, identity on the diagonal
        keep = ~np.repeat(anchor_mask[a], b)
        Dk = sp.diags(keep.astype(float))
        G = (Dk @ G @ Dk + sp.diags((~keep).astype(float))).tocsc()
        lu = spla.splu(G, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        Ginv = lu.solve(np.eye(N))
        out[a] = 0.5 * (Ginv + Ginv.T)
    return out


# --------------------------------------------------------------------------------------------
# per-robot gradients (vmapped over robots)
# --------------------------------------------------------------------------------------------


def _rotation_gradient_one(edges, anchor, R, n_max: int):
    """grad_alpha F_R at the padded global iterate R (A, n_max, d, d) and the robot's cost share.

    Cost share in the 2F convention: own edges fully, inter-robot edges half, so that the shares
    sum to 2 F_R.
    """
    Ri = R[edges.robot_i, edges.slot_i]
    Rj = R[edges.robot_j, edges.slot_j]
    E = Ri @ edges.R - Rj
    wE = edges.kappa[:, None, None] * E
    gi = jnp.where(edges.local_i[:, None, None], wE @ jnp.swapaxes(edges.R, -1, -2), 0.0)
    gj = jnp.where(edges.local_j[:, None, None], wE, 0.0)
    g = jax.ops.segment_sum(gi, edges.slot_i, n_max) - jax.ops.segment_sum(gj, edges.slot_j, n_max)
    g = jnp.where(anchor[:, None, None], 0.0, g)
    share = jnp.sum(jnp.where(edges.is_inter, 0.5, 1.0) * jnp.sum(wE * E, axis=(-1, -2)))
    return g, share


def _translation_gradient_one(edges, anchor, v, t, n_max: int):
    """Same for the translation problem; ``v`` (e_max, d) = R_i tt_e with the fixed rotations."""
    ti = t[edges.robot_i, edges.slot_i]
    tj = t[edges.robot_j, edges.slot_j]
    r = v + ti - tj
    wr = edges.tau[:, None] * r
    gi = jnp.where(edges.local_i[:, None], wr, 0.0)
    gj = jnp.where(edges.local_j[:, None], wr, 0.0)
    g = jax.ops.segment_sum(gi, edges.slot_i, n_max) - jax.ops.segment_sum(gj, edges.slot_j, n_max)
    g = jnp.where(anchor[:, None], 0.0, g)
    share = jnp.sum(jnp.where(edges.is_inter, 0.5, 1.0) * jnp.sum(wr * r, axis=-1))
    return g, share


def _rotation_gradient(edges, anchor, R):
    n_max = anchor.shape[1]
    g, share = jax.vmap(_rotation_gradient_one, in_axes=(0, 0, None, None))(edges, anchor, R, n_max)
    return g, jnp.sum(share)


def _translation_gradient(edges, anchor, v, t):
    n_max = anchor.shape[1]
    g, share = jax.vmap(_translation_gradient_one, in_axes=(0, 0, 0, None, None))(edges, anchor, v, t, n_max)
    return g, jnp.sum(share)


def _apply_inverse_rot(Ginv, G):
    """Rows of the step for every robot: (G Gamma^{-1}) in block form, G (A, n_max, d, d)."""
    A, n_max, d, _ = G.shape
    rhs = jnp.swapaxes(G, -1, -2).reshape(A, n_max * d, d)  # stacked G_i^T
    sol = jnp.einsum("aij,ajk->aik", Ginv, rhs)
    return jnp.swapaxes(sol.reshape(A, n_max, d, d), -1, -2)


def _apply_inverse_trans(Ginv, g):
    return jnp.einsum("aij,ajk->aik", Ginv, g)


# --------------------------------------------------------------------------------------------
# the accelerated MM iteration (shared by both stages)
# --------------------------------------------------------------------------------------------


class _State(eqx.Module):
    X: jax.Array  # R^k or t^k, padded (A, n_max, ...)
    Xprev: jax.Array
    G: jax.Array  # grad F(X^k)
    Gprev: jax.Array
    s: jax.Array
    k: jax.Array  # iterations done
    done: jax.Array
    history: jax.Array  # (max_iters + 1,) relaxed objective (2F convention) at X^0..X^k


RESTART = {"mode": "none"}


def _amm_run(grad_fn, apply_inv, X0, max_iters: int, budget, tol):
    """Algorithm 3 from X0: while_loop over scan chunks; returns the final _State.

    ``grad_fn(X) -> (grad, cost)``; ``apply_inv(G) -> G Gamma^{-1}`` (per robot).
    """
    G0, f0 = grad_fn(X0)
    dt = X0.dtype
    hist = jnp.full((max_iters + 1,), jnp.nan, dt).at[0].set(f0)
    state = _State(X0, X0, G0, G0, jnp.ones((X0.shape[0],), dt), jnp.asarray(0, jnp.int32), jnp.asarray(False), hist)

    def step(st: _State, _):
        active = (st.k < budget) & ~st.done
        s1 = 0.5 * (jnp.sqrt(4.0 * st.s**2 + 1.0) + 1.0)
        gam = (st.s - 1.0) / s1
        gb = gam.reshape((-1,) + (1,) * (st.X.ndim - 1))
        Y = st.X + gb * (st.X - st.Xprev)
        GY = st.G + gb * (st.G - st.Gprev)
        D = apply_inv(GY)
        Z = Y - D
        ax = tuple(range(1, st.X.ndim))
        if RESTART["mode"] == "robot":
            bad = jnp.sum(GY * (Z - st.X), axis=ax) > 0
            s1 = jnp.where(bad, 1.0, s1)
        elif RESTART["mode"] == "global":
            bad = jnp.sum(GY * (Z - st.X)) > 0
            s1 = jnp.where(bad, 1.0, s1)
        GZ, fZ = grad_fn(Z)
        decrease = jnp.sum(D * GY)  # <grad F(Y), Gamma^{-1} grad F(Y)>, 2x the model decrease
        conv = decrease <= tol * jnp.abs(fZ)
        k1 = st.k + 1
        new = _State(Z, st.X, GZ, st.G, s1, k1, conv, st.history.at[k1].set(fZ))
        st = jax.tree_util.tree_map(lambda a, b: jnp.where(active, a, b), new, st)
        return st, None

    def chunk(st):
        st, _ = jax.lax.scan(step, st, None, length=_CHUNK)
        return st

    def cond(st):
        return (st.k < budget) & ~st.done

    return jax.lax.while_loop(cond, chunk, state)


@eqx.filter_jit
def _rotation_solve(edges, anchor, Ginv, R0, budget, tol, max_iters: int):
    grad_fn = lambda R: _rotation_gradient(edges, anchor, R)  # noqa: E731
    apply_inv = lambda G: _apply_inverse_rot(Ginv, G)  # noqa: E731
    return _amm_run(grad_fn, apply_inv, R0, max_iters, budget, tol)


@eqx.filter_jit
def _translation_solve(edges, anchor, Ginv, Rglob, t0, budget, tol, max_iters: int):
    # v_e = R_i tt_e with the fixed rotations, per robot edge slot (constant over iterations)
    v = jnp.einsum("aexy,aey->aex", Rglob[edges.robot_i, edges.slot_i], edges.t)
    grad_fn = lambda t: _translation_gradient(edges, anchor, v, t)  # noqa: E731
    apply_inv = lambda g: _apply_inverse_trans(Ginv, g)  # noqa: E731
    return _amm_run(grad_fn, apply_inv, t0, max_iters, budget, tol)


# --------------------------------------------------------------------------------------------
# public API
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DistributedChordalInfo:
    """What :func:`distributed_chordal_initialization` did.

    ``*_history[k]`` is the relaxed objective in the 2F convention (2 F_R of Eq. (23) for
    rotations, 2 F_t of Eq. (26) for translations) after k iterations, k = 0..iterations.
    """

    rotation_iterations: int
    translation_iterations: int
    rotation_converged: bool
    translation_converged: bool
    rotation_history: np.ndarray
    translation_history: np.ndarray
    num_robots: int
    xi: float
    tol: float | None


def _as_partition(graph: PoseGraph, robots) -> Partition:
    if isinstance(robots, Partition):
        if robots.num_poses != graph.num_poses:
            raise ValueError(f"partition is for {robots.num_poses} poses, graph has {graph.num_poses}")
        return robots
    return make_partition(graph, robots)


def _check_iters(name, value):
    if int(value) != value or value < 0:
        raise ValueError(f"{name} must be a non-negative integer, got {value!r}")
    return int(value)


class _Setup(eqx.Module):
    part: Partition
    anchor: jax.Array  # (A, n_max) bool


def _setup(graph: PoseGraph, robots) -> _Setup:
    part = _as_partition(graph, robots)
    anchors = anchor_poses(graph)
    return _Setup(part, jnp.asarray(_padded_anchor_mask(part, anchors)))


def distributed_relaxed_rotations(
    graph: PoseGraph,
    robots=10,
    *,
    iterations: int = DEFAULT_ROTATION_ITERATIONS,
    xi: float = DEFAULT_XI,
    tol: float | None = None,
    initial=None,
    _setup_cache: _Setup | None = None,
):
    """AMM-Chordal (Algorithm 3) for the relaxed rotations: returns (R (n, d, d) unprojected,
    history (k+1,), iterations used, converged).

    ``initial``: R^(0) (n, d, d); default every block I (anchors are always I).
    """
    iterations = _check_iters("iterations", iterations)
    st = _setup_cache or _setup(graph, robots)
    part = st.part
    d = graph.dim
    dt = jnp.asarray(graph.R).dtype
    Ginv = jnp.asarray(_gamma_inverses(part, np.asarray(st.anchor), float(xi), d, rotation=True), dt)
    if initial is None:
        R0g = jnp.broadcast_to(jnp.eye(d, dtype=dt), (graph.num_poses, d, d))
    else:
        R0g = jnp.asarray(initial, dt)
        if R0g.shape != (graph.num_poses, d, d):
            raise ValueError(f"initial rotations must have shape ({graph.num_poses}, {d}, {d}), got {R0g.shape}")
    R0 = part.scatter(Poses(R0g, jnp.zeros((graph.num_poses, d), dt))).R
    R0 = jnp.where(st.anchor[..., None, None], jnp.eye(d, dtype=dt), R0)
    tol_v = jnp.asarray(-jnp.inf if tol is None else float(tol), dt)
    out = _rotation_solve(part.edges, st.anchor, Ginv, R0, jnp.asarray(iterations, jnp.int32), tol_v, iterations)
    k = int(out.k)
    R = out.X[part.robot_of_pose, part.slot_of_pose]
    return R, np.asarray(out.history)[: k + 1], k, bool(out.done)


def distributed_translations(
    graph: PoseGraph,
    R,
    robots=10,
    *,
    iterations: int = DEFAULT_TRANSLATION_ITERATIONS,
    xi: float = DEFAULT_XI,
    tol: float | None = None,
    _setup_cache: _Setup | None = None,
):
    """The same accelerated MM scheme for the translation problem (25) given rotations ``R``
    (n, d, d), t_0 = 0 (from t^(0) = 0). Returns (t (n, d), history, iterations used, converged)."""
    iterations = _check_iters("iterations", iterations)
    st = _setup_cache or _setup(graph, robots)
    part = st.part
    d = graph.dim
    dt = jnp.asarray(graph.R).dtype
    R = jnp.asarray(R, dt)
    if R.shape != (graph.num_poses, d, d):
        raise ValueError(f"rotations must have shape ({graph.num_poses}, {d}, {d}), got {R.shape}")
    Ginv = jnp.asarray(_gamma_inverses(part, np.asarray(st.anchor), float(xi), d, rotation=False), dt)
    Rpad = part.scatter(Poses(R, jnp.zeros((graph.num_poses, d), dt))).R
    t0 = jnp.zeros(part.pose_mask.shape + (d,), dt)
    tol_v = jnp.asarray(-jnp.inf if tol is None else float(tol), dt)
    out = _translation_solve(part.edges, st.anchor, Ginv, Rpad, t0, jnp.asarray(iterations, jnp.int32), tol_v, iterations)
    k = int(out.k)
    t = out.X[part.robot_of_pose, part.slot_of_pose]
    return t, np.asarray(out.history)[: k + 1], k, bool(out.done)


def distributed_chordal_initialization(
    graph: PoseGraph,
    robots=10,
    *,
    rotation_iterations: int = DEFAULT_ROTATION_ITERATIONS,
    translation_iterations: int = DEFAULT_TRANSLATION_ITERATIONS,
    xi: float = DEFAULT_XI,
    tol: float | None = None,
    initial_rotations=None,
) -> tuple[Poses, DistributedChordalInfo]:
    """Distributed chordal initialization: AMM-Chordal for the relaxed rotations, projection of
    each block to SO(d) (each robot its own poses), then the accelerated MM scheme for the
    translations (25).

    ``robots``: number of robots (contiguous blocks, NOTES §4), an (n,) robot-of-pose array, or a
    :class:`Partition`. ``tol``: relative stopping tolerance for both stages (see the module
    docstring), None to run the full iteration budgets.
    """
    st = _setup(graph, robots)
    Rrel, hR, kR, cR = distributed_relaxed_rotations(
        graph, st.part, iterations=rotation_iterations, xi=xi, tol=tol, initial=initial_rotations, _setup_cache=st
    )
    R = project_to_so(Rrel)
    t, ht, kt, ct = distributed_translations(
        graph, R, st.part, iterations=translation_iterations, xi=xi, tol=tol, _setup_cache=st
    )
    info = DistributedChordalInfo(
        rotation_iterations=kR,
        translation_iterations=kt,
        rotation_converged=cR,
        translation_converged=ct,
        rotation_history=hR,
        translation_history=ht,
        num_robots=st.part.num_robots,
        xi=float(xi),
        tol=tol,
    )
    return Poses(R, t), info
