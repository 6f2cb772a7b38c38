"""Pairwise consistency maximization (PCM) of inter-robot loop closures.

Mangelson, Dominic, Eustice and Vasudevan, "Pairwise Consistent Measurement Set Maximization for
Robust Multi-robot Map Merging", ICRA 2018; the front end of DOOR-SLAM and Kimera-Multi. For each
pair of robots (a, b), two of their loop closures z_u = (pose i of a -> pose k of b) and
z_v = (pose j of a -> pose l of b) are *consistent* when the cycle

    x_i -(z_u)-> x_k -(b's odometry)-> x_l -(z_v^-1)-> x_j -(a's odometry)-> x_i

composes to nearly the identity; the largest set of pairwise consistent closures (a maximum
clique of the consistency graph, exact: a 0/1 program solved by HiGHS, :func:`scipy.optimize.milp`,
for dense consistency graphs, networkx's branch and bound for sparse ones; among cliques of that
size, the one whose closures passed the most tests) is kept and the pair's
other closures are dropped. **Ties** (``ties="keep"``): where another clique of the same size
exists, the data give PCM no reason to prefer one (a robot pair with one correct and one wrong
closure: two cliques of one, neither passing a test); "keep" keeps the closures of every clique
that equals the one found in size and in tests passed and leaves the choice to the robust solver
after it, "break" (the default, as published) keeps the one above.
Odometry edges (j == i + 1, same robot) and intra-robot edges are always kept (intra-robot loop
closures are not checked).

**Chains.** Each robot's odometry is composed once, as a prefix product: P_p = o_start ... o_(p-1)
is pose p in the frame of the first pose of its *segment* (a maximal run of consecutive poses of
one robot joined by odometry edges; one segment per robot when the odometry is complete), computed
for all poses at once by a segmented Hillis-Steele scan in NumPy (log2 n array steps, no loop over
poses). The chain from pose p to pose q of a segment is P_p^-1 P_q.

**Test.** With M_u = P_i z_u P_k^-1 (the frame of b's segment in a's segment frame according to
z_u), the cycle is conjugate to E = M_u M_v^-1, and the test is the chi-square test on
r = Log(E) (SE(d) log, :func:`mmpgo_jax._core.geometry.se_log`, coordinates (rho, omega)):
r^T Sigma^-1 r < chi2.ppf(confidence, d(d+1)/2).

**Covariance** (first order, left perturbations in a's segment frame, linearized at the consistent
hypothesis E = I, i.e. the null distribution of the test):

    Sigma = (G_a[max(i, j)] - G_a[min(i, j)]) + Ad(M_u) (G_b[max(k, l)] - G_b[min(k, l)]) Ad(M_u)^T
            + Ad(P_i z_u) S_u Ad(P_i z_u)^T + Ad(P_j z_v) S_v Ad(P_j z_v)^T,

where S_e is the edge's covariance (the inverse of the isotropic information that
:func:`mmpgo_jax._io.g2o.information_from_weights` assigns to (kappa, tau): translation 1/tau per
axis, rotation 1/kappa in 2D and 1/(2 kappa) per axis in 3D, SE-Sync's g2o conversion) and
G[q] = sum_(s <= q) Ad(P_s) S_(odometry s-1 -> s) Ad(P_s)^T is the running (cumulative) sum of the
odometry covariances rotated into the segment's frame. G[q] - G[p] is the exact first-order
covariance of the chain p -> q (the shared prefix cancels), so the chain covariance grows with the
chain's length and its lever arms, as the odometry's own noise model says. No further bound or
scaling is applied, so the test is only as good as the graph's information: information that
overstates the odometry's noise makes long chains accept outliers (M3500's isotropic 44.7 weights:
a rotation std of 0.15 rad per step), information that understates it makes correct closures
inconsistent (benchmarks/pcm.md measures both).

Pairs of closures without an odometry path between their ends (different segments of one robot)
cannot be tested and count as consistent (counted in ``PCMResult.untestable``).

**Distributed cost** (``numbers_sent``, as if each robot pair ran PCM separately): the pair's
closures (2 pose indices, d^2 + d measurement entries and the 2 weights each) and, for the distinct
closure ends on each robot, its chain pose P_p (d^2 + d numbers) and G[p] (D(D+1)/2 numbers,
D = d(d+1)/2), plus one keep flag per closure sent back; 8 bytes per number.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .._core.geometry import se_log
from .._core.lie import so
from .._core.pose_graph import PoseGraph
from .._io.g2o import information_from_weights

__all__ = ["OdometryChains", "PCMResult", "odometry_chains", "pairwise_chi2", "pcm_filter"]

#: pairs of closures evaluated per vectorised block (memory: ~ 10 arrays of (block, D, D) float64)
BLOCK_PAIRS = 1 << 16


@dataclass(frozen=True)
class PCMResult:
    """What :func:`pcm_filter` kept. Per robot pair (rows of ``pairs``, a < b): ``closures`` (the
    pair's inter-robot edges), ``kept`` (closures kept: the maximum
    clique's size, with ``ties="keep"`` also the closures of tied cliques), ``consistent`` (closure pairs
    that passed the test), ``untestable`` (closure pairs without an odometry path, counted as
    consistent), ``numbers_sent`` (module docstring)."""

    keep: np.ndarray  # (m,) bool over the graph's edges; odometry and intra-robot edges always True
    pairs: np.ndarray  # (P, 2) robot pairs a < b that share inter-robot edges
    closures: np.ndarray  # (P,)
    kept: np.ndarray  # (P,) closures kept
    consistent: np.ndarray  # (P,)
    untestable: np.ndarray  # (P,)
    numbers_sent: np.ndarray  # (P,)
    threshold: float  # the chi-square quantile
    confidence: float
    seconds: float  # the whole call
    clique_seconds: float  # of which in the maximum-clique searches

    @property
    def bytes_sent(self) -> int:
        return int(8 * self.numbers_sent.sum())

    @property
    def rejected(self) -> np.ndarray:
        return ~self.keep

    @property
    def num_rejected(self) -> int:
        return int((~self.keep).sum())


@dataclass(frozen=True)
class OdometryChains:
    """Prefix compositions of the odometry: pose p is (R[p], t[p]) in the frame of its segment's
    first pose; ``G[p]`` the running sum of the odometry covariances in that frame (module
    docstring); ``segment[p]`` the segment's id (runs of consecutive poses joined by odometry)."""

    R: np.ndarray  # (n, d, d)
    t: np.ndarray  # (n, d)
    G: np.ndarray  # (n, D, D)
    segment: np.ndarray  # (n,) int


def _adjoint(R, t):
    """Ad of rigid motions (R (..., d, d), t (..., d)) on coordinates (rho, omega): (..., D, D),
    [[R, hat(t) Ad_R], [0, Ad_R]] with hat(t) Ad_R = -(omega -> hat(omega) t) Ad_R (Ad_R of SO(d):
    R in 3D, 1 in 2D)."""
    group = so(R.shape[-1])
    Ad = group.adjoint(R)
    top = np.concatenate([R, -group.hat_apply_matrix(t) @ Ad], -1)
    bottom = np.concatenate([np.zeros((*R.shape[:-2], group.tangent_dim, R.shape[-1])), Ad], -1)
    return np.concatenate([top, bottom], -2)


def _conj(A, S):
    """A S A^T for stacks of square matrices."""
    return A @ S @ np.swapaxes(A, -1, -2)


def _edge_covariances(kappa, tau, d: int) -> np.ndarray:
    info = information_from_weights(kappa, tau, d)
    return np.eye(info.shape[-1]) / np.diagonal(info, axis1=-2, axis2=-1)[:, None, :]


def _segmented_prefix_products(A: np.ndarray, segment: np.ndarray) -> np.ndarray:
    """Inclusive prefix products A[s] A[s+1] ... A[p] within runs of equal ``segment`` (contiguous,
    non-decreasing ids): Hillis-Steele doubling, log2 n vectorised steps."""
    X = A.copy()
    shift = 1
    while shift < X.shape[0]:
        same = segment[shift:] == segment[:-shift]
        X[shift:][same] = (X[:-shift] @ X[shift:])[same]
        shift *= 2
    return X


def odometry_chains(graph: PoseGraph, robot_of_pose) -> OdometryChains:
    """Each robot's odometry chain composed once (prefix products) with its covariance prefix sums."""
    rop = np.asarray(robot_of_pose)
    n, d = graph.num_poses, graph.dim
    i, j = np.asarray(graph.i, np.int64), np.asarray(graph.j, np.int64)
    odo = (j == i + 1) & (rop[i] == rop[j])
    # one odometry edge per step p-1 -> p (the first, if repeated)
    steps, first = np.unique(j[odo], return_index=True)
    e = np.flatnonzero(odo)[first]
    linked = np.zeros(n, bool)
    linked[steps] = True
    segment = np.cumsum(~linked) - 1
    H = np.broadcast_to(np.eye(d + 1), (n, d + 1, d + 1)).copy()
    H[steps, :d, :d] = np.asarray(graph.R, np.float64)[e]
    H[steps, :d, d] = np.asarray(graph.t, np.float64)[e]
    P = _segmented_prefix_products(H, segment)
    R, t = P[:, :d, :d], P[:, :d, d]
    D = d * (d + 1) // 2
    terms = np.zeros((n, D, D))
    S = _edge_covariances(np.asarray(graph.kappa, np.float64)[e], np.asarray(graph.tau, np.float64)[e], d)
    terms[steps] = _conj(_adjoint(R[steps], t[steps]), S)
    return OdometryChains(R=R, t=t, G=np.cumsum(terms, axis=0), segment=segment)


@dataclass(frozen=True)
class _Closures:
    """Inter-robot closures oriented from robot a (the smaller id) to robot b."""

    edge: np.ndarray  # (c,) edge index in the graph
    a: np.ndarray  # (c,) robot of the first end
    b: np.ndarray
    ia: np.ndarray  # (c,) pose on robot a
    kb: np.ndarray  # (c,) pose on robot b
    MR: np.ndarray  # (c, d, d) M = P_ia z P_kb^-1
    Mt: np.ndarray  # (c, d)
    B: np.ndarray  # (c, D, D) Ad(M)
    W: np.ndarray  # (c, D, D) Ad(P_ia z) S Ad(P_ia z)^T


def _closures(graph: PoseGraph, rop: np.ndarray, chains: OdometryChains) -> _Closures:
    i, j = np.asarray(graph.i, np.int64), np.asarray(graph.j, np.int64)
    edge = np.flatnonzero(rop[i] != rop[j])
    i, j = i[edge], j[edge]
    R, t = np.asarray(graph.R, np.float64)[edge], np.asarray(graph.t, np.float64)[edge]
    S = _edge_covariances(np.asarray(graph.kappa, np.float64)[edge], np.asarray(graph.tau, np.float64)[edge],
                          graph.dim)
    flip = rop[i] > rop[j]  # orient a -> b: the inverse measurement (R^T, -R^T t), covariance Ad(z) S Ad(z)^T
    S = np.where(flip[:, None, None], _conj(_adjoint(R, t), S), S)
    Rt = np.swapaxes(R, -1, -2)
    R, t = np.where(flip[:, None, None], Rt, R), np.where(flip[:, None], -np.einsum("cab,cb->ca", Rt, t), t)
    ia, kb = np.where(flip, j, i), np.where(flip, i, j)
    PR, Pt = chains.R[ia], chains.t[ia]
    ZR, Zt = PR @ R, np.einsum("cab,cb->ca", PR, t) + Pt  # P_ia z
    MR = ZR @ np.swapaxes(chains.R[kb], -1, -2)
    Mt = Zt - np.einsum("cab,cb->ca", MR, chains.t[kb])
    return _Closures(edge=edge, a=rop[ia], b=rop[kb], ia=ia, kb=kb, MR=MR, Mt=Mt, B=_adjoint(MR, Mt),
                     W=_conj(_adjoint(ZR, Zt), S))


def _pair_chi2(cl: _Closures, chains: OdometryChains, u: np.ndarray, v: np.ndarray):
    """Chi-square statistic of the cycles of closure pairs (u, v) (flat index arrays) and whether
    they are testable (both ends' pairs on one segment)."""
    R = cl.MR[u] @ np.swapaxes(cl.MR[v], -1, -2)
    t = cl.Mt[u] - np.einsum("kab,kb->ka", R, cl.Mt[v])
    rho, omega = se_log(R, t)
    r = np.concatenate([rho, omega], -1)
    G, seg = chains.G, chains.segment
    ia_u, ia_v, kb_u, kb_v = cl.ia[u], cl.ia[v], cl.kb[u], cl.kb[v]
    testable = (seg[ia_u] == seg[ia_v]) & (seg[kb_u] == seg[kb_v])
    # G[max] - G[min]: the chain's covariance (zero where untestable: their statistic is not used)
    chain_a = (testable * np.sign(ia_u - ia_v))[:, None, None] * (G[ia_u] - G[ia_v])
    chain_b = (testable * np.sign(kb_u - kb_v))[:, None, None] * (G[kb_u] - G[kb_v])
    Sigma = chain_a + _conj(cl.B[u], chain_b) + cl.W[u] + cl.W[v]
    chi2 = np.einsum("ka,ka->k", r, np.linalg.solve(Sigma, r[..., None])[..., 0])
    return chi2, testable


def pairwise_chi2(graph: PoseGraph, robot_of_pose):
    """Chi-square statistics of all pairs of inter-robot closures of each robot pair (diagnostics):
    ``(edges, pairs)``, ``edges`` (c,) the closures' edge indices and ``pairs`` a dict
    (a, b) -> (u, v, chi2, testable) with u < v positions in ``edges``."""
    rop = np.asarray(robot_of_pose)
    chains = odometry_chains(graph, rop)
    cl = _closures(graph, rop, chains)
    out = {}
    for (a, b), idx in _groups(cl).items():
        u, v = np.triu_indices(len(idx), 1)
        chi2, testable = _blocked_chi2(cl, chains, idx[u], idx[v])
        out[(a, b)] = (idx[u], idx[v], chi2, testable)
    return cl.edge, out


def _groups(cl: _Closures) -> dict:
    order = np.lexsort((cl.ia, cl.b, cl.a))
    keys = np.stack([cl.a[order], cl.b[order]], 1)
    uniq, start = np.unique(keys, axis=0, return_index=True)
    bounds = np.r_[start, len(order)]
    return {(int(a), int(b)): order[bounds[g]:bounds[g + 1]] for g, (a, b) in enumerate(uniq)}


def _blocked_chi2(cl, chains, u, v):
    chi2, testable = np.empty(len(u)), np.empty(len(u), bool)
    for s in range(0, len(u), BLOCK_PAIRS):  # blocks of pairs (memory), not a loop over edges
        chi2[s:s + BLOCK_PAIRS], testable[s:s + BLOCK_PAIRS] = _pair_chi2(cl, chains, u[s:s + BLOCK_PAIRS],
                                                                          v[s:s + BLOCK_PAIRS])
    return chi2, testable


#: consistency graphs with at least this fraction of their pairs consistent go to the 0/1 program,
#: sparser ones to networkx's branch and bound (the faster of the two on each side: random graphs of
#: 100-200 closures with and without a consistent half, benchmarks/pcm.md)
DENSE_CONSISTENCY = 0.65


def _evidence(k: int, degree) -> np.ndarray:
    """Vertex weights B + degree, B = max(k^2, k (max degree + 1)), int64: a clique's sum orders cliques
    by size, then by tests passed (B exceeds any clique's degree sum)."""
    degree = np.asarray(degree, np.int64)
    return max(k * k, k * (int(degree.max(initial=0)) + 1)) + degree


def _clique_weights(k: int, u, v, degree=None) -> np.ndarray:
    """Integer vertex weights :func:`_evidence` k^2 + position (int64; :func:`_maximum_clique`).
    ``degree``: the vertices' degrees (default: in the edges (u, v))."""
    if degree is None:
        degree = np.bincount(np.r_[u, v], minlength=k)
    scale, order = (k * k, np.arange(k, dtype=np.int64)) if k < 1500 else (1, 0)  # exact sums below 2^53
    return _evidence(k, degree) * scale + order


def _maximum_clique(k: int, u, v, degree=None) -> np.ndarray:
    """Positions (0..k-1) of a maximum-weight clique of the graph on k vertices with edges (u, v), exact.

    Weights (:func:`_clique_weights`): (B + degree) k^2 + position, the degrees those of (u, v) unless
    ``degree`` gives them (a subgraph searched with the whole graph's degrees). A clique of s + 1
    vertices outweighs any of s (s max-degree < B in the first term, and the second sums to under k^2); among
    the cliques of maximum size the one with the most edges to the whole graph (tests passed) wins,
    then the one whose closures come last in the group's order (the largest sum of positions: PCM has
    no evidence to prefer either; of two inconsistent closures alone in a pair the second is kept).
    The sums (about k^5) stay integers below 2^53, exact in floating point, for k < 1500; beyond, the
    last term is left out and the search picks among such ties.

    Two exact searches of the same weights, chosen by the graph's density (consistent pairs over all
    pairs): at :data:`DENSE_CONSISTENCY` or above the 0/1 program max sum_v w_v x_v subject to x_a +
    x_b <= 1 for every pair (a, b) that is not an edge, solved by :func:`scipy.optimize.milp`
    (HiGHS' branch and cut, no optimality gap); below, networkx's ``max_weight_clique`` (branch and
    bound). Each is the slow one on the other side: a pair of 200 closures, most of them pairwise
    consistent, takes 0.03-0.3 s with HiGHS where networkx took 5-90 s; a sparse graph of 200, 0.2-1.7
    s with networkx where HiGHS took 2 s to minutes (``benchmarks/pcm.md``)."""
    adjacent = np.eye(k, dtype=bool)
    adjacent[u, v] = adjacent[v, u] = True
    a, b = np.nonzero(np.triu(~adjacent, 1))
    if len(a) == 0:  # every pair consistent: one clique of all
        return np.arange(k, dtype=np.int64)
    weight = _clique_weights(k, u, v, degree)
    if len(a) <= (1.0 - DENSE_CONSISTENCY) * k * (k - 1) / 2:
        return _clique_program(k, a, b, weight)
    return _clique_search(k, u, v, weight)


def _clique_program(k: int, a, b, weight, cover=None) -> np.ndarray:
    """The maximum-weight clique as a 0/1 program over the non-edges (a, b) (HiGHS); ``cover`` (k,)
    bool: only cliques with a vertex among them."""
    from scipy.optimize import Bounds, LinearConstraint, milp

    rows = np.arange(len(a))
    conflicts = sp.csr_array((np.ones(2 * len(a)), (np.r_[rows, rows], np.r_[a, b])), shape=(len(a), k))
    constraints = [LinearConstraint(conflicts, -np.inf, 1.0)]
    if cover is not None:
        constraints.append(LinearConstraint(np.asarray(cover, float)[None], 1.0, np.inf))
    res = milp(-weight.astype(float), constraints=constraints,
               integrality=np.ones(k), bounds=Bounds(0.0, 1.0), options=dict(mip_rel_gap=0.0))
    if not res.success:  # a solver failure, not a property of the data
        raise RuntimeError(f"PCM's maximum clique: HiGHS stopped without an optimum ({res.message})")
    return np.flatnonzero(res.x > 0.5).astype(np.int64)


def _clique_search(k: int, u, v, weight) -> np.ndarray:
    """The maximum-weight clique of the edges (u, v) by networkx's branch and bound."""
    import networkx as nx

    graph = nx.Graph()
    graph.add_nodes_from((n, {"w": int(w)}) for n, w in enumerate(weight))
    graph.add_edges_from(zip(np.asarray(u).tolist(), np.asarray(v).tolist(), strict=True))
    clique, _ = nx.max_weight_clique(graph, weight="w")
    return np.sort(np.asarray(clique, dtype=np.int64))


def _tied(k: int, u, v, clique) -> np.ndarray:
    """Positions outside ``clique`` (:func:`_maximum_clique`'s of the graph on k vertices with edges
    (u, v)) that belong to another clique as good by PCM's evidence: as many closures, and as many
    tests passed (the sum of the degrees), i.e. of the same :func:`_evidence` weight. Those are PCM's
    ties, where the data give no reason to prefer the clique it found. Exact, by the density's search
    (as :func:`_maximum_clique`): for a dense graph the 0/1 program again, each time for a best clique
    with a vertex not yet covered, until the best such clique weighs less (one solve per new clique);
    for a sparse one, per vertex of degree >= size - 1, networkx's search of its neighbourhood for a
    clique of size - 1 whose weight completes the clique's."""
    size = len(clique)
    degree = np.bincount(np.r_[u, v], minlength=k).astype(np.int64)
    weight = _evidence(k, degree)
    target = int(weight[clique].sum())
    tied = np.zeros(k, bool)
    tied[clique] = True
    adjacent = np.eye(k, dtype=bool)
    adjacent[u, v] = adjacent[v, u] = True
    a, b = np.nonzero(np.triu(~adjacent, 1))
    if len(a) <= (1.0 - DENSE_CONSISTENCY) * k * (k - 1) / 2:
        while not tied.all():  # each round covers a whole clique of new ties
            other = _clique_program(k, a, b, weight, cover=~tied)
            if int(weight[other].sum()) < target:
                break
            tied[other] = True
        return np.setdiff1d(np.flatnonzero(tied), clique)
    if size == 1:  # no edges: every vertex is a clique of one, degree 0
        return np.setdiff1d(np.arange(k), clique)
    np.fill_diagonal(adjacent, False)
    for j in np.setdiff1d(np.flatnonzero(degree >= size - 1), clique):  # candidates only
        near = np.flatnonzero(adjacent[j])
        p, q = np.nonzero(np.triu(adjacent[np.ix_(near, near)], 1))
        other = near[_maximum_clique(len(near), p, q, degree[near])]
        tied[j] = len(other) == size - 1 and int(weight[other].sum()) + int(weight[j]) == target
    return np.setdiff1d(np.flatnonzero(tied), clique)


def pcm_filter(graph: PoseGraph, robot_of_pose, *, confidence: float = 0.99,
               max_pair_closures: int | None = 200, min_clique_size: int = 1,
               ties: str = "break") -> PCMResult:
    """PCM on the inter-robot loop closures of ``graph`` (module docstring).

    ``robot_of_pose`` (n,): the robot of each pose. ``confidence``: the chi-square quantile of the
    consistency test (d(d+1)/2 degrees of freedom). ``max_pair_closures``: a robot pair with more
    closures than this is split into consecutive groups (ordered by the pose on the smaller robot
    id) of at most this many, each filtered separately: the exact maximum clique is NP-hard and its
    search time can grow steeply with the number of closures (0.03-0.3 s per group of 200 on
    city10000 with HiGHS); None: no split. ``min_clique_size``: a pair (or
    group) whose maximum clique is smaller loses all its closures (1, the default, is Mangelson et
    al.'s PCM: a lone closure, or one of several mutually inconsistent ones, is kept; 2 demands
    that every kept closure be corroborated by another). ``ties``: "break" keeps one maximum clique
    per pair (Mangelson et al.; among equals the order of :func:`_maximum_clique`), "keep" keeps every
    closure of a clique as large whose closures passed as many tests (:func:`_tied`): where such
    cliques disagree PCM has no evidence either way, and the solver after it decides."""
    t0 = time.perf_counter()
    from scipy.stats import chi2 as chi2_distribution

    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence!r}")
    if ties not in ("break", "keep"):
        raise ValueError(f"ties must be 'break' or 'keep', got {ties!r}")
    rop = np.asarray(robot_of_pose)
    if rop.shape != (graph.num_poses,):
        raise ValueError(f"robot_of_pose must have shape ({graph.num_poses},), got {rop.shape}")
    d = graph.dim
    D = d * (d + 1) // 2
    threshold = float(chi2_distribution.ppf(confidence, D))
    chains = odometry_chains(graph, rop)
    cl = _closures(graph, rop, chains)
    keep = np.ones(graph.num_edges, bool)
    groups = _groups(cl)
    rows = []
    clique_seconds = 0.0
    for (a, b), idx in groups.items():
        kept = consistent = untestable = 0
        cap = len(idx) if max_pair_closures is None else max(1, int(max_pair_closures))
        for s in range(0, len(idx), cap):  # one group unless the pair exceeds the cap
            sub = idx[s:s + cap]
            u, v = np.triu_indices(len(sub), 1)
            chi2, testable = _blocked_chi2(cl, chains, sub[u], sub[v])
            ok = ~testable | (chi2 < threshold)
            consistent += int(ok.sum())
            untestable += int((~testable).sum())
            tc = time.perf_counter()
            clique = _maximum_clique(len(sub), u[ok], v[ok])
            if ties == "keep" and len(clique) >= min_clique_size:
                clique = np.r_[clique, _tied(len(sub), u[ok], v[ok], clique)]
            clique_seconds += time.perf_counter() - tc
            drop = np.ones(len(sub), bool)
            if len(clique) >= min_clique_size:
                drop[clique] = False
                kept += len(clique)
            keep[cl.edge[sub[drop]]] = False
        ends = len(np.unique(cl.ia[idx])) + len(np.unique(cl.kb[idx]))
        numbers = len(idx) * (2 + d * d + d + 2 + 1) + ends * (d * d + d + D * (D + 1) // 2)
        rows.append((a, b, len(idx), kept, consistent, untestable, numbers))
    rows = np.asarray(rows, np.int64).reshape(-1, 7)
    return PCMResult(keep=keep, pairs=rows[:, :2], closures=rows[:, 2], kept=rows[:, 3], consistent=rows[:, 4],
                     untestable=rows[:, 5], numbers_sent=rows[:, 6], threshold=threshold,
                     confidence=float(confidence), seconds=time.perf_counter() - t0, clique_seconds=clique_seconds)
