"""The preconditioner of the robot subproblem's Newton system, built from the Hessian.

The trust-region step solves H v = -grad on the tangent space at Y, with the Riemannian Hessian

    H V = P_Y(Gamma V - [0 | V_R W]),   W = sym(R^T egrad_R)  (per pose; the Weingarten term),

and Gamma^alpha constant. Preconditioning with Gamma alone (block-Jacobi of Gamma, or even Gamma's
exact inverse) leaves CG 30 iterations and more wherever the Weingarten term is large against
Gamma's rotation blocks (parking-garage at 10 robots: 29-37 per subproblem, 31 with the exact
Gamma^-1; measured on dense matrices). This preconditioner is

    M^-1 = E diag(H_ss)^-1 E^T  +  P_Y B (B^T Gamma B)^+ B^T,

1. **the Hessian's own diagonal blocks** H_ss (``preconditioner="block-jacobi"`` is this level
   alone), in tangent coordinates at each pose: a translation t (d) and a rotation R Omega(x)
   (x in R^{d(d-1)/2}). With Gamma's block at the pose [[gamma00, g^T], [g, G]] (stacked layout
   [t | R]) and M = G - W, the block is

       H_ss = [[gamma00 I, B], [B^T, C]],   B = R Omega(.) g,   C_pq = tr(Omega_p^T Omega_q M),

   which needs no factorization: its Schur complement S = C - B^T B / gamma00 is a scalar in 2D
   and 3 x 3 in 3D, and equals S_Gamma (constant) minus a term linear in W. It is rebuilt at every
   trust-region step (a few flops per pose); where it is not positive definite (a pose where the
   Weingarten term makes the block indefinite) Gamma's block alone is used, so M stays SPD.
2. **a coarse correction on aggregates** (``preconditioner="two-level"``, the default) of ``b``
   consecutive slots whose basis B is the rigid motions of each aggregate at the start X^0: the
   translation shifts and the rotations about the aggregate's centre, V_s = Omega [t0_s - c | R0_s]
   -- d(d+1)/2 unknowns per aggregate, the modes that cost (almost) nothing inside the aggregate
   (Gamma's near-null space: aggregation with near-null-space vectors, Vanek, Mandel & Brezina
   1996). B^T Gamma B is constant, factored once on the host (a pseudo-inverse: with xi = 0 Gamma
   can be singular); the correction is projected onto the tangent space at Y.

Measured (benchmarks/profile_step.md): CG iterations per subproblem solve, worst of 10 robots,
7-11 on the benchmark files with this preconditioner against 9-31 with the former Gamma-only
two-level one (block-Jacobi of Gamma plus a coarse space of the rows of X^0). Everything is
fixed-shape and vmap-able; padding slots have no edges (their block is the identity) and never
move.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._core.blas import one_blas_thread
from .._core.lie import so
from .._core.pose_graph import edge_hessian_blocks
from .._core.precision import to_device
from .majorization import soa_bmm, soa_T, tangent_soa

MIN_AGGREGATE = 4  # slots per aggregate at least
COARSE_TARGET = 128  # coarse unknowns per robot the aggregate size aims at (the dense coarse product)


def aggregate_size(robot_poses: int, d: int) -> int:
    """Slots per aggregate when the largest robot has ``robot_poses`` poses in dimension ``d``:
    the smallest size (at least 4) that keeps the dense coarse level at about ``COARSE_TARGET``
    unknowns (d(d+1)/2 per aggregate). It depends on the real poses, not on the padded slot count,
    so padding a partition does not change the preconditioner."""
    modes = d * (d + 1) // 2
    return max(MIN_AGGREGATE, -(-robot_poses * modes // COARSE_TARGET))


# --- rotations in tangent coordinates: Omega(x) = sum_q x_q Omega_q, Omega_q a basis of so(d) -----
# (the group's hat map and its relatives, :mod:`~mmpgo_jax._core.lie`, entries first)


def _matvec(M, x):
    """M (p, q, ...) times x (q, ...) -> (p, ...), unrolled (small p, q)."""
    out = M[:, 0] * x[0]
    for j in range(1, M.shape[1]):
        out = out + M[:, j] * x[j]
    return out


def _weingarten_term(W):
    """C(W) (p, p, n) for the Weingarten matrices W (d, d, n) (the group's ``trace_form``, tr(W)
    summed in index order): the Hessian's tangent block is Gamma's minus C(W), and so is the Schur
    complement, S = S_Gamma - C(W)."""
    d = W.shape[0]
    tr = W[0, 0]
    for k in range(1, d):
        tr = tr + W[k, k]
    return so(d).trace_form(W, tr, first=True)


def _aggregate_sum(x, b: int):
    """Sums over consecutive groups of ``b`` slots of x (..., n) -> (..., m), as a chain of adds: XLA
    on CPU fuses it with its producer into one loop (a reduce over the short minor axis ran 30x
    slower, measured)."""
    n = x.shape[-1]
    m = -(-n // b)
    x = jnp.pad(x, [(0, 0)] * (x.ndim - 1) + [(0, m * b - n)]).reshape(*x.shape[:-1], m, b)
    out = x[..., 0]
    for j in range(1, b):
        out = out + x[..., j]
    return out


class NewtonPreconditioner(eqx.Module):
    """The constant data of the preconditioner (one robot, or batched over robots in front), in the
    structure-of-arrays layout; :meth:`at` gives the operator at a point. Without a coarse level
    (``coarse_inverse`` None) it is the Hessian's block-Jacobi alone. ``aggregate`` (static) is the
    number of slots per aggregate; a coarse index is mode * m + aggregate."""

    gamma00: jax.Array  # (n,): Gamma_ss[0, 0]
    coupling: jax.Array  # (d, n): g = Gamma_ss[1:, 0]
    schur: jax.Array  # (p, p, n): S_Gamma, the Schur complement of Gamma's tangent block (W = 0)
    frame: jax.Array | None = None  # (d, k, n): [t0_s - c | R0_s] of the start X^0 (zero on padding)
    real: jax.Array | None = None  # (n,): 1 on real slots, 0 on padding (the translation shifts' support)
    coarse_inverse: jax.Array | None = None  # (m c, m c): (B^T Gamma B)^+, c = d(d+1)/2 modes per aggregate
    aggregate: int = eqx.field(static=True, default=0)

    @property
    def has_coarse(self) -> bool:
        return self.coarse_inverse is not None

    def without_coarse(self) -> NewtonPreconditioner:
        """The block-Jacobi level alone (``preconditioner="block-jacobi"``)."""
        return NewtonPreconditioner(self.gamma00, self.coupling, self.schur)

    def at(self, Y, weingarten):
        """M^-1 at Y (d, k, n) with the Weingarten matrices ``weingarten`` (d, d, n): a function of
        tangent vectors at Y to tangent vectors at Y."""
        R = Y[:, 1:]
        group = so(Y.shape[0])
        S_inv, ok = group.inverse_spd(self.schur - _weingarten_term(weingarten), first=True)
        S_gamma_inv, _ = group.inverse_spd(self.schur, first=True)
        S_inv = jnp.where(ok, S_inv, S_gamma_inv)

        def block_jacobi(V):
            """E diag(H_ss)^-1 E^T V, by the Schur complement in tangent coordinates."""
            Vt, VR = V[:, 0], V[:, 1:]
            rho_R = group.dual(soa_bmm(soa_T(R), VR), first=True)
            rho_R = rho_R - group.hat_apply_adjoint(self.coupling, _matvec(soa_T(R), Vt), first=True) / self.gamma00
            x_R = _matvec(S_inv, rho_R)
            x_t = (Vt - _matvec(R, group.hat_apply(x_R, self.coupling, first=True))) / self.gamma00
            return jnp.concatenate([x_t[:, None], soa_bmm(R, group.hat(x_R, first=True))], axis=1)

        if not self.has_coarse:
            return block_jacobi
        d, b, n = Y.shape[0], self.aggregate, Y.shape[-1]
        m = -(-n // b)

        def two_level(V):
            # restrict to the rigid motions of each aggregate (translations, then rotation moments)
            per_slot = jnp.concatenate([self.real * V[:, 0], group.dual(soa_bmm(V, soa_T(self.frame)), first=True)])
            coef = self.coarse_inverse @ _aggregate_sum(per_slot, b).reshape(-1)
            # prolong: every slot takes its aggregate's coefficients (a broadcast, no gather)
            coef = jnp.broadcast_to(coef.reshape(-1, m, 1), (coef.size // m, m, b)).reshape(-1, m * b)[:, :n]
            coarse = soa_bmm(group.hat(coef[d:], first=True), self.frame)
            coarse = jnp.concatenate([coarse[:, :1] + self.real * coef[:d, None], coarse[:, 1:]], axis=1)
            return block_jacobi(V) + tangent_soa(Y, coarse)

        return two_level


def _tangent_basis(frame, real, d: int):
    """The coarse basis at every slot: (..., n, c, d, k) with c = d(d+1)/2: the translation shifts
    [e_r | 0] (on real slots), then Omega_q [t0 - c | R0] (numpy, host)."""
    *lead, _, k, n = frame.shape
    c = d * (d + 1) // 2
    E = np.zeros((*lead, n, c, d, k))
    for r in range(d):
        E[..., :, r, r, 0] = real
    X = np.moveaxis(frame, -1, -3)  # (..., n, d, k)
    for q, Om in enumerate(so(d).generators()):
        E[..., :, d + q, :, :] = np.einsum("ij,...jk->...ik", Om, X)
    return E


def _coarse_matrices(diag, band, src, dst, blocks, E, b: int):
    """B^T Gamma B for every robot (host, numpy): Gamma's nonzero blocks K (out[dst] += Y[src] K)
    contribute <E_dst,i, E_src,j K> to the coarse entry (i, aggregate(dst)), (j, aggregate(src))."""
    A, n = diag.shape[:2]
    c = E.shape[2]
    m = -(-n // b)
    s = np.arange(n)
    if src.ndim == 1:
        src, dst = np.broadcast_to(src, (A, src.size)), np.broadcast_to(dst, (A, dst.size))
    # (destination slots, source slots, blocks) of every nonzero block: diagonal, band (both ways), loops
    rows = np.concatenate([np.broadcast_to(s, (A, n)), np.broadcast_to(s[:-1], (A, n - 1)),
                           np.broadcast_to(s[1:], (A, n - 1)), dst], axis=1)
    cols = np.concatenate([np.broadcast_to(s, (A, n)), np.broadcast_to(s[1:], (A, n - 1)),
                           np.broadcast_to(s[:-1], (A, n - 1)), src], axis=1)
    G = np.concatenate([diag, np.swapaxes(band[:, :-1], -1, -2), band[:, :-1], blocks], axis=1)
    a = np.arange(A)[:, None]
    contrib = np.einsum("aeirc,aejrl,aelc->aeij", E[a, rows], E[a, cols], G)  # (A, blocks, c, c)
    coarse = np.zeros((A, c * m, c * m))
    ci = np.arange(c)
    ri = (ci[:, None] * m + (rows // b)[..., None, None])
    cj = (ci[None, :] * m + (cols // b)[..., None, None])
    np.add.at(coarse, (a[..., None, None], ri, cj), contrib)
    return coarse


def _fine_constants(diag, xp):
    """(gamma00, g, S_Gamma) of Gamma's diagonal blocks (..., n, k, k) in the stacked layout, with the
    array module ``xp`` (numpy on the host, jax.numpy in the compiled step): gamma00 = Gamma_ss[0, 0],
    g = Gamma_ss[1:, 0] and the Schur complement of the tangent block (p, p) for W = 0."""
    group = so(diag.shape[-1] - 1)
    gamma00 = diag[..., 0, 0]
    g = diag[..., 1:, 0]  # (..., n, d)
    G = diag[..., 1:, 1:]
    trG = xp.trace(G, axis1=-2, axis2=-1)
    gg = xp.einsum("...i,...i->...", g, g)
    # C(G) - C(g g^T) / gamma00, C the group's trace form
    schur = group.trace_form(G, trG) - group.trace_form(g[..., :, None] * g[..., None, :], gg) \
        / gamma00[..., None, None]
    return gamma00, g, schur


def _coarse_inverse(coarse):
    """(B^T Gamma B)^+ for every robot, scaled symmetrically to a unit diagonal first (empty
    aggregates: zero rows stay zero). By Cholesky when every matrix is positive definite (xi > 0,
    the usual case: several times faster than the eigendecomposition), else the pseudo-inverse
    (xi = 0 leaves the gauge in Gamma's null space)."""
    dg = np.einsum("aii->ai", coarse)
    empty = ~(dg > 0)
    scale = np.where(empty, 0.0, 1.0 / np.sqrt(np.where(empty, 1.0, dg)))
    scaled = coarse * scale[:, :, None] * scale[:, None, :]
    eye = np.eye(coarse.shape[-1])
    try:
        L = np.linalg.cholesky(scaled + empty[:, :, None] * eye)  # empty rows: a unit diagonal, removed below
        L_inv = np.linalg.solve(L, np.broadcast_to(eye, L.shape))
        inverse = np.swapaxes(L_inv, -1, -2) @ L_inv
        # a numerically singular matrix factors but its inverse is worthless: take the pseudo-inverse
        ok = np.isfinite(inverse).all() and np.all(np.einsum("aii->ai", L) > 1e-7)
    except np.linalg.LinAlgError:
        ok = False
    if not ok:
        inverse = np.linalg.pinv(scaled, rcond=PINV_RCOND, hermitian=True)
    inverse = np.where(empty[:, :, None] | empty[:, None, :], 0.0, inverse)
    return inverse * scale[:, :, None] * scale[:, None, :]


def build_newton_preconditioner(diag, band=None, src=None, dst=None, blocks=None, X0=None, pose_mask=None,
                                dtype=np.float64, aggregate: int | None = None) -> NewtonPreconditioner:
    """The preconditioner of every robot (host, float64, once).

    Gamma's blocks in the stacked layout: ``diag`` (A, n, k, k) for the block-Jacobi level; for the
    coarse level also ``band`` (A, n, k, k), the loop closures ``src``, ``dst``, ``blocks``, the
    start poses ``X0`` (A, n, d, k) stacked [t | R] and ``pose_mask`` (A, n). ``aggregate``: slots
    per aggregate (default :func:`aggregate_size` of the largest robot; give one size to batch
    problems of different robots)."""
    diag = np.asarray(diag, np.float64)
    A, n, k, _ = diag.shape
    d = k - 1
    with np.errstate(invalid="ignore", over="ignore"):  # non-finite weights: the run reports f = inf itself
        gamma00, g, schur = _fine_constants(diag, np)

    def soa(x):  # (A, n, ...) -> (A, ..., n)
        return to_device(np.moveaxis(x, 1, -1), dtype)

    fine = dict(gamma00=to_device(gamma00, dtype), coupling=soa(g), schur=soa(schur))
    if X0 is None:
        return NewtonPreconditioner(**fine)
    band, blocks = np.asarray(band, np.float64), np.asarray(blocks, np.float64)
    src, dst = np.asarray(src), np.asarray(dst)
    X0, mask = np.asarray(X0, np.float64), np.asarray(pose_mask, bool)
    b = aggregate or aggregate_size(int(mask.sum(axis=1).max(initial=0)), d)
    m = -(-n // b)
    # the start poses, translations relative to their aggregate's mean (real slots only)
    agg = np.arange(n) // b
    count = np.zeros((A, m))
    np.add.at(count, (slice(None), agg), mask)
    centre = np.zeros((A, m, d))
    np.add.at(centre, (slice(None), agg), X0[..., 0] * mask[..., None])
    centre /= np.maximum(count, 1)[..., None]
    frame = X0.copy()
    frame[..., 0] -= centre[:, agg]
    frame *= mask[..., None, None]
    frame_soa = np.moveaxis(frame, 1, -1)  # (A, d, k, n)
    real = mask.astype(np.float64)
    coarse = _coarse_matrices(diag, band, src, dst, blocks, _tangent_basis(frame_soa, real, d), b)
    # weights float arithmetic cannot represent: no coarse level (the run reports f = inf itself)
    coarse[~np.isfinite(coarse).all(axis=(1, 2))] = 0.0
    # one BLAS thread: OpenBLAS's threads and XLA's spin against each other on a small machine
    # (this inverse took 0.5-2 s on intel's 10 robots with the default threads, 0.03 s with one)
    with one_blas_thread():
        inverse = _coarse_inverse(coarse)
    return NewtonPreconditioner(**fine, frame=to_device(frame_soa, dtype), real=to_device(real, dtype),
                                coarse_inverse=to_device(inverse, dtype), aggregate=b)


PINV_RCOND = 1e-13  # relative cut-off of the coarse matrix's pseudo-inverse (host and compiled)


# --- the preconditioner of weighted edges, rebuilt inside the compiled step (robust losses) -------
# Its fine level is a few flops per slot of Gamma's diagonal blocks. Its coarse matrix B^T Gamma B is
# linear in the edge weights: each edge's contribution (on the rigid motions of the one or two
# aggregates it touches) is computed once on the host, and the matrix is their weighted sum.


class CoarseParts(eqx.Module):
    """Per-edge and per-slot contributions to B^T Gamma B (batched over robots in front)."""

    edge_blocks: jax.Array  # (e_max, 2c, 2c): the edge's Gamma blocks at unit weight, on [modes at agg(i); at agg(j)]
    edge_index: jax.Array  # (e_max, 2c): coarse indices of those rows / columns
    slot_blocks: jax.Array  # (n, c, c): B_s^T B_s (what a slot's identity block adds)
    slot_index: jax.Array  # (n, c)


def build_coarse_parts(edges, newton: NewtonPreconditioner, n_max: int) -> CoarseParts:
    """The :class:`CoarseParts` of a partition's incident edges on the coarse space of ``newton``
    (a host-built two-level preconditioner: its start-pose frames and aggregate size; host, once)."""
    from .majorization import _edge_slots

    frame, real = np.asarray(newton.frame, np.float64), np.asarray(newton.real, np.float64)
    A, d, _, n = frame.shape
    b, c = newton.aggregate, d * (d + 1) // 2
    m = -(-n // b)
    E = _tangent_basis(frame, real, d)  # (A, n, c, d, k)
    e_max = np.asarray(edges.kappa).shape[1]
    robot, si, sj, li, lj = _edge_slots(edges)
    Hii, Hjj, Hij = edge_hessian_blocks(np.asarray(edges.R).reshape(-1, d, d), np.asarray(edges.t).reshape(-1, d),
                                        np.asarray(edges.kappa).reshape(-1), np.asarray(edges.tau).reshape(-1),
                                        unit_rotations=True)
    factor = np.where(li ^ lj, 2.0, 1.0)[:, None, None]  # an inter-robot edge: twice its local block
    own = (li & lj)[:, None, None]
    Ei, Ej = E[robot, si], E[robot, sj]  # a remote end's rows are unused: its blocks are zero

    def block(E_dst, E_src, K):  # <E_dst,p, E_src,q K>: the coarse entry of out[dst] += Y[src] @ K
        return np.einsum("eirc,ejrl,elc->eij", E_dst, E_src, K)

    top = np.concatenate([block(Ei, Ei, factor * Hii * li[:, None, None]),
                          block(Ei, Ej, np.swapaxes(Hij, -1, -2) * own)], axis=2)
    bottom = np.concatenate([block(Ej, Ei, Hij * own), block(Ej, Ej, factor * Hjj * lj[:, None, None])], axis=2)
    modes = np.arange(c) * m
    index = np.concatenate([modes + (si // b)[:, None], modes + (sj // b)[:, None]], axis=1)
    slot_blocks = np.einsum("ansrc,antrc->anst", E, E)
    slot_index = np.broadcast_to(modes + (np.arange(n) // b)[:, None], (A, n, c))
    fdt = np.asarray(edges.kappa).dtype
    return CoarseParts(edge_blocks=to_device(np.concatenate([top, bottom], axis=1).reshape(A, e_max, 2 * c, 2 * c),
                                             fdt),
                       edge_index=to_device(index.reshape(A, e_max, 2 * c), np.int32),
                       slot_blocks=to_device(slot_blocks, fdt), slot_index=to_device(slot_index, np.int32))


def _scaled_pseudo_inverse(M):
    """The host's symmetric-scaled inverse of one coarse matrix (:func:`_coarse_inverse`), in JAX.

    Cholesky written with XLA operations only: LAPACK calls (eigh, potrf, trsm) inside the sharded
    program hang with several CPU devices in one process. A pivot at rounding level (xi = 0: the
    gauge; an aggregate whose every edge has weight 0) drops its row and column, as the host's
    pseudo-inverse does for a null direction."""
    n = M.shape[0]
    M = jnp.where(jnp.all(jnp.isfinite(M)), M, 0.0)
    dg = jnp.diagonal(M)
    scale = jnp.where(dg > 0, 1.0 / jnp.sqrt(jnp.where(dg > 0, dg, 1.0)), 0.0)
    S = M * scale[:, None] * scale[None, :]
    idx = jnp.arange(n)

    def column(k, carry):
        L, dropped = carry
        row = jnp.where(idx < k, L[k], 0.0)
        pivot = S[k, k] - row @ row
        ok = pivot > 1e-10  # S has a unit diagonal: relative to it
        lkk = jnp.sqrt(jnp.where(ok, pivot, 1.0))
        col = jnp.where(idx > k, (S[:, k] - L @ row) / lkk, 0.0).at[k].set(lkk)
        col = jnp.where(ok, col, (idx == k).astype(S.dtype))
        return L.at[:, k].set(col), dropped.at[k].set(~ok)

    L, dropped = jax.lax.fori_loop(0, n, column, (jnp.zeros_like(S), jnp.zeros(n, bool)))

    def row(k, Li):  # forward substitution: row k of L^-1
        r = (jnp.where(idx == k, 1.0, 0.0) - jnp.where(idx < k, L[k], 0.0) @ Li) / L[k, k]
        return Li.at[k].set(r)

    Li = jax.lax.fori_loop(0, n, row, jnp.zeros_like(S))
    inverse = Li.T @ Li
    drop = dropped | (dg <= 0)
    inverse = jnp.where(drop[:, None] | drop[None, :], 0.0, inverse)
    return inverse * scale[:, None] * scale[None, :]


def newton_from_gamma(diag, base: NewtonPreconditioner, parts: CoarseParts | None, weights,
                      slot_weight, coarse_inverse=None, refresh=None) -> NewtonPreconditioner:
    """The preconditioner of one robot whose Gamma has the diagonal blocks ``diag`` (n, k, k) (JAX):
    its fine level from ``diag``; with a coarse level (``base`` built by
    :func:`build_newton_preconditioner`, ``parts`` by :func:`build_coarse_parts`), B^T Gamma B from
    the edge ``weights`` (e_max,) and ``slot_weight`` (n,), the coefficient of each slot's identity
    block in Gamma (xi, or 1 where the block was empty), then its pseudo-inverse, or
    ``coarse_inverse`` as given (a coarse level kept from earlier weights); with both
    ``coarse_inverse`` and a traced flag ``refresh``, the new one where ``refresh`` holds (one copy of
    the fine level in the compiled program, whichever is taken)."""
    gamma00, g, schur = _fine_constants(diag, jnp)
    fine = dict(gamma00=gamma00, coupling=jnp.moveaxis(g, 0, -1), schur=jnp.moveaxis(schur, 0, -1))
    if not base.has_coarse:
        return NewtonPreconditioner(**fine)
    size = base.coarse_inverse.shape[-1]

    def scatter(values, index):  # sum values (..., r, r) into the coarse matrix at index (..., r)
        flat = index[..., :, None] * size + index[..., None, :]
        return jax.ops.segment_sum(values.reshape(-1), flat.reshape(-1), size * size).reshape(size, size)

    def computed():
        coarse = scatter(weights[:, None, None] * parts.edge_blocks, parts.edge_index) + \
            scatter(slot_weight[:, None, None] * parts.slot_blocks, parts.slot_index)
        return _scaled_pseudo_inverse(coarse)

    if coarse_inverse is None:
        coarse_inverse = computed()
    elif refresh is not None:
        kept = coarse_inverse
        coarse_inverse = jax.lax.cond(refresh, computed, lambda: kept)
    return NewtonPreconditioner(**fine, frame=base.frame, real=base.real, coarse_inverse=coarse_inverse,
                                aggregate=base.aggregate)
