"""Outlier loop closures for robust-loss experiments (seeded) and the scores of a classification.

:func:`add_outliers` appends wrong loop closures to a graph, as perceptual aliasing produces them:

* a pair of poses (i, j) drawn uniformly among the pairs not already joined by an edge and not
  consecutive (|i - j| > 1), each pair at most once; with ``inter_robot_only`` only pairs of poses
  of different robots (``robot_of_pose``);
* a relative rotation uniform (Haar) on SO(d);
* a relative translation uniform in the box [-L, L] (per axis, L the extent max - min of the
  ``reference`` positions along that axis: the map's size);
* the weights of a typical loop closure: the median kappa and the median tau of the graph's loop
  closures (edges with |i - j| > 1; all edges when it has none).

The ``rate`` is the fraction of outliers among all loop closures after the addition: a graph with
L loop closures receives round(rate L / (1 - rate)) outliers (rate 0.5: as many outliers as
correct loop closures). The outliers are appended after the graph's edges, so edge e < m keeps its
index. All randomness comes from ``numpy.random.default_rng(seed)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._core.pose_graph import PoseGraph, Poses
from .synthetic import sample_langevin

__all__ = ["CorruptedGraph", "OutlierScores", "add_outlier_loop_closures", "add_outliers", "outlier_scores"]


@dataclass(frozen=True)
class CorruptedGraph:
    """A graph with outliers appended: ``outlier[e]`` is True for the added edges (the last ones)."""

    graph: PoseGraph
    outlier: np.ndarray  # (m,) bool
    rate: float
    seed: int

    @property
    def num_outliers(self) -> int:
        return int(self.outlier.sum())


def _loop_closures(graph: PoseGraph) -> np.ndarray:
    return np.abs(np.asarray(graph.i, np.int64) - np.asarray(graph.j, np.int64)) > 1


def _draw_pairs(rng, n: int, count: int, taken: np.ndarray, robot_of_pose) -> np.ndarray:
    """``count`` distinct unordered pairs (i < j, j > i + 1) whose codes i n + j are not in ``taken``
    (rejection, in batches; each batch is filtered with array operations: the first draw of each new
    pair is kept, in draw order)."""
    out = np.zeros((0, 2), np.int64)
    keys = np.unique(np.asarray(taken, np.int64))
    while len(out) < count:  # rejection rounds, not pairs
        need = count - len(out)
        pairs = np.sort(rng.integers(0, n, size=(2 * need + 16, 2)), axis=1)
        ok = pairs[:, 1] > pairs[:, 0] + 1
        if robot_of_pose is not None:
            ok &= robot_of_pose[pairs[:, 0]] != robot_of_pose[pairs[:, 1]]
        cand = pairs[ok]
        code = cand[:, 0] * n + cand[:, 1]
        first = np.zeros(code.shape[0], dtype=bool)
        first[np.unique(code, return_index=True)[1]] = True
        fresh = np.flatnonzero(first & ~np.isin(code, keys))
        keys = np.union1d(keys, code[fresh])
        out = np.concatenate([out, cand[fresh][:need]])
    return out


def add_outliers(graph: PoseGraph, rate: float, *, reference: Poses, seed: int = 0,
                 robot_of_pose=None, inter_robot_only: bool = False) -> CorruptedGraph:
    """``graph`` with wrong loop closures appended (module docstring); ``reference`` gives the map's
    extent (the ground truth or the outlier-free optimum). ``inter_robot_only``: between poses of
    different robots only (``robot_of_pose`` (n,) needed)."""
    if not 0.0 <= rate < 1.0:
        raise ValueError(f"rate must lie in [0, 1), got {rate!r}")
    n, d = graph.num_poses, graph.dim
    loops = _loop_closures(graph)
    count = round(rate * int(loops.sum()) / (1.0 - rate))
    rop = None
    if inter_robot_only:
        if robot_of_pose is None:
            raise ValueError("inter_robot_only needs robot_of_pose")
        rop = np.asarray(robot_of_pose)
        if len(np.unique(rop)) < 2:
            raise ValueError("inter_robot_only needs at least two robots")
    rng = np.random.default_rng(seed)
    gi, gj = np.asarray(graph.i, np.int64), np.asarray(graph.j, np.int64)
    taken = np.minimum(gi, gj) * n + np.maximum(gi, gj)
    pairs = _draw_pairs(rng, n, count, taken, rop)
    flip = rng.random(count) < 0.5  # either orientation
    I, J = np.where(flip, pairs[:, 1], pairs[:, 0]), np.where(flip, pairs[:, 0], pairs[:, 1])
    R = sample_langevin(rng, 0.0, count, d)  # kappa = 0: the uniform (Haar) distribution
    positions = np.asarray(reference.t, np.float64)
    extent = positions.max(axis=0) - positions.min(axis=0)
    t = rng.uniform(-1.0, 1.0, size=(count, d)) * extent
    typical = loops if loops.any() else np.ones_like(loops)
    kappa = np.full(count, np.median(np.asarray(graph.kappa)[typical]))
    tau = np.full(count, np.median(np.asarray(graph.tau)[typical]))
    dt = np.asarray(graph.kappa).dtype
    out = PoseGraph.from_arrays(
        np.concatenate([gi, I]), np.concatenate([gj, J]),
        np.concatenate([np.asarray(graph.R, np.float64), R]), np.concatenate([np.asarray(graph.t, np.float64), t]),
        np.concatenate([np.asarray(graph.kappa, np.float64), kappa]),
        np.concatenate([np.asarray(graph.tau, np.float64), tau]), num_poses=n, dtype=dt)
    outlier = np.concatenate([np.zeros(graph.num_edges, bool), np.ones(count, bool)])
    return CorruptedGraph(graph=out, outlier=outlier, rate=float(rate), seed=int(seed))


add_outlier_loop_closures = add_outliers  # its public name: mmpgo_jax.add_outlier_loop_closures


@dataclass(frozen=True)
class OutlierScores:
    """How an inlier mask classifies the edges against the truth. For the outliers: ``precision``
    (rejected edges that are outliers) and ``recall`` (outliers rejected); for the inliers:
    ``inlier_precision`` (kept edges that are inliers) and ``inlier_recall`` (inliers kept). A
    ratio with an empty denominator is 1."""

    precision: float
    recall: float
    inlier_precision: float
    inlier_recall: float
    rejected: int
    outliers: int


def _ratio(num: int, den: int) -> float:
    return 1.0 if den == 0 else num / den


def outlier_scores(inliers, outlier) -> OutlierScores:
    """Scores of the inlier mask ``inliers`` (m,) against the true ``outlier`` mask (m,)."""
    kept = np.asarray(inliers, bool)
    bad = np.asarray(outlier, bool)
    if kept.shape != bad.shape:
        raise ValueError(f"masks differ in shape: {kept.shape} vs {bad.shape}")
    rejected = ~kept
    return OutlierScores(
        precision=_ratio(int((rejected & bad).sum()), int(rejected.sum())),
        recall=_ratio(int((rejected & bad).sum()), int(bad.sum())),
        inlier_precision=_ratio(int((kept & ~bad).sum()), int(kept.sum())),
        inlier_recall=_ratio(int((kept & ~bad).sum()), int((~bad).sum())),
        rejected=int(rejected.sum()),
        outliers=int(bad.sum()),
    )
