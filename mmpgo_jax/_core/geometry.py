"""Rotations: construction from angles/quaternions and projection onto SO(d).

Everything here works on batches (leading axes) and is jittable.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jax import lax


def rotation_2d(theta):
    """Planar rotation matrices for angles ``theta`` (any shape) -> (..., 2, 2)."""
    c, s = jnp.cos(theta), jnp.sin(theta)
    return jnp.stack([jnp.stack([c, -s], -1), jnp.stack([s, c], -1)], -2)


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
        return _svd_projection(M, np)
    return nearest_rotations(M)


def _svd_projection(M, xp=jnp):
    """Umeyama's SVD projection of (..., d, d) blocks (``xp``: numpy or jax.numpy)."""
    U, _, Vt = xp.linalg.svd(M)
    det = xp.linalg.det(U @ Vt)
    d = M.shape[-1]
    fix = xp.concatenate([xp.ones((*M.shape[:-2], d - 1), M.dtype), det[..., None]], -1)
    return (U * fix[..., None, :]) @ Vt


class _Blocks(NamedTuple):
    """Layout adapter: where the d x d matrix axes of a batch of blocks are. ``first=False``:
    (..., d, d) (blocks last); ``first=True``: (d, d, ...) (the solver's structure-of-arrays layout).
    Each layout is indexed natively (no transposition), so both are as fast as hand-written code."""

    first: bool

    def entry(self, M, i, j):
        return M[i, j] if self.first else M[..., i, j]

    def stack_rows(self, rows):
        return jnp.stack(rows) if self.first else jnp.stack(rows, axis=-2)

    def stack_row(self, entries):
        return jnp.stack(entries) if self.first else jnp.stack(entries, -1)


def _closed_form_2d(M, L: _Blocks):
    """Nearest planar rotations; exact for any input: [c -s; s c] maximises
    tr(R^T M) = c (M00 + M11) + s (M10 - M01)."""
    a = L.entry(M, 0, 0) + L.entry(M, 1, 1)
    b = L.entry(M, 1, 0) - L.entry(M, 0, 1)
    r = jnp.sqrt(a * a + b * b)
    safe = r > 0
    c = jnp.where(safe, a / jnp.where(safe, r, 1.0), 1.0)
    s = jnp.where(safe, b / jnp.where(safe, r, 1.0), 0.0)
    return L.stack_rows([L.stack_row([c, -s]), L.stack_row([s, c])])


def _newton_polar_3d(M, max_iterations: int = 6, settled: float | None = None):
    """Orthogonal polar factor of near-rotations (3, 3, ...) (entries first: each step is an
    elementwise loop over contiguous vectors) by scaled Newton iteration (Higham).

    Converges quadratically, so it stops once a step changed no entry by more than ``settled``
    (default sqrt(eps); 0 runs all ``max_iterations`` steps): the error left after that step is of
    order eps. From ||M - R|| ~ 0.1 that is four steps; an AMM extrapolation takes one to three
    (benchmarks/projection_steps.py). Inputs with det(M) <= 0 (far from
    SO(3)) are mapped to a proper rotation by flipping the last row's sign (not the nearest
    rotation: :func:`project_to_so` is exact for those); the solver's accept/reject test guards
    against such poor points.
    """
    def step(X):
        r0, r1, r2 = X[0], X[1], X[2]
        c0, c1, c2 = jnp.cross(r1, r2, axis=0), jnp.cross(r2, r0, axis=0), jnp.cross(r0, r1, axis=0)  # det(X) X^{-T}
        det = jnp.sum(r0 * c0, axis=0)
        invT = jnp.stack([c0, c1, c2]) / det
        scale = jnp.sqrt(jnp.sqrt(jnp.sum(invT**2, axis=(0, 1)) / jnp.sum(X**2, axis=(0, 1))))
        scale = jnp.where(jnp.isfinite(scale) & (scale > 0), scale, 1.0)
        return 0.5 * (scale * X + invT / scale)

    def body(carry):
        k, X, _ = carry
        X_next = step(X)
        return k + 1, X_next, jnp.max(jnp.abs(X_next - X), initial=0.0)

    settled = jnp.sqrt(jnp.finfo(M.dtype).eps) if settled is None else settled
    _, X, _ = lax.while_loop(lambda c: (c[0] < max_iterations) & (c[2] > settled), body,
                             (0, M, jnp.asarray(jnp.inf, M.dtype)))
    det = jnp.sum(X[0] * jnp.cross(X[1], X[2], axis=0), axis=0)
    return X.at[2].multiply(jnp.where(det < 0, -1.0, 1.0))


def nearest_rotations(M, *, method: str = "svd", layout: str = "blocks-last"):
    """The one projection onto SO(d) of the package, for either block layout.

    ``layout="blocks-last"``: M (..., d, d), the matrix axes last (poses, tests, initializations);
    ``"blocks-first"``: M (d, d, ...), the matrix axes first (the solver's structure-of-arrays
    layout, where every entry is a contiguous vector). ``method="svd"``: Umeyama's SVD projection,
    exact for any input and any d (= :func:`project_to_so`). ``"fast"``: the solver's hot path,
    the closed form for d = 2 (exact as well) and a scaled Newton polar iteration for d = 3, run
    until it has converged (at most 6 steps; exact to rounding for near-rotations with det > 0,
    which is what a retraction or an AMM extrapolation produces); other d fall back to the SVD.
    """
    if layout not in ("blocks-last", "blocks-first"):
        raise ValueError(f"layout must be 'blocks-last' or 'blocks-first', got {layout!r}")
    if method not in ("svd", "fast"):
        raise ValueError(f"method must be 'svd' or 'fast', got {method!r}")
    first = layout == "blocks-first"
    d = M.shape[0] if first else M.shape[-1]
    if method == "svd" or d not in (2, 3):
        if not first:
            return _svd_projection(M)
        return jnp.moveaxis(_svd_projection(jnp.moveaxis(M, (0, 1), (-2, -1))), (-2, -1), (0, 1))
    if d == 2:
        return _closed_form_2d(M, _Blocks(first))
    if first:
        return _newton_polar_3d(M)
    # blocks last: the Newton iteration runs on the entries-first transpose (the same bits; measured
    # 1.3-1.6x faster than indexing the blocks in place, transposes included)
    return jnp.moveaxis(_newton_polar_3d(jnp.moveaxis(M, (-2, -1), (0, 1))), (0, 1), (-2, -1))


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


# --- log maps (host-side NumPy, vectorised; added for mmpgo_jax/_robust/pcm.py) -------------------


def so_log(R) -> np.ndarray:
    """Rotation vectors of rotations (..., d, d), d = 2 or 3: the angle (..., 1) in 2D, the axis times
    the angle (..., 3) in 3D (|omega| in [0, pi]; near pi the axis comes from the symmetric part)."""
    R = np.asarray(R, np.float64)
    if R.shape[-1] == 2:
        return np.arctan2(R[..., 1, 0] - R[..., 0, 1], R[..., 0, 0] + R[..., 1, 1])[..., None]
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    s, c = 0.5 * np.linalg.norm(v, axis=-1), 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    theta = np.arctan2(s, c)
    # small and moderate angles: omega = theta / (2 sin theta) v (the ratio -> 1/2 as theta -> 0)
    ratio = np.where(s > 1e-12, theta / np.maximum(2.0 * s, 1e-300), 0.5 + theta**2 / 12.0)
    omega = ratio[..., None] * v
    # theta near pi: a a^T = (sym(R) - cos theta I) / (1 - cos theta), the column of the largest diagonal
    big = c < -0.5
    if np.any(big):
        A = (sym(R[big]) - c[big][:, None, None] * np.eye(3)) / (1.0 - c[big])[:, None, None]
        k = np.argmax(np.diagonal(A, axis1=-2, axis2=-1), axis=-1)
        col = np.take_along_axis(A, k[:, None, None], axis=-1)[..., 0]
        axis = col / np.linalg.norm(col, axis=-1, keepdims=True)
        axis *= np.where(np.sum(axis * v[big], -1) < 0, -1.0, 1.0)[:, None]
        omega[big] = theta[big][:, None] * axis
    return omega


def se_log(R, t) -> tuple[np.ndarray, np.ndarray]:
    """Log of rigid motions (R (..., d, d), t (..., d)), d = 2 or 3: (rho (..., d), omega) with
    Exp(rho, omega) = (exp(hat omega), V(omega) rho), omega = :func:`so_log` (R); rho = V^-1 t."""
    omega = so_log(R)
    t = np.asarray(t, np.float64)
    theta = np.linalg.norm(omega, axis=-1)
    half = 0.5 * theta
    safe = np.where(theta > 1e-6, half, 1.0)
    a = np.where(theta > 1e-6, safe * np.cos(safe) / np.sin(safe), 1.0 - theta**2 / 12.0)  # (theta/2) cot(theta/2)
    if R.shape[-1] == 2:  # V^-1 = a I - (theta/2) J, J = [[0, -1], [1, 0]]
        w = 0.5 * omega[..., 0]
        return np.stack([a * t[..., 0] + w * t[..., 1], a * t[..., 1] - w * t[..., 0]], -1), omega
    # V^-1 = I - W/2 + (1 - a) / theta^2 W^2, W = hat(omega); W t = omega x t
    b = np.where(theta > 1e-6, (1.0 - a) / np.where(theta > 1e-6, theta, 1.0) ** 2, 1.0 / 12.0)
    wt = np.cross(omega, t)
    return t - 0.5 * wt + b[..., None] * np.cross(omega, wt), omega
