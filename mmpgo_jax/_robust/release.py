"""What leaving out one accepted inter-robot loop closure (or any move of the classification) would
change, judged robot pair by robot pair.

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

:func:`move_changes` predicts any move of the classification the same way (closures admitted, left
out, or both: an exchange), with every robot the moved closures touch re-optimized; the robust
search's exchanges (``mmpgo_jax._solve.solve._exchanged_in_run``) are proposed by it.
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
    return move_changes(graph, robot_of_pose, poses, kept, [((), (int(e),)) for e in candidates], scale_squared)


def move_changes(graph: PoseGraph, robot_of_pose, poses: Poses, kept, moves, scale_squared: float,
                 warm: dict | None = None) -> np.ndarray:
    """(k,) the change of 2 F_rho predicted for each of ``moves``: (admitted, left out), two tuples of
    edge indices, the first rejected by ``kept`` (m,), the second accepted. The robots the moved edges
    touch are re-optimized over the kept edges touching them, before and after the move (the other
    robots' poses held at ``poses``); the change is the optimum after less the one before, plus c^2 per
    edge left out (it now costs c^2) and minus c^2 per edge admitted (it cost c^2). A re-admission is
    a move of one admitted edge, a removal one of one left out, an exchange one of each.

    ``warm``: a dict kept by the caller across calls on nearby poses (the robust search's rounds,
    each from the last one's result): per move, the free poses its last solve after the move ended
    at, from which its next solve starts (the held poses at their new values). A move that admits a
    closure far from its robots' maps starts far from its optimum: from ``poses``, Newton needed about
    30 iterations (0.3 s on a 10 x 500-pose team's pair of robots, against 2-4 for the same robots
    before the move), from its last optimum a few."""
    g = host_view(graph)
    robot = np.asarray(robot_of_pose)
    kept = np.asarray(kept, bool)
    R, t = np.asarray(poses.R, np.float64), np.asarray(poses.t, np.float64)
    before = {}  # per set of free robots: the optimum of the kept edges (the same for each of its moves)
    out = np.empty(len(moves))
    for k, (admitted, left_out) in enumerate(moves):
        moved = np.asarray([*admitted, *left_out], np.int64)
        robots = tuple(sorted(set(robot[g.i[moved]].tolist()) | set(robot[g.j[moved]].tolist())))
        free = np.isin(robot, robots)
        edges = kept & (free[g.i] | free[g.j])
        if robots not in before:
            before[robots] = _pair_optimum(g, R, t, edges, free)[0]
        edges[list(admitted)] = True
        edges[list(left_out)] = False
        start = (R, t)
        if warm is not None and (admitted, left_out) in warm:
            at, R_last, t_last = warm[(admitted, left_out)]
            start = (R.copy(), t.copy())
            start[0][at], start[1][at] = R_last, t_last
        after, at, R_after, t_after = _pair_optimum(g, *start, edges, free)
        if warm is not None:
            warm[(admitted, left_out)] = (at, R_after, t_after)
        out[k] = after - before[robots] + scale_squared * (len(left_out) - len(admitted))
    return out


def _pair_optimum(g: HostGraph, R: np.ndarray, t: np.ndarray, edges: np.ndarray, free: np.ndarray) -> tuple:
    """(min over the ``free`` poses of the cost of ``edges``, the other poses they touch held at (R, t);
    the free poses' indices and their values there)."""
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
    moved = np.flatnonzero(free[poses])
    return float(np.sum(edge_costs(sub, Poses(Ro, to)))), poses[moved], Ro[moved], to[moved]
