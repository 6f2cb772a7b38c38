"""Two-level preconditioner for the robot subproblem: block-Jacobi plus a coarse correction.

Block-Jacobi (the inverses of Gamma's per-pose diagonal blocks) leaves the smooth, long-range
modes of Gamma -- bending a long odometry chain, moving a loop of poses together -- to CG, which
needs many iterations for them (the count grows with the chain's length: 150 CG iterations per
subproblem on kitti_00). The coarse level removes them: the robot's poses are cut into aggregates
of ``b`` consecutive slots, and on each aggregate the coarse space holds the modes that cost
(almost) nothing inside it, i.e. Gamma's near-null space. Gamma acts on each of the d rows of the
stacked poses Y_i = [t_i | R_i] alike, and a row x (one scalar translation and d rotation entries
per pose) has zero cost on an edge when x_j = x_i [[1, t~_ij], [0, R~_ij]], which holds for

  * the translation shift x_i = (1, 0, ..., 0), and
  * the d rows of any poses consistent with the measurements: x_i = row r of [t_i | R_i].

So the coarse basis on an aggregate is the shift and the d rows of the start estimate X^0 there
(consistent with the measurements up to their noise), ``d + 1`` coarse unknowns per aggregate:
"aggregation with near-null-space vectors" (smoothed-aggregation AMG without the smoothing step;
Vanek, Mandel & Brezina 1996). With P the (prolongation) matrix of these columns, the
preconditioner is the additive two-level one

    M^{-1} = blockdiag(Gamma_ii)^{-1} + P (P^T Gamma P)^+ P^T,

symmetric positive definite; P^T Gamma P is small and dense and, Gamma being constant, it is
factored once, when the problem is built (a pseudo-inverse: a robot with no anchor, xi = 0, has a
singular Gamma). Aggregates have 16 slots, more on large robots (:func:`aggregate_size`,
measured in benchmarks/profile_step.md). An X^0 far from consistent only makes the coarse space less
useful: the preconditioner stays positive definite and the accept test of the trust region guards
every step.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .majorization import SoAPreconditioner, soa_bmm, soa_T

MIN_AGGREGATE = 16  # slots per aggregate at least
SMALL_COARSE = 96  # coarse unknowns per robot the aggregate size aims at on large robots
MAX_COARSE = 1536  # coarse unknowns per robot at most: bounds the (A, m k, m k) dense factor's memory


def aggregate_size(robot_poses: int, pose_dim: int) -> int:
    """Slots per aggregate when the largest robot has ``robot_poses`` poses (``pose_dim`` = d + 1
    unknowns per slot and row): 16 on robots of up to 512 (2D) / 384 (3D) poses; on larger ones
    enough for about 96 coarse unknowns (the dense coarse product then stays cheaper than a Gamma
    product: city10000's 1000-pose robots ran at 11.1 ms per AMM iteration with 16 slots, 7.1 with
    32), but not more than about sqrt(n) (so that the coarse level keeps reaching the smooth modes of
    very large robots), and never more than ``MAX_COARSE`` coarse unknowns. It depends on the real
    poses, not on the padded slot count, so padding a partition does not change the preconditioner."""
    b = max(MIN_AGGREGATE, min(round(float(np.sqrt(robot_poses))), -(-robot_poses * pose_dim // SMALL_COARSE)))
    return max(b, -(-robot_poses * pose_dim // MAX_COARSE))


class TwoLevelSoA(SoAPreconditioner):
    """M^{-1} = block-Jacobi + P (P^T Gamma P)^+ P^T in the structure-of-arrays layout (one robot,
    or batched over robots in front). ``aggregate`` (static) is the number of slots per
    aggregate."""

    diag_inverse: jax.Array  # (k, k, n): inverses of Gamma's diagonal blocks
    basis: jax.Array  # (k, k, n): basis[q, c, s] = entry q at slot s of coarse column c
    coarse_inverse: jax.Array  # (m k, m k): (P^T Gamma P)^+, coarse index = aggregate * k + c
    aggregate: int = eqx.field(static=True)

    def __call__(self, V):
        """M^{-1} applied to V (d, k, n) (Gamma acts from the right on each of the d rows)."""
        d, k, n = V.shape
        b = self.aggregate
        m = -(-n // b)
        W = jnp.pad(soa_bmm(V, self.basis), ((0, 0), (0, 0), (0, m * b - n)))
        W = W.reshape(d, k, m, b).sum(-1)  # P^T V: (d, k, m)
        W = jnp.swapaxes(W, 1, 2).reshape(d, m * k) @ self.coarse_inverse
        W = jnp.repeat(jnp.swapaxes(W.reshape(d, m, k), 1, 2), b, axis=-1)[..., :n]
        return soa_bmm(V, self.diag_inverse) + soa_bmm(W, soa_T(self.basis))


def _coarse_matrices(diag, band, src, dst, blocks, basis, b: int):
    """P^T Gamma P for every robot (host, numpy): Gamma's nonzero blocks Gamma_ss' contribute
    B_s^T Gamma_ss' B_s' to the coarse block of (aggregate(s), aggregate(s'))."""
    A, n, k, _ = diag.shape
    m = -(-n // b)
    B = np.moveaxis(basis, -1, 1)  # (A, n, q, c)
    s = np.arange(n)
    if src.ndim == 1:
        src, dst = np.broadcast_to(src, (A, src.size)), np.broadcast_to(dst, (A, dst.size))
    # (row slots, column slots, blocks) of every nonzero block: diagonal, band (both ways), loops
    rows = np.concatenate([np.broadcast_to(s, (A, n)), np.broadcast_to(s[:-1], (A, n - 1)),
                           np.broadcast_to(s[1:], (A, n - 1)), src], axis=1)
    cols = np.concatenate([np.broadcast_to(s, (A, n)), np.broadcast_to(s[1:], (A, n - 1)),
                           np.broadcast_to(s[:-1], (A, n - 1)), dst], axis=1)
    G = np.concatenate([diag, band[:, :-1], np.swapaxes(band[:, :-1], -1, -2), blocks], axis=1)
    a = np.arange(A)[:, None]
    contrib = np.einsum("aeqc,aeqr,aerg->aecg", B[a, rows], G, B[a, cols])  # (A, E, k, k)
    coarse = np.zeros((A, m * k, m * k))
    ck = np.arange(k)
    ri = ((rows // b) * k)[..., None, None] + ck[:, None]
    ci = ((cols // b) * k)[..., None, None] + ck[None, :]
    np.add.at(coarse, (a[..., None, None], ri, ci), contrib)
    return coarse


def build_two_level(diag, band, src, dst, blocks, diag_inverse, X0, pose_mask, dtype) -> TwoLevelSoA:
    """The two-level preconditioner of every robot (host, float64, once).

    Gamma's blocks in the stacked layout (``diag``, ``band`` (A, n, k, k); loop closures ``src``,
    ``dst``, ``blocks``); ``diag_inverse`` (A, k, k, n) the block-Jacobi part (structure of
    arrays); ``X0`` (A, n, d, k) the start poses, stacked [t | R]; ``pose_mask`` (A, n)."""
    diag, band, blocks = (np.asarray(x, np.float64) for x in (diag, band, blocks))
    src, dst = np.asarray(src), np.asarray(dst)
    X0, mask = np.asarray(X0, np.float64), np.asarray(pose_mask, bool)
    A, n, k, _ = diag.shape
    b = aggregate_size(int(mask.sum(axis=1).max(initial=0)), k)
    basis = np.zeros((A, k, k, n))
    basis[:, 0, 0, :] = 1.0  # the translation shift
    basis[:, :, 1:, :] = np.transpose(X0, (0, 3, 2, 1))  # column 1 + r: row r of [t | R]
    basis *= mask[:, None, None, :]
    # The same space, better conditioned: translations relative to their aggregate's mean (minus a
    # multiple of the shift column), so that metres-large coordinates do not swamp the rotations.
    m = -(-n // b)
    agg = np.arange(n) // b
    count = np.zeros((A, m))
    np.add.at(count, (slice(None), agg), mask)
    mean = np.zeros((A, k, m))
    np.add.at(mean, (slice(None), slice(None), agg), basis[:, 0, :, :])
    mean /= np.maximum(count, 1)[:, None, :]
    basis[:, 0, 1:, :] -= mean[:, 1:, agg] * mask[:, None, :]
    coarse = _coarse_matrices(diag, band, src, dst, blocks, basis, b)
    # weights float arithmetic cannot represent: no coarse level (the run reports f = inf itself)
    coarse[~np.isfinite(coarse).all(axis=(1, 2))] = 0.0
    # symmetric diagonal scaling before the pseudo-inverse (empty aggregates: zero rows stay zero)
    dg = np.einsum("aii->ai", coarse)
    scale = np.where(dg > 0, 1.0 / np.sqrt(np.where(dg > 0, dg, 1.0)), 0.0)
    scaled = coarse * scale[:, :, None] * scale[:, None, :]
    inverse = np.linalg.pinv(scaled, rcond=1e-13, hermitian=True) * scale[:, :, None] * scale[:, None, :]
    return TwoLevelSoA(diag_inverse=jnp.asarray(diag_inverse, dtype), basis=jnp.asarray(basis, dtype),
                       coarse_inverse=jnp.asarray(inverse, dtype), aggregate=b)
