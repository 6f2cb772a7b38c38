"""A start that outlier loop closures do not bend: GNC-TLS whose stages are chordal solves.

Least squares, and so the chordal initialization, is pulled far off by a few wrong loop closures
(a 200-pose Cube with 10 % outlier loop closures: ATE 0.76 against 0.054 without them,
benchmarks/robust.md). Graduated non-convexity (Yang, Antonante, Tzoumas & Carlone, RA-L 2020)
assumes that each stage's weighted least squares is solved *globally*; a local solver warm-started
from the previous stage instead follows a path that depends on the early, badly bent iterates, and
on that Cube it rejected correct loop closures at 10 % and 30 % outliers while succeeding at 50 %
(measured with one robot as with four: the failure is not the distribution). GTSAM's GncOptimizer
re-solves every stage from the initial guess, which succeeds at low rates but fails from 50 %.

Here every stage is solved as this package solves the least-squares problem from scratch: the
chordal relaxation of the *weighted* graph (a linear least-squares problem, so its solution does
not depend on the previous iterate; docs/conventions.md §5), then Newton / Levenberg–Marquardt
refinement of the weighted objective from it (:func:`~mmpgo_jax._mm.centralized.newton_optimum`),
so that the residuals that set the next weights are those of a weighted optimum, not of the
relaxation (the relaxation's residuals alone misclassify many correct edges). The weights follow
GNC-TLS's closed form (:func:`~mmpgo_jax._mm.robust.gnc_weight`), mu starts at
c^2 / (2 s_max - c^2) over the residuals of the chordal relaxation of all edges and grows by
``factor`` per stage, and GNC ends when the weights are binary. Odometry is trusted (weight 1)
unless ``trust_odometry=False``. On that Cube it finds every outlier and no correct edge at 10-80 %
outliers and two seeds (benchmarks/robust.md).

This start is centralized, like the default chordal start of the least-squares runs (the paper's
Section VII starts from the centralized chordal initialization as well); it costs about
``stages`` sparse factorizations of the chordal system plus the Newton refinements. What keeps
that cost down on large graphs with many wrong closures (city10000 with 30 % wrong inter-robot
closures: did not finish in 19 minutes before; the start and the TLS run after it now take 53 s,
exact; measured 2026-12-05, benchmarks/robust_distributed_files_findings.md):

* the least-squares stage over all edges is the chordal relaxation alone: its Newton refinement,
  pulled by every outlier, ran to its iteration limit without converging (M3500 with 30 %: 200
  iterations, 460 factorizations, f still 3x its final value) and only set mu and the first
  weights;
* the stage solves' Levenberg–Marquardt damping decreases by Nielsen's 1/3 (:data:`STAGE_NEWTON`);
* on graphs factored by PARDISO, the Newton matrix leaves out the couplings of edges of negligible
  weight when they multiply the factor's nonzeros (:data:`NEGLIGIBLE_WEIGHT`, :data:`THIN_FILL`):
  random long-range wrong closures otherwise fill the factorization, and their tiny weights'
  products run into subnormal numbers;
* the chordal solves use PARDISO from the Newton steps' size;
* a weight counts as decided only at 0 or within ``weight_tolerance`` of 1 (see
  :func:`gnc_chordal_initialization`).

Measured against the previous stage solves on the Cube (10-80 %), MIT, intel (10-50 %) and M3500
(10-70 %, three seeds) graphs: the same classification on most runs, better on some (MIT 50 %: one
correct closure rejected instead of six), worse on others (M3500 30 % seeds 2 and 3: four and five
correct closures rejected instead of two and one), and 1-4x faster.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .._core import sparse
from .._core.gauge import FixedPoses
from .._core.pose_graph import PoseGraph, Poses, edge_costs, host_graph
from .._core.sparse import cholesky_fill, pardiso_available
from .._mm.centralized import PARDISO_NEWTON_MIN_SIZE, NewtonConfig, newton_optimum
from .._mm.driver import Termination
from .._mm.robust import TLS, chi2_scale, gnc_initial_mu, gnc_weight
from .chordal import chordal_initialization

__all__ = ["RobustStart", "gnc_chordal_initialization"]


@dataclass(frozen=True)
class RobustStart:
    """The robust start: ``poses`` (host float64), the final TLS ``weights`` (m,) in {0, 1} (1 on
    trusted edges), the GNC ``stages`` run and the ``scale`` c used."""

    poses: Poses
    weights: np.ndarray
    stages: int
    scale: float


def _weighted(graph: PoseGraph, w: np.ndarray) -> PoseGraph:
    """The graph with kappa, tau scaled by ``w`` and the zero-weight edges left out."""
    keep = w > 0
    g = graph.select_edges(keep)
    return PoseGraph(g.i, g.j, g.R, g.t, g.kappa * w[keep], g.tau * w[keep], num_poses=g.num_poses)


#: Weights below which an edge is left out of the Newton matrix's couplings when that thins the
#: factorization enough (:data:`THIN_FILL`): against the trusted edges' weight 1, such an edge adds
#: at most 1e-3 of a trusted edge's stiffness.
NEGLIGIBLE_WEIGHT = 1e-3

#: How many times fewer nonzeros the Cholesky factor must have without the couplings of the
#: negligible-weight edges for the stage's Newton steps to leave them out. Leaving them out costs
#: iterations (an inexact Newton matrix: M3500 with 30 % wrong inter-robot closures, 2452 against
#: 1641 factorizations) and pays only when the wrong closures' random long-range couplings fill
#: the factor (city10000 with 30 %: 22x the nonzeros of its correct edges' factor, each
#: factorization 1.4 s against 0.02 s without them, the tiny weights' products also running into
#: subnormal numbers; M3500 with 30 %: 3.3x).
THIN_FILL = 4.0

#: Levenberg-Marquardt for the stage solves: Nielsen's damping decrease (see NewtonConfig).
STAGE_NEWTON = NewtonConfig(damping_decrease=1.0 / 3.0)


def _large(graph: PoseGraph) -> bool:
    """Whether the graph's Newton systems are factored by PARDISO (installed, large enough). Asks the
    sparse module itself, as the Newton solver does: the module-level ``pardiso_available`` here only
    decides the missing-PARDISO note."""
    unknowns = graph.num_poses * graph.dim * (graph.dim + 1) // 2
    return unknowns >= PARDISO_NEWTON_MIN_SIZE and sparse.pardiso_available()


def _coupled(wg: PoseGraph, w: np.ndarray) -> np.ndarray | None:
    """The edges of the weighted graph ``wg`` (weights ``w`` > 0) whose couplings enter the Newton
    matrix: all (None) unless leaving out the negligible-weight ones thins the factor ``THIN_FILL``
    times (only for graphs factored by PARDISO, which reports the fill)."""
    coupled = w >= NEGLIGIBLE_WEIGHT
    if coupled.all() or not _large(wg):
        return None
    n, i, j = wg.num_poses, np.asarray(wg.i), np.asarray(wg.j)
    if cholesky_fill(n, i, j) < THIN_FILL * cholesky_fill(n, i[coupled], j[coupled]):
        return None
    return coupled


def _chordal(graph: PoseGraph, fixed) -> Poses:
    """The chordal relaxation; by PARDISO from the Newton steps' size (when installed): the wrong
    closures' fill makes SuperLU several times slower there (city10000 with 30 % wrong inter-robot
    closures: 8.1 s against 2.0 s)."""
    return chordal_initialization(graph, fixed, backend="pardiso" if _large(graph) else "auto")


def _stage_solution(graph: PoseGraph, w: np.ndarray, fixed, termination) -> Poses:
    """The weighted least-squares solution from scratch: chordal relaxation, then Newton."""
    keep = w > 0
    wg = _weighted(graph, w)
    X = _chordal(wg, fixed)
    R, t, *_ = newton_optimum(wg, np.asarray(X.R, np.float64), np.asarray(X.t, np.float64), termination,
                              fixed=fixed, config=STAGE_NEWTON, coupled=_coupled(wg, w[keep]))
    return Poses(R, t)


#: What a graph's GNC start says once when its Newton steps would use PARDISO but it is not installed.
MISSING_PARDISO = ("the GNC start's Newton steps use SciPy's SuperLU because MKL PARDISO is not installed: "
                   "several times slower on graphs this size (M3500 with 30 % wrong inter-robot closures: 68 s "
                   "against 17 s on a 2-core CPU); "
                   "pip install 'mmpgo-jax[large]' (x86-64)")


def _note_missing_pardiso(graph: PoseGraph, say: Callable[[str], None]) -> None:
    """Tell the user (a warning, and the progress line) when the start's Newton systems are large
    enough for PARDISO (``PARDISO_NEWTON_MIN_SIZE`` unknowns) and it is missing."""
    unknowns = graph.num_poses * graph.dim * (graph.dim + 1) // 2
    if unknowns >= PARDISO_NEWTON_MIN_SIZE and not pardiso_available():
        warnings.warn(MISSING_PARDISO, stacklevel=3)
        say("GNC start: " + MISSING_PARDISO)


def gnc_chordal_initialization(
    graph: PoseGraph,
    *,
    scale: float | None = None,
    trust_odometry: bool = True,
    fixed: FixedPoses | None = None,
    factor: float = 1.4,
    max_stages: int = 100,
    weight_tolerance: float = 1e-4,
    grad_tol: float = 1e-6,
    trusted: np.ndarray | None = None,
    progress: Callable[[str], None] | None = None,
) -> RobustStart:
    """GNC-TLS with chordal + Newton stages (module docstring) at scale c = ``scale`` (default
    :func:`~mmpgo_jax.chi2_scale` of the graph's dimension). ``grad_tol`` ends each stage's Newton
    refinement (relative to nothing: the gradient norm of the weighted f = 2F). ``trusted``: (m,) bool,
    edges known to be inliers (weight 1) besides the odometry of ``trust_odometry``. ``progress(text)``
    is called before the first chordal relaxation and after every GNC stage (a line for a progress
    bar). GNC ends when every robust edge's weight is 0 or at least 1 - ``weight_tolerance``: a
    weight that is tiny but not 0 is not decided (while mu is small every loop closure's weight is
    tiny beside the trusted odometry's 1; counting those as rejected ended GNC after two stages with
    every correct closure rejected on kitti_00 with 50 % wrong inter-robot closures). When no stage
    runs (every residual within the scale, or an infinite one) the start is the least-squares
    optimum of all edges."""
    if not factor > 1.0:
        raise ValueError(f"factor must be > 1, got {factor!r}")
    g = host_graph(graph)
    c2 = float(chi2_scale(g.dim) if scale is None else scale) ** 2
    robust = np.abs(g.i - g.j) != 1 if trust_odometry else np.ones(g.num_edges, bool)
    if trusted is not None:
        robust &= ~np.asarray(trusted, bool)
    termination = Termination(200, 1, grad_tol, stop_when_stalled=False)  # each stage to grad_tol, as before
    say = progress or (lambda text: None)
    _note_missing_pardiso(g, say)
    say(f"GNC start: chordal relaxation of all {g.num_edges} edges")
    X = _chordal(g, fixed)
    if g.num_edges == 0:  # a robot's map of one pose, a frame graph of one robot: nothing to weigh or refine
        return RobustStart(poses=X, weights=np.ones(0), stages=0, scale=float(np.sqrt(c2)))
    s = np.asarray(edge_costs(g, X))
    w = np.ones(g.num_edges)
    mu = float(gnc_initial_mu(TLS, np.max(s[robust], initial=0.0), c2))
    stages = 0
    while np.isfinite(mu) and stages < max_stages:
        w = np.where(robust, np.asarray(gnc_weight(TLS, s, c2, mu)), 1.0)
        X = _stage_solution(g, w, fixed, termination)
        s = np.asarray(edge_costs(g, X))
        stages += 1
        between = robust & (w > 0.0) & (w < 1.0 - weight_tolerance)
        say(f"GNC start: stage {stages}, {int(between.sum())} of {int(robust.sum())} edges undecided, "
            f"{int((robust & (w == 0.0)).sum())} rejected")
        if not between.any():
            break
        mu *= factor
    if stages == 0:  # every residual within the scale already (or an infinite scale): least squares
        X = _stage_solution(g, w, fixed, termination)
    w = np.where(robust, (w >= 0.5).astype(np.float64), 1.0)
    return RobustStart(poses=X, weights=w, stages=stages, scale=float(np.sqrt(c2)))
