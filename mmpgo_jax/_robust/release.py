"""What leaving out one accepted inter-robot loop closure would change, judged robot pair by robot pair.

A wrong closure the start accepted can bend its two robots' maps until it fits them: at the run's
result its own cost is small, and what it costs shows only in the robots' other edges. Leaving it
out changes the truncated least-squares objective 2 F_rho by c^2 - (its cost) - (what its robots'
other edges release once it is gone). The release is estimated here per robot pair: the two robots'
poses re-optimized (Newton, :func:`~mmpgo_jax._mm.centralized.newton_optimum`) over the edges the
run keeps that touch them, every other robot's poses held where they are (what the pair's neighbours
send them), once with the closure and once without it. A whole run, whose other robots move too, can
release more, so the prediction is conservative: a closure predicted to lower the objective is worth
a trial run, one predicted not to may still be wrong. No step needs more than two robots' maps and
their neighbours' boundary poses. Measured on a 10 x 500-pose team with the Cube's noise (seed 1,
benchmarks/robust_teams.md): the one wrong closure the run kept is predicted at -6.4, every correct
closure of a pair holding at most two at +6.6 or more.
"""

from __future__ import annotations

import numpy as np

from .._core.gauge import FixedPoses
from .._core.pose_graph import HostGraph, PoseGraph, Poses, edge_costs, host_view
from .._mm.centralized import newton_optimum
from .._mm.driver import Termination

#: the pair solves' stopping rule: ||grad F|| <= GRAD_TOL or MAX_ITERATIONS Newton iterations. The
#: maps start at the run's result, so a few iterations reach the pair's optimum (2-6 on 10 x 500-pose
#: teams); the estimate needs F to a small fraction of c^2, not the certificate's gradient.
GRAD_TOL = 1e-6
MAX_ITERATIONS = 50


def removal_changes(graph: PoseGraph, robot_of_pose, poses: Poses, kept, candidates, scale_squared: float
                    ) -> np.ndarray:
    """(k,) the change of 2 F_rho (truncated least squares at ``scale_squared`` = c^2) predicted for
    leaving out each of ``candidates`` (edge indices, each accepted and between two robots): the
    optimum of its two robots' maps over the ``kept`` (m,) edges touching them without it, plus c^2,
    less that optimum with it (other robots' poses held at ``poses``). Negative: leaving it out is
    predicted to lower the objective."""
    g = host_view(graph)
    robot = np.asarray(robot_of_pose)
    kept = np.asarray(kept, bool)
    R, t = np.asarray(poses.R, np.float64), np.asarray(poses.t, np.float64)
    with_it = {}  # per robot pair: the optimum with every kept edge (the same for each of its closures)
    out = np.empty(len(candidates))
    for k, e in enumerate(np.asarray(candidates, np.int64)):
        pair = tuple(sorted((int(robot[g.i[e]]), int(robot[g.j[e]]))))
        free = np.isin(robot, pair)
        edges = kept & (free[g.i] | free[g.j])
        if pair not in with_it:
            with_it[pair] = _pair_optimum(g, R, t, edges, free)
        edges[e] = False
        out[k] = _pair_optimum(g, R, t, edges, free) + scale_squared - with_it[pair]
    return out


def _pair_optimum(g: HostGraph, R: np.ndarray, t: np.ndarray, edges: np.ndarray, free: np.ndarray) -> float:
    """min over the ``free`` poses of the cost of ``edges``, the other poses they touch held at (R, t)."""
    i, j = g.i[edges], g.j[edges]
    poses = np.unique(np.concatenate([i, j]))
    renumber = np.empty(g.num_poses, np.int64)
    renumber[poses] = np.arange(poses.size)
    sub = PoseGraph(renumber[i], renumber[j], g.R[edges], g.t[edges], g.kappa[edges], g.tau[edges],
                    num_poses=int(poses.size))
    held = np.flatnonzero(~free[poses])
    fixed = FixedPoses(held, R[poses[held]], t[poses[held]]) if held.size else None
    Ro, to, *_ = newton_optimum(sub, R[poses], t[poses], Termination(MAX_ITERATIONS, 1, GRAD_TOL,
                                                                     stop_when_stalled=False), fixed=fixed)
    return float(np.sum(edge_costs(sub, Poses(Ro, to))))
