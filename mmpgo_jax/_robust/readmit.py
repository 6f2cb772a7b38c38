"""Greedy re-admission of rejected loop closures by the robust objective (centralized).

A robust run's classification can sit in a local minimum that no single weight update leaves: on
robot teams of long odometry chains with one or two closures per robot pair, a few correct
long-range closures are rejected because the map, bent without them, puts their residuals far
beyond the scale c, and each one alone cannot pull it back within c. The test here is the
objective itself: a rejected closure is re-admitted when the optimum of the kept edges plus it
(centralized Newton from the current poses, :func:`~mmpgo_jax._mm.centralized.newton_optimum`)
has a lower f = 2 F_rho (:func:`~mmpgo_jax._mm.robust.robust_objective`, every edge of the graph
at that optimum) than the current one. Each round tries every rejected closure and re-admits the
one that lowers f most; rounds repeat until none lowers it. Only re-admissions are tried (the
robust run already rejected what it found too costly), so f never rises and the search ends.

Cost: one Newton solve of the kept edges per rejected closure per round (a 5000-pose 2D team with
16 rejected closures: 58 solves, about 40 s on a 2-core AMD EPYC). It is meant for graphs with tens
to a few hundred rejected closures, e.g. after PCM (:func:`~mmpgo_jax.pcm_filter`) and TLS on robot
teams; it gathers the whole graph in one place (not for ``distributed=True`` runs). It follows the
objective: where the information matrices overstate the noise the objective may prefer an outlier
that bends the map slightly, and it warns when the kept edges' residuals say so.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from .._core.gauge import FixedPoses
from .._core.noise import noise_level
from .._core.pose_graph import HostPoses, PoseGraph, Poses, connected_subgraph, host_graph
from .._mm.centralized import newton_optimum
from .._mm.driver import Termination
from .._mm.robust import RobustLoss, robust_edges, robust_objective

#: the Newton solves' stopping rule: ||grad F|| <= GRAD_TOL (as :func:`~mmpgo_jax.centralized_optimum`)
GRAD_TOL = 1e-6
MAX_NEWTON_ITERATIONS = 500


@dataclass(frozen=True)
class Readmission:
    """What :func:`readmit_loop_closures` found: ``inliers`` (m,) the kept edges after re-admission,
    ``poses`` the optimum of those edges (host arrays, the solver's gauge), ``f`` = 2 F_rho there,
    ``f_before`` at the given poses, ``readmitted`` the edge indices re-admitted in order and
    ``solves`` the Newton solves tried."""

    inliers: np.ndarray
    poses: HostPoses
    f: float
    f_before: float
    readmitted: np.ndarray
    solves: int


def readmit_loop_closures(graph: PoseGraph, inliers, poses: Poses, loss: RobustLoss, *,
                          fixed: FixedPoses | None = None) -> Readmission:
    """Re-admit rejected loop closures (edges the loss applies to, ``~inliers``) one at a time while
    that lowers f = 2 F_rho (module docstring). ``inliers`` (m,) bool and ``poses``: a robust run's
    (e.g. ``result.inliers``, ``result.poses``), in ``graph``'s edge order (for a run with
    ``prefilter="pcm"``, the original graph: PCM's removals are candidates too); ``loss``: its loss
    (``result.loss``). Run a robust solve from ``Readmission.poses`` (``solve(..., start=r.poses)``)
    for a result of the whole pipeline. A candidate whose kept edges leave the graph disconnected is
    not tried."""
    inliers = np.asarray(inliers, bool)
    if inliers.shape != (graph.num_edges,):
        raise ValueError(f"inliers: expected ({graph.num_edges},) booleans (one per edge), got shape {inliers.shape}")
    hg = host_graph(graph)  # every trial selects, solves and scores on the host
    candidates = robust_edges(loss, hg.i, hg.j) & ~inliers
    X = HostPoses(np.asarray(poses.R, np.float64), np.asarray(poses.t, np.float64))
    _warn_if_loose(hg.select_edges(inliers), X)
    f_before = f = robust_objective(loss, hg, X)
    kept, readmitted, solves = inliers.copy(), [], 0
    while True:
        best = None
        for e in np.flatnonzero(candidates & ~kept):
            trial = kept.copy()
            trial[e] = True
            Y = _kept_optimum(hg, trial, X, fixed)
            if Y is None:
                continue
            solves += 1
            f_trial = robust_objective(loss, hg, Y)
            if f_trial < f and (best is None or f_trial < best[0]):
                best = (f_trial, e, Y)
        if best is None:
            break
        f, e, X = best
        kept[e] = True
        readmitted.append(int(e))
    return Readmission(kept, X, float(f), float(f_before), np.asarray(readmitted, np.int64), solves)


def _warn_if_loose(kept: PoseGraph, X: HostPoses) -> None:
    """A warning when the kept edges' residuals are significantly below what their information
    matrices predict (:func:`~mmpgo_jax.noise_level`, 99 % interval below 1): the scale c is then loose
    for these data, and the objective may prefer an outlier that bends the map slightly (M3500 at 10 %
    wrong inter-robot closures: one was re-admitted, benchmarks/robust_teams.md)."""
    level = noise_level(kept, X)
    if level.redundancy > 0 and level.high < 1.0:
        warnings.warn(f"readmit_loop_closures: the kept edges' residuals are {level.factor:.3g}x what their "
                      "information matrices predict, so the loss's scale is loose for these data and "
                      "re-admission, which follows the robust objective, may take outliers that bend the map "
                      "slightly", stacklevel=3)


def _kept_optimum(graph: PoseGraph, kept: np.ndarray, X: HostPoses, fixed) -> HostPoses | None:
    """The optimum of the ``kept`` edges by Newton from X; None when they leave the graph disconnected."""
    sub = connected_subgraph(graph, kept)
    if sub is None:
        return None
    termination = Termination(MAX_NEWTON_ITERATIONS, 1, GRAD_TOL, stop_when_stalled=False)
    R, t, *_ = newton_optimum(sub, X.R, X.t, termination, fixed=fixed)
    return HostPoses(np.asarray(R), np.asarray(t))
