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
largest residual. Each round drops one of the two accepted inter-robot closures of largest residual (a
max-reduction over robots), each dropped on trial with the map solved again: the one whose map has the
lower TLS objective (every edge: odometry at its cost s, loop closures at min(s, c^2); a sum-reduction)
goes, or both when the two differ by less than c^2 (one closure's share), where the map cannot tell
which is wrong: the run's weights and the search then judge both at a better map. On a 10 x 500-pose
team (seed 2 at 50 %, benchmarks/robust_teams.md) a wrong closure and a correct one of another robot
pair pulled one robot two ways, both at 3.4 c^2, the correct one's residual the larger by a hair:
dropping the largest residual lost it for good; their maps' objectives were 1 623.5 and 1 622.7, and as
both could not go (the robot would be cut off) the wrong one went. The same objective at each round's
map says which round was best, and the check ends when ``patience`` rounds in a row found no lower
objective or no accepted closure's residual exceeds c^2 (one that fits within c is no suspect), keeping
the acceptance of the round of lowest objective. The chordal map is not an optimum, so its objective is
noisy: removing a wrong closure lowered it by 1e5-2e7 on that graph and removing a correct one moved it
by 1e2-1e4 either way, and a wrong closure's removal raised it once while 83 were left; hence the
patience rather than the first rise. A correct closure can be dropped while wrong ones still bend the
map (on a 4-robot team with three wrong closures the second round's largest residual was a correct one,
400 c^2 there and 2.7 c^2 at the final map, where putting it back raised the chordal map's objective by
about c^2). The check only prepares the start: the pipelines' search re-admits rejected closures,
cheapest first, in batches (:func:`~mmpgo_jax._solve.solve.solve`); a plain TLS run from the start need
not take such a closure back (that one stayed at 2.7 c^2, beyond c).

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
    ``poses`` the chordal map of those edges, ``removed`` the edges dropped (in order), ``rounds`` the
    round that dropped each (one or two per round), ``objective`` the TLS objective at each round's
    map (round 0: the given acceptance), ``cg_iterations`` (solves, 2): the rotation and translation
    CG iterations of every distributed chordal solve the check made (trials included), what its
    neighbour exchanges follow."""

    accepted: np.ndarray
    poses: HostPoses
    removed: np.ndarray
    rounds: np.ndarray
    objective: np.ndarray
    cg_iterations: np.ndarray


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

    cg_iterations = []

    def chordal_map(keep):
        kept = connected_subgraph(g, keep)
        if kept is None:  # dropping that closure would split the team: it stays
            return None
        X, info = distributed_chordal_initialization(kept, robot)
        cg_iterations.append((info.rotation_iterations, info.translation_iterations))
        return HostPoses(np.asarray(X.R, np.float64), np.asarray(X.t, np.float64))

    X = chordal_map(acc)
    if X is None:
        raise ValueError("check_inter_robot_closures: the accepted edges do not join every pose")
    best = (np.inf, acc.copy(), X, 0)
    objective, removed, rounds, since = [], [], [], 0
    kept_in = np.zeros(g.num_edges, bool)  # closures whose removal would split the team
    while X is not None:
        s = host_edge_costs(g, X)
        f = _tls_objective(s, trusted, c2)
        objective.append(f)
        if f < best[0]:
            best, since = (f, acc.copy(), X, len(removed)), 0
        else:
            since += 1
        if since >= patience:
            break
        suspect = candidate & (s > c2)  # a closure that fits within c is no suspect
        dropped, X = _next_drop(acc, s, suspect, kept_in, chordal_map, lambda Y: _tls_objective(
            host_edge_costs(g, Y), trusted, c2), c2)
        removed += dropped
        rounds += [len(objective)] * len(dropped)
    _, acc, X, count = best
    return ClosureCheck(accepted=acc, poses=X, removed=np.asarray(removed[:count], np.int64),
                        rounds=np.asarray(rounds[:count], np.int64), objective=np.asarray(objective),
                        cg_iterations=np.asarray(cg_iterations, np.int64).reshape(-1, 2))


def _tls_objective(s: np.ndarray, trusted: np.ndarray, c2: float) -> float:
    """The TLS objective of every edge: trusted edges at their cost s, the others at min(s, c^2)."""
    return float(np.sum(np.where(trusted, s, np.minimum(s, c2))))


def _dropped_map(acc, s, candidate, kept_in, chordal_map, skip=-1):
    """(edge, map) for the open candidate of largest residual ``s`` other than ``skip``, whose
    removal does not split the team (one that would is marked in ``kept_in`` and the next tried);
    None when no candidate is left. ``acc`` is left as given."""
    while True:
        open_ = np.flatnonzero(acc & candidate & ~kept_in)
        open_ = open_[open_ != skip]
        if not open_.size:
            return None
        edge = int(open_[np.argmax(s[open_])])
        acc[edge] = False
        X = chordal_map(acc)
        acc[edge] = True
        if X is not None:
            return edge, X
        kept_in[edge] = True


def _next_drop(acc, s, candidate, kept_in, chordal_map, objective_of, c2):
    """One round: the closures dropped (``acc`` updated) and the chordal map after, or ([], None)
    when no candidate is left. The two open candidates of largest residual are each dropped on
    trial; the one whose map has the lower objective goes, or both when the two objectives differ by
    less than c^2 (one closure's share of the objective): the map cannot tell which of them is wrong
    (a wrong and a correct closure pulling one robot two ways show the same residual), so neither
    is held, and the run's TLS weights and the search's re-admissions judge them at a better map."""
    first = _dropped_map(acc, s, candidate, kept_in, chordal_map)
    if first is None:
        return [], None
    second = _dropped_map(acc, s, candidate, kept_in, chordal_map, skip=first[0])
    if second is None:
        acc[first[0]] = False
        return [first[0]], first[1]
    (a, Xa), (b, Xb) = first, second
    fa, fb = objective_of(Xa), objective_of(Xb)
    if abs(fa - fb) < c2:
        acc[[a, b]] = False
        both = chordal_map(acc)
        if both is not None:
            return [a, b], both
        acc[[a, b]] = True
    edge, X = (a, Xa) if fa <= fb else (b, Xb)
    acc[edge] = False
    return [edge], X
