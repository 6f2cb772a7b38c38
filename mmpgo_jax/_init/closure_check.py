"""The accepted inter-robot loop closures checked against the whole team's map.

The distributed robust start (:mod:`~mmpgo_jax._init.robust_distributed`) judges every inter-robot
closure against the robots' own maps held rigid, with their drift as a variance. On long noisy
chains that drift is radians, and wrong closures pass: on a 15 000-pose planar graph of 10 robots
(benchmarks/robust_teams.md) its frame test accepted 19 of 73 wrong closures, and holding them bends
the team's map so far that TLS then rejects most correct closures (F_rho at the held edges' optimum
1.4e6 against about 1e4; the same collapse from the rigid maps even with the right classification
given, because the distributed solver does not straighten 1 500-pose chains from rigid maps in 1 000
iterations).

This check places every pose at once: the distributed chordal start
(:func:`~mmpgo_jax._init.distributed_chordal.distributed_chordal_initialization`, neighbour exchanges
only) of the edges accepted so far, where a wrong closure pulls the chains it joins and shows the
largest residual. Each round drops the accepted inter-robot closure of largest residual (a
max-reduction over robots) and solves again; the TLS objective of every edge at each round's map
(odometry at its cost s, loop closures at min(s, c^2); a sum-reduction) says which round was best,
and the check ends when ``patience`` rounds in a row found no lower objective or no accepted
closure's residual exceeds c^2 (one that fits within c is no suspect), keeping the acceptance of the
round of lowest objective. The chordal map is not an optimum, so its objective is noisy: removing
a wrong closure lowered it by 1e5-2e7 on that graph and removing a correct one moved it by 1e2-1e4
either way, and a wrong closure's removal raised it once while 83 were left; hence the patience
rather than the first rise. A correct closure can be dropped while wrong ones still bend the map
(on a 4-robot team with three wrong closures the second round's largest residual was a correct
one, 400 c^2 there and 2.7 c^2 at the final map, where putting it back raised the chordal map's
objective by about c^2). The check only prepares the start: the pipelines' search re-admits rejected
closures, cheapest first, in batches (:func:`~mmpgo_jax._solve.solve.solve`); a plain TLS run from the start need not
take such a closure back (that one stayed at 2.7 c^2, beyond c).

Trusted edges (consecutive poses) are never candidates, nor a closure whose removal would split the
team's graph.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._core.pose_graph import HostPoses, PoseGraph, connected_subgraph, host_edge_costs, host_graph

#: Rounds in a row without a lower objective after which the check ends (see the module docstring).
DEFAULT_PATIENCE = 10


@dataclass(frozen=True)
class ClosureCheck:
    """What :func:`check_inter_robot_closures` found: ``accepted`` (m,) bool after the check,
    ``poses`` the chordal map of those edges, ``removed`` the edges dropped (in order), ``objective``
    the TLS objective at each round's map (round 0: the given acceptance)."""

    accepted: np.ndarray
    poses: HostPoses
    removed: np.ndarray
    objective: np.ndarray


def check_inter_robot_closures(graph: PoseGraph, robot_of_pose: np.ndarray, accepted, scale: float, *,
                               trusted=None, patience: int = DEFAULT_PATIENCE) -> ClosureCheck:
    """Drop accepted inter-robot loop closures while the team's chordal map says they are wrong
    (module docstring). ``accepted`` (m,) bool: the edges accepted so far (every trusted edge among
    them); ``scale``: c of the TLS objective; ``trusted`` (m,) bool: edges never dropped (default:
    those between consecutive poses)."""
    from .distributed_chordal import distributed_chordal_initialization

    if int(patience) < 1:
        raise ValueError(f"patience must be >= 1, got {patience!r}")
    g = host_graph(graph)
    robot = np.asarray(robot_of_pose)
    trusted = np.abs(g.i - g.j) == 1 if trusted is None else np.asarray(trusted, bool)
    candidate = (robot[g.i] != robot[g.j]) & ~trusted
    acc = np.array(accepted, bool)
    c2 = float(scale) ** 2

    def chordal_map(keep):
        kept = connected_subgraph(g, keep)
        if kept is None:  # dropping that closure would split the team: it stays
            return None
        X, _ = distributed_chordal_initialization(kept, robot)
        return HostPoses(np.asarray(X.R, np.float64), np.asarray(X.t, np.float64))

    X = chordal_map(acc)
    if X is None:
        raise ValueError("check_inter_robot_closures: the accepted edges do not join every pose")
    best = (np.inf, acc.copy(), X, 0)
    objective, removed, since = [], [], 0
    kept_in = np.zeros(g.num_edges, bool)  # closures whose removal would split the team
    while X is not None:
        s = host_edge_costs(g, X)
        f = _tls_objective(s, trusted, c2)
        objective.append(f)
        if f < best[0]:
            best, since = (f, acc.copy(), X, len(removed)), 0
        else:
            since += 1
        suspect = candidate & (s > c2)  # a closure that fits within c is no suspect
        X = None if since >= patience else _next_map(acc, s, suspect, kept_in, removed, chordal_map)
    _, acc, X, count = best
    return ClosureCheck(accepted=acc, poses=X, removed=np.asarray(removed[:count], np.int64),
                        objective=np.asarray(objective))


def _tls_objective(s: np.ndarray, trusted: np.ndarray, c2: float) -> float:
    """The TLS objective of every edge: trusted edges at their cost s, the others at min(s, c^2)."""
    return float(np.sum(np.where(trusted, s, np.minimum(s, c2))))


def _next_map(acc, s, candidate, kept_in, removed, chordal_map):
    """The chordal map after dropping the open candidate of largest residual ``s`` (``acc``,
    ``removed`` updated); a candidate whose removal would split the team is kept (``kept_in``) and
    the next one tried. None when no candidate is left."""
    while True:
        open_ = np.flatnonzero(acc & candidate & ~kept_in)
        if not open_.size:
            return None
        edge = int(open_[np.argmax(s[open_])])
        acc[edge] = False
        X = chordal_map(acc)
        if X is not None:
            removed.append(edge)
            return X
        acc[edge], kept_in[edge] = True, True
