"""Pre-filters of :func:`~mmpgo_jax.solve`: inter-robot loop closures removed before the start and
the solve (``solve(..., prefilter="pcm")`` or ``prefilter=PCM(confidence=...)``).

PCM (:func:`~mmpgo_jax._robust.pcm.pcm_filter`) keeps, per robot pair, the largest set of mutually
consistent inter-robot loop closures. Its test needs only the two robots' odometry chains and their
shared closures, so it is a per-pair computation that fits a distributed run. The solve then runs on
the graph without the rejected edges (same poses, edge order kept), and the result is put back in
the original edge order, so that removed edges are never silent: ``result.prefiltered`` (m,) marks
them, ``result.inliers`` marks them False (for least squares too: there ``inliers`` is exactly
``~prefiltered``), ``result.weights`` (robust losses) holds 0 for them, and ``result.stats`` gains
``pcm_rejected``, ``pcm_seconds``, ``pcm_confidence`` and ``pcm_components``.

A robot whose every closure to the others was rejected leaves the filtered graph disconnected
(``pcm_components`` > 1): every start anchors the first pose of each component at the identity
(:func:`~mmpgo_jax._core.gauge.anchor_set`), the solvers keep that gauge per component, so the run
succeeds but that robot's map sits in its own frame (its placement relative to the others is
arbitrary, not estimated).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from .._core.partition import Partition, split_robots
from .._core.pose_graph import PoseGraph, component_labels
from .._core.validate import check_count, check_real

__all__ = ["PCM", "Prefiltered", "apply_prefilter", "as_prefilter"]


@dataclass(frozen=True)
class PCM:
    """PCM as a pre-filter of :func:`~mmpgo_jax.solve`; the fields are
    :func:`~mmpgo_jax.pcm_filter`'s (``confidence``: the chi-square quantile of the pairwise test)."""

    confidence: float = 0.99
    max_pair_closures: int | None = 200
    min_clique_size: int = 1
    ties: str = "break"

    def __post_init__(self):
        check_real("PCM", "confidence", self.confidence, 0.0, 1.0, low_open=True, high_open=True, scalar=True)
        check_count("PCM", "max_pair_closures", self.max_pair_closures, 1, optional=True, scalar=True)
        check_count("PCM", "min_clique_size", self.min_clique_size, 1, scalar=True)
        if self.ties not in ("break", "keep"):
            raise ValueError(f"PCM: ties must be 'break' or 'keep', got {self.ties!r}")


def as_prefilter(prefilter) -> PCM | None:
    """``solve``'s ``prefilter``: None, ``"pcm"`` (PCM's defaults) or a :class:`PCM`."""
    if prefilter is None or isinstance(prefilter, PCM):
        return prefilter
    if isinstance(prefilter, str) and prefilter.lower() == "pcm":
        return PCM()
    raise ValueError(f"prefilter must be None, 'pcm' or a PCM(...), got {prefilter!r}")


@dataclass(frozen=True)
class Prefiltered:
    """A graph after the pre-filter: ``graph`` (the kept edges, in their original order),
    ``rejected`` (m,) bool over the original edges, ``robot_of_pose`` (n,) and the filter's stats."""

    graph: PoseGraph
    rejected: np.ndarray
    robot_of_pose: np.ndarray
    stats: dict

    def report(self, result):
        """``result`` (a solve of :attr:`graph`) with its per-edge arrays in the original edge order
        and the removed edges marked (module docstring)."""
        keep = ~self.rejected
        inliers = keep.copy()
        if result.inliers is not None:
            inliers[keep] = np.asarray(result.inliers, bool)
        def widened(w):  # removed edges: weight 0
            if w is None:
                return None
            out = np.zeros(keep.shape, np.asarray(w).dtype)
            out[keep] = np.asarray(w)
            return out

        stats = {**result.stats, **self.stats}
        if "starts" in stats:  # the edges of the revisits, re-admissions, removals and exchanges: original order
            original = np.flatnonzero(keep)

            def renumbered(rounds, *edges):  # an edge, or a list of them (a batch of re-admissions)
                return [dict(r, **{e: original[r[e]].tolist() for e in edges}) for r in rounds]

            def moves_renumbered(rounds):  # an exchange's (admitted, left out); None (admitted alone) stays None
                return [dict(r, moves=[(int(original[a]), None if out is None else int(original[out]))
                                       for a, out in r["moves"]]) for r in rounds]

            stats["starts"] = [dict(row, revisits=renumbered(row.get("revisits", []), "excluded"),
                                    readmissions=renumbered(row.get("readmissions", []), "admitted"),
                                    removals=renumbered(row.get("removals", []), "removed"),
                                    exchanges=moves_renumbered(row.get("exchanges", [])))
                               for row in stats["starts"]]
        return dataclasses.replace(result, inliers=inliers, weights=widened(result.weights),
                                   start_weights=widened(result.start_weights), prefiltered=self.rejected.copy(),
                                   stats=stats)


def robot_of_pose(graph: PoseGraph, robots) -> np.ndarray:
    """(n,) robot of each pose of ``solve``'s ``robots`` (a count, an array or a :class:`Partition`)."""
    if isinstance(robots, Partition):
        return np.asarray(robots.robot_of_pose, np.int64)[: graph.num_poses]
    return split_robots(graph, robots)


def apply_prefilter(graph: PoseGraph, robots, prefilter) -> Prefiltered | None:
    """Run the pre-filter (None: nothing to do) and return the filtered graph with what it removed."""
    config = as_prefilter(prefilter)
    if config is None:
        return None
    from .._robust.pcm import pcm_filter

    t0 = time.perf_counter()
    rop = robot_of_pose(graph, robots)
    pcm = pcm_filter(graph, rop, confidence=config.confidence, max_pair_closures=config.max_pair_closures,
                     min_clique_size=config.min_clique_size, ties=config.ties)
    rejected = ~pcm.keep
    kept = graph.select_edges(pcm.keep) if rejected.any() else graph
    _, sizes, _ = component_labels(graph.num_poses, np.asarray(kept.i), np.asarray(kept.j))
    stats = dict(pcm_rejected=int(rejected.sum()), pcm_closures=int(pcm.closures.sum()),
                 pcm_confidence=float(config.confidence), pcm_components=len(sizes),
                 pcm_seconds=time.perf_counter() - t0)
    return Prefiltered(kept, rejected, rop, stats)
