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
* One sparse LDLᵀ per step (SuperLU, :mod:`~mmpgo_jax._core.sparse`), the matrix assembled
  directly in METIS's nested-dissection order of the poses. The gauge is fixed by holding the
  anchor poses (:func:`~mmpgo_jax._core.gauge.anchor_set`: the fixed poses, else the first pose of
  each connected component): their rows are the identity and their steps zero.

Everything runs in float64 NumPy on the host: no compilation. ``||grad F||`` (the stopping rule)
is the Riemannian gradient over the poses that are not fixed, as in :func:`~mmpgo_jax.solve`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .._core.gauge import FixedPoses, anchor_set
from .._core.pose_graph import (
    PoseGraph,
    Poses,
    cost,
    euclidean_gradient,
    host_graph,
    riemannian_gradient_from_euclidean,
)
from .._core.sparse import factor_symmetric, pose_order
from .driver import RESULTS, History, Monitor, Termination, drive

__all__ = ["NewtonConfig", "newton_optimum"]


@dataclass(frozen=True)
class NewtonConfig:
    """Levenberg–Marquardt parameters (checked on construction): ``initial_damping`` lambda_0 (absolute,
    >= 0; grown automatically while H + lambda I is not positive definite), ``max_retries`` rejected
    trial steps per iteration before giving up."""

    initial_damping: float = 1e-6
    max_retries: int = 60

    def __post_init__(self):
        if not (np.isfinite(self.initial_damping) and self.initial_damping >= 0):
            raise ValueError(f"initial_damping must be a finite number >= 0, got {self.initial_damping!r}")
        if isinstance(self.max_retries, bool) or not isinstance(self.max_retries, int) or self.max_retries < 1:
            raise ValueError(f"max_retries must be an integer >= 1, got {self.max_retries!r}")


def _generators(d: int) -> np.ndarray:
    """Basis E_k of so(d), (p, d, d), p = d(d-1)/2 (the hat map for d = 3)."""
    rows, cols = np.triu_indices(d, 1)
    E = np.zeros((rows.size, d, d))
    k = np.arange(rows.size)
    E[k, cols, rows] = 1.0
    E[k, rows, cols] = -1.0
    if d == 3:  # omega = (x, y, z): hat(omega) = [[0, -z, y], [z, 0, -x], [-y, x, 0]]
        E = E[[2, 1, 0]] * np.array([1.0, -1.0, 1.0])[:, None, None]
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
    W = np.einsum("nk,kab->nab", omega, _generators(3))
    return np.eye(3) + a[:, None, None] * W + b[:, None, None] * (W @ W)


class _Problem:
    """The host-side data of one centralized solve: the graph in float64, the dof layout in
    nested-dissection order, the anchors."""

    def __init__(self, graph: PoseGraph, fixed: FixedPoses | None):
        self.graph = host_graph(graph)
        g = self.graph
        n, d = g.num_poses, g.dim
        self.n, self.d = n, d
        self.p = d * (d - 1) // 2
        self.b = self.p + d  # unknowns per pose: omega, then delta
        self.E = _generators(d)
        rank = np.empty(n, dtype=np.int64)
        rank[pose_order(n, g.i, g.j)] = np.arange(n)
        self.index = self.b * rank[:, None] + np.arange(self.b)  # (n, b) rows of each pose, ND order
        held = anchor_set(graph, fixed).index
        self.held = np.zeros(n, dtype=bool)
        self.held[held] = True
        self.free_poses = np.ones(n, dtype=bool) if fixed is None else ~fixed.mask(n)
        self.sqrt_kappa = np.sqrt(g.kappa)
        self.sqrt_tau = np.sqrt(g.tau)
        self._pattern()

    def cost(self, R, t) -> float:
        return float(cost(self.graph, Poses(R, t)))

    def grad_norm(self, R, t) -> float:
        """||grad F|| over the poses that are not fixed (Riemannian, of F)."""
        X = Poses(R, t)
        rg = riemannian_gradient_from_euclidean(X, euclidean_gradient(self.graph, X))
        keep = self.free_poses
        return float(np.sqrt(np.sum(rg.R[keep] ** 2) + np.sum(rg.t[keep] ** 2)))

    def jacobians(self, R, t):
        """Residuals r (m, q) and their Jacobians J_i, J_j (m, q, b) in local coordinates, q = d^2 + d."""
        g, d, p = self.graph, self.d, self.p
        m = g.i.shape[0]
        Ri, Rj = R[g.i], R[g.j]
        sk, st = self.sqrt_kappa[:, None], self.sqrt_tau[:, None]
        r = np.concatenate([sk * (Ri @ g.R - Rj).reshape(m, d * d),
                            st * (np.einsum("mab,mb->ma", Ri, g.t) + t[g.i] - t[g.j])], 1)
        RiE = np.einsum("mab,kbc->mkac", Ri, self.E)  # (m, p, d, d): R_i E_k
        Ji = np.zeros((m, d * d + d, self.b))
        Jj = np.zeros_like(Ji)
        Ji[:, : d * d, :p] = sk[:, :, None] * (RiE @ g.R[:, None]).reshape(m, p, d * d).transpose(0, 2, 1)
        Ji[:, d * d :, :p] = st[:, :, None] * np.einsum("mkab,mb->mak", RiE, g.t)
        Jj[:, : d * d, :p] = -sk[:, :, None] * np.einsum("mab,kbc->mkac", Rj, self.E).reshape(m, p, d * d).transpose(
            0, 2, 1)
        eye = np.eye(d)
        Ji[:, d * d :, p:] = st[:, :, None] * eye
        Jj[:, d * d :, p:] = -st[:, :, None] * eye
        return r, Ji, Jj

    def _pattern(self):
        """The Hessian's sparsity (constant): CSC indices and indptr, and for every entry of the
        block list :meth:`linearize` assembles (pose-pair blocks, curvature blocks, then the anchors'
        unit diagonal) its slot in the CSC data (duplicates summed by one bincount per iteration)."""
        g, n, b, p = self.graph, self.n, self.b, self.p
        N = b * n
        idx = self.index
        ri, rj = idx[g.i], idx[g.j]
        rows = [ri, rj, ri, rj, idx[:, :p]]
        cols = [ri, rj, rj, ri, idx[:, :p]]
        widths = [b, b, b, b, p]
        r_all = np.concatenate([np.broadcast_to(rr[:, :, None], (rr.shape[0], rr.shape[1], w)).reshape(-1)
                                for rr, w in zip(rows, widths, strict=True)])
        c_all = np.concatenate([np.broadcast_to(cc[:, None, :], (cc.shape[0], w, cc.shape[1])).reshape(-1)
                                for cc, w in zip(cols, widths, strict=True)])
        self.held_rows = np.zeros(N, dtype=bool)
        self.held_rows[idx[self.held].reshape(-1)] = True
        self._keep = ~(self.held_rows[r_all] | self.held_rows[c_all])
        diag = np.flatnonzero(self.held_rows)
        key = np.concatenate([c_all[self._keep], diag]) * N + np.concatenate([r_all[self._keep], diag])
        unique, self._slot = np.unique(key, return_inverse=True)  # sorted by (column, row): CSC order
        self._indices = (unique % N).astype(np.int64)
        self._indptr = np.searchsorted(unique // N, np.arange(N + 1)).astype(np.int64)
        self._anchor_ones = np.ones(diag.size)
        free_diag = np.flatnonzero(~self.held_rows)
        self.free_diagonal = np.searchsorted(unique, free_diag * N + free_diag)  # slots of the free rows' diagonal
        self._edge_rows = (ri, rj)

    def matrix(self, data: np.ndarray) -> sp.csc_matrix:
        """The N x N matrix with the Hessian's pattern and CSC values ``data``."""
        N = self.b * self.n
        return sp.csc_matrix((data, self._indices, self._indptr), shape=(N, N))

    def linearize(self, R, t):
        """Gradient g (N,) and the Hessian's CSC values (pattern :meth:`matrix`, nested-dissection
        order) of the pulled-back F at (R, t), N = b n; the anchors' rows and columns are those of
        the identity, g = 0 there."""
        g, n, b, p = self.graph, self.n, self.b, self.p
        r, Ji, Jj = self.jacobians(R, t)
        JiT, JjT = np.swapaxes(Ji, 1, 2), np.swapaxes(Jj, 1, 2)
        ri, rj = self._edge_rows
        N = b * n
        grad = (np.bincount(ri.reshape(-1), (JiT @ r[:, :, None]).reshape(-1), minlength=N)
                + np.bincount(rj.reshape(-1), (JjT @ r[:, :, None]).reshape(-1), minlength=N))
        Hij = JiT @ Jj
        # the exponential's curvature: C_kl = sym <R^T G, E_k E_l>, G = dF/dR (Euclidean)
        A = np.swapaxes(R, 1, 2) @ euclidean_gradient(g, Poses(R, t)).R
        EE = np.einsum("kab,lbc->klac", self.E, self.E)
        C = (A.reshape(n, -1) @ EE.reshape(p * p, -1).T).reshape(n, p, p)
        C = 0.5 * (C + np.swapaxes(C, 1, 2))
        values = np.concatenate([(JiT @ Ji).reshape(-1), (JjT @ Jj).reshape(-1), Hij.reshape(-1),
                                 np.swapaxes(Hij, 1, 2).reshape(-1), C.reshape(-1)])
        data = np.bincount(self._slot, np.concatenate([values[self._keep], self._anchor_ones]),
                           minlength=self._indices.size)
        grad[self.held_rows] = 0.0
        return grad, data

    def retract(self, R, t, step: np.ndarray):
        """(R_i Exp(omega_i), t_i + delta_i) for the step (in nested-dissection order)."""
        s = step[self.index]  # (n, b)
        return R @ _exp(s[:, : self.p], self.d), t + s[:, self.p :]


class _LM:
    """One Levenberg–Marquardt iteration per call (the accepted step), for :func:`drive`."""

    def __init__(self, problem: _Problem, R, t, config: NewtonConfig):
        self.pb = problem
        self.R, self.t = R, t
        self.f = problem.cost(R, t)  # 2F
        self.lam = config.initial_damping
        self.nu = 2.0
        self.config = config
        self.factorizations = 0

    def step(self) -> None:
        pb, cfg = self.pb, self.config
        g, data = pb.linearize(self.R, self.t)
        H = pb.matrix(data)
        scale = float(np.max(np.abs(data[pb.free_diagonal]), initial=1.0))
        for _ in range(cfg.max_retries):
            damped = data.copy()
            damped[pb.free_diagonal] += self.lam
            factor = factor_symmetric(pb.matrix(damped), "ordered")
            self.factorizations += 1
            if factor is None or factor.negative_pivots() != 0:  # not positive definite: more damping
                self.lam = max(4.0 * self.lam, 1e-10 * scale)
                continue
            s = -factor.solve(g)
            predicted = -(g @ s + 0.5 * s @ (H @ s))  # decrease of F predicted by the quadratic model
            R, t = pb.retract(self.R, self.t, s)
            f = pb.cost(R, t)
            actual = 0.5 * (self.f - f)
            tiny = 1e-13 * max(abs(self.f), 1e-300)  # below the rounding of F: trust the model
            rho = 1.0 if predicted <= tiny and actual >= -tiny else actual / predicted if predicted > 0 else -1.0
            if rho > 1e-4:
                self.R, self.t, self.f = R, t, f
                self.lam *= max(0.1, 1.0 - (2.0 * rho - 1.0) ** 3)
                self.nu = 2.0
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
    start = (np.float64(lm.f), np.float64(problem.grad_norm(lm.R, lm.t)), np.zeros(1, bool))
    build_seconds = time.perf_counter() - t_build

    def host_chunk(state, length, limit):
        def chunk(lm, limit):
            lm.step()
            record = (np.array([lm.f]), np.array([problem.grad_norm(lm.R, lm.t)]), np.zeros((1, 1), bool))
            return lm, record

        return chunk

    one_by_one = Termination(termination.iterations, 1, termination.grad_tol, termination.f_target,
                             termination.rel_decrease_tol)
    out = drive(host_chunk, lm, start, one_by_one, fetch=lambda rec: rec, callback=callback, monitor=monitor)
    stats = dict(build_seconds=build_seconds, solve_seconds=out.solve_seconds + out.compile_seconds,
                 factorizations=lm.factorizations)
    history = History(out.history.f, out.history.grad_norm, out.history.restarts)
    result: RESULTS = out.result
    return lm.R, lm.t, history, result, stats
