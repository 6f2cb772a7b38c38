"""RBCD's lifted rank r > d: the lift of the start, the block solve's preconditioner on the Stiefel
manifold, and the rounding of the lifted solution back to SE(d) (:class:`~mmpgo_jax.RBCD`).

Lifted poses are Y_i = [t_i | R_i] with r rows: t_i in R^r, R_i in St(d, r) (orthonormal columns).
F is the same quadratic form (it acts on the right, rows are free), so the gradients and the block
solve's value, tangent projection and Weingarten term are shape-generic
(:mod:`~mmpgo_jax._mm.subproblem`); what depends on r lives here.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._core.lie import inverse_sym, project_svd
from .._mm.majorization import soa_bmm, soa_T
from .._mm.preconditioner import NewtonPreconditioner

__all__ = ["LIFT_SEED", "LiftedPreconditioner", "lift_matrix", "round_lifted"]

LIFT_SEED = 1  # the lift is one fixed matrix per (r, d), as dpgo's fixedStiefelVariable (std::srand(1))


def lift_matrix(r: int, d: int) -> np.ndarray:
    """The fixed r x d Stiefel matrix the start is lifted by, Y_i = P X_i (host, float64): the
    orthonormal factor of a Gaussian matrix drawn with :data:`LIFT_SEED` (dpgo lifts by a fixed
    random Stiefel element too). Every iterate stays in its column span when the start has rank d
    (F's gradient and the polar retraction keep the rows' span), so the run explores O(d) per block
    (no determinant constraint) within that span; the rounding reads the rank-d solution back."""
    Q, Rq = np.linalg.qr(np.random.default_rng(LIFT_SEED).standard_normal((r, d)))
    return Q * np.sign(np.diagonal(Rq))


def _identity_frames(Y):
    """[0 | I_d] at every slot, entries first (d, d+1, n): the frame of tangent coordinates."""
    d, n = Y.shape[1] - 1, Y.shape[-1]
    eye = jnp.broadcast_to(jnp.eye(d, dtype=Y.dtype)[..., None], (d, d, n))
    return jnp.concatenate([jnp.zeros((d, 1, n), Y.dtype), eye], axis=1)


class LiftedPreconditioner(eqx.Module):
    """The block-Jacobi preconditioner of the Hessian (:class:`NewtonPreconditioner` without a coarse
    level) on lifted poses: the inverse of each pose's diagonal Hessian block, exact for r rows.

    A tangent vector at Y_i splits into rows in R_i's span, [R_i a | R_i Omega] (Omega skew), and rows
    orthogonal to it, [b | K]. The block H_ss = P(. Gamma_ss - [0 | . W]) does not couple the two:
    the first part is the SO(d) block in R_i's coordinates (the d x d preconditioner at the identity,
    applied to R_i^T V), and every orthogonal row solves [b | K] D = [u | U] with
    D = Gamma_ss - [0 0; 0 W] (Gamma_ss alone where D is not positive definite, as the SO(d) level
    falls back to Gamma's block)."""

    base: NewtonPreconditioner
    diag: jax.Array  # (d+1, d+1, n): Gamma's diagonal blocks, structure of arrays

    def at(self, Y, weingarten):
        R = Y[:, 1:]
        inner = self.base.without_coarse().at(_identity_frames(Y), weingarten)
        gamma00, g = self.diag[0, 0], self.diag[1:, 0]
        gg = g[:, None] * g[None] / gamma00
        S_inv, ok = inverse_sym(self.diag[1:, 1:] - weingarten - gg)
        S_gamma_inv, _ = inverse_sym(self.diag[1:, 1:] - gg)
        S_inv = jnp.where(ok, S_inv, S_gamma_inv)

        def apply(V):
            Vc = soa_bmm(soa_T(R), V)  # R^T V: the part in R's span, in R's coordinates
            P = V - soa_bmm(R, Vc)  # the rows orthogonal to R
            u, U = P[:, 0], P[:, 1:]
            K = soa_bmm(U - u[:, None] * g[None] / gamma00, S_inv)  # K S = U - u g^T / gamma00
            b = (u - jnp.sum(K * g[None], axis=1)) / gamma00
            return soa_bmm(R, inner(Vc)) + jnp.concatenate([b[:, None], K], axis=1)

        return apply


def round_lifted(X, pose_mask, lift, free=None) -> np.ndarray:
    """Lifted poses X (A, n_max, r, d+1) rounded to SE(d) (host, numpy), as SE-Sync and dpgo do: the
    real poses side by side, Y (r x N(d+1)), are replaced by Sigma_d V_d^T of Y's SVD (Y projected
    onto its top d left singular directions), reflected (last row negated) when fewer than half the
    rotation blocks have det > 0, every rotation block projected to SO(d); translations follow.
    With fixed poses (``free`` (A, n_max) bool) the result is moved rigidly so that the first fixed
    pose is back at its value, lift^T Y_i (the gauge they hold; every fixed pose then equals its
    value to rounding, ~1e-14, not bit for bit as at rank d). Padding slots get [0 | I]."""
    X, mask = np.asarray(X, np.float64), np.asarray(pose_mask, bool)
    d = X.shape[-1] - 1
    real = X[mask]  # (N, r, d+1)
    N, r, k = real.shape
    _, s, Vt = np.linalg.svd(np.moveaxis(real, 1, 0).reshape(r, N * k), full_matrices=False)
    Z = np.moveaxis((s[:d, None] * Vt[:d]).reshape(d, N, k), 1, 0).copy()
    if np.sum(np.linalg.det(Z[..., 1:]) > 0) < N / 2:
        Z[:, -1] *= -1.0
    Z[..., 1:] = project_svd(Z[..., 1:])
    out = np.zeros((*mask.shape, d, k))
    out[..., 1:] = np.eye(d)
    out[mask] = Z
    if free is not None and not np.all(np.asarray(free)[mask]):
        a, i = np.argwhere(mask & ~np.asarray(free))[0]
        target = np.asarray(lift).T @ X[a, i]
        Q = project_svd(target[:, 1:] @ out[a, i, :, 1:].T)
        shift = target[:, 0] - Q @ out[a, i, :, 0]
        moved = np.einsum("ij,...jk->...ik", Q, out)
        moved[..., 0] += shift
        out = np.where(mask[..., None, None], moved, out)
    return out
