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
* Cost, gradient and Hessian come from one layout of the weighted residuals (d x (d + 1) per edge,
  :class:`_Problem`), a few whole-array operations per quantity: on tiny graphs the solve's time
  is the count of NumPy calls (tinyGrid3D, 9 poses: about 1 ms in all, 5 iterations).
* The sparse problems run with one OpenBLAS thread (``threadpoolctl``), their start included: their
  NumPy and SuperLU operations are small or memory-bound, OpenBLAS's threads only added
  synchronization (measured under cProfile on a shared 2-core machine: sphere2500 2.2 s -> 1.2 s),
  and threads woken by a large reduction kept spinning while PARDISO's threads factored (intel 3x
  slower factorizations).

Everything runs in float64 NumPy on the host: no compilation. ``||grad F||`` (the stopping rule)
is the Riemannian gradient over the poses that are not fixed, as in :func:`~mmpgo_jax.solve`.
"""

from __future__ import annotations

import contextlib
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
from .._core.lie import SO2, SO3, so
from .._core.pose_graph import PoseGraph, host_view
from .._core.sparse import PardisoCholesky, factor_symmetric, pardiso_available, pose_order
from .._core.validate import check_count, check_real
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
    13 -> 7). ``damping_decrease``: the least factor lambda shrinks by after a successful step
    (Nielsen's rule shrinks it by max(this, 1 - (2 rho - 1)^3)); Nielsen's own value is 1/3, the
    default 0.1 returns to pure Newton steps sooner from the chordal start; far from a stage optimum
    of the GNC start 1/3 needs fewer factorizations (M3500 with 30 % wrong inter-robot closures:
    1641 against 2892, the H + lambda I of the shrunk lambda being indefinite less often).
    """

    initial_damping: float = 0.0
    max_retries: int = 60
    gauss_newton_steps: int | None = None
    reuse_contraction: float | None = None
    damping_decrease: float = 0.1

    def __post_init__(self):
        owner = "NewtonConfig"
        check_real(owner, "initial_damping", self.initial_damping, 0.0, scalar=True)
        check_count(owner, "max_retries", self.max_retries, 1, scalar=True)
        check_count(owner, "gauss_newton_steps", self.gauss_newton_steps, 0, optional=True, scalar=True)
        check_real(owner, "reuse_contraction", self.reuse_contraction, 0.0, 1.0, high_open=True, optional=True,
                   scalar=True)
        check_real(owner, "damping_decrease", self.damping_decrease, 0.0, 1.0, low_open=True, high_open=True,
                   scalar=True)

    @functools.lru_cache(maxsize=64)  # noqa: B019 (frozen and hashable: a few configurations per process)
    def resolved(self, d: int, dense: bool = False) -> NewtonConfig:
        """This configuration with the defaults (None) of dimension d filled in (``dense``: the
        problem is factored densely)."""
        steps, contraction = _NEWTON_DEFAULTS[so(d)]
        return replace(self, gauss_newton_steps=steps if self.gauss_newton_steps is None else self.gauss_newton_steps,
                       reuse_contraction=(0.0 if dense else contraction) if self.reuse_contraction is None
                       else self.reuse_contraction)


#: The defaults of :class:`NewtonConfig` per group: (gauss_newton_steps, reuse_contraction), measured
#: (see its docstring).
_NEWTON_DEFAULTS = {SO2: (0, 0.0), SO3: (1, 0.25)}


#: Unknowns (6 per pose in 3D, 3 in 2D) up to which the Newton steps are factored densely (LAPACK's
#: Cholesky, rows in pose order) instead of by a sparse factorization: on graphs this small the
#: sparse machinery's fixed costs exceed the work (measured in benchmarks/centralized.md).
DENSE_NEWTON_MAX_SIZE = 200

#: Unknowns (6 per pose in 3D, 3 in 2D) from which the Newton steps are factored by PARDISO
#: (:class:`~mmpgo_jax._core.sparse.PardisoCholesky`, when installed) instead of SuperLU: measured
#: crossover in benchmarks/centralized.md.
PARDISO_NEWTON_MIN_SIZE = 5000


@functools.cache
def _local_constants(d: int):
    """The constants of dimension d that the local coordinates need (read-only, built once): the
    generators E_k; [E_k, 0] (pose j's rotation Jacobians); the map of A_i (flattened) to
    <A_i, sym(E_k E_l)> (the curvature); the squared-norm weights of the local gradient (1/2 per
    rotation coordinate, see :meth:`_Problem.linearization`); and the diagonal of the translation
    rows in the residuals' d x (d + 1) layout, as (row, entry) index arrays."""
    E = so(d).generators()
    p = E.shape[0]
    Ej = np.concatenate([E, np.zeros((p, d, 1))], 2)
    EE = E[:, None] @ E[None]  # (p, p, d, d): E_k E_l
    EE = 0.5 * (EE + np.swapaxes(EE, 0, 1))
    curvature_map = np.ascontiguousarray(EE.reshape(p * p, d * d).T)  # (d^2, p^2)
    weights = np.concatenate([np.full(p, 0.5), np.ones(d)])
    last_column = (np.arange(d), np.arange(d) * (d + 1) + d)
    for array in (Ej, curvature_map, weights, *last_column):
        array.setflags(write=False)
    return E, Ej, curvature_map, weights, last_column


class _Point(NamedTuple):
    """An iterate: poses (R, t), the rotations at the edges' ends (R_i of every edge, then R_j), the
    weighted residuals r (m, d, d + 1) (:meth:`_Problem.evaluate`) and f = 2F = sum of r²."""

    R: np.ndarray
    t: np.ndarray
    R_ends: np.ndarray
    r: np.ndarray
    f: float


class _Gradient(NamedTuple):
    """F's gradient at a point: ``g`` in local coordinates (N,), ``norm`` = ||grad F|| over the
    poses that are not fixed."""

    g: np.ndarray
    norm: float


class _Linearization(NamedTuple):
    """A point, the residuals' transposed Jacobians J (m, 2b, d (d + 1)) there, and F's gradient."""

    point: _Point
    J: np.ndarray
    gradient: _Gradient


class _Problem:
    """The host-side data of one centralized solve: the graph in float64, the dof layout (in
    nested-dissection order for the sparse factorizations), the anchors, and the constant parts of
    the residuals and their Jacobians.

    The residuals of an edge, weighted, are laid out as a d x (d + 1) array r_e = R_i K_e +
    [-sqrt(kappa) R_j, sqrt(tau) (t_i - t_j)] with K_e = [sqrt(kappa) R~, sqrt(tau) t~]: the
    rotation residual sqrt(kappa) (R_i R~ - R_j) in the first d columns, the translation residual
    sqrt(tau) (R_i t~ + t_i - t_j) in the last, so that f = 2F = sum of r². Along omega_k of pose i
    they change by R_i E_k K_e, along omega_k of pose j by R_j [-sqrt(kappa) E_k, 0], along the
    translations by ±sqrt(tau) in the last column. Cost, gradient and Hessian are all computed
    from this layout, a few whole-array operations each (tiny graphs pay per operation)."""

    def __init__(self, graph: PoseGraph, fixed: FixedPoses | None, dense: bool | None = None,
                 coupled: np.ndarray | None = None):
        self.graph = host_view(graph)
        self.coupled = None if coupled is None else np.asarray(coupled, dtype=bool)
        g = self.graph
        n, d = g.num_poses, g.R.shape[-1]
        self.n, self.d = n, d
        self.group = so(d)
        self.p = self.group.tangent_dim
        self.b = self.p + d  # unknowns per pose: omega, then delta
        self.dense = self.b * n <= DENSE_NEWTON_MAX_SIZE if dense is None else bool(dense)
        # each pose's place in the unknowns: nested-dissection order for the sparse factorizations
        coupled = slice(None) if self.coupled is None else self.coupled
        self.rank = np.arange(n) if self.dense else np.argsort(pose_order(n, g.i[coupled], g.j[coupled]))
        self.index = self.b * self.rank[:, None] + np.arange(self.b)  # (n, b) rows of each pose
        held = anchor_set(g, fixed).index  # (the host view: no device array read again)
        self.held = np.zeros(n, dtype=bool)
        self.held[held] = True
        self.free_poses = None if fixed is None else ~fixed.mask(n)  # None: all
        self._residual_constants()
        self._pattern()

    def _residual_constants(self):
        """The constant parts of the residuals and their Jacobians (see the class docstring)."""
        g, d = self.graph, self.d
        m, n, q = g.i.shape[0], self.n, d * (d + 1)
        self._m = m
        sk, st = np.sqrt(g.kappa), np.sqrt(g.tau)
        E, Ej, self._curvature_map, self._norm_weights, last_column = _local_constants(d)
        self._ends = np.concatenate([g.i, g.j])  # each edge's tail, then each edge's head
        self._K = np.concatenate([sk[:, None, None] * g.R, (st[:, None] * g.t)[:, :, None]], 2)  # (m, d, d+1)
        self._KT = np.ascontiguousarray(np.swapaxes(self._K, 1, 2))
        self._minus_sk = -sk[:, None, None]
        self._st = st[:, None]
        # the rotation rows of the transposed Jacobians are R_end K_end: E_k K_e for the tails,
        # -sqrt(kappa) [E_k, 0] for the heads; the translation rows are constant
        self._K_ends = np.concatenate([E @ self._K[:, None], self._minus_sk[:, None] * Ej])  # (2m, p, d, d+1)
        self._T_tail = np.zeros((m, d, q))
        self._T_tail[:, last_column[0], last_column[1]] = st[:, None]
        self._T_head = -self._T_tail
        # where each edge's terms go: its ends' local unknowns (gradient), its ends' d x d blocks (A)
        b = self.b
        self._end_slots = (b * self._ends.reshape(2, m).T[:, :, None] + np.arange(b)).reshape(-1)
        self._A_slots = (d * d * self._ends[:, None] + np.arange(d * d)).reshape(-1)
        self._local_size, self._A_size = n * b, n * d * d

    def evaluate(self, R, t) -> _Point:
        """The point (R, t) with its weighted residuals and f = 2F."""
        m, d = self._m, self.d
        R_ends, t_ends = R[self._ends], t[self._ends]
        r = R_ends[:m] @ self._K
        r[..., :d] += self._minus_sk * R_ends[m:]
        r[..., d] += self._st * (t_ends[:m] - t_ends[m:])
        return _Point(R, t, R_ends, r, float(np.vdot(r, r)))

    def cost(self, R, t) -> float:
        """f = 2F at (R, t)."""
        return self.evaluate(R, t).f

    def linearization(self, x: _Point) -> _Linearization:
        """The Jacobians and F's gradient at the point x: in local coordinates g = Jᵀ r (anchors'
        entries zero), and ||grad F|| over the poses that are not fixed: with A_i = R_iᵀ ∂F/∂R_i,
        g's rotation entries are <A_i, E_k>, and the Riemannian gradient's rotation part
        R_i skew(A_i) has squared norm ||skew(A_i)||² = ½ Σ_k <A_i, E_k>² (the E_k are orthogonal,
        of squared norm 2); its translation parts are ∂F/∂t_i = g_i's last d entries."""
        n, p, b, m = self.n, self.p, self.b, self._m
        rotation = (x.R_ends[:, None] @ self._K_ends).reshape(2, m, p, -1)
        J = np.concatenate([rotation[0], self._T_tail, rotation[1], self._T_head], 1)
        local = np.bincount(self._end_slots, (J @ x.r.reshape(m, -1, 1)).reshape(-1),
                            minlength=self._local_size).reshape(n, b)
        squares = (local * local) @ self._norm_weights
        norm = float(np.sqrt(squares.sum() if self.free_poses is None else squares[self.free_poses].sum()))
        local[self.held] = 0.0
        if self.dense:
            grad = local.reshape(-1)
        else:
            grad = np.empty(self.b * n)
            grad[self.index] = local
        return _Linearization(x, J, _Gradient(grad, norm))

    def curvature(self, x: _Point) -> np.ndarray:
        """The exponential's curvature blocks at x, C_i,kl = <A_i, sym(E_k E_l)> (n, p^2): the
        second derivative of R_i Exp(omega), paired with A_i = R_iᵀ ∂F/∂R_i, summed from the
        residuals: R_iᵀ r_e K_eᵀ over the edges pose i starts, -sqrt(kappa) R_jᵀ r_e[:, :d] over
        those it ends."""
        d = self.d
        ends_terms = np.swapaxes(x.R_ends, 1, 2) @ np.concatenate([x.r @ self._KT, self._minus_sk * x.r[..., :d]])
        A = np.bincount(self._A_slots, ends_terms.reshape(-1), minlength=self._A_size)
        return A.reshape(self.n, d * d) @ self._curvature_map

    def gradient(self, R, t) -> _Gradient:
        """F's gradient at (R, t) (:meth:`linearization`)."""
        return self.linearization(self.evaluate(R, t)).gradient

    def _pattern(self):
        """Where every entry :meth:`hessian` assembles goes in the matrix's values: for each
        edge, its (2b, 2b) block JᵀJ (pose-pair blocks (i, i), (i, j), (j, i), (j, j)); for each
        pose, its curvature block; plus the anchors' unit diagonal. One bincount per part then sums
        the duplicates into the CSC data of the Hessian's constant sparsity, or the row-major
        entries of a dense matrix. Entries of held poses go to one extra slot (dropped)."""
        if self.dense:
            self._dense_pattern()
            return
        g, n, b, p = self.graph, self.n, self.b, self.p
        m = g.i.shape[0]
        rank = self.rank
        held = np.zeros(n, dtype=bool)  # per pose rank
        held[rank[self.held]] = True
        si, sj, diag_poses = rank[g.i], rank[g.j], rank
        # block instances (row pose, column pose): (i, i), (j, j), (i, j), (j, i) for every edge,
        # then (k, k) for every pose (curvature)
        brow = np.concatenate([si, sj, si, sj, diag_poses])
        bcol = np.concatenate([si, sj, sj, si, diag_poses])
        keep = ~(held[brow] | held[bcol])
        if self.coupled is not None:  # the other edges keep their diagonal blocks only: no fill
            keep[2 * m : 4 * m] &= np.tile(self.coupled, 2)
        local = np.arange(b)
        held_cols = (b * np.flatnonzero(held)[:, None] + local).reshape(-1)
        free = np.flatnonzero(~held)
        # entry [instance, row a, column c] of a block sits at start[instance, c] + a (CSC)
        start, self._anchor_slots = self._sparse_pattern(brow[keep], bcol[keep], held, held_cols, free)
        self._size = self._indices.size
        slots = np.full((keep.size, b, b), self._size)  # the extra slot for what is dropped
        slots[keep] = start[:, None, :] + local[:, None]
        pairs = slots[: 4 * m].reshape(4, m, b, b)
        edge_slots = np.empty((m, 2 * b, 2 * b), dtype=np.int64)  # [edge, row, column] of JᵀJ
        edge_slots[:, :b, :b], edge_slots[:, b:, b:] = pairs[0], pairs[1]
        edge_slots[:, :b, b:], edge_slots[:, b:, :b] = pairs[2], pairs[3]
        self._slot_pairs = edge_slots.reshape(-1)
        self._slot_curvature = slots[4 * m :, :p, :p].reshape(-1)
        self.held_rows = np.zeros(b * n, dtype=bool)
        self.held_rows[held_cols] = True

    def _dense_pattern(self):
        """:meth:`_pattern` for a dense matrix in pose order: entry (row, column) at N row + column."""
        g, n, b, p = self.graph, self.n, self.b, self.p
        N = b * n
        self._size = N * N
        self.held_rows = np.repeat(self.held, b)
        unknowns = (b * np.stack([g.i, g.j], 1)[:, :, None] + np.arange(b)).reshape(-1, 2 * b)  # of each edge
        slots = N * unknowns[:, :, None] + unknowns[:, None, :]
        dropped = self.held_rows[unknowns]
        slots[dropped[:, :, None] | dropped[:, None, :]] = self._size
        if self.coupled is not None:
            slots[~self.coupled, :b, b:] = slots[~self.coupled, b:, :b] = self._size
        self._slot_pairs = slots.reshape(-1)
        rotations = b * np.arange(n)[:, None] + np.arange(p)  # each pose's rotation unknowns
        curvature = N * rotations[:, :, None] + rotations[:, None, :]
        curvature[self.held] = self._size
        self._slot_curvature = curvature.reshape(-1)
        self._anchor_slots = np.flatnonzero(self.held_rows) * (N + 1)
        self.free_diagonal = np.flatnonzero(~self.held_rows) * (N + 1)

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
        lin = self.linearization(self.evaluate(R, t))
        return lin.gradient.g, self.hessian(lin)

    def hessian(self, lin: _Linearization, curvature: bool = True) -> np.ndarray:
        """The Hessian's values at a point (:meth:`matrix`), from its linearization: the
        Gauss–Newton matrix JᵀJ (with the anchors' unit diagonal; positive semidefinite) plus, with
        ``curvature``, the exponential's curvature C (block diagonal, zero at the anchors)."""
        size = self._size + 1  # the last slot collects what the anchors drop
        J = lin.J
        values = np.bincount(self._slot_pairs, (J @ np.swapaxes(J, 1, 2)).reshape(-1), minlength=size)
        if curvature:
            values += np.bincount(self._slot_curvature, self.curvature(lin.point).reshape(-1), minlength=size)
        values = values[:-1]
        values[self._anchor_slots] = 1.0
        return values

    def retract(self, R, t, step: np.ndarray):
        """(R_i Exp(omega_i), t_i + delta_i) for the step (in nested-dissection order)."""
        s = step.reshape(self.n, self.b) if self.dense else step[self.index]  # (n, b)
        return R @ self.group.exp(s[:, : self.p]), t + s[:, self.p :]


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
        self.point = problem.evaluate(R, t)
        self._linearization = None  # at the point, once computed
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
        return self.linearization().gradient

    def linearization(self) -> _Linearization:
        """The linearization at the current point (computed once per point)."""
        if self._linearization is None:
            self._linearization = self.pb.linearization(self.point)
        return self._linearization

    def _accept(self, point: _Point) -> None:
        self.point, self._linearization = point, None

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
        """The retraction of the step s (a :class:`_Point`) and the gain ratio: F's decrease over
        the decrease predicted by the quadratic model g, H."""
        predicted = -(g @ s + 0.5 * (s @ (H @ s)))
        x = self.point
        trial = self.pb.evaluate(*self.pb.retract(x.R, x.t, s))
        actual = 0.5 * (x.f - trial.f)
        tiny = 1e-13 * max(abs(x.f), 1e-300)  # below the rounding of F: trust the model
        rho = 1.0 if predicted <= tiny and actual >= -tiny else actual / predicted if predicted > 0 else -1.0
        return trial, rho

    def step(self) -> None:
        pb, cfg = self.pb, self.config
        lin = self.linearization()
        gradient = lin.gradient
        g = gradient.g
        newton = self.iteration >= cfg.gauss_newton_steps
        self.iteration += 1
        data = pb.hessian(lin, curvature=newton)
        H = pb.matrix(data)
        g_norm = float(np.sqrt(g @ g))
        reuse = self.reuse is not None and newton and g_norm <= cfg.reuse_contraction * self.g_norm
        self.g_norm = g_norm
        if reuse:  # quadratic regime: the previous factorization of H + lambda I still fits
            trial, rho = self._gain(g, -self.reuse.solve(g), H)
            if rho > 0.5:
                self._accept(trial)
                return
        self.reuse = None

        def least_damping():  # after a failure: relative to the diagonal's scale (rarely needed)
            return 1e-10 * float(np.max(np.abs(data[pb.free_diagonal]), initial=1.0))

        for _ in range(cfg.max_retries):
            if self.lam > 0:
                damped = data.copy()
                damped[pb.free_diagonal] += self.lam
            else:  # undamped (the usual Newton step): the factorizations leave their input unchanged
                damped = data
            factor = self._factor(damped)
            if factor is None:  # not positive definite: more damping
                self.lam = max(4.0 * self.lam, least_damping())
                continue
            trial, rho = self._gain(g, -factor.solve(g), H)
            if rho > 1e-4:
                self._accept(trial)
                self.lam *= max(cfg.damping_decrease, 1.0 - (2.0 * rho - 1.0) ** 3)
                self.nu = 2.0
                if newton and rho > 0.5 and cfg.reuse_contraction > 0:
                    self.reuse = factor
                return
            self.lam = max(self.lam * self.nu, least_damping())
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
    coupled: np.ndarray | None = None,
):
    """Levenberg–Marquardt / Newton iterations from (R0, t0) (host float64 arrays; the fixed poses
    already at their values) until ``termination`` (its rules are checked after every iteration).

    ``coupled``: (m,) bool, the edges whose full Jᵀ J enters the Newton matrix (default: all); the
    others enter the cost, the gradient, the curvature and their poses' diagonal blocks, but not the
    block that couples their two poses, so that they add no fill to the factorization (an inexact
    Newton matrix, for edges of negligible weight; the gain ratio still checks every step against F).

    Returns (R, t, history, result, stats) with stats = build_seconds (orderings, anchors),
    solve_seconds (the iterations) and factorizations (accepted and rejected trial steps).
    """
    config = config or NewtonConfig()
    monitor = monitor or Monitor()
    t_build = time.perf_counter()
    problem = _Problem(graph, fixed, coupled=coupled)

    def host_chunk(state, length, limit):
        def chunk(lm, limit):
            lm.step()
            record = (np.array([lm.point.f]), np.array([lm.gradient().norm]), np.zeros((1, 1), bool))
            return lm, record

        return chunk

    # no stall rule: near the optimum Newton's f changes by O(||grad||^2), below rounding while the
    # gradient still falls quadratically to grad_tol (which the certificate needs)
    one_by_one = Termination(termination.iterations, 1, termination.grad_tol, termination.f_target,
                             termination.rel_decrease_tol, stop_when_stalled=False)
    # One BLAS thread for all the numerical work, the start's included: the iterations are small or
    # memory-bound NumPy / SuperLU operations, where OpenBLAS's threads only add synchronization
    # (measured: 1.8x faster on sphere2500, 2-core machine), and OpenBLAS threads woken by a large
    # reduction keep spinning while PARDISO's threads factor (measured: intel's factorization 3x
    # slower). Not for the dense problems, where setting and restoring the limit costs more than
    # it saves (measured: tinyGrid3D's whole solve 1.07 -> 1.01 ms without it).
    with contextlib.nullcontext() if problem.dense else one_blas_thread():
        lm = _LM(problem, np.asarray(R0, dtype=np.float64), np.asarray(t0, dtype=np.float64), config)
        try:
            start = (np.float64(lm.point.f), np.float64(lm.gradient().norm), np.zeros(1, bool))
            build_seconds = time.perf_counter() - t_build
            out = drive(host_chunk, lm, start, one_by_one, fetch=lambda rec: rec, callback=callback,
                        monitor=monitor)
        finally:
            lm.close()
    stats = dict(build_seconds=build_seconds, solve_seconds=out.solve_seconds + out.compile_seconds,
                 factorizations=lm.factorizations)
    history = History(out.history.f, out.history.grad_norm, out.history.restarts)
    result: RESULTS = out.result
    return lm.point.R, lm.point.t, history, result, stats
