"""The rotation groups SO(2) and SO(3) behind one interface, one class per group (as in jaxlie).

Every formula that depends on the dimension of the rotations lives here: the rest of the package
asks :func:`so` for the group of dimension d and calls its methods, so its code reads the same in
2D and 3D and has no ``d == 2`` branch of its own.

Conventions. Tangent coordinates omega (``tangent_dim`` = p = d(d-1)/2 numbers) map to so(d) by
``hat(omega) = sum_q omega_q E_q`` with the generators E_q of :meth:`generators`: in 2D E = J =
[[0, -1], [1, 0]], in 3D hat(omega) v = omega x v. Methods are static and take NumPy or JAX arrays:
NumPy in, NumPy out (host-side callers compute in float64 without JAX dispatch), while JAX arrays
and tracers go through jax.numpy (jittable). Coordinates and matrices have their axes last,
(..., p) and (..., d, d), or with ``first=True`` first, (p, ...) and (d, d, ...): the solver's
structure-of-arrays layout, where every entry is a contiguous vector.

The formulas keep the exact floating-point operations of the copies they replaced: the solver has
bit-for-bit references.
"""

from __future__ import annotations

import functools
import math
from types import MappingProxyType
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jax import lax

from .precision import array_module

__all__ = ["GROUPS", "SO2", "SO3", "inverse_sym", "newton_polar", "project_svd", "so", "stiefel_polar"]


class _Axes(NamedTuple):
    """Where the coordinate / matrix axes are: last (``first=False``) or first. Each layout is
    indexed natively (no transposition), so both are as fast as code written for one of them."""

    first: bool

    def get(self, x, *index):
        return x[index] if self.first else x[(..., *index)]

    def vector(self, xp, entries):
        return xp.stack(entries) if self.first else xp.stack(entries, -1)

    def matrix(self, xp, rows):
        if self.first:
            return xp.stack([xp.stack(row) for row in rows])
        return xp.stack([xp.stack(row, -1) for row in rows], -2)

    def expand(self, x):
        """A per-block scalar (...) as a 1 x 1 block that broadcasts against (d, d, ...) / (..., d, d)."""
        return x[None, None] if self.first else x[..., None, None]

    def eye(self, xp, d: int, like):
        eye = xp.eye(d, dtype=like.dtype)
        return eye.reshape(d, d, *(1,) * (like.ndim - 2)) if self.first else eye


def project_svd(M):
    """Nearest rotation (Frobenius norm) to each d x d block of M (..., d, d), any d: Umeyama's SVD
    projection U diag(1, .., det(U V^T)) V^T, exact for any input."""
    xp = array_module(M)
    U, _, Vt = xp.linalg.svd(M)
    det = xp.linalg.det(U @ Vt)
    d = M.shape[-1]
    fix = xp.concatenate([xp.ones((*M.shape[:-2], d - 1), M.dtype), det[..., None]], -1)
    return (U * fix[..., None, :]) @ Vt


def newton_polar(M, max_iterations: int = 6, settled: float | None = None):
    """Orthogonal polar factor of near-rotations (3, 3, ...) (entries first: each step is an
    elementwise loop over contiguous vectors) by scaled Newton iteration (Higham); JAX.

    Converges quadratically, so it stops once a step changed no entry by more than ``settled``
    (default sqrt(eps); 0 runs all ``max_iterations`` steps): the error left after that step is of
    order eps. From ||M - R|| ~ 0.1 that is four steps; an AMM extrapolation takes one to three
    (benchmarks/projection_steps.py). Inputs with det(M) <= 0 (far from SO(3)) are mapped to a
    proper rotation by flipping the last row's sign (not the nearest rotation: :func:`project_svd`
    is exact for those); the solver's accept/reject test guards against such poor points.
    """
    def inverse_T(X):
        r0, r1, r2 = X[0], X[1], X[2]
        c0, c1, c2 = jnp.cross(r1, r2, axis=0), jnp.cross(r2, r0, axis=0), jnp.cross(r0, r1, axis=0)  # det(X) X^{-T}
        det = jnp.sum(r0 * c0, axis=0)
        return jnp.stack([c0, c1, c2]) / det

    X = _scaled_newton(inverse_T, M, max_iterations, settled)
    det = jnp.sum(X[0] * jnp.cross(X[1], X[2], axis=0), axis=0)
    return X.at[2].multiply(jnp.where(det < 0, -1.0, 1.0))


def inverse_sym(S):
    """Inverse of symmetric d x d blocks S (d, d, ...) entries first, d = 2 or 3, by the adjugate (no
    LAPACK call), and whether each block is positive definite."""
    if S.shape[0] == 3:
        return SO3.inverse_spd(S, first=True)  # a symmetric 3 x 3 adjugate, whatever the block means
    a, b, c = S[0, 0], S[0, 1], S[1, 1]
    det = a * c - b * b
    ok = (a > 0) & (det > 0)
    inv = jnp.stack([jnp.stack([c, -b]), jnp.stack([-b, a])])
    return inv / jnp.where(ok | (det != 0), det, 1.0), ok


def stiefel_polar(M, max_iterations: int = 20, settled: float | None = None):
    """Orthogonal polar factor U V^T of tall blocks (r, d, ...) (entries first, r > d, d = 2 or 3):
    the projection onto the Stiefel manifold St(d, r), no determinant fix. Scaled Newton iteration
    X <- (s X + X (X^T X)^-1 / s) / 2, :func:`newton_polar`'s iteration with the pseudo-inverse of a
    full-rank tall matrix (each singular value goes to 1, the singular vectors stay): no LAPACK call,
    so it runs inside sharded programs. It stops once a step changed no entry by more than
    ``settled`` (default sqrt(eps)), when the error left is of order eps."""
    def pseudo_inverse_T(X):  # (X^+)^T = X (X^T X)^-1
        return _bmm_first(X, inverse_sym(_bmm_first(jnp.swapaxes(X, 0, 1), X))[0])

    return _scaled_newton(pseudo_inverse_T, M, max_iterations, settled)


def _scaled_newton(inverse_T, M, max_iterations: int, settled: float | None):
    """The scaled Newton polar iteration X <- (s X + inverse_T(X) / s) / 2 (Frobenius scaling s)
    from M, entries first, until a step changes no entry by more than ``settled`` (default
    sqrt(eps)) or after ``max_iterations`` steps."""
    def step(X):
        invT = inverse_T(X)
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
    return X


def _half_cot(theta, xp):
    """(theta/2) cot(theta/2), its series near 0: the shared factor of SE(d)'s V^-1."""
    half = 0.5 * theta
    safe = xp.where(theta > 1e-6, half, 1.0)
    return xp.where(theta > 1e-6, safe * xp.cos(safe) / xp.sin(safe), 1.0 - theta**2 / 12.0)


class _SO:
    """The interface both groups implement (class attributes and static methods only)."""

    #: d, the size of the rotation matrices
    dim: int
    #: p = d(d-1)/2, the number of tangent coordinates
    tangent_dim: int
    #: sqrt(E theta^2) of a Haar-random rotation, theta its angle in [0, pi]: the largest RMS angle
    haar_rms_angle: float

    @staticmethod
    def haar_angle_density(theta: float) -> float:
        """Density of the angle theta in [0, pi] of a Haar-random rotation, up to a constant factor
        (a float, for quadratures)."""
        raise NotImplementedError

    @classmethod
    def generators(cls) -> np.ndarray:
        """The basis E_q = hat(e_q) of so(d), (p, d, d) float64, read-only (built once)."""
        return _generators(cls)


@functools.cache
def _generators(group) -> np.ndarray:
    E = group.hat(np.eye(group.tangent_dim)) + 0.0  # + 0.0: no negative zeros
    E.setflags(write=False)
    return E


class SO2(_SO):
    """Planar rotations; the tangent coordinate is the angle."""

    dim = 2
    tangent_dim = 1
    haar_rms_angle = math.pi / math.sqrt(3.0)

    @staticmethod
    def haar_angle_density(theta: float) -> float:
        """Uniform: 1."""
        return 1.0

    @staticmethod
    def hat(omega, *, first=False):
        """omega (..., 1) -> omega J (..., 2, 2)."""
        ax, xp = _Axes(first), array_module(omega)
        w = ax.get(omega, 0)
        z = xp.zeros_like(w)
        return ax.matrix(xp, [[z, -w], [w, z]])

    @staticmethod
    def vee(Omega, *, first=False):
        """Inverse of :meth:`hat` on so(2): (..., 2, 2) -> (..., 1)."""
        ax, xp = _Axes(first), array_module(Omega)
        return ax.vector(xp, [ax.get(Omega, 1, 0)])

    @staticmethod
    def dual(A, *, first=False):
        """(<E_q, A>)_q for any A (..., 2, 2): the coordinates dual to hat (= 2 vee(skew(A)))."""
        ax, xp = _Axes(first), array_module(A)
        return ax.vector(xp, [ax.get(A, 1, 0) - ax.get(A, 0, 1)])

    @staticmethod
    def hat_apply(omega, v, *, first=False):
        """hat(omega) v for vectors v (..., 2), without forming the matrix."""
        ax, xp = _Axes(first), array_module(omega, v)
        w = ax.get(omega, 0)
        return ax.vector(xp, [-w * ax.get(v, 1), w * ax.get(v, 0)])

    @staticmethod
    def hat_apply_adjoint(v, u, *, first=False):
        """(<E_q v, u>)_q: the adjoint of omega -> hat(omega) v, applied to u (..., 2)."""
        ax, xp = _Axes(first), array_module(v, u)
        return ax.vector(xp, [ax.get(v, 0) * ax.get(u, 1) - ax.get(v, 1) * ax.get(u, 0)])

    @staticmethod
    def hat_apply_matrix(v):
        """The matrix (..., 2, 1) of omega -> hat(omega) v: J v."""
        xp = array_module(v)
        return xp.stack([-v[..., 1], v[..., 0]], -1)[..., None]

    @staticmethod
    def adjoint(R):
        """Ad_R on tangent coordinates, (..., 1, 1): 1 (the group is abelian)."""
        xp = array_module(R)
        return xp.ones((*R.shape[:-2], 1, 1), R.dtype)

    @staticmethod
    def exp(omega):
        """Rotations by the angles omega (..., 1) -> (..., 2, 2)."""
        xp = array_module(omega)
        c, s = xp.cos(omega[..., 0]), xp.sin(omega[..., 0])
        return xp.stack([xp.stack([c, -s], -1), xp.stack([s, c], -1)], -2)

    @staticmethod
    def log(R):
        """Angles in (-pi, pi] (..., 1) of rotations (..., 2, 2) (from both columns: accurate for
        rotations that are off SO(2) by rounding)."""
        xp = array_module(R)
        return xp.arctan2(R[..., 1, 0] - R[..., 0, 1], R[..., 0, 0] + R[..., 1, 1])[..., None]

    @staticmethod
    def angle(R):
        """Geodesic angle in [0, pi] of rotations (..., 2, 2): |log R|."""
        xp = array_module(R)
        return xp.abs(xp.arctan2(R[..., 1, 0] - R[..., 0, 1], R[..., 0, 0] + R[..., 1, 1]))

    @staticmethod
    def apply_V_inverse(omega, t):
        """V(omega)^-1 t, V the left Jacobian (SE(2)'s exp moves by V rho): the translation
        coordinates rho of SE(2)'s log. V^-1 = a I - (theta/2) J, a = (theta/2) cot(theta/2)."""
        xp = array_module(omega, t)
        a = _half_cot(xp.linalg.norm(omega, axis=-1), xp)
        w = 0.5 * omega[..., 0]
        return xp.stack([a * t[..., 0] + w * t[..., 1], a * t[..., 1] - w * t[..., 0]], -1)

    @staticmethod
    def project(M):
        """Nearest rotations (..., 2, 2), exact for any input, in closed form."""
        return _closed_form_2d(M, _Axes(False), array_module(M))

    @staticmethod
    def project_fast(M, *, first=False):
        """The solver's projection (JAX): the closed form of :meth:`project`, exact as well."""
        return _closed_form_2d(M, _Axes(first), jnp)

    @staticmethod
    def retract(R, B):
        """The polar retraction of R + B (B tangent at R), entries first (2, 2, ...): the closed-form
        projection, exact."""
        return SO2.project_fast(R + B, first=True)

    @staticmethod
    def trace_form(M, tr, *, first=False):
        """C(M) (p, p) with C_pq = tr(E_p^T E_q M), given tr = tr(M) (callers choose how it is
        summed): tr(M) in 2D. The tangent block of a quadratic form whose rotation block is M."""
        return _Axes(first).expand(tr)

    @staticmethod
    def inverse_spd(S, *, first=False):
        """Inverse of symmetric p x p blocks S and whether each is positive definite: 1 / s."""
        ax = _Axes(first)
        s = ax.get(S, 0, 0)
        ok = s > 0
        return ax.expand(1.0 / array_module(S).where(ok, s, 1.0)), ok


def _closed_form_2d(M, ax: _Axes, xp):
    """Nearest planar rotations; exact for any input: [c -s; s c] maximises
    tr(R^T M) = c (M00 + M11) + s (M10 - M01)."""
    a = ax.get(M, 0, 0) + ax.get(M, 1, 1)
    b = ax.get(M, 1, 0) - ax.get(M, 0, 1)
    r = xp.sqrt(a * a + b * b)
    safe = r > 0
    c = xp.where(safe, a / xp.where(safe, r, 1.0), 1.0)
    s = xp.where(safe, b / xp.where(safe, r, 1.0), 0.0)
    return ax.matrix(xp, [[c, -s], [s, c]])


class SO3(_SO):
    """Rotations of space; tangent coordinates are rotation vectors (axis times angle)."""

    dim = 3
    tangent_dim = 3
    haar_rms_angle = math.sqrt(math.pi**2 / 3 + 2)

    @staticmethod
    def haar_angle_density(theta: float) -> float:
        """sin^2(theta/2), proportional to 1 - cos(theta)."""
        return math.sin(0.5 * theta) ** 2

    @staticmethod
    def hat(omega, *, first=False):
        """omega (..., 3) -> the cross-product matrix [[0, -z, y], [z, 0, -x], [-y, x, 0]]."""
        ax, xp = _Axes(first), array_module(omega)
        x, y, z = (ax.get(omega, k) for k in range(3))
        o = xp.zeros_like(x)
        return ax.matrix(xp, [[o, -z, y], [z, o, -x], [-y, x, o]])

    @staticmethod
    def vee(Omega, *, first=False):
        """Inverse of :meth:`hat` on so(3): (..., 3, 3) -> (..., 3)."""
        ax, xp = _Axes(first), array_module(Omega)
        return ax.vector(xp, [ax.get(Omega, 2, 1), ax.get(Omega, 0, 2), ax.get(Omega, 1, 0)])

    @staticmethod
    def dual(A, *, first=False):
        """(<E_q, A>)_q for any A (..., 3, 3): the coordinates dual to hat (= 2 vee(skew(A)))."""
        ax, xp = _Axes(first), array_module(A)
        g = ax.get
        return ax.vector(xp, [g(A, 2, 1) - g(A, 1, 2), g(A, 0, 2) - g(A, 2, 0), g(A, 1, 0) - g(A, 0, 1)])

    @staticmethod
    def hat_apply(omega, v, *, first=False):
        """hat(omega) v = omega x v."""
        return array_module(omega, v).cross(omega, v, axis=0 if first else -1)

    @staticmethod
    def hat_apply_adjoint(v, u, *, first=False):
        """(<E_q v, u>)_q = v x u: the adjoint of omega -> omega x v, applied to u."""
        return array_module(v, u).cross(v, u, axis=0 if first else -1)

    @staticmethod
    def hat_apply_matrix(v):
        """The matrix (..., 3, 3) of omega -> omega x v: -hat(v)."""
        return -SO3.hat(v)

    @staticmethod
    def adjoint(R):
        """Ad_R on tangent coordinates: R itself (R hat(omega) R^T = hat(R omega))."""
        return R

    @staticmethod
    def exp(omega):
        """Rodrigues' formula: rotation vectors (..., 3) -> rotations (..., 3, 3).

        (SciPy's compiled Rotation.from_rotvec takes half the time per call, but importing
        scipy.spatial costs ~60 ms, more than fifty host-side solves of a tiny graph.)"""
        xp = array_module(omega)
        theta = xp.sqrt(xp.sum(omega * omega, axis=-1))
        small = theta < 1e-8
        safe = xp.where(small, 1.0, theta)
        a = xp.where(small, 1.0 - theta**2 / 6.0, xp.sin(theta) / safe)
        b = xp.where(small, 0.5 - theta**2 / 24.0, (1.0 - xp.cos(theta)) / safe**2)
        W = SO3.hat(omega)
        return xp.eye(3, dtype=W.dtype) + a[..., None, None] * W + b[..., None, None] * (W @ W)

    @staticmethod
    def log(R):
        """Rotation vectors (..., 3) of rotations (..., 3, 3), |omega| in [0, pi]: atan2 of the
        axis vector and the trace term (accurate near 0 and pi, unlike arccos); near pi the axis
        comes from the symmetric part, where the skew part vanishes."""
        xp = array_module(R)
        v = SO3.dual(R)
        s, c = 0.5 * xp.linalg.norm(v, axis=-1), 0.5 * (xp.trace(R, axis1=-2, axis2=-1) - 1.0)
        theta = xp.arctan2(s, c)
        # small and moderate angles: omega = theta / (2 sin theta) v (the ratio -> 1/2 as theta -> 0)
        ratio = xp.where(s > 1e-12, theta / xp.maximum(2.0 * s, 1e-300), 0.5 + theta**2 / 12.0)
        omega = ratio[..., None] * v
        # theta near pi: a a^T = (sym(R) - cos theta I) / (1 - cos theta), the column of the largest diagonal
        big = c < -0.5
        A = (0.5 * (R + xp.swapaxes(R, -1, -2)) - c[..., None, None] * xp.eye(3, dtype=R.dtype)) \
            / xp.where(big, 1.0 - c, 1.0)[..., None, None]
        k = xp.argmax(xp.diagonal(A, axis1=-2, axis2=-1), axis=-1)
        col = xp.take_along_axis(A, k[..., None, None], axis=-1)[..., 0]
        norm = xp.linalg.norm(col, axis=-1, keepdims=True)
        axis = col / xp.where(norm > 0, norm, 1.0)
        axis = axis * xp.where(xp.sum(axis * v, -1) < 0, -1.0, 1.0)[..., None]
        return xp.where(big[..., None], theta[..., None] * axis, omega)

    @staticmethod
    def angle(R):
        """Geodesic angle in [0, pi] of rotations (..., 3, 3) (= |log R|, without the axis)."""
        xp = array_module(R)
        v = SO3.dual(R)
        return xp.arctan2(0.5 * xp.linalg.norm(v, axis=-1), 0.5 * (xp.trace(R, axis1=-2, axis2=-1) - 1.0))

    @staticmethod
    def apply_V_inverse(omega, t):
        """V(omega)^-1 t, V the left Jacobian (SE(3)'s exp moves by V rho): the translation
        coordinates rho of SE(3)'s log. V^-1 = I - W/2 + (1 - a) / theta^2 W^2, W = hat(omega),
        a = (theta/2) cot(theta/2)."""
        xp = array_module(omega, t)
        theta = xp.linalg.norm(omega, axis=-1)
        a = _half_cot(theta, xp)
        b = xp.where(theta > 1e-6, (1.0 - a) / xp.where(theta > 1e-6, theta, 1.0) ** 2, 1.0 / 12.0)
        wt = xp.cross(omega, t)
        return t - 0.5 * wt + b[..., None] * xp.cross(omega, wt)

    @staticmethod
    def from_quaternion(q):
        """Unit quaternions (..., 4) in (x, y, z, w) order -> rotations (..., 3, 3) (not normalised)."""
        xp = array_module(q)
        x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
        return xp.stack(
            [
                xp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
                xp.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
                xp.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
            ],
            -2,
        )

    @staticmethod
    def project(M):
        """Nearest rotations (..., 3, 3), exact for any input: :func:`project_svd`."""
        return project_svd(M)

    @staticmethod
    def project_fast(M, *, first=False):
        """The solver's projection (JAX): :func:`newton_polar`, run until it has converged (exact to
        rounding for near-rotations with det > 0, what a retraction or an extrapolation gives)."""
        if first:
            return newton_polar(M)
        # blocks last: the iteration runs on the entries-first transpose (the same bits; measured
        # 1.3-1.6x faster than indexing the blocks in place, transposes included)
        return jnp.moveaxis(newton_polar(jnp.moveaxis(M, (-2, -1), (0, 1))), (0, 1), (-2, -1))

    @staticmethod
    def retract(R, B):
        """The polar retraction of R + B (B tangent at R), entries first (3, 3, ...): in float64 the
        closed form polar(I + Omega) = I + Omega / s + Omega^2 / (s (s + 1)), Omega = skew(R^T B),
        s = sqrt(1 + |omega|^2) (Omega^2 has eigenvalues -|omega|^2 twice and 0), a third of the work
        of the Newton iteration (benchmarks/profile_step.md). The closed form keeps R's own distance
        from SO(3) and adds rounding: over 1000 MM iterations that drift is ~1e-13 in float64 but
        ~3e-5 in float32 (measured on sphere2500), so float32 re-projects with :meth:`project_fast`."""
        if R.dtype != jnp.float64:
            return SO3.project_fast(R + B, first=True)
        Om = _bmm_first(jnp.swapaxes(R, 0, 1), B)
        Om = 0.5 * (Om - jnp.swapaxes(Om, 0, 1))
        s = jnp.sqrt(1.0 + 0.5 * jnp.sum(Om * Om, axis=(0, 1)))
        ROm = _bmm_first(R, Om)
        return R + ROm / s + _bmm_first(ROm, Om) / (s * (s + 1.0))

    @staticmethod
    def trace_form(M, tr, *, first=False):
        """C(M) (p, p) with C_pq = tr(E_p^T E_q M), given tr = tr(M) (callers choose how it is
        summed): tr(M) I - M in 3D, for symmetric M."""
        ax = _Axes(first)
        return ax.expand(tr) * ax.eye(array_module(M, tr), 3, M) - M

    @staticmethod
    def inverse_spd(S, *, first=False):
        """Inverse of symmetric 3 x 3 blocks S and whether each is positive definite (leading minors
        > 0), by the adjugate (no factorization)."""
        ax, xp = _Axes(first), array_module(S)
        a, b, c = ax.get(S, 0, 0), ax.get(S, 0, 1), ax.get(S, 0, 2)
        e, f, i = ax.get(S, 1, 1), ax.get(S, 1, 2), ax.get(S, 2, 2)
        A00, A01, A02 = e * i - f * f, c * f - b * i, b * f - c * e
        A11, A12, A22 = a * i - c * c, b * c - a * f, a * e - b * b
        det = a * A00 + b * A01 + c * A02
        ok = (a > 0) & (A22 > 0) & (det > 0)
        inv = ax.matrix(xp, [[A00, A01, A02], [A01, A11, A12], [A02, A12, A22]])
        return inv / ax.expand(xp.where(ok, det, 1.0)), ok


#: The groups by dimension (read-only); ``GROUPS.get(d)`` for callers with a fallback for other d.
GROUPS = MappingProxyType({2: SO2, 3: SO3})


def _bmm_first(a, b):
    """Products of small matrices stored entries first: (p, q, ...) x (q, r, ...) -> (p, r, ...)."""
    out = a[:, 0, None] * b[None, 0]
    for k in range(1, a.shape[1]):
        out = out + a[:, k, None] * b[None, k]
    return out


def so(d: int) -> type[SO2] | type[SO3]:
    """The rotation group of dimension ``d``: :class:`SO2` or :class:`SO3` (ValueError otherwise).
    The one place where the package branches on the dimension."""
    group = GROUPS.get(int(d))
    if group is None:
        raise ValueError(f"rotations of dimension 2 or 3 only (SO(2), SO(3)), got d = {d}")
    return group
