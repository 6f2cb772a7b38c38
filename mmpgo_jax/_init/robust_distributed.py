"""A distributed robust start: each robot's own robust map, then the robots' frames from their
inter-robot loop closures (the robust initialization of Kimera-Multi and mit-acl/dpgo).

**Local maps.** Every robot solves its own graph (its poses, its odometry and intra-robot loop
closures) with the GNC-chordal start (:func:`~mmpgo_jax._init.robust_start.gnc_chordal_initialization`:
its own GNC-TLS). All robots are solved by one call on the union of their subgraphs, i.e. the graph
with every inter-robot edge removed: a disconnected graph whose components are solved independently
by the chordal relaxation and Newton (each anchored at its first pose, :func:`~mmpgo_jax._core.gauge.anchor_set`),
with no loop over robots. A *local map* is a connected component of that graph (one per robot when
its odometry is complete; a robot whose odometry has gaps has several, each placed on its own and
counted in ``DistributedRobustStart.maps_of_robot``). The GNC schedule (mu and its stages) is shared
by the components: mu_0 is set by the largest residual of all robots, which for a robot with smaller
residuals is a more convex first surrogate than its own mu_0 (GNC needs mu_0 *at most* c^2 / (2
s_max - c^2)), and the stages go on until every robot's weights are binary, which for a robot already
binary re-solves the same weighted problem (its weights change only for residuals within the
narrowing band around c^2 of the later stages). So the shared schedule is not the per-robot one and
its weights may differ: measured against one GNC-chordal call per robot on 3-robot teams of 60 poses
with 30 % wrong loop closures (five draws), both classified every intra-robot closure right on four,
and on the fifth the per-robot call rejected robot 0's four correct closures (its own, larger mu_0)
where the shared schedule kept them (tests/test_robust_distributed_start.py, marked slow). The one
call also compiles once: 2 s against 15-73 s for three per-robot calls (their shapes differ). A
robot's result depends on the other robots only through the schedule: s_max (one max-reduction
before GNC) and whether any robot's weights are still between 0 and 1 (one or-reduction per stage).

**Frame hypotheses.** An inter-robot closure Z_e from pose i of map a to pose j of map b says where
b's frame is in a's: with the local solutions T_i, T_j, M_e = T_i Z_e T_j^-1 (F_a^-1 F_b, F the
maps' frames in the world). It becomes an edge a -> b of a *frame graph* of K nodes (the local maps)
with the closure's weights kappa_e, tau_e; its cost at frames F is the closure's cost at the poses
F T up to the lever arm of the rotation error (equal when the rotation residual is zero).

**Pair averaging** (:func:`pair_average`, vectorised over all map pairs with segment sums): per pair,
GNC-TLS on the rotations (a kappa-weighted chordal mean, residual kappa_e ||R_e - R_ab||_F^2 against
chi^2_{d(d-1)/2}(``quantile``)), then the tau-weighted mean of the translations of the rotation
inliers, residual tau_e ||t_e - t_ab||^2 against chi^2_d(``quantile``); a pair is usable with at
least ``min_inliers`` inliers. With one closure a pair has nothing to check; with two that disagree
both residuals are equal (the mean lies between them) and both are rejected, or both kept.

**Frames** (``frames=``):

* ``"graph"`` (default): GNC-TLS (chordal + Newton stages, the same solver) on the frame graph with
  one edge per closure, scale sqrt(chi^2_{d(d+1)/2}(``quantile``)), no edge trusted. A closure is then
  checked against every other closure of its pair *and* every cycle of maps through it (robot
  triples and longer): a pair's single closure is judged by the other pairs. GNC is a heuristic and
  on frame graphs of a few maps it was seen to end in a wrong solution that the tree below avoids
  (4 robots, 11 hypotheses: it accepted an outlier whose residual at the true frames is 3400 c^2);
  so the frames of the tree below are a second candidate, and a consensus search a third: random
  spanning trees of the frame graph (one hypothesis per pair, RANSAC-like), each tree's frames then
  refitted to the hypotheses within c of them plus its own (weighted least squares) until its
  inliers stop changing -- the local optimisation of LO-RANSAC (Chum et al., 2003). Without the
  refit a tree's frames carry the drift of its few closures, so the all-correct trees scored worse
  than wrong ones: on 10 x 500-pose teams (low noise, 30 % of the inter-robot closures wrong, seed 0)
  it accepted an outlier and rejected four correct closures, with the refit none
  (tests/test_robust_distributed_start.py). The candidate with the lowest TLS cost
  sum min(s_e, c^2) over all hypotheses decides which hypotheses are accepted (s_e <= c^2). The
  accepted closures of a pair with fewer than ``min_inliers`` of them are dropped, and the frames are
  the least-squares solution of the accepted hypotheses (chordal + Newton).
* ``"tree"``: dpgo's order: the pair averages, then the maps placed along a maximum spanning tree of
  the usable pairs (weights: inlier counts; scipy's minimum spanning tree of the negated counts),
  the frames composed along it (an exact chordal solve of the tree's graph). Closures of usable pairs
  off the tree are then accepted when their residual at the composed frames is within the scale.

The frame graph is small (K nodes, one edge per inter-robot closure, (d^2 + d + 2) numbers each,
the closures' implied transforms): no step gathers a robot's poses or its own edges. Where the
frame graph is solved is left to the caller (here: in the process that calls the start).

**What it cannot decide.** A closure of a pair that is a bridge of the accepted pair graph (no cycle
of maps through it) and the pair's only closure is unverified: nothing else constrains it, so it is
accepted if it is the only link (``DistributedRobustStart.unverified``). Maps that no accepted closure
joins to the map of pose 0 are not placed in its frame (``placed`` False; ``unplaced_robots``): each
group of maps joined among themselves keeps the frame of its first map (a map alone: its local frame).
The local maps' own error is the weak point: the hypotheses of correct closures scatter with the
maps' drift (on 10 x 500-pose teams at 0.005 pi rad per step: up to 0.44 rad and 6.5 cells at the true
frames), far beyond the closures' information (dpgo's test, ``map_sigma=(0, 0)``, rejected every
correct closure there). The default ``map_sigma="odometry"`` adds the odometry chain's drift, which
ignores the intra-robot closures and so over-states it (one of two such teams: 2 of 13 outliers
accepted, 4 correct closures rejected); with the Cube's noise (0.02 pi rad per step) the maps are off
by up to 8 cells and no threshold separates the hypotheses (benchmarks/robust_teams.md).

**Result.** X^0 = each map's local solution moved to its frame; ``weights`` (m,) in {0, 1}: the local
GNC's on intra-robot edges (1 on odometry) and the acceptance of each inter-robot closure. The
robust solver does not take weights: it starts with rho'(s) at X^0 (TLS: 1 where s <= c^2), and at
X^0 the maps are rigid, so correct inter-robot closures have s far above c^2 and TLS drops them all.
Least squares on the accepted edges from X^0, then TLS, reached the outlier-free optimum wherever the
start had sorted the closures right (benchmarks/robust_teams.md): a solver that starts from these
weights is the intended use. :func:`~mmpgo_jax._init.start.initialize` returns the poses only and
warns when a robot is not placed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._core.geometry import project_to_so
from .._core.noise import noise_level
from .._core.pose_graph import HostPoses, PoseGraph, component_labels, host_graph
from .._mm.robust import TLS, chi2_scale, gnc_initial_mu, gnc_weight
from .chordal import chordal_initialization
from .closure_check import DEFAULT_PATIENCE, ClosureCheck, check_inter_robot_closures
from .robust_start import gnc_chordal_initialization

__all__ = ["FRAME_METHODS", "DistributedRobustStart", "PairAverages", "chain_variances",
           "distributed_robust_initialization", "pair_average"]

TREE_SAMPLES = 256  # random spanning trees of the frame graph's consensus search
MAX_REFITS = 20  # refits of a sampled tree until its inliers stop changing (2-4 on the teams measured)
# hypotheses x refitted samples per refit (one chordal solve of that many edges): all 256 samples below
# ~800 hypotheses (teams with one or two closures per robot pair, where the search matters); fewer on
# frame graphs of thousands of closures (city10000: several per pair, which the pair averages decide)
REFIT_EDGES = 200_000
VARIANCE_FACTOR_FLOOR = 1e-6  # rounding of noise-free maps, not a noise level
MAP_ERRORS = ("closures", "odometry")  # models of the local maps' own error (map_sigma=)
FRAME_METHODS = ("graph", "tree")


@dataclass(frozen=True)
class PairAverages:
    """Robust averages of the frame hypotheses per map pair (rows of ``pairs``, a < b): ``R``, ``t``
    (b's frame in a's), ``closures`` and ``inliers`` per pair; ``inlier`` (h,) per hypothesis; ``pair``
    (h,) the row of each hypothesis."""

    pairs: np.ndarray
    R: np.ndarray
    t: np.ndarray
    closures: np.ndarray
    inliers: np.ndarray
    inlier: np.ndarray
    pair: np.ndarray


@dataclass(frozen=True)
class DistributedRobustStart:
    """The distributed robust start (module docstring). Per pose: ``poses`` (world), ``local`` (in its
    map's frame), ``map_of_pose``; per edge: ``weights`` (m,) in {0, 1}, ``inter`` (inter-robot);
    per map: ``robot_of_map``, ``frames`` (HostPoses (K,)), ``placed``; ``pairs`` the pair averages
    (:class:`PairAverages`); per inter-robot closure (in edge order): ``unverified`` (accepted but
    checked by nothing); ``unplaced_robots``; ``local_stages`` and ``frame_stages`` (GNC stages);
    ``hypothesis_cost`` (m,): each inter-robot closure's frame-hypothesis cost at the final frames under
    the test's variance model (NaN on the other edges and on excluded ones), ``frame_scale`` the test's
    c (a hypothesis is accepted within c^2 unless the frame search found it cheaper to reject);
    ``variance_factor``: the local maps' a-posteriori variance factor (:func:`variance_factor`; 1 with
    ``map_sigma`` given as numbers); ``team_check``: what the check of the accepted closures at the
    team's chordal map found (:class:`~mmpgo_jax._init.closure_check.ClosureCheck`), None when not
    asked for."""

    poses: HostPoses
    local: HostPoses
    map_of_pose: np.ndarray
    robot_of_map: np.ndarray
    frames: HostPoses
    placed: np.ndarray
    weights: np.ndarray
    inter: np.ndarray
    unverified: np.ndarray
    pairs: PairAverages
    unplaced_robots: np.ndarray
    local_stages: int
    frame_stages: int
    hypothesis_cost: np.ndarray | None = None
    frame_scale: float = float("nan")
    variance_factor: float = 1.0
    team_check: ClosureCheck | None = None

    @property
    def accepted(self) -> np.ndarray:
        """(m,) bool: the inter-robot closures accepted (False on the other edges)."""
        return self.inter & (self.weights > 0.5)

    @property
    def maps_of_robot(self) -> np.ndarray:
        """(A,) number of local maps of each robot (1 with complete odometry)."""
        return np.bincount(self.robot_of_map)


def _robot_of_pose(graph, robots) -> np.ndarray:
    from .._core.partition import Partition, contiguous_robots

    n = graph.num_poses
    if robots is None:
        raise ValueError("distributed-robust needs robots= (a count, an (n,) robot-of-pose array or a Partition)")
    if isinstance(robots, Partition):
        rop = np.asarray(robots.robot_of_pose, np.int64)
    elif np.ndim(robots) == 0:
        rop = contiguous_robots(n, int(robots))
    else:
        rop = np.asarray(robots, np.int64).reshape(-1)
    if rop.shape != (n,) or (n and rop.min() < 0):
        raise ValueError(f"robots: need a non-negative robot index for each of the {n} poses, got shape {rop.shape}")
    return rop


@dataclass(frozen=True)
class StartTraffic:
    """What a robot team exchanges for the distributed robust start (float64 numbers, 8 bytes each),
    counted for the step's distributed form (this module computes it in one process, with only the
    information these messages carry): ``closure_numbers``: for each inter-robot closure, the robot of
    its far end sends that pose in its map (d^2 + d numbers) and its two map variances to the robot of
    the near end; ``hypothesis_numbers``: every frame hypothesis (R, t, its two weights, the two map
    indices: d^2 + d + 4) goes to every other robot, so that each solves the small frame graph itself
    (an all-gather); ``reduction_numbers``: the variance factor's two sums, each robot sending and
    receiving them (an all-reduce). The robots' own GNC maps exchange nothing."""

    robots: int
    closures: int
    closure_numbers: int
    hypothesis_numbers: int
    reduction_numbers: int

    @property
    def bytes(self) -> int:
        return 8 * (self.closure_numbers + self.hypothesis_numbers + self.reduction_numbers)


def start_traffic(graph: PoseGraph, robots) -> StartTraffic:
    """:class:`StartTraffic` of :func:`distributed_robust_initialization` on ``graph`` split by
    ``robots`` (a count, an (n,) robot-of-pose array or a Partition)."""
    rop = _robot_of_pose(graph, robots)
    i, j = np.asarray(graph.i), np.asarray(graph.j)
    closures = int(np.count_nonzero(rop[i] != rop[j]))
    A = int(np.unique(rop).size)
    d = graph.dim
    return StartTraffic(robots=A, closures=closures, closure_numbers=closures * (d * d + d + 2),
                        hypothesis_numbers=closures * (d * d + d + 4) * (A - 1), reduction_numbers=2 * 2 * A)


def _segment_sum(values, index, size):
    out = np.zeros((size, *values.shape[1:]))
    np.add.at(out, index, values)
    return out


def _inverse(R, t):
    Rt = np.swapaxes(R, -1, -2)
    return Rt, -np.einsum("...ab,...b->...a", Rt, t)


def _compose(Ra, ta, Rb, tb):
    return Ra @ Rb, np.einsum("...ab,...b->...a", Ra, tb) + ta


def _gnc_tls_mean(x, w0, pair, num_pairs, c2, mean, residual, max_stages=100, factor=1.4, tol=1e-4):
    """GNC-TLS of a weighted mean per segment (vectorised over segments): ``mean(weights)`` gives the
    (P, ...) means, ``residual(means)`` the (h,) residuals s; mu per segment from its own largest
    residual. Returns (means, inlier (h,) bool)."""
    w = np.ones(len(pair))
    m = mean(w0 * w)
    s = residual(m)
    s_max = np.full(num_pairs, 0.0)
    np.maximum.at(s_max, pair, s)
    mu = np.asarray(gnc_initial_mu(TLS, s_max, c2))
    for _ in range(max_stages):  # GNC stages (a loop over stages, every pair at once)
        active = np.isfinite(mu)
        if not active.any():
            break
        w_new = np.asarray(gnc_weight(TLS, s, c2, np.where(active, mu, 1.0)[pair]))
        w = np.where(active[pair], w_new, (s <= c2).astype(np.float64))
        m = mean(w0 * w)
        s = residual(m)
        between = (w > tol) & (w < 1 - tol)
        open_pair = np.zeros(num_pairs, bool)
        open_pair[pair[between]] = True
        mu = np.where(open_pair, mu * factor, np.inf)
    inlier = s <= c2
    return m, inlier


def pair_average(pair, R, t, kappa, tau, num_pairs: int, *, quantile: float = 0.9):
    """Robust per-pair averages of hypotheses (R (h, d, d), t (h, d)) of segment ``pair`` (h,):
    rotations first (GNC-TLS on a kappa-weighted chordal mean, chi^2_{d(d-1)/2}(quantile)), then
    translations of the rotation inliers (GNC-TLS on a tau-weighted mean, chi^2_d(quantile)).
    Returns (R (P, d, d), t (P, d), inlier (h,) bool); a pair without inliers keeps its plain mean."""
    from scipy import stats

    d = R.shape[-1]
    c2R = float(stats.chi2.ppf(quantile, d * (d - 1) // 2))
    c2t = float(stats.chi2.ppf(quantile, d))

    def rot_mean(w):
        S = _segment_sum(w[:, None, None] * R, pair, num_pairs)
        empty = _segment_sum(w, pair, num_pairs) <= 0
        S[empty] = _segment_sum(kappa[:, None, None] * R, pair, num_pairs)[empty]
        return project_to_so(S)

    Rm, in_rot = _gnc_tls_mean(R, kappa, pair, num_pairs, c2R, rot_mean,
                               lambda M: kappa * np.sum((R - M[pair]) ** 2, axis=(-1, -2)))

    def trans_mean(w):
        ws = _segment_sum(w, pair, num_pairs)
        fallback = ws <= 0
        ws_all = _segment_sum(tau, pair, num_pairs)
        S = np.where(fallback[:, None], _segment_sum(tau[:, None] * t, pair, num_pairs),
                     _segment_sum(w[:, None] * t, pair, num_pairs))
        return S / np.where(fallback, ws_all, ws)[:, None]

    w0 = tau * in_rot
    tm, in_t = _gnc_tls_mean(t, w0, pair, num_pairs, c2t, trans_mean,
                             lambda m: tau * np.sum((t - m[pair]) ** 2, axis=-1))
    return Rm, tm, in_rot & in_t


def chain_variances(graph, t, map_of_pose):
    """(var_R (n,), var_t (n,)): first-order, isotropic variances of each pose of a local map relative
    to the map's first pose along its odometry chain (poses in index order, odometry edges (k, k + 1)
    of the map): var_R(p) = sum over the steps k < p of 1 / (2 kappa_k) (the variance of one rotation
    angle under SE-Sync's noise model), var_t(p) = sum 1 / tau_k + sum v_k ||t_p - t_k||^2 (each
    step's rotation error swings the rest of the chain about pose k; t the local solution). All by
    prefix sums (n log-free cumulative sums, no loop over poses). The intra-robot loop closures are
    not counted, so this bounds a well-closed map's error from above; a map with odometry gaps gets
    only the steps it has."""
    n = graph.num_poses
    odo = (graph.j == graph.i + 1) & (map_of_pose[graph.i] == map_of_pose[graph.j])
    k = graph.i[odo]
    v = np.zeros(n)
    u = np.zeros(n)
    np.add.at(v, k + 1, 0.5 / graph.kappa[odo])  # step k -> k+1 counts for the poses after k
    np.add.at(u, k + 1, 1.0 / graph.tau[odo])
    pivot = np.zeros(n, np.int64)
    pivot[k + 1] = k
    tk = t[pivot]
    first = np.zeros(map_of_pose.max() + 1 if n else 0, np.int64) + n
    np.minimum.at(first, map_of_pose, np.arange(n))
    start = first[map_of_pose]

    def since_start(x):
        c = np.cumsum(x, axis=0)
        return c - c[start] + x[start]  # the map's first pose has no step of its own (its x is 0)

    S0, S1, S2 = since_start(v), since_start(v[:, None] * tk), since_start(v * np.sum(tk**2, -1))
    var_t = since_start(u) + np.sum(t**2, -1) * S0 - 2.0 * np.sum(t * S1, -1) + S2
    return S0, np.maximum(var_t, 0.0)


def _grounded_resistances(n, i, j, conductance, anchors, probes: int, rng) -> np.ndarray:
    """(n,) effective resistance between each node and its component's anchor in the graph of edges
    (i, j) with ``conductance`` (anchors: 0), by the Johnson-Lindenstrauss estimate of Spielman &
    Srivastava: R(p) = ||W^1/2 B L_g^-1 e_p||^2 ~ ||Q W^1/2 B L_g^-1 e_p||^2 with Q a random
    (probes x edges) sign matrix / sqrt(probes), i.e. ``probes`` solves with one sparse factorization
    of the grounded Laplacian L_g (relative error about sqrt(2 / probes) per node)."""
    import scipy.sparse as sp

    from .._core.sparse import pose_order, solve_spd

    free = np.ones(n, bool)
    free[anchors] = False
    m = len(i)
    B = sp.csr_matrix((np.concatenate([np.ones(m), -np.ones(m)]),
                       (np.concatenate([np.arange(m)] * 2), np.concatenate([i, j]))), shape=(m, n))[:, free]
    sw = np.sqrt(conductance)
    L = (B.T @ sp.diags(conductance) @ B).tocsc()
    Q = rng.choice([-1.0, 1.0], size=(m, probes)) / np.sqrt(probes)
    rhs = B.T @ (sw[:, None] * Q)
    index = np.cumsum(free) - 1
    both = free[i] & free[j]

    def order():  # nested dissection of the free poses (the Laplacian's pattern is the graph's)
        return pose_order(int(free.sum()), index[i[both]], index[j[both]])

    Y = solve_spd(L, np.asarray(rhs), perm=order)
    out = np.zeros(n)
    out[free] = np.sum(Y**2, axis=1)
    return out


def closure_variances(graph, t, map_of_pose, keep=None, *, probes: int = 64, seed: int = 0):
    """(var_R (n,), var_t (n,)): first-order, isotropic variances of each pose of a local map relative
    to the map's first pose, counting every edge of the map (``keep``: the edges its own GNC kept;
    default all edges inside a map): var_R(p) is the effective resistance between the first pose and
    p with conductance 2 kappa per edge (a chain gives :func:`chain_variances`' sum of 1 / (2 kappa)),
    var_t(p) the resistance with conductance tau plus the chain's lever-arm term (each rotation error
    swinging the rest of the chain) scaled by how much the loop closures shrink the rotation variance,
    var_R(p) / var_R_chain(p). Resistances by :func:`_grounded_resistances` (``probes`` sparse solves,
    a fixed ``seed``: the same result on every call). Each robot needs only its own edges."""
    n = graph.num_poses
    inside = map_of_pose[graph.i] == map_of_pose[graph.j]
    if keep is not None:
        inside &= keep
    first = np.full(map_of_pose.max() + 1 if n else 0, n, np.int64)
    np.minimum.at(first, map_of_pose, np.arange(n))
    rng = np.random.default_rng(seed)
    gi, gj = graph.i[inside], graph.j[inside]
    var_R = _grounded_resistances(n, gi, gj, 2.0 * graph.kappa[inside], first, probes, rng)
    res_t = _grounded_resistances(n, gi, gj, graph.tau[inside], first, probes, rng)
    chain_R, chain_t = chain_variances(graph, t, map_of_pose)
    odo = (graph.j == graph.i + 1) & (map_of_pose[graph.i] == map_of_pose[graph.j])
    steps = np.zeros(n)
    np.add.at(steps, graph.i[odo] + 1, 1.0 / graph.tau[odo])
    start = first[map_of_pose]
    c = np.cumsum(steps)
    lever = np.maximum(chain_t - (c - c[start] + steps[start]), 0.0)
    shrink = np.clip(var_R / np.maximum(chain_R, 1e-300), 0.0, 1.0)
    var_R = np.minimum(var_R, np.where(chain_R > 0, chain_R, var_R))
    return var_R, res_t + lever * shrink


def variance_factor(local_graph: PoseGraph, poses: HostPoses, num_maps: int) -> float:
    """The a-posteriori variance factor of the local maps, kept at 1 unless the data says otherwise
    (:func:`~mmpgo_jax._core.noise.noise_level` of their kept edges with K = ``num_maps`` gauges, at
    99 %: sum s over the redundancy p (m - n + K), about 1 when the information matrices are right):
    the value of its interval nearest to 1, so 1 when the interval holds 1 (few closures say
    little), otherwise its nearer end (files whose information matrices overstate the noise, e.g.
    M3500: about 0.03). Every variance of the frame tests is multiplied by it. 1 without redundancy
    (chains). A sum over the robots (one number each), like GNC's shared schedule."""
    level = noise_level(local_graph, poses, num_maps)
    return max(level.nearest_one(), VARIANCE_FACTOR_FLOOR)


_LOCAL_MAPS: dict = {}  # the last few local-map solves, by their graphs' bytes (see _local_maps)
LOCAL_MAPS_KEPT = 2


def _local_maps(local_g: PoseGraph, scale, trust_odometry: bool):
    """The robots' own GNC-chordal maps (step 1), solved once per process for the same robots'
    graphs: a robust solve that remakes the start (its revisits) changes only inter-robot
    closures, so the maps are the same (a deterministic function of these inputs) and their solve,
    most of the start's time, is not repeated. Keyed by a digest of the graph's arrays and the
    options; the last :data:`LOCAL_MAPS_KEPT` are kept."""
    import hashlib

    digest = hashlib.sha256()
    for x in (local_g.i, local_g.j, local_g.R, local_g.t, local_g.kappa, local_g.tau):
        digest.update(np.ascontiguousarray(x).tobytes())
    key = (digest.hexdigest(), local_g.num_poses, None if scale is None else float(scale), bool(trust_odometry))
    if key not in _LOCAL_MAPS:
        while len(_LOCAL_MAPS) >= LOCAL_MAPS_KEPT:
            _LOCAL_MAPS.pop(next(iter(_LOCAL_MAPS)))
        _LOCAL_MAPS[key] = gnc_chordal_initialization(local_g, scale=scale, trust_odometry=trust_odometry)
    return _LOCAL_MAPS[key]


def _frame_graph(a, b, R, t, kappa, tau, K) -> PoseGraph:
    return PoseGraph(a, b, R, t, kappa, tau, num_poses=K)


def _tree_frames(pairs, counts, Rp, tp, K, d):
    """Frames (R, t) (K,) composed along a maximum spanning tree (on ``counts``) of the pairs with
    counts > 0, and the tree's pair rows."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import minimum_spanning_tree

    use = np.flatnonzero(counts > 0)
    if use.size == 0:
        return np.broadcast_to(np.eye(d), (K, d, d)).copy(), np.zeros((K, d)), use
    top = counts.max() + 1
    W = coo_matrix((top - counts[use], (pairs[use, 0], pairs[use, 1])), shape=(K, K)).tocsr()
    T = minimum_spanning_tree(W).tocoo()
    key = pairs[use, 0] * K + pairs[use, 1]
    tk = np.minimum(T.row, T.col) * K + np.maximum(T.row, T.col)
    tree = use[np.isin(key, tk)]
    g = _frame_graph(pairs[tree, 0], pairs[tree, 1], Rp[tree], tp[tree], np.ones(len(tree)), np.ones(len(tree)), K)
    X = chordal_initialization(g)  # a tree: the chordal solution composes the pair transforms exactly
    return np.asarray(X.R, np.float64), np.asarray(X.t, np.float64), tree


def _sampled_tree_costs(a, b, Rh, th, kap, tau, trusted, K, d, samples: int, rng, c2: float,
                        max_refits: int) -> np.ndarray:
    """(S, H) costs of every hypothesis at the frames of S random spanning trees of the frame graph
    (a consensus search, RANSAC-like: each tree takes one random hypothesis per map pair, the trusted
    ones first, and composes the frames along it exactly). All S trees are one disconnected graph:
    one minimum-spanning-tree call and one chordal solve, no loop over samples or maps. With
    ``max_refits`` > 0, (S + R, H): R more rows, the first R trees' frames refitted to their inliers
    (within ``c2``) and their tree until the inliers stop changing (at most ``max_refits`` rounds),
    R = :data:`REFIT_EDGES` / H within [16, S]."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import minimum_spanning_tree

    H = len(a)
    if H == 0:  # one map, no frame to choose (a connected graph without inter-robot closures)
        return np.zeros((samples, 0))
    key = np.where(trusted, 0.5, 1.0 + rng.random((samples, H)))  # trusted: always the pair's pick
    pair_id = a * K + b
    order = np.lexsort((np.zeros(H), pair_id))
    starts = np.flatnonzero(np.r_[True, pair_id[order][1:] != pair_id[order][:-1]])
    best = np.minimum.reduceat(key[:, order], starts, axis=1)  # (S, P) the pick's key per pair
    pick_of = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, H]))
    chosen = key[:, order] == best[:, pick_of]  # (S, H) in ``order``: the picked hypothesis of each pair
    s_idx, col = np.nonzero(chosen)
    h = order[col]
    base = s_idx * K
    W = coo_matrix((key[s_idx, h], (base + a[h], base + b[h])), shape=(samples * K, samples * K)).tocsr()
    T = minimum_spanning_tree(W).tocoo()
    lo, hi = np.minimum(T.row, T.col), np.maximum(T.row, T.col)
    edge_key = (base + a[h]) * (samples * K) + base + b[h]
    tree = np.isin(edge_key, lo * (samples * K) + hi)
    hs, ss = h[tree], s_idx[tree]
    g = _frame_graph(ss * K + a[hs], ss * K + b[hs], Rh[hs], th[hs], np.ones(len(hs)), np.ones(len(hs)), samples * K)
    X = chordal_initialization(g)  # a forest: the chordal solution composes each tree's transforms exactly
    costs = _forest_costs(X, samples, K, d, a, b, Rh, th, kap, tau)
    if max_refits == 0:
        return costs
    R = int(np.clip(REFIT_EDGES // max(H, 1), 16, samples))  # the first R samples are refitted
    in_tree = np.zeros((R, H), bool)
    in_tree[ss[ss < R], hs[ss < R]] = True
    refit, inlier = costs[:R], costs[:R] <= c2
    for _ in range(max_refits):  # until no sample's inlier set changes (a fixed point of the refit)
        refit = _refit_costs(inlier, in_tree | trusted, R, K, d, a, b, Rh, th, kap, tau)
        inlier, before = refit <= c2, inlier
        if np.array_equal(inlier, before):
            break
    return np.concatenate([costs, refit])


def _forest_costs(X, samples, K, d, a, b, Rh, th, kap, tau):
    FR = np.asarray(X.R, np.float64).reshape(samples, K, d, d)
    Ft = np.asarray(X.t, np.float64).reshape(samples, K, d)
    return _hypothesis_costs(FR[:, a], Ft[:, a], FR[:, b], Ft[:, b], Rh, th, kap, tau)


def _refit_costs(inlier, always, samples, K, d, a, b, Rh, th, kap, tau):
    """(S, H) costs at the weighted least-squares frames of each sample's hypotheses in ``inlier`` |
    ``always`` (S, H) (its tree: the sample stays connected): the local optimisation of LO-RANSAC, all
    samples as one disconnected graph (one chordal solve)."""
    s_idx, h = np.nonzero(inlier | always)
    base = s_idx * K
    g = _frame_graph(base + a[h], base + b[h], Rh[h], th[h], kap[h], tau[h], samples * K)
    return _forest_costs(chordal_initialization(g), samples, K, d, a, b, Rh, th, kap, tau)


def _hypothesis_costs(Ra, ta, Rb, tb, Rh, th, kappa, tau):
    """Cost of frame-graph edges (Rh, th) between frames a and b (the edge-cost convention)."""
    rot = Ra @ Rh - Rb
    trans = np.einsum("...ab,...b->...a", Ra, th) + ta - tb
    return kappa * np.sum(rot**2, axis=(-1, -2)) + tau * np.sum(trans**2, axis=-1)


def _bridges(K, a, b) -> np.ndarray:
    """(len(a),) bool: the edges (a, b) that are bridges of the multigraph on K nodes."""
    import networkx as nx

    G = nx.MultiGraph()
    G.add_nodes_from(range(K))
    G.add_edges_from(zip(a.tolist(), b.tolist(), strict=True))
    bridge = {tuple(sorted(e)) for e in nx.bridges(nx.Graph(G)) if G.number_of_edges(*e) == 1}
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    key = set(bridge)
    return np.fromiter(((int(x), int(y)) in key for x, y in zip(lo, hi, strict=True)), bool, count=len(a))


def distributed_robust_initialization(
    graph: PoseGraph,
    robots,
    *,
    scale: float | None = None,
    quantile: float = 0.9,
    min_inliers: int = 1,
    frames: str = "graph",
    map_sigma="closures",
    trust_odometry: bool = True,
    seed: int = 0,
    excluded=None,
    team_check: bool = False,
    patience: int = DEFAULT_PATIENCE,
) -> DistributedRobustStart:
    """The distributed robust start (module docstring). ``robots``: a count (contiguous blocks), an
    (n,) robot-of-pose array or a Partition. ``scale``: the local GNC's c (default
    :func:`~mmpgo_jax.chi2_scale`, as the GNC-chordal start); ``quantile``: of the chi-square tests of
    the frame hypotheses (dpgo's 0.9); ``min_inliers``: accepted closures a pair needs to be used;
    ``frames``: ``"graph"`` or ``"tree"``; ``map_sigma``: the local maps' own error at a closure's
    ends, added to the closure's noise in every test of the frame hypotheses: ``"closures"`` (default:
    the first-order variance of each pose relative to its map's first pose with every kept edge of the
    map, :func:`closure_variances`), ``"odometry"`` (the odometry chain's drift alone,
    :func:`chain_variances`, an upper bound), both times :func:`variance_factor`; or (sigma_R in rad,
    sigma_t in map units) for every pose ((0, 0): the closure's information alone, as dpgo), as given.
    ``seed``: of the random probes and spanning trees (the result is a function of it). ``excluded``:
    (m,) bool, edges left out of every step (weight 0; a robust solve that overruled the start's
    acceptance of them, :func:`~mmpgo_jax._solve.solve.solve`). ``team_check``: then check the
    accepted inter-robot closures at the team's distributed chordal map, dropping them one by one by
    residual while the TLS objective there falls (``patience`` rounds without a lower one end it;
    :func:`~mmpgo_jax._init.closure_check.check_inter_robot_closures`); the start is then that
    chordal map of the edges kept, not the rigid maps in their frames (for long noisy chains, where
    the frame test passes wrong closures and rigid maps are far from the team's optimum); only when
    every map is placed (otherwise the accepted edges do not join the team, and the start warns)."""
    if frames not in FRAME_METHODS:
        raise ValueError(f"frames must be one of {', '.join(FRAME_METHODS)}, got {frames!r}")
    if int(min_inliers) < 1:
        raise ValueError(f"min_inliers must be >= 1, got {min_inliers!r}")
    if not 0.0 < quantile < 1.0:
        raise ValueError(f"quantile must be in (0, 1), got {quantile!r}")
    g = host_graph(graph)
    n, d, m = g.num_poses, g.dim, g.num_edges
    rop = _robot_of_pose(g, robots)
    inter = rop[g.i] != rop[g.j]
    use = np.ones(m, bool) if excluded is None else ~np.asarray(excluded, bool).reshape(-1)
    if use.shape != (m,):
        raise ValueError(f"excluded: need one bool per edge, shape ({m},), got {use.shape}")

    # 1. local maps: every robot's own graph, one GNC-chordal call over their union
    local_g = g.select_edges(~inter & use)
    local = _local_maps(local_g, scale, trust_odometry)
    TR, Tt = np.array(local.poses.R, np.float64), np.array(local.poses.t, np.float64)  # the cached maps stay intact
    labels, _, firsts = component_labels(n, local_g.i, local_g.j)
    order = np.argsort(firsts)  # maps numbered by their first pose: map 0 holds pose 0
    renumber = np.empty_like(order)
    renumber[order] = np.arange(len(order))
    map_of_pose = renumber[labels]
    K = len(order)
    robot_of_map = rop[firsts[order]]

    # 2. frame hypotheses, one per inter-robot closure, oriented a < b
    e = np.flatnonzero(inter & use)
    i, j = g.i[e], g.j[e]
    Ri, ti = _compose(TR[i], Tt[i], g.R[e], g.t[e])
    Rj_inv, tj_inv = _inverse(TR[j], Tt[j])
    Rh, th = _compose(Ri, ti, Rj_inv, tj_inv)
    a, b = map_of_pose[i], map_of_pose[j]
    flip = a > b
    Rf, tf = _inverse(Rh[flip], th[flip])
    Rh[flip], th[flip] = Rf, tf
    a, b = np.minimum(a, b), np.maximum(a, b)
    if isinstance(map_sigma, str):
        if map_sigma not in MAP_ERRORS:
            raise ValueError(f"map_sigma must be one of {', '.join(map(repr, MAP_ERRORS))} or (sigma_R, sigma_t), "
                             f"got {map_sigma!r}")
        kept = use.copy()
        kept[~inter & use] = np.asarray(local.weights) > 0.5
        if map_sigma == "odometry":
            vR, vt = chain_variances(g, Tt, map_of_pose)
        else:
            vR, vt = closure_variances(g, Tt, map_of_pose, kept, seed=seed)
        factor = variance_factor(g.select_edges(kept & ~inter), HostPoses(TR, Tt), K)
    else:
        sR, st = (float(x) for x in map_sigma)
        if not (sR >= 0 and st >= 0 and np.isfinite(sR) and np.isfinite(st)):
            raise ValueError(f"map_sigma must be two finite numbers >= 0, got {map_sigma!r}")
        vR, vt = np.full(n, sR**2), np.full(n, st**2)
        factor = 1.0
    kap = 1.0 / (factor * (1.0 / g.kappa[e] + 2.0 * (vR[i] + vR[j])))
    tau = 1.0 / (factor * (1.0 / g.tau[e] + vt[i] + vt[j]))

    # an inter-robot odometry edge (consecutive poses of two robots, e.g. a contiguous split) is trusted
    # as the robots' own odometry is: always accepted, never truncated by the frame graph's GNC
    trusted = (np.abs(i - j) == 1) if trust_odometry else np.zeros(len(e), bool)
    pair_keys, pair = np.unique(a * K + b, return_inverse=True)
    P = len(pair_keys)
    pairs = np.stack([pair_keys // K, pair_keys % K], 1)
    Rp, tp, inlier = pair_average(pair, Rh, th, kap, tau, P, quantile=quantile)
    counts = np.bincount(pair, weights=inlier, minlength=P).astype(np.int64)
    averages = PairAverages(pairs=pairs, R=Rp, t=tp, closures=np.bincount(pair, minlength=P), inliers=counts,
                            inlier=inlier, pair=pair)

    # 3. the maps' frames
    c_frame = chi2_scale(d, quantile)
    frame_stages = 0
    c2 = c_frame**2
    usable = np.where(counts >= min_inliers, counts, 0)
    FR, Ft, _ = _tree_frames(pairs, usable, Rp, tp, K, d)
    s = _hypothesis_costs(FR[a], Ft[a], FR[b], Ft[b], Rh, th, kap, tau)
    keep = (usable[pair] > 0) & (s <= c2)
    keep |= trusted
    if frames == "graph":
        fg = _frame_graph(a, b, Rh, th, kap, tau, K)
        res = gnc_chordal_initialization(fg, scale=c_frame, trust_odometry=False, trusted=trusted)
        frame_stages = res.stages
        GR, Gt = np.asarray(res.poses.R, np.float64), np.asarray(res.poses.t, np.float64)
        s_gnc = _hypothesis_costs(GR[a], Gt[a], GR[b], Gt[b], Rh, th, kap, tau)

        def tls_cost(x):  # trusted hypotheses cost s (never truncated)
            return np.where(trusted, x, np.minimum(x, c2)).sum(axis=-1)

        samples = int(np.clip(2_000_000 // max(len(a), 1), 16, TREE_SAMPLES))
        s_trees = _sampled_tree_costs(a, b, Rh, th, kap, tau, trusted, K, d, samples, np.random.default_rng(seed),
                                      c2, MAX_REFITS)
        candidates = [s, s_gnc, s_trees[np.argmin(tls_cost(s_trees))]]  # the lowest TLS cost of the three
        best = candidates[int(np.argmin([tls_cost(x) for x in candidates]))]
        if best is not s:
            keep = best <= c2
        keep &= np.bincount(pair, weights=keep, minlength=P)[pair] >= min_inliers
        keep |= trusted
        FR, Ft = _solve_frames(fg, keep, K, d)

    # 4. placed maps: joined to map 0 by accepted closures
    comp, _, _ = component_labels(K, a[keep], b[keep]) if K > 1 else (np.zeros(1, np.int64), None, None)
    placed = comp == comp[0]
    R = FR[map_of_pose] @ TR
    t = np.einsum("nab,nb->na", FR[map_of_pose], Tt) + Ft[map_of_pose]

    cost = np.full(m, np.nan)
    cost[e] = _hypothesis_costs(FR[a], Ft[a], FR[b], Ft[b], Rh, th, kap, tau)
    w = np.zeros(m)
    w[~inter & use] = np.asarray(local.weights, np.float64)
    w[e] = keep.astype(np.float64)
    unverified = np.zeros(m, bool)
    if keep.any():
        single = np.bincount(pair, weights=keep, minlength=P)[pair] == 1
        unverified[e[keep]] = single[keep] & _bridges(K, a[keep], b[keep]) & ~trusted[keep]
    checked = None
    if team_check and placed.all():
        c_team = float(chi2_scale(d) if scale is None else scale)
        checked = check_inter_robot_closures(g, rop, w > 0.5, c_team, patience=patience,
                                             trusted=np.abs(g.i - g.j) == 1 if trust_odometry else np.zeros(m, bool))
        w = checked.accepted.astype(np.float64)
        R, t = checked.poses.R, checked.poses.t
    return DistributedRobustStart(
        poses=HostPoses(R, t), local=HostPoses(TR, Tt), map_of_pose=map_of_pose, robot_of_map=robot_of_map,
        frames=HostPoses(FR, Ft), placed=placed, weights=w, inter=inter, unverified=unverified, pairs=averages,
        unplaced_robots=np.unique(robot_of_map[~placed]), local_stages=local.stages, frame_stages=frame_stages,
        hypothesis_cost=cost, frame_scale=c_frame, variance_factor=float(factor), team_check=checked)


def _solve_frames(fg: PoseGraph, keep, K, d):
    """Frames from the kept frame-graph edges (chordal + Newton of the weighted frame graph)."""
    if not keep.any():
        return np.broadcast_to(np.eye(d), (K, d, d)).copy(), np.zeros((K, d))
    sub = fg.select_edges(keep)
    res = gnc_chordal_initialization(sub, scale=np.inf, trust_odometry=False)
    return np.asarray(res.poses.R, np.float64).copy(), np.asarray(res.poses.t, np.float64).copy()
