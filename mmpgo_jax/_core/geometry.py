"""Rotations: construction from angles/quaternions and projection onto SO(d).

Everything here works on batches (leading axes) and is jittable.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np


def rotation_2d(theta):
    """Planar rotation matrices for angles ``theta`` (any shape) -> (..., 2, 2)."""
    c, s = jnp.cos(theta), jnp.sin(theta)
    return jnp.stack([jnp.stack([c, -s], -1), jnp.stack([s, c], -1)], -2)


def angle_2d(R):
    """Angle of planar rotations (..., 2, 2) -> (...)."""
    return jnp.arctan2(R[..., 1, 0], R[..., 0, 0])


def quaternion_to_rotation(q):
    """Unit quaternions (..., 4) in (x, y, z, w) order -> rotation matrices (..., 3, 3).

    The quaternion is normalised first, as SE-Sync does for g2o measurements.
    """
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return jnp.stack(
        [
            jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            jnp.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            jnp.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def rotation_to_quaternion(R) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4) in (x, y, z, w) order, w >= 0.

    Host-side (numpy): used by writers, never on the hot path.
    """
    R = np.asarray(R, dtype=np.float64)
    batch = R.shape[:-2]
    R = R.reshape(-1, 3, 3)
    # Shepperd's method: pick the largest of the four squared components for stability.
    tr = np.trace(R, axis1=1, axis2=2)
    diag = np.stack([R[:, 0, 0], R[:, 1, 1], R[:, 2, 2], tr], 1)
    k = np.argmax(diag, axis=1)
    q = np.empty((R.shape[0], 4))
    for idx in range(R.shape[0]):
        m = R[idx]
        if k[idx] == 3:
            s = 2.0 * np.sqrt(max(1.0 + tr[idx], 0.0))
            q[idx] = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
        elif k[idx] == 0:
            s = 2.0 * np.sqrt(max(1.0 + m[0, 0] - m[1, 1] - m[2, 2], 0.0))
            q[idx] = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
        elif k[idx] == 1:
            s = 2.0 * np.sqrt(max(1.0 + m[1, 1] - m[0, 0] - m[2, 2], 0.0))
            q[idx] = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
        else:
            s = 2.0 * np.sqrt(max(1.0 + m[2, 2] - m[0, 0] - m[1, 1], 0.0))
            q[idx] = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1
    return q.reshape(*batch, 4)


def project_to_so(M):
    """Nearest rotation (Frobenius norm) to each d x d block of ``M`` (..., d, d).

    SVD projection with the determinant fixed to +1 (Umeyama): U diag(1, .., det(U V^T)) V^T.
    """
    U, _, Vt = jnp.linalg.svd(M)
    det = jnp.linalg.det(U @ Vt)
    d = M.shape[-1]
    fix = jnp.concatenate([jnp.ones(M.shape[:-2] + (d - 1,), M.dtype), det[..., None]], -1)
    return (U * fix[..., None, :]) @ Vt


def sym(M):
    """Symmetric part of square blocks (..., d, d)."""
    return 0.5 * (M + jnp.swapaxes(M, -1, -2))


def skew(M):
    """Skew-symmetric part of square blocks (..., d, d)."""
    return 0.5 * (M - jnp.swapaxes(M, -1, -2))


def random_rotations(rng: np.random.Generator, shape, dim: int) -> np.ndarray:
    """Haar-distributed random rotations (host-side, for tests and synthetic data)."""
    A = rng.standard_normal(tuple(shape) + (dim, dim))
    Q, Rr = np.linalg.qr(A)
    Q = Q * np.sign(np.diagonal(Rr, axis1=-2, axis2=-1))[..., None, :]
    det = np.linalg.det(Q)
    Q[..., :, 0] *= det[..., None]
    return Q


def bmm(a, b):
    """Batched product of small matrices, unrolled over the inner dimension.

    XLA's CPU dot for batches of 2x2..4x4 matrices is several times slower than this fused
    elementwise form (measured); semantics are exactly ``a @ b`` with broadcasting.
    """
    out = a[..., :, 0, None] * b[..., None, 0, :]
    for k in range(1, a.shape[-1]):
        out = out + a[..., :, k, None] * b[..., None, k, :]
    return out


def mT(a):
    """Transpose of the last two axes."""
    return jnp.swapaxes(a, -1, -2)
