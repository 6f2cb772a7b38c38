"""The centralized reference solver: Riemannian Newton steps with a sparse direct solve (host-side).

It gives f* for every gap the project reports (:func:`~mmpgo_jax.centralized_optimum`), so it must
converge to a tight gradient tolerance quickly on every benchmark file, ill-conditioned ones
included (parking-garage's rotation weights span 9 decades). This is the classical method of the
centralized solvers (SE-Sync's Riemannian trust region, GTSAM's Levenberg–Marquardt), on this
package's isotropic objective F (Eq. (3), SE-Sync's weights):

* Local coordinates per pose: R_i <- R_i Exp(omega_i) (omega_i in so(d), d(d-1)/2 numbers),
  t_i <- t_i + delta_i. The residuals r_e = (sqrt(kappa) (R_i R~ - R_j), sqrt(tau) (R_i t~ + t_i -
  t_j)) are linear in (R, t), so the Hessian of the pulled-back F at omega = delta = 0 is exactly
  JᵀJ + C, with J the residuals' Jacobian in these coordinates and C the block diagonal of the
  exponential's curvature, C_kl = sym <R_iᵀ ∂F/∂R_i, E_k E_l> (E_k the generators of so(d)); at a
  critical point it is the Riemannian Hessian, so full steps converge quadratically.
* Levenberg–Marquardt damping (H + lambda I) s = -g with the gain-ratio rule of Nielsen
  (Madsen, Nielsen and Tingleff, "Methods for non-linear least squares problems", 2004, §3.2):
  lambda shrinks towards 0 (pure Newton) when the quadratic model predicts the decrease well, and
  grows when a step fails or H + lambda I is not positive definite (its LDLᵀ has a negative pivot).
* In 3D, the first iteration (:attr:`NewtonConfig.gauss_newton_steps`) uses the Gauss–Newton matrix JᵀJ
  (positive semidefinite, what GTSAM's Levenberg–Marquardt uses throughout) in place of JᵀJ + C:
  far from the optimum C makes H indefinite and the Newton model poor (measured from the chordal
  start: sphere2500 1971.2 -> 1699.1 by a Newton step, -> 1687.40 by a Gauss–Newton step, f* =
  1687.006; smallGrid3D needed 6 factorizations for its first Newton step). Later iterations use
  the full H, which keeps the quadratic convergence (Gauss–Newton alone converges linearly on F:
  95 iterations on sphere2500).
* One sparse factorization per trial step, the matrix assembled directly in METIS's
  nested-dissection order of the poses: from :data:`PARDISO_NEWTON_MIN_SIZE` unknowns, when MKL's
  PARDISO is installed, its Cholesky with the symbolic analysis done once for the constant pattern
  (:class:`~mmpgo_jax._core.sparse.PardisoCholesky`; a failed Cholesky means H + lambda I is not
  positive definite), else SuperLU's LDLᵀ (:mod:`~mmpgo_jax._core.sparse`; a negative pivot
  means the same), except, in 3D, in the quadratic regime: once
  ||g|| has shrunk 4x since a successful Newton step, the next step solves with that step's
  factorization (a chord Newton step: one triangular solve, no factorization), kept when its gain
  ratio exceeds 1/2. The gauge is fixed by holding the anchor poses
  (:func:`~mmpgo_jax._core.gauge.anchor_set`: the fixed poses, else the first pose of each
  connected component): their rows are the identity and their steps zero.
* Problems of at most :data:`DENSE_NEWTON_MAX_SIZE` unknowns (33 poses in 3D, 66 in 2D) are
  factored densely instead (LAPACK's Cholesky, poses in their own order; the same entries summed
  into a dense matrix), without chord steps: there the sparse machinery's fixed costs and the
  extra iterations of chord steps exceed the work of a factorization. The gradient of a point is
  computed once, for the stopping rule, and reused by the step that follows.
* The iterations run with one OpenBLAS thread (``threadpoolctl``): their NumPy and SuperLU operations
  are small or memory-bound, and OpenBLAS's threads only added synchronization (measured under
  cProfile on a shared 2-core machine: sphere2500 2.2 s -> 1.2 s).

Everything runs in float64 NumPy on the host: no compilation. ``||grad F||`` (the stopping rule)
is the Riemannian gradient over the poses that are not fixed, as in :func:`~mmpgo_jax.solve`.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
from scipy.linalg import lapack

from .._core.blas import one_blas_thread
from .._core.gauge import FixedPoses, anchor_set
from .._core.pose_graph import HostPoses, PoseGraph, cost, euclidean_gradient, host_view
from .._core.sparse import PardisoCholesky, factor_symmetric, pardiso_available, pose_order
from .driver import RESULTS, History, Monitor, Termination, drive

__all__ = ["NewtonConfig", "newton_optimum"]


@dataclass(frozen=True)
class NewtonConfig:
    """Levenberg–Marquardt parameters (checked on construction).

    ``initial_damping``: lambda_0 (absolute, >= 0; grown automatically while H + lambda I is not
    positive definite or a step fails). ``max_retries``: rejected trial steps per iteration before
    giving up. ``gauss_newton_steps``: the first iterations use the Gauss–Newton matrix JᵀJ
    (positive semidefinite) instead of the Hessian JᵀJ + C, whose curvature term C makes it
    indefinite far from the optimum. ``reuse_contraction``: an iteration solves with the previous
    iteration's factorization (no new one) when that was a successful Newton step and ||g|| has
    since shrunk by at least this factor (the quadratic regime, where H barely changes); the reused
    step is kept when its gain ratio exceeds 1/2, else the matrix is factored anew; 0 never reuses.
    None (the defaults of both): 1 and 0.25 in 3D, 0 and 0 in 2D, where the Newton step from the
    chordal start is already good and the factorization cheap (its L + U holds 50–100 nonzeros
    per measurement on the 2D benchmark files, 150–700 on the 3D ones), so that a Gauss–Newton
    step or a chord step only adds iterations (measured on MIT, intel, M3500, kitti_00). Problems
    small enough for the dense factorization (:data:`DENSE_NEWTON_MAX_SIZE`) never reuse one: it
    costs less than the rest of an iteration, and chord steps converge only linearly (measured:
    tinyGrid3D 7 -> 5 iterations, the graphs of smallGrid3D's first 20 and 33 poses 7 -> 5 and
    13 -> 7).
    """

    initial_damping: float = 0.0
    max_retries: int = 60
    gauss_newton_steps: int | None = None
    reuse_contraction: float | None = None

    def __post_init__(self):
        if not (np.isfinite(self.initial_damping) and self.initial_damping >= 0):
            raise ValueError(f"initial_damping must be a finite number >= 0, got {self.initial_damping!r}")
        if isinstance(self.max_retries, bool) or not isinstance(self.max_retries, int) or self.max_retries < 1:
            raise ValueError(f"max_retries must be an integer >= 1, got {self.max_retries!r}")
        steps = self.gauss_newton_steps
        if steps is not None and (isinstance(steps, bool) or not isinstance(steps, int) or steps < 0):
            raise ValueError(f"gauss_newton_steps must be None or an integer >= 0, got {steps!r}")
        if self.reuse_contraction is not None and not (0.0 <= self.reuse_contraction < 1.0):
            raise ValueError(f"reuse_contraction must be None or in [0, 1), got {self.reuse_contraction!r}")

    def resolved(self, d: int, dense: bool = False) -> NewtonConfig:
        """This configuration with the defaults (None) of dimension d filled in (``dense``: the
        problem is factored densely)."""
        return replace(self, gauss_newton_steps=(1 if d == 3 else 0) if self.gauss_newton_steps is None
                       else self.gauss_newton_steps,
                       reuse_contraction=(0.25 if d == 3 and not dense else 0.0) if self.reuse_contraction is None
                       else self.reuse_contraction)


#: Unknowns (6 per pose in 3D, 3 in 2D) up to which the Newton steps are factored densely (LAPACK's
#: Cholesky, rows in pose order) instead of by a sparse factorization: on graphs this small the
#: sparse machinery's fixed costs exceed the work (measured in benchmarks/centralized.md).
DENSE_NEWTON_MAX_SIZE = 200

#: Unknowns (6 per pose in 3D, 3 in 2D) from which the Newton steps are factored by PARDISO
#: (:class:`~mmpgo_jax._core.sparse.PardisoCholesky`, when installed) instead of SuperLU: measured
#: crossover in benchmarks/centralized.md.
PARDISO_NEWTON_MIN_SIZE = 5000


@functools.cache
def _generators(d: int) -> np.ndarray:
    """Basis E_k of so(d), (p, d, d), p = d(d-1)/2 (the hat map for d = 3); read-only, built once."""
    rows, cols = np.triu_indices(d, 1)
    E = np.zeros((rows.size, d, d))
    k = np.arange(rows.size)
    E[k, cols, rows] = 1.0
    E[k, rows, cols] = -1.0
    if d == 3:  # omega = (x, y, z): hat(omega) = [[0, -z, y], [z, 0, -x], [-y, x, 0]]
        E = E[[2, 1, 0]] * np.array([1.0, -1.0, 1.0])[:, None, None]
    E.setflags(write=False)
    return E


def _exp(omega: np.ndarray, d: int) -> np.ndarray:
    """Exp of hat(omega) for each pose: (n, p) -> (n, d, d) (Rodrigues for d = 3)."""
    if d == 2:
        c, s = np.cos(omega[:, 0]), np.sin(omega[:, 0])
        return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    theta = np.linalg.norm(omega, axis=1)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(theta) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(theta)) / safe**2)
    W = (omega @ _generators(3).reshape(3, 9)).reshape(-1, 3, 3)
    return np.eye(3) + a[:, None, None] * W + b[:, None, None] * (W @ W)


class _Gradient(NamedTuple):
    """F's gradient at a point: ``g`` in local coordinates (N,), A_i = R_iᵀ ∂F/∂R_i (n, d, d),
    ``norm`` = ||grad F|| over the poses that are not fixed."""

    g: np.ndarray
    A: np.ndarray
    norm: float


class _Problem:
    """The host-side data of one centralized solve: the graph in float64, the dof layout (in
    nested-dissection order for the sparse factorizations), the anchors."""

    def __init__(self, graph: PoseGraph, fixed: FixedPoses | None, dense: bool | None = None):
        self.graph = host_view(graph)
        g = self.graph
        n, d = g.num_poses, g.R.shape[-1]
        self.n, self.d = n, d
        self.p = d * (d - 1) // 2
        self.b = self.p + d  # unknowns per pose: omega, then delta
        self.dense = self.b * n <= DENSE_NEWTON_MAX_SIZE if dense is None else bool(dense)
        self.E = _generators(d)
        self.EE = self.E[:, None] @ self.E[None]  # (p, p, d, d): E_k E_l
        # each pose's place in the unknowns: nested-dissection order for the sparse factorizations
        self.rank = np.arange(n) if self.dense else np.argsort(pose_order(n, g.i, g.j))
        self.index = self.b * self.rank[:, None] + np.arange(self.b)  # (n, b) rows of each pose
        held = anchor_set(graph, fixed).index
        self.held = np.zeros(n, dtype=bool)
        self.held[held] = True
        self.free_poses = np.ones(n, dtype=bool) if fixed is None else ~fixed.mask(n)
        self.sqrt_kappa = np.sqrt(g.kappa)
        self.sqrt_tau = np.sqrt(g.tau)
        self._pattern()

    def cost(self, R, t) -> float:
        """f = 2F at (R, t)."""
        return float(cost(self.graph, HostPoses(R, t)))

    def gradient(self, R, t) -> _Gradient:
        """F's gradient at (R, t): in local coordinates (anchors' entries zero), A_i = R_iᵀ ∂F/∂R_i
        (for the curvature) and ||grad F|| over the poses that are not fixed (Riemannian: the
        rotation part of pose i is R_i skew(A_i), the translation part ∂F/∂t_i)."""
        n, d = self.n, self.d
        G = euclidean_gradient(self.graph, HostPoses(R, t))
        A = np.swapaxes(R, 1, 2) @ G.R
        skew = A - np.swapaxes(A, 1, 2)  # 2 skew(A_i)
        keep = self.free_poses
        norm = float(np.sqrt(0.25 * np.sum(skew[keep] ** 2) + np.sum(G.t[keep] ** 2)))
        local = np.concatenate([A.reshape(n, d * d) @ self.E.reshape(self.p, d * d).T, G.t], 1)  # <A_i, E_k>
        local[self.held] = 0.0
        grad = np.empty(self.b * n)
        grad[self.index] = local
        return _Gradient(grad, A, norm)

    def jacobians(self, R):
        """The residuals' Jacobians J_i, J_j (m, q, b) in local coordinates, q = d^2 + d (the
        residuals, weighted, are (sqrt(kappa) (R_i R~ - R_j), sqrt(tau) (R_i t~ + t_i - t_j)))."""
        g, d, p = self.graph, self.d, self.p
        m = g.i.shape[0]
        Ri, Rj = R[g.i], R[g.j]
        sk, st = self.sqrt_kappa[:, None], self.sqrt_tau[:, None]
        # matmul, not einsum: NumPy's einsum is several times slower on these small operands
        RiE = Ri[:, None] @ self.E  # (m, p, d, d): R_i E_k
        Ji = np.zeros((m, d * d + d, self.b))
        Jj = np.zeros_like(Ji)
        Ji[:, : d * d, :p] = sk[:, :, None] * (RiE @ g.R[:, None]).reshape(m, p, d * d).transpose(0, 2, 1)
        Ji[:, d * d :, :p] = st[:, :, None] * (RiE @ g.t[:, None, :, None])[..., 0].transpose(0, 2, 1)
        Jj[:, : d * d, :p] = -sk[:, :, None] * (Rj[:, None] @ self.E).reshape(m, p, d * d).transpose(0, 2, 1)
        eye = np.eye(d)
        Ji[:, d * d :, p:] = st[:, :, None] * eye
        Jj[:, d * d :, p:] = -st[:, :, None] * eye
        return Ji, Jj

    def _pattern(self):
        """Where every entry :meth:`hessian_parts` assembles goes in the matrix's values (the
        pose-pair blocks of each edge, then the anchors' unit diagonal; the curvature blocks), so
        that one bincount per part sums the duplicates: the CSC data of the Hessian's constant
        sparsity, or the row-major entries of a dense matrix."""
        g, n, b, p = self.graph, self.n, self.b, self.p
        rank = self.rank
        held = np.zeros(n, dtype=bool)  # per pose rank
        held[rank[self.held]] = True
        si, sj, diag_poses = rank[g.i], rank[g.j], rank
        # block instances (row pose, column pose), in the order of hessian_parts' values:
        # (i, i), (j, j), (i, j), (j, i) for every edge, then (k, k) for every pose (curvature)
        brow = np.concatenate([si, sj, si, sj, diag_poses])
        bcol = np.concatenate([si, sj, sj, si, diag_poses])
        keep = ~(held[brow] | held[bcol])
        local = np.arange(b)
        held_cols = (b * np.flatnonzero(held)[:, None] + local).reshape(-1)
        free = np.flatnonzero(~held)
        # entry [instance, row a, column c] of a block sits at start[instance, c] + a * row_stride
        if self.dense:
            N = b * n
            start = (b * N * brow[keep])[:, None] + b * bcol[keep][:, None] + local
            row_stride, self._size = N, N * N
            anchor_slots = held_cols * (N + 1)
            self.free_diagonal = ((b * free[:, None] + local) * (N + 1)).reshape(-1)
        else:
            start, anchor_slots = self._sparse_pattern(brow[keep], bcol[keep], held, held_cols, free)
            row_stride, self._size = 1, self._indices.size
        num_pairs = 4 * si.size
        kp, kc = keep[:num_pairs], keep[num_pairs:]
        kept_pairs = int(kp.sum())  # start holds the kept pair blocks, then the kept curvature blocks
        self._keep_pairs = np.repeat(kp, b * b)
        self._slot_pairs = np.concatenate([(start[:kept_pairs][:, None, :] + row_stride * local[:, None]).reshape(-1),
                                           anchor_slots])
        self._keep_curvature = np.repeat(kc, p * p)
        self._slot_curvature = (start[kept_pairs:][:, None, :p] + row_stride * local[:p, None]).reshape(-1)
        self._anchor_ones = np.ones(held_cols.size)
        self.held_rows = np.zeros(b * n, dtype=bool)
        self.held_rows[held_cols] = True

    def _sparse_pattern(self, brow, bcol, held, held_cols, free):
        """The Hessian's sparsity (constant), built per pose block (no sort of the entries): CSC
        indices and indptr; returns each kept block instance's column starts (instance, b) and the
        anchors' diagonal slots, and sets :attr:`free_diagonal`."""
        n, b = self.n, self.b
        blocks, inverse = np.unique(bcol * n + brow, return_inverse=True)  # CSC order of blocks
        ucol, urow = blocks // n, blocks % n
        position = np.arange(blocks.size) - np.searchsorted(ucol, ucol)  # among the blocks of its column
        per_column = np.repeat(np.where(held, 1, b * np.bincount(ucol, minlength=n)), b)
        indptr = np.concatenate([[0], np.cumsum(per_column)]).astype(np.int64)
        local = np.arange(b)
        start = indptr[ucol[:, None] * b + local] + b * position[:, None]  # (block, column in block)
        indices = np.empty(int(indptr[-1]), dtype=np.int64)
        indices[start[:, :, None] + local] = (b * urow)[:, None, None] + local  # [block, column, row]
        indices[indptr[held_cols]] = held_cols
        self._indices, self._indptr = indices, indptr
        self.free_diagonal = (start[np.searchsorted(blocks, free * n + free)] + local).reshape(-1)  # slots
        return start[inverse.reshape(-1)], indptr[held_cols]

    def upper_triangle(self) -> tuple[np.ndarray, sp.csr_matrix]:
        """The sparse pattern's upper triangle as CSR (for PARDISO) and, for each of its entries, its
        slot in the CSC data: by symmetry, the CSC entries with row >= column, read as CSR."""
        N, indices, indptr = self.b * self.n, self._indices, self._indptr
        column = np.repeat(np.arange(N), np.diff(indptr))
        entries = np.flatnonzero(indices >= column)
        row_ptr = np.concatenate([[0], np.cumsum(np.bincount(column[entries], minlength=N))])
        return entries, sp.csr_matrix((np.zeros(entries.size), indices[entries], row_ptr), shape=(N, N))

    def matrix(self, data: np.ndarray) -> sp.csc_matrix | np.ndarray:
        """The N x N matrix with values ``data``: sparse CSC with the Hessian's pattern, or dense."""
        N = self.b * self.n
        if self.dense:
            return data.reshape(N, N)
        return sp.csc_matrix((data, self._indices, self._indptr), shape=(N, N))

    def linearize(self, R, t):
        """Gradient g (N,) and the Hessian's values (:meth:`matrix`) of the pulled-back F at
        (R, t), N = b n; the anchors' rows and columns are those of the identity, g = 0 there."""
        gradient = self.gradient(R, t)
        gauss_newton, curvature = self.hessian_parts(R, gradient.A)
        return gradient.g, gauss_newton + curvature

    def hessian_parts(self, R, A):
        """The Hessian's two parts at rotations R (values, :meth:`matrix`), given A_i = R_iᵀ ∂F/∂R_i
        (:meth:`gradient`): the Gauss–Newton matrix JᵀJ (with the anchors' unit diagonal; positive
        semidefinite) and the exponential's curvature C (block diagonal, zero at the anchors),
        C_kl = sym <A_i, E_k E_l>; the Hessian is their sum."""
        n, p = self.n, self.p
        Ji, Jj = self.jacobians(R)
        JiT, JjT = np.swapaxes(Ji, 1, 2), np.swapaxes(Jj, 1, 2)
        Hij = JiT @ Jj
        C = (A.reshape(n, -1) @ self.EE.reshape(p * p, -1).T).reshape(n, p, p)
        C = 0.5 * (C + np.swapaxes(C, 1, 2))
        pairs = np.concatenate([(JiT @ Ji).reshape(-1), (JjT @ Jj).reshape(-1), Hij.reshape(-1),
                                np.swapaxes(Hij, 1, 2).reshape(-1)])
        gauss_newton = np.bincount(self._slot_pairs, np.concatenate([pairs[self._keep_pairs], self._anchor_ones]),
                                   minlength=self._size)
        curvature = np.bincount(self._slot_curvature, C.reshape(-1)[self._keep_curvature], minlength=self._size)
        return gauss_newton, curvature

    def retract(self, R, t, step: np.ndarray):
        """(R_i Exp(omega_i), t_i + delta_i) for the step (in nested-dissection order)."""
        s = step[self.index]  # (n, b)
        return R @ _exp(s[:, : self.p], self.d), t + s[:, self.p :]


class _DenseCholesky:
    """LAPACK's Cholesky factor of a small dense matrix (potrf / potrs called directly: SciPy's
    wrappers' checks cost more than the factorization at this size)."""

    def __init__(self, lower: np.ndarray):
        self.lower = lower

    @staticmethod
    def factor(H: np.ndarray) -> _DenseCholesky | None:
        """The factor of H, or None when H is not positive definite."""
        lower, info = lapack.dpotrf(H, lower=1, clean=0)
        return _DenseCholesky(lower) if info == 0 else None

    def solve(self, g: np.ndarray) -> np.ndarray:
        return lapack.dpotrs(self.lower, g, lower=1)[0]


class _LM:
    """One Levenberg–Marquardt iteration per call (the accepted step), for :func:`drive`."""

    def __init__(self, problem: _Problem, R, t, config: NewtonConfig):
        self.pb = problem
        self.R, self.t = R, t
        self.f = problem.cost(R, t)  # 2F
        self._gradient = None  # at (R, t), once computed
        self.lam = config.initial_damping
        self.nu = 2.0
        self.config = config.resolved(problem.d, problem.dense)
        self.factorizations = 0
        self.iteration = 0
        self.reuse = None  # the last successful Newton step's factorization
        self.g_norm = np.inf  # ||g|| at the previous iteration
        self.cholesky = None
        if not problem.dense and problem.b * problem.n >= PARDISO_NEWTON_MIN_SIZE and pardiso_available():
            self.upper_entries, upper = problem.upper_triangle()
            self.cholesky = PardisoCholesky(upper)

    def gradient(self) -> _Gradient:
        """F's gradient at the current point (computed once per point: the iteration that follows
        reuses the one the stopping rule needed)."""
        if self._gradient is None:
            self._gradient = self.pb.gradient(self.R, self.t)
        return self._gradient

    def _accept(self, R, t, f) -> None:
        self.R, self.t, self.f, self._gradient = R, t, f, None

    def _factor(self, data: np.ndarray):
        """A factorization of the matrix with values ``data`` (an object with ``solve``), or None
        when it is not positive definite."""
        self.factorizations += 1
        if self.pb.dense:
            return _DenseCholesky.factor(self.pb.matrix(data))
        if self.cholesky is not None:
            return self.cholesky if self.cholesky.factor(data[self.upper_entries]) else None
        factor = factor_symmetric(self.pb.matrix(data), "ordered")
        return None if factor is None or factor.negative_pivots() != 0 else factor

    def close(self) -> None:
        if self.cholesky is not None:
            self.cholesky.close()

    def _gain(self, g, s, H):
        """The retraction of the step s, its 2F, and the gain ratio: F's decrease over the decrease
        predicted by the quadratic model g, H."""
        predicted = -(np.sum(g * s) + 0.5 * np.sum(s * (H @ s)))
        R, t = self.pb.retract(self.R, self.t, s)
        f = self.pb.cost(R, t)
        actual = 0.5 * (self.f - f)
        tiny = 1e-13 * max(abs(self.f), 1e-300)  # below the rounding of F: trust the model
        rho = 1.0 if predicted <= tiny and actual >= -tiny else actual / predicted if predicted > 0 else -1.0
        return R, t, f, rho

    def step(self) -> None:
        pb, cfg = self.pb, self.config
        gradient = self.gradient()
        g = gradient.g
        gauss_newton, curvature = pb.hessian_parts(self.R, gradient.A)
        newton = self.iteration >= cfg.gauss_newton_steps
        self.iteration += 1
        data = gauss_newton + curvature if newton else gauss_newton
        H = pb.matrix(data)
        g_norm = float(np.sqrt(np.sum(g * g)))
        reuse = self.reuse is not None and newton and g_norm <= cfg.reuse_contraction * self.g_norm
        self.g_norm = g_norm
        if reuse:  # quadratic regime: the previous factorization of H + lambda I still fits
            R, t, f, rho = self._gain(g, -self.reuse.solve(g), H)
            if rho > 0.5:
                self._accept(R, t, f)
                return
        self.reuse = None
        scale = float(np.max(np.abs(data[pb.free_diagonal]), initial=1.0))
        for _ in range(cfg.max_retries):
            damped = data.copy()
            damped[pb.free_diagonal] += self.lam
            factor = self._factor(damped)
            if factor is None:  # not positive definite: more damping
                self.lam = max(4.0 * self.lam, 1e-10 * scale)
                continue
            R, t, f, rho = self._gain(g, -factor.solve(g), H)
            if rho > 1e-4:
                self._accept(R, t, f)
                self.lam *= max(0.1, 1.0 - (2.0 * rho - 1.0) ** 3)
                self.nu = 2.0
                if newton and rho > 0.5 and cfg.reuse_contraction > 0:
                    self.reuse = factor
                return
            self.lam = max(self.lam * self.nu, 1e-10 * scale)
            self.nu *= 2.0
        # no acceptable step: the point is stationary to rounding; keep it (the history shows it)


def newton_optimum(
    graph: PoseGraph,
    R0: np.ndarray,
    t0: np.ndarray,
    termination: Termination,
    *,
    fixed: FixedPoses | None = None,
    config: NewtonConfig | None = None,
    callback: Callable[[int, np.ndarray], bool | None] | None = None,
    monitor: Monitor | None = None,
):
    """Levenberg–Marquardt / Newton iterations from (R0, t0) (host float64 arrays; the fixed poses
    already at their values) until ``termination`` (its rules are checked after every iteration).

    Returns (R, t, history, result, stats) with stats = build_seconds (orderings, anchors),
    solve_seconds (the iterations) and factorizations (accepted and rejected trial steps).
    """
    config = config or NewtonConfig()
    monitor = monitor or Monitor()
    t_build = time.perf_counter()
    problem = _Problem(graph, fixed)
    lm = _LM(problem, np.array(R0, dtype=np.float64), np.array(t0, dtype=np.float64), config)
    start = (np.float64(lm.f), np.float64(lm.gradient().norm), np.zeros(1, bool))
    build_seconds = time.perf_counter() - t_build

    def host_chunk(state, length, limit):
        def chunk(lm, limit):
            lm.step()
            record = (np.array([lm.f]), np.array([lm.gradient().norm]), np.zeros((1, 1), bool))
            return lm, record

        return chunk

    one_by_one = Termination(termination.iterations, 1, termination.grad_tol, termination.f_target,
                             termination.rel_decrease_tol)
    # one BLAS thread: the iterations are small or memory-bound NumPy / SuperLU operations, where
    # OpenBLAS's threads only add synchronization (measured: 1.8x faster on sphere2500, 2-core machine)
    try:
        with one_blas_thread():
            out = drive(host_chunk, lm, start, one_by_one, fetch=lambda rec: rec, callback=callback,
                        monitor=monitor)
    finally:
        lm.close()
    stats = dict(build_seconds=build_seconds, solve_seconds=out.solve_seconds + out.compile_seconds,
                 factorizations=lm.factorizations)
    history = History(out.history.f, out.history.grad_norm, out.history.restarts)
    result: RESULTS = out.result
    return lm.R, lm.t, history, result, stats
