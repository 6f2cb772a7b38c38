"""How noisy the data are against what their information matrices say: the a-posteriori variance
factor of a least-squares fit (geodesy's sigma_0^2), host-side.

With SE-Sync's noise model each edge's cost s = kappa ||R_j - R_i R_ij||^2 + tau ||t_j - t_i - R_i
t_ij||^2 is about chi^2 with p = d(d+1)/2 degrees of freedom when the information matrices are
right, so at the optimum sum s ~ chi^2_r with the redundancy r = p (m - n + K) (m edges, n poses, K
components each fixing one pose's gauge), and sum s / r is about 1. Far from 1 it says the
information matrices over- or understate the noise, by that factor in variance. A robust loss's
scale c is set in the information's units (:func:`~mmpgo_jax.chi2_scale`): a factor far below 1
makes c loose (an outlier that bends the map a little costs less than c^2), far above 1 tight
(correct edges beyond c)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .pose_graph import PoseGraph, Poses, connected_components, edge_costs, host_graph


class NoiseLevel(NamedTuple):
    """``factor`` = sum s / ``redundancy`` (the a-posteriori variance factor) and its two-sided
    ``confidence`` interval [``low``, ``high``] (sum s / chi^2_r quantiles); ``factor`` is nan
    without redundancy (chains: the fit is exact whatever the noise)."""

    factor: float
    low: float
    high: float
    redundancy: int
    confidence: float

    def nearest_one(self) -> float:
        """1 when the interval holds 1 (the data do not contradict their information), else its end
        nearer to 1; 1 without redundancy."""
        if self.redundancy <= 0:
            return 1.0
        return float(np.clip(1.0, self.low, self.high))


def noise_level(graph: PoseGraph, poses: Poses, num_components: int | None = None,
                confidence: float = 0.99) -> NoiseLevel:
    """The :class:`NoiseLevel` of ``graph``'s edges at ``poses`` (an optimum of those edges, e.g. a
    robust run's poses with ``graph.select_edges(result.inliers)``). ``num_components``: gauges
    fixed (default: the connected components of the graph's edges)."""
    from scipy import stats

    if not 0.0 < confidence < 1.0:
        raise ValueError(f"noise_level.confidence must be in (0, 1), got {confidence!r}")
    g = host_graph(graph)
    if num_components is None:
        num_components = len(connected_components(g.num_poses, np.asarray(g.i), np.asarray(g.j)))
    p = g.dim * (g.dim + 1) // 2
    redundancy = int(p * (g.num_edges - g.num_poses + num_components))
    if redundancy <= 0:
        return NoiseLevel(float("nan"), float("nan"), float("nan"), redundancy, confidence)
    total = float(np.sum(edge_costs(g, Poses(np.asarray(poses.R), np.asarray(poses.t)))))
    tail = (1.0 - confidence) / 2.0
    low = total / stats.chi2.ppf(1.0 - tail, redundancy)
    high = total / stats.chi2.ppf(tail, redundancy)
    return NoiseLevel(total / redundancy, float(low), float(high), redundancy, confidence)
