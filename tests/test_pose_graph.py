"""The pose-graph model: cost, data matrix M~ (Eq. 4), gradients, layouts, components.

Every quantity is checked against an independent reference: a plain per-edge numpy loop, a dense
M~ assembled edge by edge, finite differences, or a closed-form fact (noise-free optimum,
invariance under a global rigid motion).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.linalg import expm

import mmpgo_jax._core.pose_graph as pg
from mmpgo_jax import (
    PoseGraph,
    Poses,
    connected_components,
    data_matrix,
    matrix_to_poses,
    poses_to_matrix,
)
from mmpgo_jax._core.geometry import random_rotations

# Jitted once at module level: eager dispatch recompiles every primitive for each new shape.
cost = jax.jit(pg.cost)
objective = jax.jit(pg.objective)
edge_costs = jax.jit(pg.edge_costs)
euclidean_gradient = jax.jit(pg.euclidean_gradient)
riemannian_gradient = jax.jit(pg.riemannian_gradient)
riemannian_gradient_norm = jax.jit(pg.riemannian_gradient_norm)
tangent_norm = jax.jit(pg.tangent_norm)

SETTINGS = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])


# ----------------------------------------------------------------------------------------------
# Random problems
# ----------------------------------------------------------------------------------------------


def random_graph(rng: np.random.Generator, n: int, m: int, d: int, duplicates: int = 0) -> PoseGraph:
    """m random edges without self-loops, the last ``duplicates`` of them repeating earlier ones
    (same endpoints, fresh measurement), and positive weights."""
    i = rng.integers(0, n, m)
    j = rng.integers(0, n - 1, m)
    j = j + (j >= i)  # never equal to i
    dup = min(duplicates, m - 1)
    if dup:
        k = rng.integers(0, m - dup, dup)
        i[m - dup:], j[m - dup:] = i[k], j[k]
    R = random_rotations(rng, (m,), d)
    t = rng.standard_normal((m, d))
    kappa = rng.uniform(0.1, 5.0, m)
    tau = rng.uniform(0.1, 5.0, m)
    return PoseGraph.from_arrays(i, j, R, t, kappa, tau, num_poses=n, dtype=jnp.float64)


def random_poses(rng: np.random.Generator, n: int, d: int) -> Poses:
    return Poses(jnp.asarray(random_rotations(rng, (n,), d)), jnp.asarray(rng.standard_normal((n, d))))


# Shapes are drawn from a small set so that the jitted functions below compile only a few times.
@st.composite
def problems(draw, sizes=(3, 6), edge_counts=(8,)):
    """(rng, graph, poses) for a small random 2D or 3D graph (possibly with duplicate edges)."""
    seed = draw(st.integers(0, 2**32 - 1))
    d = draw(st.sampled_from([2, 3]))
    n = draw(st.sampled_from(sizes))
    m = draw(st.sampled_from(edge_counts))
    dup = draw(st.integers(0, 3))
    rng = np.random.default_rng(seed)
    graph = random_graph(rng, n, m, d, dup)
    poses = random_poses(rng, n, d)
    return rng, graph, poses


def np_graph(graph):
    return (np.asarray(graph.i), np.asarray(graph.j), np.asarray(graph.R), np.asarray(graph.t),
            np.asarray(graph.kappa), np.asarray(graph.tau))


def reference_cost(graph, R, t) -> float:
    """f = 2F by a plain per-edge loop."""
    I, J, Rm, tm, kap, tau = np_graph(graph)
    R, t = np.asarray(R), np.asarray(t)
    total = 0.0
    for e in range(len(I)):
        a, b = I[e], J[e]
        total += kap[e] * np.sum((R[a] @ Rm[e] - R[b]) ** 2)
        total += tau[e] * np.sum((R[a] @ tm[e] + t[a] - t[b]) ** 2)
    return total


def reference_data_matrix(graph) -> np.ndarray:
    """Dense M~ = sum_e tau a a^T + kappa B B^T, with the residuals r = X a and Q = X B."""
    I, J, Rm, tm, kap, tau = np_graph(graph)
    n, d = graph.num_poses, graph.dim
    M = np.zeros(((d + 1) * n, (d + 1) * n))
    for e in range(len(I)):
        a = np.zeros((d + 1) * n)
        a[I[e]] += 1.0
        a[J[e]] -= 1.0
        a[n + d * I[e]: n + d * (I[e] + 1)] += tm[e]
        B = np.zeros(((d + 1) * n, d))
        B[n + d * I[e]: n + d * (I[e] + 1)] += Rm[e]
        B[n + d * J[e]: n + d * (J[e] + 1)] -= np.eye(d)
        M += tau[e] * np.outer(a, a) + kap[e] * B @ B.T
    return M


def random_skew(rng, n, d):
    W = rng.standard_normal((n, d, d))
    return W - np.swapaxes(W, 1, 2)


# ----------------------------------------------------------------------------------------------
# Cost and data matrix
# ----------------------------------------------------------------------------------------------


@SETTINGS
@given(problems())
def test_cost_matches_per_edge_loop_and_trace(problem):
    _, graph, poses = problem
    ref = reference_cost(graph, poses.R, poses.t)
    f = float(cost(graph, poses))
    assert f == pytest.approx(ref, rel=1e-12, abs=1e-12)
    assert float(objective(graph, poses)) == pytest.approx(0.5 * ref, rel=1e-12, abs=1e-12)
    assert float(jnp.sum(edge_costs(graph, poses))) == pytest.approx(ref, rel=1e-12, abs=1e-12)
    # f = tr(X M~ X^T) = 2F, F = 1/2 tr(X M~ X^T) (Eq. 4)
    X = poses_to_matrix(poses)
    M = data_matrix(graph)
    assert np.trace(X @ (M @ X.T)) == pytest.approx(ref, rel=1e-11, abs=1e-11)


@SETTINGS
@given(problems())
def test_data_matrix_matches_dense_reference_and_is_psd(problem):
    _, graph, _ = problem
    M = data_matrix(graph).toarray()
    Mref = reference_data_matrix(graph)
    n, d = graph.num_poses, graph.dim
    assert M.shape == ((d + 1) * n, (d + 1) * n)
    np.testing.assert_allclose(M, Mref, rtol=0, atol=1e-12 * max(1.0, np.abs(Mref).max()))
    np.testing.assert_allclose(M, M.T, rtol=0, atol=1e-13 * np.abs(M).max())
    ev = np.linalg.eigvalsh(0.5 * (M + M.T))
    assert ev.min() >= -1e-9 * max(1.0, np.abs(ev).max())


@SETTINGS
@given(problems())
def test_data_matrix_block_structure(problem):
    rng, graph, _ = problem
    I, J, _Rm, tm, kap, tau = np_graph(graph)
    n, d = graph.num_poses, graph.dim
    M = data_matrix(graph).toarray()
    # Translation block: the tau-weighted graph Laplacian.
    L = np.zeros((n, n))
    for e in range(len(I)):
        L[I[e], I[e]] += tau[e]
        L[J[e], J[e]] += tau[e]
        L[I[e], J[e]] -= tau[e]
        L[J[e], I[e]] -= tau[e]
    np.testing.assert_allclose(M[:n, :n], L, atol=1e-12)
    # Diagonal rotation blocks: (sum kappa of incident edges) I + sum over tail edges tau tt tt^T.
    for p in range(n):
        blk = np.zeros((d, d))
        for e in range(len(I)):
            if I[e] == p:
                blk += kap[e] * np.eye(d) + tau[e] * np.outer(tm[e], tm[e])
            if J[e] == p:
                blk += kap[e] * np.eye(d)
        np.testing.assert_allclose(M[n + d * p: n + d * (p + 1), n + d * p: n + d * (p + 1)], blk, atol=1e-12)
    # Null space: every X with all t equal and R = 0 (a global translation direction).
    c = rng.standard_normal(d)
    X = np.zeros((d, (d + 1) * n))
    X[:, :n] = c[:, None]
    np.testing.assert_allclose(X @ M, 0.0, atol=1e-12)
    assert abs(np.trace(X @ M @ X.T)) < 1e-12
    ones = np.concatenate([np.ones(n), np.zeros(d * n)])
    np.testing.assert_allclose(M @ ones, 0.0, atol=1e-12)


def test_data_matrix_tiny_by_hand():
    """One planar edge 0 -> 1 with Rt = Rot(90 deg), tt = (1, 2), kappa = 3, tau = 5."""
    Rt = np.array([[0.0, -1.0], [1.0, 0.0]])
    tt = np.array([1.0, 2.0])
    g = PoseGraph.from_arrays([0], [1], Rt[None], tt[None], [3.0], [5.0], dtype=jnp.float64)
    M = data_matrix(g).toarray()
    # Columns: t0, t1, R0 (2 cols), R1 (2 cols)
    a = np.array([1.0, -1.0, 1.0, 2.0, 0.0, 0.0])
    B = np.zeros((6, 2))
    B[2:4] = Rt
    B[4:6] = -np.eye(2)
    np.testing.assert_allclose(M, 5.0 * np.outer(a, a) + 3.0 * B @ B.T, atol=1e-14)


@SETTINGS
@given(problems())
def test_edge_blocks_give_the_per_edge_costs(problem):
    """tr(Y_i H_ii Y_i^T) + tr(Y_j H_jj Y_j^T) + 2 tr(Y_i H_ij Y_j^T) = kappa ||.||^2 + tau ||.||^2 per edge
    (Y_p = [t_p | R_p]), and the kappa-only / tau-only blocks split it into its two terms."""
    _, graph, poses = problem
    I, J, Rm, tm, kap, tau = np_graph(graph)
    Y = np.concatenate([np.asarray(poses.t)[:, :, None], np.asarray(poses.R)], axis=2)  # (n, d, d+1)

    def tr(A, H, B):  # tr(A_e H_e B_e^T) per edge
        return np.einsum("mab,mbc,mac->m", A, H, B)

    def quad(blocks):
        Hii, Hjj, Hij = blocks
        Yi, Yj = Y[I], Y[J]
        return tr(Yi, Hii, Yi) + tr(Yj, Hjj, Yj) + 2 * tr(Yi, Hij, Yj)

    rot = kap * np.sum((np.asarray(poses.R)[I] @ Rm - np.asarray(poses.R)[J]) ** 2, axis=(1, 2))
    res = np.einsum("mab,mb->ma", np.asarray(poses.R)[I], tm) + np.asarray(poses.t)[I] - np.asarray(poses.t)[J]
    trans = tau * np.sum(res**2, axis=1)
    np.testing.assert_allclose(quad(pg.edge_blocks(graph)), rot + trans, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(quad(pg.edge_blocks(graph, translation=False)), rot, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(quad(pg.edge_blocks(graph, rotation=False)), trans, rtol=1e-10, atol=1e-10)
    unit = pg.edge_hessian_blocks(Rm, tm, kap, tau, unit_rotations=True)
    for a, b in zip(unit, pg.edge_blocks(graph), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-12)  # R~ R~^T = I for measurements in SO(d)


# ----------------------------------------------------------------------------------------------
# Gradients
# ----------------------------------------------------------------------------------------------


def _F(graph, R, t):
    return float(objective(graph, Poses(jnp.asarray(R), jnp.asarray(t))))


@SETTINGS
@given(problems())
def test_euclidean_gradient_finite_differences_and_XM(problem):
    rng, graph, poses = problem
    g = euclidean_gradient(graph, poses)
    R, t = np.asarray(poses.R), np.asarray(poses.t)
    assert g.R.shape == R.shape and g.t.shape == t.shape
    h = 1e-5
    for _ in range(3):
        VR = rng.standard_normal(R.shape)
        Vt = rng.standard_normal(t.shape)
        fd = (_F(graph, R + h * VR, t + h * Vt) - _F(graph, R - h * VR, t - h * Vt)) / (2 * h)
        an = float(np.sum(np.asarray(g.R) * VR) + np.sum(np.asarray(g.t) * Vt))
        scale = max(1.0, abs(fd), float(tangent_norm(g)) * np.sqrt(VR.size + Vt.size))
        assert abs(fd - an) <= 1e-6 * scale
    # Paper: grad F(X) = X M~ (same column layout).
    XM = poses_to_matrix(poses) @ data_matrix(graph)
    G = matrix_to_poses(np.asarray(XM))
    scale = max(1.0, float(np.abs(XM).max()))
    np.testing.assert_allclose(np.asarray(g.R), np.asarray(G.R), rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(np.asarray(g.t), np.asarray(G.t), rtol=0, atol=1e-12 * scale)


@SETTINGS
@given(problems())
def test_riemannian_gradient_tangent_and_directional_derivative(problem):
    rng, graph, poses = problem
    n, d = graph.num_poses, graph.dim
    rg = riemannian_gradient(graph, poses)
    R, t = np.asarray(poses.R), np.asarray(poses.t)
    gR, gt = np.asarray(rg.R), np.asarray(rg.t)
    # Tangent: R_i^T grad_R_i is skew-symmetric.
    S = np.swapaxes(R, 1, 2) @ gR
    np.testing.assert_allclose(S + np.swapaxes(S, 1, 2), 0.0, atol=1e-12 * max(1.0, np.abs(S).max()))
    # Translation part equals the Euclidean one.
    np.testing.assert_allclose(gt, np.asarray(euclidean_gradient(graph, poses).t), atol=1e-14)
    assert float(riemannian_gradient_norm(graph, poses)) == pytest.approx(
        np.sqrt(np.sum(gR**2) + np.sum(gt**2)), rel=1e-12, abs=1e-14)
    # <grad F, V> = d/de F(R exp(e Omega), t + e V_t) for V_R = R Omega.
    Om = random_skew(rng, n, d)
    Vt = rng.standard_normal((n, d))
    h = 1e-5

    def along(eps):
        Re = R @ np.stack([expm(eps * w) for w in Om])
        return _F(graph, Re, t + eps * Vt)

    fd = (along(h) - along(-h)) / (2 * h)
    an = float(np.sum(gR * (R @ Om)) + np.sum(gt * Vt))
    scale = max(1.0, abs(fd), abs(float(objective(graph, poses))))
    assert abs(fd - an) <= 1e-6 * scale


@SETTINGS
@given(problems())
def test_noise_free_graph_optimum(problem):
    """Measurements generated from ground-truth poses: cost and Riemannian gradient vanish there."""
    _, graph, truth = problem
    I, J = np.asarray(graph.i), np.asarray(graph.j)
    R, t = np.asarray(truth.R), np.asarray(truth.t)
    Rm = np.swapaxes(R[I], 1, 2) @ R[J]
    tm = np.einsum("mba,mb->ma", R[I], t[J] - t[I])
    clean = PoseGraph.from_arrays(I, J, Rm, tm, graph.kappa, graph.tau, num_poses=graph.num_poses,
                                  dtype=jnp.float64)
    assert float(cost(clean, truth)) < 1e-20
    assert float(riemannian_gradient_norm(clean, truth)) < 1e-12
    assert float(tangent_norm(riemannian_gradient(clean, truth))) < 1e-12
    # The Euclidean gradient is also zero (all residuals vanish).
    assert float(tangent_norm(euclidean_gradient(clean, truth))) < 1e-12


# ----------------------------------------------------------------------------------------------
# Invariance, layout, components
# ----------------------------------------------------------------------------------------------


@SETTINGS
@given(problems())
def test_cost_invariant_under_global_rigid_motion(problem):
    rng, graph, poses = problem
    d = graph.dim
    Q = random_rotations(rng, (), d)
    s = rng.standard_normal(d) * 10.0
    R, t = np.asarray(poses.R), np.asarray(poses.t)
    moved = Poses(jnp.asarray(Q @ R), jnp.asarray(t @ Q.T + s))
    f0 = float(cost(graph, poses))
    assert float(cost(graph, moved)) == pytest.approx(f0, rel=1e-10, abs=1e-10)
    # The gradient transforms covariantly: grad_R -> Q grad_R, grad_t -> Q grad_t.
    g0, g1 = euclidean_gradient(graph, poses), euclidean_gradient(graph, moved)
    np.testing.assert_allclose(np.asarray(g1.R), Q @ np.asarray(g0.R), atol=1e-9)
    np.testing.assert_allclose(np.asarray(g1.t), np.asarray(g0.t) @ Q.T, atol=1e-9)


@SETTINGS
@given(problems())
def test_poses_matrix_round_trip(problem):
    rng, graph, poses = problem
    n, d = graph.num_poses, graph.dim
    X = poses_to_matrix(poses)
    assert X.shape == (d, (d + 1) * n)
    R, t = np.asarray(poses.R), np.asarray(poses.t)
    # Layout: X = [t_1 .. t_n R_1 .. R_n]
    for p in range(n):
        np.testing.assert_array_equal(X[:, p], t[p])
        np.testing.assert_array_equal(X[:, n + d * p: n + d * (p + 1)], R[p])
    back = matrix_to_poses(X)
    np.testing.assert_array_equal(np.asarray(back.R), R)
    np.testing.assert_array_equal(np.asarray(back.t), t)
    Y = rng.standard_normal((d, (d + 1) * n))
    np.testing.assert_array_equal(poses_to_matrix(matrix_to_poses(Y)), Y)


def test_connected_components_two_components():
    # Component {0, 2, 5, 6} and component {1, 3, 4}; edges in both directions, one duplicate.
    i = [0, 2, 6, 1, 4, 5, 3]
    j = [2, 5, 5, 3, 3, 0, 1]
    comps = connected_components(7, i, j)
    assert len(comps) == 2
    np.testing.assert_array_equal(comps[0], [0, 2, 5, 6])
    np.testing.assert_array_equal(comps[1], [1, 3, 4])


def test_connected_components_isolated_and_ordering():
    # Components {0, 3}, {4, 5}, {1}, {2}: largest first, ties broken by smallest pose index.
    comps = connected_components(6, [4, 0, 3], [5, 3, 0])
    sizes = [len(c) for c in comps]
    assert sizes == sorted(sizes, reverse=True)
    assert sorted(np.concatenate(comps).tolist()) == list(range(6))
    np.testing.assert_array_equal(comps[0], [0, 3])
    assert [c.tolist() for c in comps] == [[0, 3], [4, 5], [1], [2]]
    assert [c.tolist() for c in connected_components(3, [], [])] == [[0], [1], [2]]


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 30), st.integers(0, 40), st.booleans(), st.integers(0, 2**31 - 1))
def test_component_labels_shortcut_for_odometry_chains_matches_the_graph_search(n, m, chain, seed):
    """A chain of consecutive poses (in either direction) joins every pose: the shortcut's labels,
    sizes and firsts equal those of the general search (scipy's connected components), and graphs
    without a full chain take the search."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components as scipy_components

    rng = np.random.default_rng(seed)
    i, j = rng.integers(0, n, m), rng.integers(0, n, m)
    if chain:
        k = np.arange(n - 1)
        flip = rng.random(n - 1) < 0.5
        i, j = np.concatenate([i, np.where(flip, k + 1, k)]), np.concatenate([j, np.where(flip, k, k + 1)])
    labels, sizes, firsts = pg.component_labels(n, i, j)
    count, reference = scipy_components(coo_matrix((np.ones(i.size), (i, j)), shape=(n, n)), directed=False)
    connects = pg._odometry_connects(n, i, j)
    assert connects or not (chain or n == 1)
    assert count == 1 or not connects
    assert labels.shape == (n,) and sizes.sum() == n and len(sizes) == count
    # the same partition of the poses, numbered largest first (ties: smallest pose), firsts the smallest
    same = labels[:, None] == labels[None, :]
    np.testing.assert_array_equal(same, reference[:, None] == reference[None, :])
    np.testing.assert_array_equal(sizes, np.bincount(labels))
    assert np.all(np.diff(sizes) <= 0)
    np.testing.assert_array_equal(firsts, [np.flatnonzero(labels == c).min() for c in range(count)])


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 40), st.integers(0, 60), st.integers(0, 2**31 - 1))
def test_anchor_set_holds_one_pose_per_unheld_component(n, m, seed):
    """Every component gets exactly one anchor: its fixed poses if it has any, else its smallest
    pose at the identity; checked against a union-find over the edges."""
    from mmpgo_jax._core.gauge import FixedPoses, anchor_set

    rng = np.random.default_rng(seed)
    i, j = rng.integers(0, n, m), rng.integers(0, n, m)
    parent = list(range(n))

    def root(p):
        while parent[p] != p:
            p = parent[p]
        return p

    for a, b in zip(i.tolist(), j.tolist(), strict=True):
        parent[root(a)] = root(b)
    roots = np.array([root(p) for p in range(n)])
    smallest = {r: int(np.flatnonzero(roots == r)[0]) for r in set(roots.tolist())}
    g = PoseGraph.from_arrays(i, j, np.broadcast_to(np.eye(2), (m, 2, 2)), np.zeros((m, 2)), np.ones(m),
                              np.ones(m), num_poses=n, dtype=np.float64)
    assert sorted(anchor_set(g).index.tolist()) == sorted(smallest.values())
    fixed_idx = np.unique(rng.integers(0, n, rng.integers(1, 4)))
    fixed = FixedPoses(fixed_idx, np.broadcast_to(np.eye(2), (fixed_idx.size, 2, 2)).copy(),
                       rng.standard_normal((fixed_idx.size, 2)))
    held = {roots[p] for p in fixed_idx.tolist()}
    expected = set(fixed_idx.tolist()) | {smallest[r] for r in smallest if r not in held}
    anchors = anchor_set(g, fixed)
    assert sorted(anchors.index.tolist()) == sorted(expected)
    at = {int(p): k for k, p in enumerate(anchors.index.tolist())}
    np.testing.assert_array_equal(anchors.t[[at[p] for p in fixed_idx.tolist()]], fixed.t)  # held at their values
    free = [at[p] for p in expected - set(fixed_idx.tolist())]
    np.testing.assert_array_equal(anchors.t[free], 0.0)


def test_connected_subgraph_is_the_selection_or_none_when_it_disconnects():
    import mmpgo_jax as mm

    g = pg.host_graph(mm.cube_dataset(0, grid=3, num_poses=30).graph)
    loop = np.abs(np.asarray(g.i) - np.asarray(g.j)) != 1
    sub = pg.connected_subgraph(g, ~loop)  # the odometry chain alone: connected
    assert sub is not None and sub.num_edges == int((~loop).sum())
    np.testing.assert_array_equal(np.asarray(sub.i), np.asarray(g.i)[~loop])
    cut = ~loop & (np.asarray(g.i) != 10)  # the chain cut after pose 10
    assert pg.connected_subgraph(g, cut) is None
