"""Sparse symmetric solves on the structure of a pose graph (host-side: scipy, pymetis, MKL PARDISO).

Every large linear system of the package (the chordal initialization's rotation and translation
systems, the centralized Newton steps, the certificate) has one block of unknowns per pose and
couples two poses exactly when a measurement joins them. The fill-reducing order of such a system
is therefore an order of the poses: METIS's nested dissection of the measurement graph
(:func:`pose_order`, through ``pymetis``), expanded to the blocks (:func:`block_order`). SuperLU
then factors the symmetrically permuted matrix with diagonal pivots (an LDLᵀ in LU form).

Measured (benchmarks/scaling.md): on the Cube graphs, SuperLU's own minimum-degree order
(``MMD_AT_PLUS_A``) factors the chordal rotation system of 10 000 poses in 12.6 s and of 20 000
in 197 s; nested dissection takes 0.8 s and 2.3 s, and 11 s at 100 000 poses. CHOLMOD through
``cholespy`` (its own AMD order, which cannot be replaced) took 40 s at 100 000 poses. On the
benchmark files (at most 10 000 poses) both orders take under 0.5 s.

Large positive-definite systems (:data:`PARDISO_MIN_SIZE` unknowns and more) go to MKL's PARDISO
(``pypardiso``, the ``large`` extra; x86-64 wheels of MKL, no system library): a supernodal,
multithreaded Cholesky in its own METIS nested-dissection order. Measured on the chordal start
of the Cube graphs, same machine (benchmarks/scaling.md): 10^5 poses 4.2 s against
SuperLU's 6.8 s, 3·10^5 poses 16 s against 47 s, 10^6 poses 97 s and 10.1 GB where SuperLU had
not finished after 19 minutes and 18.5 GB. Below the threshold SuperLU stays (faster there, and
every benchmark file keeps its results bit for bit).
"""

from __future__ import annotations

import ctypes
import functools
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

__all__ = ["PARDISO_MIN_SIZE", "PardisoCholesky", "SymmetricFactor", "block_order", "cholesky_fill", "factor_symmetric",
           "pardiso_available", "pose_order", "solve_spd"]

#: Unknowns from which :func:`solve_spd` uses PARDISO when it is installed (the measured
#: crossover on the Cube graphs' chordal systems lies between 6·10^4 and 1.5·10^5 unknowns).
PARDISO_MIN_SIZE = 100_000


def pose_order(num_poses: int, i, j) -> np.ndarray:
    """A fill-reducing order of the poses (METIS nested dissection of the measurement graph): the
    matrix permuted to ``A[order][:, order]`` (per pose block) factors with little fill."""
    import pymetis

    i = np.asarray(i, dtype=np.int64)
    j = np.asarray(j, dtype=np.int64)
    keep = i != j
    src = np.concatenate([i[keep], j[keep]])
    dst = np.concatenate([j[keep], i[keep]])
    if num_poses < 3 or src.size == 0:
        return np.arange(num_poses, dtype=np.int64)
    adj = sp.csr_matrix((np.ones(src.size, dtype=np.int8), (src, dst)), shape=(num_poses, num_poses))
    adj.sum_duplicates()  # one entry per neighbour, sorted
    order, _ = pymetis.nested_dissection(pymetis.CSRAdjacency(adj.indptr.astype(np.int64),
                                                              adj.indices.astype(np.int64)))
    return np.asarray(order, dtype=np.int64)


def block_order(order: np.ndarray, block: int, free: np.ndarray | None = None) -> np.ndarray:
    """The pose order ``order`` on the unknowns of a system with ``block`` unknowns per pose (pose
    p's are ``block * p + 0..block-1``). ``free`` (unknowns, bool): the order restricted to them,
    numbered among the free unknowns (the system of the free unknowns alone)."""
    perm = (block * np.asarray(order, dtype=np.int64)[:, None] + np.arange(block)).ravel()
    if free is None:
        return perm
    free = np.asarray(free, dtype=bool)
    rank = np.cumsum(free) - 1
    return rank[perm[free[perm]]]


class SymmetricFactor:
    """SuperLU factorization of a symmetric matrix in a given symmetric order, with diagonal pivots
    (so U's diagonal holds the pivots of an LDLᵀ and their signs give the inertia).

    ``perm``: the order (an array, e.g. :func:`block_order`), ``"ordered"`` when ``A`` is already
    assembled in its fill-reducing order, or None for SuperLU's minimum-degree order.
    """

    def __init__(self, A: sp.spmatrix, perm: np.ndarray | str | None):
        self.size = A.shape[0]
        self.perm = None
        if isinstance(perm, str):
            if perm != "ordered":
                raise ValueError(f"perm must be an array, 'ordered' or None, got {perm!r}")
        elif perm is not None:
            self.perm = np.asarray(perm, dtype=np.int64)
            A = sp.csr_matrix(A)[self.perm][:, self.perm]
            self.inverse = np.empty_like(self.perm)
            self.inverse[self.perm] = np.arange(self.perm.size)
        spec = "MMD_AT_PLUS_A" if perm is None else "NATURAL"
        self._lu = spla.splu(sp.csc_matrix(A), permc_spec=spec, diag_pivot_thresh=0.0,
                             options={"SymmetricMode": True})

    def solve(self, B: np.ndarray) -> np.ndarray:
        B = np.asarray(B, dtype=np.float64)
        if self.perm is None:
            return self._lu.solve(np.ascontiguousarray(B))
        return self._lu.solve(np.ascontiguousarray(B[self.perm]))[self.inverse]

    @property
    def diagonal_pivots(self) -> bool:
        """Whether every pivot was taken on the diagonal (else the inertia cannot be read)."""
        return bool(np.array_equal(self._lu.perm_r, self._lu.perm_c))

    def negative_pivots(self) -> int | None:
        """Number of negative eigenvalues (Sylvester's law of inertia), None without diagonal pivots."""
        return int(np.sum(self._lu.U.diagonal() < 0)) if self.diagonal_pivots else None


def factor_symmetric(A: sp.spmatrix, perm: np.ndarray | str | None = None) -> SymmetricFactor | None:
    """:class:`SymmetricFactor` of ``A`` in the order ``perm``, or None when SuperLU finds it
    exactly singular."""
    try:
        return SymmetricFactor(A, perm)
    except RuntimeError:  # "Factor is exactly singular"
        return None


def _locate_mkl_runtime() -> None:
    """Point ``pypardiso`` at the MKL runtime of the ``mkl`` wheel (``PYPARDISO_MKL_RT``) unless set:
    its own search walks the whole environment's ``lib`` tree (0.3 s, twice per process)."""
    if os.environ.get("PYPARDISO_MKL_RT"):
        return
    try:
        from importlib import metadata

        dist = metadata.distribution("mkl")
        found = [dist.locate_file(f) for f in dist.files or () if "libmkl_rt" in f.name or "mkl_rt" in f.name]
    except metadata.PackageNotFoundError:
        return
    for path in sorted(found, key=lambda p: len(str(p))):
        if Path(path).is_file():
            os.environ["PYPARDISO_MKL_RT"] = str(Path(path).resolve())
            return


def pardiso_available() -> bool:
    """Whether MKL's PARDISO can be loaded (``pypardiso`` and its MKL runtime installed)."""
    _locate_mkl_runtime()
    try:
        import pypardiso  # noqa: F401
    except (ImportError, OSError):
        return False
    return True


@functools.cache
def _pardiso_function():
    """MKL's ``pardiso`` entry point, from the runtime ``pypardiso`` finds, through a handle of our
    own (``pypardiso`` sets argument types of its own on its handle); looked up once."""
    _locate_mkl_runtime()
    import pypardiso

    function = ctypes.CDLL(pypardiso.PyPardisoSolver(mtype=2).libmkl._name).pardiso
    function.restype = None
    return function


def _threads() -> int:
    """The threads PARDISO runs on (MKL's default: every processor this process may use)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


class PardisoCholesky:
    """Cholesky factorizations (PARDISO, matrix type 2) of positive-definite matrices that share one
    sparsity pattern: the ordering and symbolic analysis run once, each :meth:`factor` is numeric
    only. Measured on the centralized Newton steps' Hessians (benchmarks/centralized.md):
    sphere2500 (15 000 unknowns) 0.015 s per factorization against SuperLU's 0.097 s, torus3D
    0.024 s against 0.23 s; the analysis costs 0.04-0.07 s once.

    ``upper``: the pattern's upper triangle as CSR with sorted column indices (values ignored).
    PARDISO is called directly (``ctypes``, the MKL runtime that ``pypardiso`` loads): it keeps
    pointers to the index arrays between its phases, so they must stay the same arrays, which
    ``pypardiso``'s per-call conversion does not allow."""

    def __init__(self, upper: sp.csr_matrix):
        self._call = _pardiso_function()
        self._n = upper.shape[0]
        self._ia = np.ascontiguousarray(upper.indptr, dtype=np.int32) + 1  # one-based, kept alive
        self._ja = np.ascontiguousarray(upper.indices, dtype=np.int32) + 1
        self._a = np.zeros(upper.nnz)
        self._pt = np.zeros(64, dtype=np.int64)  # PARDISO's internal handle
        self._iparm = np.zeros(64, dtype=np.int32)
        self._iparm[[0, 1, 9]] = (1, 2, 8)  # own settings; METIS order; pivot perturbation 1e-8
        # conditional numerical reproducibility: with several threads PARDISO's sums otherwise run in
        # a varying order, and a GNC start on top of it classified M3500's outliers differently
        # from run to run (measured 2026-12-05: 19-25 stages, weights differing, same input)
        self._iparm[33] = _threads()
        self._iparm[17] = -1  # report the factor's nonzeros
        self._ptr = ctypes.c_void_p
        self._int = ctypes.c_int32
        self._factored = False
        self._run(11, np.zeros(1), np.zeros(1))

    @property
    def factor_nonzeros(self) -> int:
        """PARDISO's count of the factor's nonzeros in its fill-reducing order, from the analysis (its
        own count: about twice those of the lower triangle, a measure of the factorization's size)."""
        return int(self._iparm[17])

    def _run(self, phase: int, b: np.ndarray, x: np.ndarray, nrhs: int = 1) -> int:
        error = ctypes.c_int32(0)
        ref = ctypes.byref
        self._call(self._pt.ctypes.data_as(self._ptr), ref(self._int(1)), ref(self._int(1)), ref(self._int(2)),
                   ref(self._int(phase)), ref(self._int(self._n)), self._a.ctypes.data_as(self._ptr),
                   self._ia.ctypes.data_as(self._ptr), self._ja.ctypes.data_as(self._ptr), None,
                   ref(self._int(nrhs)), self._iparm.ctypes.data_as(self._ptr), ref(self._int(0)),
                   b.ctypes.data_as(self._ptr), x.ctypes.data_as(self._ptr), ref(error))
        if error.value not in (0, -4):
            raise RuntimeError(f"PARDISO phase {phase} failed with error {error.value}")
        return error.value

    def factor(self, data: np.ndarray) -> bool:
        """Factor the matrix with these values of the pattern's upper triangle; False when it is
        not positive definite (PARDISO's error -4, a non-positive pivot)."""
        self._a[:] = data
        self._factored = self._run(22, np.zeros(1), np.zeros(1)) == 0
        return self._factored

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solve with the last successful factorization."""
        if not self._factored:
            raise RuntimeError("no successful factorization to solve with")
        rhs = np.array(b, dtype=np.float64, order="F").reshape(self._n, -1)
        x = np.zeros_like(rhs, order="F")
        self._run(33, rhs, x, rhs.shape[1])
        return x.reshape(np.shape(b))

    def close(self) -> None:
        """Release PARDISO's memory for this pattern."""
        self._run(-1, np.zeros(1), np.zeros(1))


def cholesky_fill(n: int, i: np.ndarray, j: np.ndarray) -> int:
    """The size of the Cholesky factor of the n x n pattern of the edges (i, j) and the diagonal (one
    node per pose): :attr:`PardisoCholesky.factor_nonzeros` of PARDISO's analysis (METIS order); the
    factorization's work grows with it. Needs :func:`pardiso_available`."""
    lo, hi = np.minimum(i, j), np.maximum(i, j)
    rows = np.concatenate([np.arange(n), lo])
    cols = np.concatenate([np.arange(n), hi])
    upper = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n))
    upper.sum_duplicates()
    upper.sort_indices()
    chol = PardisoCholesky(upper)
    try:
        return chol.factor_nonzeros
    finally:
        chol.close()


def _pardiso_solve_spd(A: sp.spmatrix, B: np.ndarray) -> np.ndarray:
    """Solve with :class:`PardisoCholesky` (one analysis, one factorization); its memory is
    released before returning."""
    upper = sp.triu(A, format="csr")
    upper.sort_indices()
    chol = PardisoCholesky(upper)
    try:
        if not chol.factor(upper.data):
            raise np.linalg.LinAlgError(
                "the system is not positive definite (singular: is every connected component anchored?); "
                "PARDISO found a non-positive pivot")
        return chol.solve(B)
    finally:
        chol.close()


def solve_spd(A: sp.spmatrix, B: np.ndarray,
              perm: np.ndarray | Callable[[], np.ndarray] | None = None, *,
              backend: str = "auto") -> np.ndarray:
    """Solve A X = B for a sparse symmetric positive-definite A.

    ``backend``: ``"superlu"`` (SuperLU in the order ``perm``, e.g. :func:`block_order` of
    :func:`pose_order`; a callable is evaluated only here, so that PARDISO does not pay for an
    order it does not use), ``"pardiso"`` (MKL PARDISO, its own order) or ``"auto"``: PARDISO from
    :data:`PARDISO_MIN_SIZE` unknowns when it is installed, else SuperLU.
    """
    if backend not in ("auto", "superlu", "pardiso"):
        raise ValueError(f"backend must be 'auto', 'superlu' or 'pardiso', got {backend!r}")
    if A.shape[0] == 0:
        return np.zeros_like(np.asarray(B, dtype=np.float64))
    if backend == "auto":
        large = A.shape[0] >= PARDISO_MIN_SIZE
        backend = "pardiso" if large and pardiso_available() else "superlu"
    if backend == "pardiso":
        return _pardiso_solve_spd(A, B)
    factor = factor_symmetric(A, perm() if callable(perm) else perm)
    if factor is None:
        raise np.linalg.LinAlgError("the system is singular (is every connected component anchored?)")
    return factor.solve(B)
