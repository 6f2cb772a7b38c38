"""Rotations: construction from angles/quaternions and projection onto SO(d).

Everything here works on batches (leading axes) and is jittable. The formulas that depend on the
dimension are the groups' of :mod:`~mmpgo_jax._core.lie`; this module keeps the package's
dimension-free entry points (and the names its callers import).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .lie import GROUPS, SO2, SO3, newton_polar, project_svd, so

# the former private name of the 3D Newton polar iteration (benchmarks/projection_steps.py)
_newton_polar_3d = newton_polar


def rotation_2d(theta):
    """Planar rotation matrices for angles ``theta`` (any shape) -> (..., 2, 2)."""
    return SO2.exp(jnp.asarray(theta)[..., None])


def angle_2d(R):
    """Angle of planar rotations (..., 2, 2) -> (...), atan2(R_10, R_00).

    A NumPy array stays NumPy (computed on the host in its own precision: the g2o writer's float64
    angles); anything else (JAX arrays, tracers) goes through ``jax.numpy`` and is jittable.
    """
    xp = np if isinstance(R, np.ndarray) else jnp
    return xp.arctan2(R[..., 1, 0], R[..., 0, 0])


def quaternion_to_rotation(q):
    """Unit quaternions (..., 4) in (x, y, z, w) order -> rotation matrices (..., 3, 3).

    The quaternion is normalised first, as SE-Sync does for g2o measurements.
    """
    q = jnp.asarray(q)
    return SO3.from_quaternion(q / jnp.linalg.norm(q, axis=-1, keepdims=True))


def rotation_to_quaternion(R) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4) in (x, y, z, w) order, w >= 0.

    Host-side (numpy, vectorised): used by writers, never on the hot path.
    """
    R = np.asarray(R, dtype=np.float64)
    batch = R.shape[:-2]
    R = R.reshape(-1, 3, 3)
    # Shepperd's method: pick the largest of the four squared components for stability.
    m = {(a, b): R[:, a, b] for a in range(3) for b in range(3)}
    tr = np.trace(R, axis1=1, axis2=2)
    k = np.argmax(np.stack([m[0, 0], m[1, 1], m[2, 2], tr], 1), axis=1)
    # each case's 2 sqrt(1 + ...) and its quaternion, then the one of the largest component
    s = 2.0 * np.sqrt(np.maximum(np.stack([1.0 + m[0, 0] - m[1, 1] - m[2, 2], 1.0 + m[1, 1] - m[0, 0] - m[2, 2],
                                         1.0 + m[2, 2] - m[0, 0] - m[1, 1], 1.0 + tr]), 0.0))
    s = np.where(s > 0, s, 1.0)
    cases = np.stack([
        [0.25 * s[0], (m[0, 1] + m[1, 0]) / s[0], (m[0, 2] + m[2, 0]) / s[0], (m[2, 1] - m[1, 2]) / s[0]],
        [(m[0, 1] + m[1, 0]) / s[1], 0.25 * s[1], (m[1, 2] + m[2, 1]) / s[1], (m[0, 2] - m[2, 0]) / s[1]],
        [(m[0, 2] + m[2, 0]) / s[2], (m[1, 2] + m[2, 1]) / s[2], 0.25 * s[2], (m[1, 0] - m[0, 1]) / s[2]],
        [(m[2, 1] - m[1, 2]) / s[3], (m[0, 2] - m[2, 0]) / s[3], (m[1, 0] - m[0, 1]) / s[3], 0.25 * s[3]],
    ])  # (case, component, rotation)
    q = cases[k, :, np.arange(R.shape[0])]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1
    return q.reshape(*batch, 4)


def project_to_so(M):
    """Nearest rotation (Frobenius norm) to each d x d block of ``M`` (..., d, d).

    SVD projection with the determinant fixed to +1 (Umeyama): U diag(1, .., det(U V^T)) V^T.
    Exact for any input and any d; :func:`nearest_rotations` with ``method="fast"`` is the
    solver's hot-path form of the same projection. A NumPy array stays NumPy (computed on the
    host, no JAX dispatch: the initializations' form); anything else goes through ``jax.numpy``.
    """
    if isinstance(M, np.ndarray):
        return project_svd(M)
    return nearest_rotations(M)


def nearest_rotations(M, *, method: str = "svd", layout: str = "blocks-last"):
    """The one projection onto SO(d) of the package, for either block layout.

    ``layout="blocks-last"``: M (..., d, d), the matrix axes last (poses, tests, initializations);
    ``"blocks-first"``: M (d, d, ...), the matrix axes first (the solver's structure-of-arrays
    layout, where every entry is a contiguous vector). ``method="svd"``: Umeyama's SVD projection,
    exact for any input and any d (= :func:`project_to_so`). ``"fast"``: the solver's hot path,
    the group's :meth:`~mmpgo_jax._core.lie.SO3.project_fast` (the closed form in 2D, exact as well;
    a scaled Newton polar iteration in 3D, exact to rounding for near-rotations with det > 0,
    which is what a retraction or an AMM extrapolation produces); other d fall back to the SVD.
    """
    if layout not in ("blocks-last", "blocks-first"):
        raise ValueError(f"layout must be 'blocks-last' or 'blocks-first', got {layout!r}")
    if method not in ("svd", "fast"):
        raise ValueError(f"method must be 'svd' or 'fast', got {method!r}")
    first = layout == "blocks-first"
    M = jnp.asarray(M)
    group = GROUPS.get(M.shape[0] if first else M.shape[-1])
    if method == "fast" and group is not None:
        return group.project_fast(M, first=first)
    if not first:
        return project_svd(M)
    return jnp.moveaxis(project_svd(jnp.moveaxis(M, (0, 1), (-2, -1))), (-2, -1), (0, 1))


def sym(M):
    """Symmetric part of square blocks (..., d, d) (NumPy or JAX arrays)."""
    return 0.5 * (M + M.swapaxes(-1, -2))


def skew(M):
    """Skew-symmetric part of square blocks (..., d, d)."""
    return 0.5 * (M - jnp.swapaxes(M, -1, -2))


def random_rotations(rng: np.random.Generator, shape, dim: int) -> np.ndarray:
    """Haar-distributed random rotations (host-side, for tests and synthetic data)."""
    A = rng.standard_normal((*shape, dim, dim))
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


# --- log maps (host-side NumPy, float64; for mmpgo_jax/_robust/pcm.py) ------------------------------


def so_log(R) -> np.ndarray:
    """Rotation vectors of rotations (..., d, d), d = 2 or 3: the angle (..., 1) in 2D, the axis times
    the angle (..., 3) in 3D (|omega| in [0, pi]): :meth:`~mmpgo_jax._core.lie.SO3.log` in float64."""
    R = np.asarray(R, np.float64)
    return so(R.shape[-1]).log(R)


def se_log(R, t) -> tuple[np.ndarray, np.ndarray]:
    """Log of rigid motions (R (..., d, d), t (..., d)), d = 2 or 3: (rho (..., d), omega) with
    Exp(rho, omega) = (exp(hat omega), V(omega) rho), omega = :func:`so_log` (R); rho = V^-1 t."""
    R = np.asarray(R, np.float64)
    group = so(R.shape[-1])
    omega = group.log(R)
    return group.apply_V_inverse(omega, np.asarray(t, np.float64)), omega
