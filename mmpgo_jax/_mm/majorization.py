"""Per-robot quantities of the majorization (paper §IV-V, Appendix A; docs/conventions.md §3).

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

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._core.geometry import bmm, mT
from .._core.partition import RobotEdges
from .._core.pose_graph import Poses, edge_hessian_blocks
from .._core.precision import to_device


def global_soa(X):
    """All robots' stacked poses (A, n_max, d, d+1) as (d, d+1, A n_max): the array edge ends are
    gathered from (slot s of robot r at r n_max + s). Every entry is a contiguous vector, so the
    gathers, residuals and scatters below are elementwise loops along the edge axis (measured
    1.5-2x faster than the same arithmetic on (n, d, d+1) blocks, benchmarks/profile_step.md)."""
    A, n, d, d1 = X.shape
    return jnp.transpose(X, (2, 3, 0, 1)).reshape(d, d1, A * n)


def _edge_maps(edges: RobotEdges):
    """T_e = [1 0; tt_e Rt_e] per edge, structure of arrays (d+1, d+1, e_max): the residual of edge
    e in the stacked layout is Y_i T_e - Y_j = [R_i tt + t_i - t_j | R_i Rt - R_j]."""
    d = edges.t.shape[-1]
    e = edges.t.shape[0]
    dt = edges.t.dtype
    top = jnp.concatenate([jnp.ones((1, 1, e), dt), jnp.zeros((1, d, e), dt)], axis=1)
    rest = jnp.concatenate([jnp.moveaxis(edges.t, 0, -1)[:, None], jnp.moveaxis(edges.R, 0, -1)], axis=1)
    return jnp.concatenate([top, rest], axis=0)


def _column_weights(edges: RobotEdges, scale=None):
    """(d+1, e_max): tau_e on the translation column, kappa_e on the rotation columns (times ``scale``)."""
    d = edges.t.shape[-1]
    w = jnp.concatenate([edges.tau[None], jnp.broadcast_to(edges.kappa, (d, edges.kappa.shape[0]))], axis=0)
    return w if scale is None else w * scale


def _residuals(T, Yi, Yj):
    return soa_bmm(Yi, T) - Yj


def _adjoint_to_slots(edges: RobotEdges, T, EW, n_max: int):
    """Scatter weighted residuals EW (d, d+1, e) back to the robot's own endpoint slots (the adjoint
    of the residual map): + EW T^T at slot i, - EW at slot j. Returns (d, d+1, n_max)."""
    gi = jnp.where(edges.local_i, soa_bmm(EW, soa_T(T)), 0.0)
    gj = jnp.where(edges.local_j, -EW, 0.0)
    out = jnp.zeros((*EW.shape[:2], n_max), EW.dtype)
    return out.at[..., edges.slot_i].add(gi).at[..., edges.slot_j].add(gj)


def _incident(edges: RobotEdges, X):
    """(T, residuals (d, d+1, e_max)) of the robot's incident edges, both ends gathered from the
    padded global stacked poses ``X`` (A, n_max, d, d+1)."""
    n_max = X.shape[1]
    Xg = global_soa(X)  # independent of the robot: computed once under vmap
    T = _edge_maps(edges)
    Yi, Yj = Xg[..., edges.robot_i * n_max + edges.slot_i], Xg[..., edges.robot_j * n_max + edges.slot_j]
    return T, _residuals(T, Yi, Yj)


def gradient_and_share(edges: RobotEdges, X, n_max: int):
    """(grad_alpha F(X) over local slots (n_max, d, d+1), Gbar^alpha(X), local cost) for one robot.

    The local cost counts every incident edge fully (own and inter-robot): the objective the
    robot would see if its neighbours were fixed.

    ``X`` is the padded GLOBAL stacked pose array (A, n_max, d, d+1): endpoint poses are gathered
    from it, which is exactly the neighbour communication of one iteration.
    """
    T, E = _incident(edges, X)
    EW = E * _column_weights(edges)
    edge_F = 0.5 * jnp.sum(EW * E, axis=(0, 1))
    share = jnp.sum(jnp.where(edges.is_inter, 0.5, 1.0) * edge_F)
    return from_soa(_adjoint_to_slots(edges, T, EW, n_max)), share, jnp.sum(edge_F)


def incident_residuals(edges: RobotEdges, X):
    """(residuals E (d, d+1, e_max), s) of one robot's incident edges at the padded global stacked
    poses ``X`` (A, n_max, d, d+1): E_e = [R_i tt + t_i - t_j | R_i Rt - R_j] and
    s_e = kappa ||R_i Rt - R_j||^2 + tau ||R_i tt + t_i - t_j||^2 (0 on padding)."""
    E = _incident(edges, X)[1]
    return E, jnp.sum(E * E * _column_weights(edges), axis=(0, 1))


def weighted_gradient(edges: RobotEdges, E, weights, n_max: int):
    """grad_alpha of 1/2 sum_e w_e s_e over the robot's local slots (n_max, d, d+1), from its edges'
    residuals E (:func:`incident_residuals`)."""
    return from_soa(_adjoint_to_slots(edges, _edge_maps(edges), E * _column_weights(edges, weights), n_max))


def robot_share(edges: RobotEdges, edge_cost):
    """The robot's share 1/2 sum(own edges) c_e + 1/4 sum(inter edges) c_e of per-edge costs c_e in
    the f = 2F convention (the shares of all robots add up to 1/2 sum_e c_e, docs/conventions.md §3.4)."""
    return 0.5 * jnp.sum(jnp.where(edges.is_inter, 0.5, 1.0) * edge_cost)


def apply_gamma(edges: RobotEdges, xi, V: Poses) -> Poses:
    """Gamma^alpha V for a local tangent/ambient direction V (n_max slots), edge by edge: the
    residual map of the robot's own edge ends (remote ends held fixed: zero), weighted, and its
    adjoint (an independent form of :class:`GammaOperator`, for tests)."""
    n_max = V.R.shape[0]
    Vs = to_soa(stack(V))
    T = _edge_maps(edges)
    E = _residuals(T, jnp.where(edges.local_i, Vs[..., edges.slot_i], 0.0),
                   jnp.where(edges.local_j, Vs[..., edges.slot_j], 0.0))
    # Inter-robot edges enter the majorizer with factor 2 on the local end (Eq. (5)).
    EW = E * _column_weights(edges, jnp.where(edges.is_inter, 2.0, 1.0))
    return unstack(from_soa(_adjoint_to_slots(edges, T, EW, n_max)) + xi * stack(V))


def gamma_diagonal_blocks(edges: RobotEdges, xi, n_max: int, weights=None):
    """Diagonal blocks (n_max, d+1, d+1) of Gamma^alpha in the layout Y_i = [t_i | R_i]; with per-edge
    ``weights`` (e_max,), those of the weighted majorizer (kappa and tau of edge e times w_e)."""
    d = edges.t.shape[-1]
    dt = edges.t.dtype
    w = jnp.where(edges.is_inter, 2.0, 1.0)
    if weights is not None:
        w = w * weights
    tail, head, _ = edge_hessian_blocks(edges.R, edges.t, w * edges.kappa, w * edges.tau, unit_rotations=True,
                                        xp=jnp)
    B = jax.ops.segment_sum(jnp.where(edges.local_i[:, None, None], tail, 0.0), edges.slot_i, n_max)
    B = B + jax.ops.segment_sum(jnp.where(edges.local_j[:, None, None], head, 0.0), edges.slot_j, n_max)
    return B + xi * jnp.eye(d + 1, dtype=dt)


def inner(a: Poses, b: Poses):
    """Frobenius inner product of two Poses-shaped pairs."""
    return jnp.sum(a.R * b.R) + jnp.sum(a.t * b.t)


def majorizer_decrease(edges: RobotEdges, xi, D: Poses, grad: Poses):
    """G^alpha(X^alpha + D | X) - Gbar^alpha(X) = 1/2 <Gamma D, D> + <grad_alpha F(X), D>."""
    return 0.5 * inner(apply_gamma(edges, xi, D), D) + inner(grad, D)


# ----------------------------------------------------------------------------------------------
# Gamma^alpha as a block-sparse operator (built once on the host, applied every inner iteration).
#
# In the stacked layout Y_i = [t_i | R_i] (d x (d+1)) an edge e = (i, j) contributes
# F_e = 1/2 tr([Y_i Y_j] H_e [Y_i Y_j]^T) with, for a = [1; tt_e], e0 = [1; 0], S = diag(0, I_d):
#   H_ii = tau a a^T + kappa S,  H_jj = tau e0 e0^T + kappa S,  H_ij = -tau a e0^T - kappa [0 0; 0 Rt_e].
# Gamma^alpha keeps own edges whole and folds each inter-robot edge into twice its local diagonal
# block (Eq. (5)), so its off-diagonal part only has own edges. Pose graphs are mostly chains, so
# couplings between consecutive slots (odometry) are stored as a band (shifted dense products, no
# gather/scatter) and only the remaining own edges (loop closures) as a sorted coordinate list.
# ----------------------------------------------------------------------------------------------


class GammaOperator(eqx.Module):
    """Per-robot block-sparse Gamma^alpha, arrays with a leading robot axis when batched."""

    diag: jax.Array  # (n_max, d+1, d+1) diagonal blocks, xi I included
    band: jax.Array  # (n_max, d+1, d+1): band[s] = block coupling slot s to slot s+1 (H_{s,s+1})
    src: jax.Array  # (k,) int: loop-closure couplings out[dst] += Y[src] @ blocks
    dst: jax.Array  # (k,) int, sorted
    blocks: jax.Array  # (k, d+1, d+1)

    def __call__(self, Y):
        """Gamma Y for Y (n_max, d, d+1) in the stacked layout (Gamma acts from the right)."""
        out = bmm(Y, self.diag)
        up = bmm(Y[1:], mT(self.band[:-1]))  # from slot s+1 into slot s
        down = bmm(Y[:-1], self.band[:-1])  # from slot s into slot s+1
        out = out.at[:-1].add(up).at[1:].add(down)
        coo = jax.ops.segment_sum(bmm(Y[self.src], self.blocks), self.dst, Y.shape[0], indices_are_sorted=True)
        return out + coo


def _loop_closure_edges(edges: RobotEdges):
    """(robot of each incident-edge slot, mask of own edges that are not consecutive-slot chain
    edges): the couplings :func:`build_gamma_operator` stores as a coordinate list (host)."""
    A, e_max = np.asarray(edges.kappa).shape
    si = np.asarray(edges.slot_i).reshape(-1).astype(np.int64)
    sj = np.asarray(edges.slot_j).reshape(-1).astype(np.int64)
    own = np.asarray(edges.local_i).reshape(-1) & np.asarray(edges.local_j).reshape(-1)
    chain = (sj == si + 1) | (si == sj + 1)
    return np.repeat(np.arange(A), e_max), own & ~chain


def _coupling_list(robot, si, sj, rest, A: int, e_max: int, n_max: int, min_couplings: int):
    """The loop-closure couplings of Gamma as per-robot lists sorted by destination slot (host):
    (src, dst, edge, transposed, valid), each (A, k). Each edge in ``rest`` gives two directed
    couplings: out[i] += Y[j] @ H_ij^T (transposed) and out[j] += Y[i] @ H_ij; ``edge`` is its
    incident-edge slot; padding entries (``valid`` False) add a zero block to the last slot."""
    r_rob = np.concatenate([robot[rest], robot[rest]])
    r_src = np.concatenate([sj[rest], si[rest]])
    r_dst = np.concatenate([si[rest], sj[rest]])
    r_edge = np.concatenate([np.flatnonzero(rest), np.flatnonzero(rest)]) % e_max
    r_T = np.repeat([True, False], int(rest.sum()))
    counts = np.bincount(r_rob, minlength=A)
    k = max(int(counts.max(initial=0)), 1, min_couplings)
    src = np.zeros((A, k), np.int64)
    dst = np.full((A, k), n_max - 1, np.int64)
    edge = np.zeros((A, k), np.int64)
    transposed = np.zeros((A, k), bool)
    valid = np.zeros((A, k), bool)
    order = np.lexsort((r_dst, r_rob))
    r_rob, r_src, r_dst, r_edge, r_T = r_rob[order], r_src[order], r_dst[order], r_edge[order], r_T[order]
    pos = np.arange(len(r_rob)) - np.repeat(np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
    src[r_rob, pos], dst[r_rob, pos], edge[r_rob, pos], transposed[r_rob, pos] = r_src, r_dst, r_edge, r_T
    valid[r_rob, pos] = True
    return src, dst, edge, transposed, valid


def gamma_couplings(edges: RobotEdges) -> int:
    """The loop-closure coupling count k of ``build_gamma_operator(edges, ...)`` without padding
    (host, cheap: no Gamma is built). Pass the largest k of a batch as ``min_couplings``."""
    robot, rest = _loop_closure_edges(edges)
    A = np.asarray(edges.kappa).shape[0]
    return max(int(2 * np.bincount(robot[rest], minlength=A).max(initial=0)), 1)


def build_gamma_operator(edges: RobotEdges, xi: float, n_max: int, *, min_couplings: int = 0,
                         host: bool = False, inter_weight: float = 2.0) -> GammaOperator:
    """Assemble the batched block-sparse Gamma^alpha of every robot from its incident edges (on the
    host; ``host=True`` keeps its arrays there, as NumPy, for a caller that converts them anyway).

    ``inter_weight`` multiplies an inter-robot edge's block at its local end: 2 is the majorizer of
    Eq. (5); 1 is the exact Hessian of F in the robot's poses with its neighbours held fixed (the
    block problem of block-coordinate descent, :mod:`~mmpgo_jax._baselines.rbcd`)."""
    A, e_max = np.asarray(edges.kappa).shape
    d = np.asarray(edges.t).shape[-1]
    kappa = np.asarray(edges.kappa, np.float64).reshape(-1)
    tau = np.asarray(edges.tau, np.float64).reshape(-1)
    robot, si, sj, li, lj = _edge_slots(edges)
    own = li & lj
    inter = li ^ lj
    w = np.where(inter, inter_weight, 1.0)[:, None, None]
    diag = np.zeros((A, n_max, d + 1, d + 1))
    # data float arithmetic cannot represent: no NumPy warning here, the run stops on f = inf with
    # a one-line error of its own (NonFiniteError)
    with np.errstate(over="ignore", invalid="ignore"):
        Hii, Hjj, Hij = edge_hessian_blocks(np.asarray(edges.R).reshape(-1, d, d), np.asarray(edges.t).reshape(-1, d),
                                            kappa, tau, unit_rotations=True)
        np.add.at(diag, (robot[li], si[li]), (w * Hii)[li])
        np.add.at(diag, (robot[lj], sj[lj]), (w * Hjj)[lj])
        diag += xi * np.eye(d + 1)
    # Slots without edges (padding) would have a zero block when xi = 0: give them I instead.
    # Their gradient is zero, so they never move and no result changes.
    empty = ~np.any(diag != 0.0, axis=(-1, -2))
    diag[empty] = np.eye(d + 1)
    band = np.zeros((A, n_max, d + 1, d + 1))
    fwd = own & (sj == si + 1)  # edge from slot s to s+1: H_{s,s+1} = H_ij
    bwd = own & (si == sj + 1)  # edge from slot s+1 to s: H_{s,s+1} = H_ji = H_ij^T
    np.add.at(band, (robot[fwd], si[fwd]), Hij[fwd])
    np.add.at(band, (robot[bwd], sj[bwd]), np.swapaxes(Hij[bwd], -1, -2))
    src, dst, edge, transposed, valid = _coupling_list(robot, si, sj, own & ~fwd & ~bwd, A, e_max, n_max,
                                                       min_couplings)
    flat = np.arange(A)[:, None] * e_max + edge
    blk = np.where(transposed[..., None, None], np.swapaxes(Hij[flat], -1, -2), Hij[flat])
    blk[~valid] = 0.0
    fdt = np.asarray(edges.kappa).dtype
    put = np.asarray if host else to_device
    return GammaOperator(diag=put(diag, fdt), band=put(band, fdt), src=put(src, np.int32), dst=put(dst, np.int32),
                         blocks=put(blk, fdt))


def _edge_slots(edges: RobotEdges):
    """(robot, slot_i, slot_j, local_i, local_j) of every incident edge, flattened (host)."""
    A, e_max = np.asarray(edges.kappa).shape
    robot = np.repeat(np.arange(A), e_max)
    si = np.asarray(edges.slot_i).reshape(-1).astype(np.int64)
    sj = np.asarray(edges.slot_j).reshape(-1).astype(np.int64)
    return robot, si, sj, np.asarray(edges.local_i).reshape(-1), np.asarray(edges.local_j).reshape(-1)


# ----------------------------------------------------------------------------------------------
# Gamma^alpha of weighted edges, assembled inside the compiled step (robust losses). Gamma's blocks
# are linear in the per-edge weights with a sparsity fixed by the partition: the layout (which band
# slot or loop-closure coupling an edge feeds) is computed once on the host; the blocks themselves
# are a few flops per edge and are recomputed from the edges at each assembly.
# ----------------------------------------------------------------------------------------------


class GammaLayout(eqx.Module):
    """Where each robot's incident edges go in its :class:`GammaOperator` (batched over robots),
    for :func:`assemble_gamma`; the loop-closure list is :func:`build_gamma_operator`'s."""

    band_slot: jax.Array  # (e_max,): band entry a consecutive-slot own edge adds to (n_max: none)
    band_transposed: jax.Array  # (e_max,) bool: the edge runs from slot s+1 to s (adds H_ij^T)
    src: jax.Array  # (k,) loop-closure couplings, as GammaOperator.src / dst
    dst: jax.Array
    coupling_edge: jax.Array  # (k,): the incident edge of each coupling
    coupling_transposed: jax.Array  # (k,) bool: the coupling's block is H_ij^T
    coupling_valid: jax.Array  # (k,) bool: False on padding (a zero block)


def gamma_layout(edges: RobotEdges, n_max: int, *, min_couplings: int = 0) -> GammaLayout:
    """The :class:`GammaLayout` of a partition's edges (host, once; ``min_couplings`` as for
    :func:`build_gamma_operator`, whose couplings it lists in the same order)."""
    A, e_max = np.asarray(edges.kappa).shape
    robot, si, sj, li, lj = _edge_slots(edges)
    own = li & lj
    fwd = own & (sj == si + 1)
    bwd = own & (si == sj + 1)
    band_slot = np.where(fwd, si, np.where(bwd, sj, n_max)).reshape(A, e_max)
    src, dst, edge, transposed, valid = _coupling_list(robot, si, sj, own & ~fwd & ~bwd, A, e_max, n_max,
                                                       min_couplings)
    i32 = np.int32
    return GammaLayout(band_slot=to_device(band_slot, i32), band_transposed=to_device(bwd.reshape(A, e_max)),
                       src=to_device(src, i32), dst=to_device(dst, i32), coupling_edge=to_device(edge, i32),
                       coupling_transposed=to_device(transposed), coupling_valid=to_device(valid))


def _off_diagonal_blocks(edges: RobotEdges):
    """H_ij = -tau a e0^T - kappa diag(0, Rt) per edge (e_max, d+1, d+1) (:func:`edge_hessian_blocks`)."""
    return edge_hessian_blocks(edges.R, edges.t, edges.kappa, edges.tau, unit_rotations=True, xp=jnp)[2]


def assemble_gamma(edges: RobotEdges, layout: GammaLayout, weights, xi, n_max: int):
    """Gamma^alpha of one robot (stacked layout) for per-edge ``weights`` (e_max,): kappa and tau of
    edge e times w_e (JAX; :func:`build_gamma_operator` of the weighted edges, up to rounding).
    Slots whose diagonal block vanishes (padding; with xi = 0, a pose whose every edge has weight 0)
    get I, as on the host: their gradient is zero, and the extra proximal term keeps G a majorizer.
    Returns (Gamma, those slots (n_max,) bool)."""
    k = edges.t.shape[-1] + 1
    diag = gamma_diagonal_blocks(edges, xi, n_max, weights)
    empty = ~jnp.any(diag != 0.0, axis=(-1, -2))
    diag = jnp.where(empty[:, None, None], jnp.eye(k, dtype=diag.dtype), diag)
    H = weights[:, None, None] * _off_diagonal_blocks(edges)
    band = jax.ops.segment_sum(jnp.where(layout.band_transposed[:, None, None], mT(H), H), layout.band_slot, n_max)
    C = H[layout.coupling_edge]
    blocks = jnp.where(layout.coupling_valid[:, None, None], jnp.where(layout.coupling_transposed[:, None, None],
                                                                       mT(C), C), 0.0)
    return GammaOperator(diag=diag, band=band, src=layout.src, dst=layout.dst, blocks=blocks), empty


def stack(P: Poses):
    """Poses (..., n, d, d) + (..., n, d) -> stacked Y (..., n, d, d+1) = [t | R]; numpy arrays stay
    on the host (op by op on the device every new shape would compile a concatenation)."""
    xp = np if isinstance(P.t, np.ndarray) and isinstance(P.R, np.ndarray) else jnp
    return xp.concatenate([P.t[..., None], P.R], axis=-1)


def unstack(Y) -> Poses:
    return Poses(Y[..., 1:], Y[..., 0])


# ----------------------------------------------------------------------------------------------
# Structure-of-arrays forms used inside the solver: poses as (d, d+1, n_max) and blocks as
# (d+1, d+1, n_max), so that every small-matrix product is an elementwise expression along the
# long pose axis (vectorizes on CPU; measured 2x faster than the (n, d, d+1) layout).
# ----------------------------------------------------------------------------------------------


def to_soa(Y):
    """(..., n, p, q) -> (..., p, q, n)."""
    return jnp.moveaxis(Y, -3, -1)


def from_soa(Y):
    """(..., p, q, n) -> (..., n, p, q)."""
    return jnp.moveaxis(Y, -1, -3)


def soa_bmm(a, b):
    """Product of small matrices stored along the last axis: (p, q, n) x (q, r, n) -> (p, r, n)."""
    # static slices (not a[:, k, None] * b[None, k]): the same products and sums, in the same order,
    # without NumPy-style indexing, whose tracing is most of this function's share of a compile
    def term(k):
        return jax.lax.slice_in_dim(a, k, k + 1, axis=1) * jax.lax.slice_in_dim(b, k, k + 1, axis=0)

    out = term(0)
    for k in range(1, a.shape[1]):
        out = out + term(k)
    return out


def soa_T(a):
    return jnp.swapaxes(a, 0, 1)


def sym0(M):
    """Symmetric part of square blocks stored entries first (d, d, ...)."""
    return 0.5 * (M + soa_T(M))


def tangent_soa(Y, V):
    """Orthogonal projection onto T_Y (structure of arrays): [a | B] -> [a | B - R sym(R^T B)].
    Written as one concatenation (not an in-place update of the rotation part) so that XLA fuses it
    into one loop."""
    R, B = Y[:, 1:], V[:, 1:]
    return jnp.concatenate([V[:, :1], B - soa_bmm(R, sym0(soa_bmm(soa_T(R), B)))], axis=1)


class GammaSoA(eqx.Module):
    """:class:`GammaOperator` in the structure-of-arrays layout (one robot, or batched in front)."""

    diag: jax.Array  # (d+1, d+1, n_max)
    band: jax.Array  # (d+1, d+1, n_max)
    band_T: jax.Array  # (d+1, d+1, n_max)
    src: jax.Array  # (k,)
    dst: jax.Array  # (k,)
    blocks: jax.Array  # (d+1, d+1, k)

    def __call__(self, Y):
        """Gamma Y for Y (d, d+1, n_max)."""
        # the band's two shifted products as padded terms (not in-place updates of slices): XLA then
        # computes the diagonal and the band in one fused loop
        pad = [(0, 0)] * (Y.ndim - 1)
        out = (soa_bmm(Y, self.diag)
               + jnp.pad(soa_bmm(Y[..., 1:], self.band_T[..., :-1]), [*pad, (0, 1)])
               + jnp.pad(soa_bmm(Y[..., :-1], self.band[..., :-1]), [*pad, (1, 0)]))
        contrib = soa_bmm(Y[..., self.src], self.blocks)
        return out.at[..., self.dst].add(contrib, indices_are_sorted=True)


def gamma_to_soa(gamma: GammaOperator) -> GammaSoA:
    """Convert (batched or not) block arrays; works under vmap as well."""
    return GammaSoA(
        diag=to_soa(gamma.diag),
        band=to_soa(gamma.band),
        band_T=to_soa(mT(gamma.band)),
        src=gamma.src,
        dst=gamma.dst,
        blocks=to_soa(gamma.blocks),
    )


def host_soa(gamma: GammaOperator) -> GammaSoA:
    """:func:`gamma_to_soa` of a batched operator (NumPy or device arrays), computed with numpy on
    the host (set-up runs once: op-by-op JAX would compile every transposition)."""
    def soa(x):
        return to_device(np.moveaxis(np.asarray(x), -3, -1))

    band = np.asarray(gamma.band)
    return GammaSoA(diag=soa(gamma.diag), band=soa(band), band_T=soa(np.swapaxes(band, -1, -2)),
                    src=to_device(gamma.src), dst=to_device(gamma.dst), blocks=soa(gamma.blocks))


def soa_to_gamma(gamma: GammaSoA) -> GammaOperator:
    """The stacked-layout :class:`GammaOperator` of a :class:`GammaSoA` (exact: a transposition)."""
    return GammaOperator(
        diag=from_soa(gamma.diag),
        band=from_soa(gamma.band),
        src=gamma.src,
        dst=gamma.dst,
        blocks=from_soa(gamma.blocks),
    )
