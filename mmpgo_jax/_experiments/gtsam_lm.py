"""GTSAM's Levenberg–Marquardt on a pose graph, as the timing reference of the centralized solver,
and GTSAM's GNC-TLS (``GncOptimizer``) as an independent reference of the robust start.

Optional: needs ``gtsam`` (``pip install "mmpgo-jax[benchmark]"``; wheels for Linux and macOS),
which is not a dependency of the package. Used by ``mmpgo bench`` (when gtsam is installed) and
``benchmarks/centralized.py``.

The factors are GTSAM's Between factors with diagonal precisions 2 kappa on the rotation tangent
coordinates and tau on the translation ones: they match this package's weights to second order
(the chordal ||R_a - R_b||_F^2 is 2 theta^2 + O(theta^4)). GTSAM minimises the geodesic
objective, not F: its optimum differs from f* by the two objectives' difference, so compare
F at GTSAM's result with f*, not its own error. Pose 0 is held by a prior of precision 1e12 (the
gauge).
"""

from __future__ import annotations

import importlib.util
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from .._core.lie import SO2, SO3, so
from .._core.pose_graph import PoseGraph, Poses

__all__ = ["GtsamGncResult", "GtsamResult", "gtsam_available", "gtsam_gnc", "gtsam_levenberg_marquardt"]


def gtsam_available() -> bool:
    return importlib.util.find_spec("gtsam") is not None


@dataclass(frozen=True)
class GtsamResult:
    poses: Poses  # host float64 arrays
    seconds: float  # optimize() alone (building GTSAM's graph and values is not counted)
    iterations: int


class _GtsamPoses(NamedTuple):
    """GTSAM's pose type of one group: a pose from (R, t), the Between factor's diagonal precisions
    from (kappa, tau) in its tangent order, its Between and Prior factor types, and the poses (R, t)
    of an optimizer's result."""

    pose: Callable
    precisions: Callable
    between: type
    prior: type
    read: Callable[[object, int], Poses]


def _gtsam_pose2(gtsam) -> _GtsamPoses:
    def read(result, n):
        ps = [result.atPose2(k) for k in range(n)]
        return Poses(SO2.exp(np.array([p.theta() for p in ps])[:, None]), np.array([[p.x(), p.y()] for p in ps]))

    return _GtsamPoses(lambda R, t: gtsam.Pose2(t[0], t[1], np.arctan2(R[1, 0], R[0, 0])),
                       lambda k, w: np.array([w, w, 2 * k]),  # Pose2 tangent: (x, y, theta)
                       gtsam.BetweenFactorPose2, gtsam.PriorFactorPose2, read)


def _gtsam_pose3(gtsam) -> _GtsamPoses:
    def read(result, n):
        ps = [result.atPose3(k) for k in range(n)]
        return Poses(np.array([p.rotation().matrix() for p in ps]), np.array([p.translation() for p in ps]))

    return _GtsamPoses(lambda R, t: gtsam.Pose3(gtsam.Rot3(R), t),
                       lambda k, w: np.array([2 * k] * 3 + [w] * 3),  # Pose3 tangent: (rotation, translation)
                       gtsam.BetweenFactorPose3, gtsam.PriorFactorPose3, read)


_GTSAM_POSES = {SO2: _gtsam_pose2, SO3: _gtsam_pose3}


def _pose_type(d: int) -> _GtsamPoses:
    import gtsam

    return _GTSAM_POSES[so(d)](gtsam)


def _problem(graph: PoseGraph, start: Poses):
    import gtsam

    d = graph.dim
    pose, precisions, between, prior, _ = _pose_type(d)
    i, j = np.asarray(graph.i), np.asarray(graph.j)
    Rm, tm = np.asarray(graph.R, np.float64), np.asarray(graph.t, np.float64)
    kappa, tau = np.asarray(graph.kappa, np.float64), np.asarray(graph.tau, np.float64)
    R0, t0 = np.asarray(start.R, np.float64), np.asarray(start.t, np.float64)
    fg = gtsam.NonlinearFactorGraph()
    for e in range(i.size):  # GTSAM's Python API builds factors one by one
        noise = gtsam.noiseModel.Diagonal.Precisions(precisions(kappa[e], tau[e]))
        fg.add(between(int(i[e]), int(j[e]), pose(Rm[e], tm[e]), noise))
    fg.add(prior(0, pose(R0[0], t0[0]), gtsam.noiseModel.Isotropic.Precision(d + so(d).tangent_dim, 1e12)))
    values = gtsam.Values()
    for k in range(graph.num_poses):
        values.insert(k, pose(R0[k], t0[k]))
    return fg, values


def _poses(result, n: int, d: int) -> Poses:
    return _pose_type(d).read(result, n)


def gtsam_levenberg_marquardt(graph: PoseGraph, start: Poses, *, error_tol: float = 1e-10,
                              max_iterations: int = 200) -> GtsamResult:
    """GTSAM's ``LevenbergMarquardtOptimizer`` from ``start`` (its defaults: COLAMD ordering,
    multifrontal Cholesky), relative and absolute error-decrease thresholds ``error_tol`` (GTSAM's
    default 1e-5 stops well above the optimum). Raises ImportError when gtsam is not installed."""
    if not gtsam_available():
        raise ImportError("GTSAM's reference needs gtsam: pip install 'mmpgo-jax[benchmark]' (or pip install gtsam)")
    import gtsam

    fg, values = _problem(graph, start)
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(error_tol)
    params.setAbsoluteErrorTol(error_tol)
    params.setMaxIterations(max_iterations)
    optimizer = gtsam.LevenbergMarquardtOptimizer(fg, values, params)
    t = time.perf_counter()
    result = optimizer.optimize()
    seconds = time.perf_counter() - t
    return GtsamResult(_poses(result, graph.num_poses, graph.dim), seconds, int(optimizer.iterations()))


@dataclass(frozen=True)
class GtsamGncResult:
    poses: Poses  # host float64 arrays
    weights: np.ndarray  # (m,) GNC's final weights of the graph's edges
    seconds: float  # optimize() alone


def gtsam_gnc(graph: PoseGraph, start: Poses, *, scale: float, trust_odometry: bool = True) -> GtsamGncResult:
    """GTSAM's ``GncOptimizer`` with TLS and Levenberg–Marquardt stages from ``start``: the inlier
    threshold is this package's scale c (GTSAM's factor error is half the squared residual, so its
    threshold is c^2 / 2), odometry edges (|i - j| = 1) and the gauge prior are known inliers when
    ``trust_odometry``. GTSAM re-solves every stage from ``start`` (see
    :mod:`~mmpgo_jax._init.robust_start`)."""
    if not gtsam_available():
        raise ImportError("GTSAM's reference needs gtsam: pip install 'mmpgo-jax[benchmark]' (or pip install gtsam)")
    import gtsam

    fg, values = _problem(graph, start)
    i, j = np.asarray(graph.i), np.asarray(graph.j)
    known = np.flatnonzero(np.abs(i - j) == 1) if trust_odometry else np.zeros(0, np.int64)
    params = gtsam.GncLMParams(gtsam.LevenbergMarquardtParams())
    params.setLossType(gtsam.GncLossType.TLS)
    params.setKnownInliers([*map(int, known), graph.num_edges])  # the prior is the last factor
    optimizer = gtsam.GncLMOptimizer(fg, values, params)
    optimizer.setInlierCostThresholds(0.5 * scale**2)
    t = time.perf_counter()
    result = optimizer.optimize()
    seconds = time.perf_counter() - t
    weights = np.asarray(optimizer.getWeights())[: graph.num_edges]
    return GtsamGncResult(_poses(result, graph.num_poses, graph.dim), weights, seconds)
