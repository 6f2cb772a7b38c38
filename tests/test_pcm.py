"""PCM (mmpgo_jax/_robust/pcm.py): the SE(d) log, the odometry chains, the chi-square statistic's
distribution, and the filter on multi-robot Cube (3D) and grid (2D) graphs with planted outliers."""

import numpy as np
import pytest
import scipy.linalg
from lie_cases import each_dim
from scipy.spatial.transform import Rotation

import mmpgo_jax as mm
from mmpgo_jax._core.geometry import random_rotations, se_log, so_log
from mmpgo_jax._core.pose_graph import PoseGraph
from mmpgo_jax._experiments.outliers import add_outliers, outlier_scores
from mmpgo_jax._experiments.synthetic import grid_2d_dataset
from mmpgo_jax._robust.pcm import odometry_chains, pairwise_chi2, pcm_filter

# The 3D Cube's odometry is noisy (0.02 pi rad per step): over chains of ~100 steps one noise draw
# makes a few percent of the correct pairs fail the 0.99 test (the tests of a draw are correlated),
# and the maximum clique then drops a correct closure; 0.9999 keeps them all (benchmarks/pcm.md).
CONFIDENCE = {2: 0.99, 3: 0.9999}


def _hat(w):
    if w.size == 1:
        return np.array([[0.0, -w[0]], [w[0], 0.0]])
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _multi_robot(dim: int, seed: int = 0):
    """Three contiguous robots without odometry between them: every inter-robot edge is a loop closure."""
    if dim == 3:
        ds = mm.cube_dataset(seed=seed, grid=4, num_poses=300)
    else:
        ds = grid_2d_dataset(seed=seed, grid=5, num_poses=150)
    g = ds.graph
    rop = mm.contiguous_robots(g.num_poses, 3)
    i, j = np.asarray(g.i), np.asarray(g.j)
    return g.select_edges(~((j == i + 1) & (rop[i] != rop[j]))), rop, ds.ground_truth


def _inter(graph, rop):
    return rop[np.asarray(graph.i)] != rop[np.asarray(graph.j)]


def _append(graph: PoseGraph, i, j, R, t) -> PoseGraph:
    k = np.full(len(i), np.median(np.asarray(graph.kappa)))
    tau = np.full(len(i), np.median(np.asarray(graph.tau)))
    return PoseGraph.from_arrays(np.r_[np.asarray(graph.i), i], np.r_[np.asarray(graph.j), j],
                                 np.concatenate([np.asarray(graph.R), R]), np.concatenate([np.asarray(graph.t), t]),
                                 np.r_[np.asarray(graph.kappa), k], np.r_[np.asarray(graph.tau), tau],
                                 num_poses=graph.num_poses, dtype=np.float64)


@each_dim
def test_se_log_inverts_exp(d):
    rng = np.random.default_rng(d)
    p = d * (d - 1) // 2
    omegas, rhos = [], []
    for angle in (0.0, 1e-9, 1e-4, 0.3, 2.0, np.pi - 1e-4, np.pi - 1e-9):
        for _ in range(4):
            w = rng.standard_normal(p)
            omegas.append(w / np.linalg.norm(w) * angle)
            rhos.append(rng.standard_normal(d) * 5)
    X = np.zeros((len(omegas), d + 1, d + 1))
    for k, (w, rho) in enumerate(zip(omegas, rhos, strict=True)):
        A = np.zeros((d + 1, d + 1))
        A[:d, :d], A[:d, d] = _hat(w), rho
        X[k] = scipy.linalg.expm(A)
    rho, omega = se_log(X[:, :d, :d], X[:, :d, d])
    np.testing.assert_allclose(omega, np.array(omegas), atol=1e-7)
    np.testing.assert_allclose(rho, np.array(rhos), atol=1e-6)
    np.testing.assert_allclose(so_log(X[:, :d, :d]), np.array(omegas), atol=1e-7)


def test_chains_are_the_composed_odometry_and_stop_at_gaps():
    graph, rop, _ = _multi_robot(2)
    chains = odometry_chains(graph, rop)
    i, j = np.asarray(graph.i), np.asarray(graph.j)
    R, t = np.asarray(graph.R), np.asarray(graph.t)
    odo = {int(a): e for e, a in enumerate(i) if j[e] == a + 1 and rop[a] == rop[a + 1]}
    for p, q in [(3, 40), (60, 99), (100, 149), (0, 49)]:  # reference: the product, step by step
        T = np.eye(3)
        for s in range(p, q):
            step = np.eye(3)
            step[:2, :2], step[:2, 2] = R[odo[s]], t[odo[s]]
            T = T @ step
        Pp, Pq = np.eye(3), np.eye(3)
        Pp[:2, :2], Pp[:2, 2], Pq[:2, :2], Pq[:2, 2] = chains.R[p], chains.t[p], chains.R[q], chains.t[q]
        np.testing.assert_allclose(np.linalg.solve(Pp, Pq), T, atol=1e-10)
    np.testing.assert_array_equal(chains.segment, rop)  # one segment per robot
    # without the odometry edge 70 -> 71, robot 1 has two segments; the chain restarts at 71
    cut = graph.select_edges(~((i == 70) & (j == 71)))
    chains = odometry_chains(cut, rop)
    assert len(np.unique(chains.segment)) == 4
    np.testing.assert_allclose(chains.R[71], np.eye(2))
    np.testing.assert_allclose(chains.t[71], 0.0)
    np.testing.assert_allclose(chains.G[71], chains.G[70])  # no covariance added at a segment start


@pytest.mark.parametrize("d", [2, 3])
def test_statistic_is_chi_square_under_the_noise_model(d):
    """Two robots (chains of 30 poses), two closures, noise drawn from the covariance PCM assumes:
    the statistic's mean is d(d+1)/2 and 1 % of the draws exceed the 0.99 quantile."""
    rng = np.random.default_rng(7)
    nr, kappa, tau = 30, 400.0, 900.0
    n = 2 * nr
    Rg, tg = random_rotations(rng, (n,), d), rng.standard_normal((n, d)) * 3
    I = np.r_[np.arange(nr - 1), np.arange(nr, n - 1), 0, nr - 1]
    J = np.r_[np.arange(1, nr), np.arange(nr + 1, n), nr + 5, n - 1]
    m = len(I)
    R0 = np.swapaxes(Rg[I], 1, 2) @ Rg[J]
    t0 = np.einsum("mba,mb->ma", Rg[I], tg[J] - tg[I])
    rop = np.repeat([0, 1], nr)
    rot_var = 1.0 / kappa if d == 2 else 1.0 / (2.0 * kappa)  # information_from_weights's convention
    stats = []
    for _ in range(300):
        w = rng.standard_normal((m, d * (d - 1) // 2)) * np.sqrt(rot_var)
        noise = Rotation.from_rotvec(w).as_matrix() if d == 3 else np.stack(
            [np.stack([np.cos(w[:, 0]), -np.sin(w[:, 0])], -1), np.stack([np.sin(w[:, 0]), np.cos(w[:, 0])], -1)], -2)
        g = PoseGraph.from_arrays(I, J, R0 @ noise, t0 + rng.standard_normal((m, d)) / np.sqrt(tau),
                                  np.full(m, kappa), np.full(m, tau), num_poses=n, dtype=np.float64)
        _, pairs = pairwise_chi2(g, rop)
        stats.append(pairs[(0, 1)][2][0])
    dof = d * (d + 1) // 2
    assert abs(np.mean(stats) - dof) < 0.12 * dof
    assert np.mean(np.array(stats) > {3: 11.345, 6: 16.812}[dof]) < 0.03


@pytest.mark.parametrize("d", [2, 3])
def test_keeps_consistent_closures_and_drops_a_planted_one(d):
    graph, rop, truth = _multi_robot(d)
    clean = pcm_filter(graph, rop, confidence=CONFIDENCE[d])
    assert clean.keep.all()
    np.testing.assert_array_equal(clean.kept, clean.closures)
    assert clean.closures.sum() == _inter(graph, rop).sum()
    # one closure with a random relative pose between a pose of robot 0 and one of robot 2
    rng = np.random.default_rng(3)
    extent = np.ptp(np.asarray(truth.t), axis=0)
    bad = _append(graph, [20], [260 if d == 3 else 130], random_rotations(rng, (1,), d),
                  rng.uniform(-1, 1, (1, d)) * extent)
    r = pcm_filter(bad, rop, confidence=CONFIDENCE[d])
    assert np.flatnonzero(~r.keep).tolist() == [graph.num_edges]


@pytest.mark.parametrize("d", [2, 3])
def test_rejects_planted_outliers_and_no_correct_closure(d):
    graph, rop, truth = _multi_robot(d)
    i, j = np.asarray(graph.i), np.asarray(graph.j)
    # add_outliers' rate counts all loop closures: choose it to add 30 % of the inter-robot count
    x = 0.3 * _inter(graph, rop).sum() / (np.abs(i - j) > 1).sum()
    bad = add_outliers(graph, x / (1 + x), reference=truth, seed=1, robot_of_pose=rop, inter_robot_only=True)
    assert bad.num_outliers == round(0.3 * _inter(graph, rop).sum())
    r = pcm_filter(bad.graph, rop, confidence=CONFIDENCE[d])
    scores = outlier_scores(r.keep, bad.outlier)
    assert scores.recall >= 0.9
    assert scores.inlier_recall == 1.0  # no correct edge dropped
    assert r.keep[~_inter(bad.graph, rop)].all()  # odometry and intra-robot loop closures untouched
    # the result's bookkeeping
    assert r.pairs.tolist() == [[0, 1], [0, 2], [1, 2]]
    assert r.closures.sum() == _inter(bad.graph, rop).sum()
    assert r.kept.sum() == r.closures.sum() - r.num_rejected
    assert (r.consistent <= r.closures * (r.closures - 1) // 2).all() and r.untestable.sum() == 0
    D = d * (d + 1) // 2
    per_closure, per_end = 2 + d * d + d + 2 + 1, d * d + d + D * (D + 1) // 2
    assert (r.numbers_sent >= r.closures * (per_closure + per_end)).all()
    assert (r.numbers_sent <= r.closures * (per_closure + 2 * per_end)).all()
    assert r.bytes_sent == 8 * r.numbers_sent.sum() and 0 < r.clique_seconds <= r.seconds


def test_untestable_pairs_lone_closures_and_the_cap():
    graph, rop, _ = _multi_robot(2)
    i, j = np.asarray(graph.i), np.asarray(graph.j)
    cut = graph.select_edges(~((i == 70) & (j == 71)))  # robot 1 in two segments
    r = pcm_filter(cut, rop)
    assert r.untestable.sum() > 0 and r.keep.all()  # pairs across the gap count as consistent
    # a robot pair with a single closure: kept by PCM, dropped with min_clique_size=2
    inter = _inter(graph, rop)
    pair = np.minimum(rop[i], rop[j]) * 3 + np.maximum(rop[i], rop[j])
    keep = ~(inter & (pair == 2))
    keep[np.flatnonzero(inter & (pair == 2))[0]] = True
    one = graph.select_edges(keep)
    assert pcm_filter(one, rop).keep.all()
    r2 = pcm_filter(one, rop, min_clique_size=2)
    assert r2.num_rejected == 1 and r2.kept[r2.pairs.tolist().index([0, 2])] == 0
    # the cap: groups of at most 10 closures, each filtered on its own
    capped = pcm_filter(graph, rop, max_pair_closures=10)
    assert capped.keep.all()
    assert capped.consistent.sum() < pcm_filter(graph, rop).consistent.sum()
    with pytest.raises(ValueError, match="confidence"):
        pcm_filter(graph, rop, confidence=1.0)
    with pytest.raises(ValueError, match="robot_of_pose"):
        pcm_filter(graph, rop[:-1])


def test_maximum_clique_is_the_best_subset_of_a_brute_force_search():
    """Both clique searches (HiGHS' 0/1 program and networkx's branch and bound) and the choice
    between them against every subset of small random graphs, dense and sparse: the most vertices,
    then the most edges to the whole graph, then the largest sum of positions (the documented order
    of preference)."""
    from itertools import combinations

    from mmpgo_jax._robust.pcm import _clique_program, _clique_search, _clique_weights, _maximum_clique

    rng = np.random.default_rng(7)
    for trial in range(60):
        k = int(rng.integers(1, 11))
        u, v = np.triu_indices(k, 1)
        keep = rng.random(len(u)) < (0.9 if trial % 2 else 0.4)
        u, v = u[keep], v[keep]
        adjacent = np.eye(k, dtype=bool)
        adjacent[u, v] = adjacent[v, u] = True
        degree = adjacent.sum(1) - 1
        best = max((c for s in range(1, k + 1) for c in combinations(range(k), s) if adjacent[np.ix_(c, c)].all()),
                   key=lambda c: (len(c), degree[list(c)].sum(), sum(c)))
        a, b = np.nonzero(np.triu(~adjacent, 1))
        weight = _clique_weights(k, u, v)
        found = [_maximum_clique(k, u, v), _clique_search(k, u, v, weight)]
        if len(a):
            found.append(_clique_program(k, a, b, weight))
        for got in found:
            assert adjacent[np.ix_(got, got)].all(), (k, u, v, got)
            assert (len(got), degree[got].sum(), got.sum()) == (len(best), degree[list(best)].sum(), sum(best))


def test_the_clique_search_follows_the_density(monkeypatch):
    """HiGHS' 0/1 program for dense consistency graphs, networkx's search for sparse ones."""
    from mmpgo_jax._robust import pcm

    used = []
    monkeypatch.setattr(pcm, "_clique_program", lambda k, a, b, w: used.append("program") or np.arange(1))
    monkeypatch.setattr(pcm, "_clique_search", lambda k, u, v, w: used.append("search") or np.arange(1))
    k = 20
    u, v = np.triu_indices(k, 1)
    pcm._maximum_clique(k, u[1:], v[1:])  # one inconsistent pair of 190
    pcm._maximum_clique(k, u[::3], v[::3])  # a third of the pairs consistent
    cut = int(np.ceil(pcm.DENSE_CONSISTENCY * len(u)))
    pcm._maximum_clique(k, u[:cut], v[:cut])  # at the threshold
    pcm._maximum_clique(k, u[:cut - 1], v[:cut - 1])  # just below it
    assert used == ["program", "search", "program", "search"]


def test_ties_are_the_vertices_of_every_maximum_clique():
    """``ties="keep"``'s extra closures against every subset of small random graphs: exactly the
    vertices of the cliques that equal the best in size and in tests passed (the sum of degrees)."""
    from itertools import combinations

    from mmpgo_jax._robust.pcm import _maximum_clique, _tied

    rng = np.random.default_rng(11)
    for trial in range(150):
        k = int(rng.integers(1, 11))
        u, v = np.triu_indices(k, 1)
        keep = rng.random(len(u)) < (0.3, 0.6, 0.9)[trial % 3]
        u, v = u[keep], v[keep]
        adjacent = np.eye(k, dtype=bool)
        adjacent[u, v] = adjacent[v, u] = True
        degree = adjacent.sum(1) - 1
        cliques = [c for s in range(1, k + 1) for c in combinations(range(k), s) if adjacent[np.ix_(c, c)].all()]
        best = max((len(c), degree[list(c)].sum()) for c in cliques)
        expected = sorted({n for c in cliques if (len(c), degree[list(c)].sum()) == best for n in c})
        clique = _maximum_clique(k, u, v)
        assert sorted(np.r_[clique, _tied(k, u, v, clique)].tolist()) == expected, (k, u, v)


def test_ties_keep_both_of_two_inconsistent_lone_closures():
    """A robot pair whose only closures are one correct and one wrong: "break" keeps one of them,
    "keep" both (PCM has no evidence either way)."""
    graph, rop, truth = _multi_robot(2)
    i, j = np.asarray(graph.i), np.asarray(graph.j)
    pair02 = _inter(graph, rop) & (np.minimum(rop[i], rop[j]) == 0) & (np.maximum(rop[i], rop[j]) == 2)
    keep = ~pair02
    keep[np.flatnonzero(pair02)[0]] = True
    one = graph.select_edges(keep)
    rng = np.random.default_rng(5)
    bad = _append(one, [20], [130], random_rotations(rng, (1,), 2), rng.uniform(-1, 1, (1, 2)) * 10.0)
    row = [[0, 1], [0, 2], [1, 2]].index([0, 2])
    broke = pcm_filter(bad, rop)
    assert broke.num_rejected == 1 and broke.kept[row] == 1
    kept = pcm_filter(bad, rop, ties="keep")
    assert kept.keep.all() and kept.kept[row] == 2
    with pytest.raises(ValueError, match="ties"):
        pcm_filter(bad, rop, ties="both")
