"""Centralized chordal / odometry initialization and the ``initialize`` dispatcher."""

from __future__ import annotations

import time

import jax.numpy as jnp
import numpy as np
import pytest

from mmpgo_jax import PoseGraph, Poses, cost
from mmpgo_jax._core.geometry import random_rotations
from mmpgo_jax._init.chordal import (
    anchor_poses,
    chordal_initialization,
    chordal_relaxed_rotations,
    odometry_initialization,
    relaxed_rotation_cost,
    relaxed_translation_cost,
    translations_given_rotations,
)
from mmpgo_jax._init.start import initialize

# f = 2F at the centralized chordal initialization, docs/conventions.md §5.
CHORDAL_F = {
    "MIT.g2o": 88.132,
    "CSAIL.g2o": 31.718,
    "intel.g2o": 53.395,
    "M3500.g2o": 222.62,
    "city10000.g2o": 715.65,
    "sphere2500.g2o": 1971.2,
    "torus3D.g2o": 24669.0,
    "parking-garage.g2o": 1.4153,
}


def random_graph(n, d, extra, seed, *, noise=None, chain=True):
    """Random connected graph: odometry chain (or a random tree) plus ``extra`` random edges.

    Measurements are random (noise=None) or ground-truth relative poses perturbed by ``noise``.
    Returns (graph, ground-truth R, t).
    """
    rng = np.random.default_rng(seed)
    if chain:
        i = list(range(n - 1))
        j = list(range(1, n))
    else:  # random tree: parent of k is a random earlier pose, stored in random orientation
        i, j = [], []
        for k in range(1, n):
            p = int(rng.integers(0, k))
            if k > p + 1 and rng.random() < 0.5:
                i.append(k), j.append(p)
            else:
                i.append(p), j.append(k)
    for _ in range(extra):
        a, b = rng.choice(n, 2, replace=False)
        i.append(int(a)), j.append(int(b))
    i, j = np.array(i), np.array(j)
    m = len(i)
    Rg = random_rotations(rng, (n,), d)
    tg = rng.standard_normal((n, d)) * 3
    Rg = np.einsum("ab,nbc->nac", Rg[0].T, Rg)  # ground truth with pose 0 at the origin
    tg = tg - tg[0]
    if noise is None:
        Rm = random_rotations(rng, (m,), d)
        tm = rng.standard_normal((m, d))
    else:
        Rm = np.swapaxes(Rg[i], 1, 2) @ Rg[j]
        tm = np.einsum("mba,mb->ma", Rg[i], tg[j] - tg[i])
        if noise > 0:
            Rm = np.asarray(_proj(Rm + noise * rng.standard_normal((m, d, d))))
            tm = tm + noise * rng.standard_normal((m, d))
    kappa = rng.uniform(0.5, 3.0, m)
    tau = rng.uniform(0.5, 3.0, m)
    g = PoseGraph.from_arrays(i, j, Rm, tm, kappa, tau, n)
    return g, Rg, tg


def _proj(M):
    from mmpgo_jax import project_to_so

    return project_to_so(jnp.asarray(M))


# ---------------------------------------------------------------------------------------------
# dense least-squares references (explicitly built linear systems, numpy lstsq)
# ---------------------------------------------------------------------------------------------


def dense_relaxed_rotations(g: PoseGraph) -> np.ndarray:
    """min sum kappa ||R_i Rt - R_j||^2 over R_1..R_{n-1} in R^{dxd}, R_0 = I, by lstsq.

    Unknown x = [vec(R_1); ...; vec(R_{n-1})] with row-major vec; vec(R_i Rt) = (I kron Rt^T) vec(R_i).
    """
    n, d = g.num_poses, g.dim
    I_, J_ = np.asarray(g.i), np.asarray(g.j)
    Rm, kap = np.asarray(g.R), np.asarray(g.kappa)
    q = d * d
    A = np.zeros((len(I_) * q, (n - 1) * q))
    b = np.zeros(len(I_) * q)
    for e, (i, j) in enumerate(zip(I_, J_, strict=True)):
        w = np.sqrt(kap[e])
        rows = slice(e * q, (e + 1) * q)
        Mi = w * np.kron(np.eye(d), Rm[e].T)
        Mj = -w * np.eye(q)
        for p, M in ((i, Mi), (j, Mj)):
            if p == 0:
                b[rows] -= M @ np.eye(d).ravel()
            else:
                A[rows, (p - 1) * q : p * q] += M
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    return np.concatenate([np.eye(d)[None], x.reshape(n - 1, d, d)])


def dense_translations(g: PoseGraph, R) -> np.ndarray:
    """min sum tau ||R_i tt + t_i - t_j||^2 over t_1..t_{n-1}, t_0 = 0, by lstsq."""
    n, d = g.num_poses, g.dim
    I_, J_ = np.asarray(g.i), np.asarray(g.j)
    tm, tau = np.asarray(g.t), np.asarray(g.tau)
    R = np.asarray(R)
    A = np.zeros((len(I_) * d, (n - 1) * d))
    b = np.zeros(len(I_) * d)
    for e, (i, j) in enumerate(zip(I_, J_, strict=True)):
        w = np.sqrt(tau[e])
        rows = slice(e * d, (e + 1) * d)
        b[rows] = -w * R[i] @ tm[e]
        if i > 0:
            A[rows, (i - 1) * d : i * d] += w * np.eye(d)
        if j > 0:
            A[rows, (j - 1) * d : j * d] -= w * np.eye(d)
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    return np.concatenate([np.zeros((1, d)), x.reshape(n - 1, d)])


@pytest.mark.parametrize("d", [2, 3])
def test_relaxed_rotations_match_dense_lstsq(d):
    g, _, _ = random_graph(30, d, 25, seed=d)
    R = chordal_relaxed_rotations(g)
    Rref = dense_relaxed_rotations(g)
    np.testing.assert_allclose(R, Rref, atol=1e-10, rtol=0)
    np.testing.assert_array_equal(R[0], np.eye(d))
    # the cost helper is the explicit sum
    I_, J_ = np.asarray(g.i), np.asarray(g.j)
    explicit = sum(
        float(g.kappa[e]) * np.sum((R[I_[e]] @ np.asarray(g.R[e]) - R[J_[e]]) ** 2) for e in range(len(I_))
    )
    assert relaxed_rotation_cost(g, R) == pytest.approx(explicit, rel=1e-12)
    # it is the minimum: perturbing a free block increases the cost
    Rp = R.copy()
    Rp[5] += 1e-3
    assert relaxed_rotation_cost(g, Rp) > relaxed_rotation_cost(g, R)


@pytest.mark.parametrize("d", [2, 3])
def test_translations_match_dense_lstsq(d):
    g, _, _ = random_graph(30, d, 25, seed=10 + d)
    R = np.asarray(_proj(chordal_relaxed_rotations(g)))
    t = translations_given_rotations(g, R)
    np.testing.assert_allclose(t, dense_translations(g, R), atol=1e-10, rtol=0)
    np.testing.assert_array_equal(t[0], np.zeros(d))
    res = np.einsum("mab,mb->ma", R[np.asarray(g.i)], np.asarray(g.t)) + t[np.asarray(g.i)] - t[np.asarray(g.j)]
    assert relaxed_translation_cost(g, R, t) == pytest.approx(float(np.sum(np.asarray(g.tau) * np.sum(res**2, 1))))


@pytest.mark.parametrize("d", [2, 3])
def test_chordal_initialization_in_SOd(d):
    g, _, _ = random_graph(40, d, 30, seed=20 + d)
    p = chordal_initialization(g)
    R = np.asarray(p.R)
    assert R.shape == (40, d, d) and p.t.shape == (40, d)
    np.testing.assert_allclose(np.swapaxes(R, 1, 2) @ R, np.broadcast_to(np.eye(d), R.shape), atol=1e-10)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-10)
    # rotations are the projection of the relaxed solution, translations solve (25) for them
    np.testing.assert_allclose(R, np.asarray(_proj(chordal_relaxed_rotations(g))), atol=1e-12)
    np.testing.assert_allclose(np.asarray(p.t), dense_translations(g, R), atol=1e-9)
    assert p.R.dtype == g.R.dtype


@pytest.mark.parametrize("d", [2, 3])
def test_noise_free_graph_recovers_ground_truth(d):
    g, Rg, tg = random_graph(25, d, 20, seed=30 + d, noise=0.0)
    for p in (chordal_initialization(g), odometry_initialization(g)):
        np.testing.assert_allclose(np.asarray(p.R), Rg, atol=1e-9)
        np.testing.assert_allclose(np.asarray(p.t), tg, atol=1e-9)
        assert float(cost(g, p)) < 1e-10


def test_disconnected_graph_anchors_each_component():
    g1, _, _ = random_graph(10, 2, 5, seed=1)
    g2, _, _ = random_graph(8, 2, 4, seed=2)
    g = PoseGraph.from_arrays(
        np.concatenate([g1.i, g2.i + 10]),
        np.concatenate([g1.j, g2.j + 10]),
        np.concatenate([g1.R, g2.R]),
        np.concatenate([g1.t, g2.t]),
        np.concatenate([g1.kappa, g2.kappa]),
        np.concatenate([g1.tau, g2.tau]),
        18,
    )
    np.testing.assert_array_equal(anchor_poses(g), [0, 10])
    p = chordal_initialization(g)
    p1 = chordal_initialization(g1)
    p2 = chordal_initialization(g2)
    np.testing.assert_allclose(np.asarray(p.R), np.concatenate([p1.R, p2.R]), atol=1e-12)
    np.testing.assert_allclose(np.asarray(p.t), np.concatenate([p1.t, p2.t]), atol=1e-12)
    o = odometry_initialization(g)
    np.testing.assert_allclose(np.asarray(o.R[10]), np.eye(2), atol=1e-15)


def test_odometry_follows_chain_and_ignores_loop_closures():
    g, _, _ = random_graph(20, 3, 15, seed=5)  # random (inconsistent) measurements
    p = odometry_initialization(g)
    I_, J_ = np.asarray(g.i), np.asarray(g.j)
    Rm, tm = np.asarray(g.R), np.asarray(g.t)
    R, t = np.eye(3), np.zeros(3)
    for k in range(1, 20):
        e = np.flatnonzero((k - 1 == I_) & (k == J_))[0]
        R, t = R @ Rm[e], t + R @ tm[e]
        np.testing.assert_allclose(np.asarray(p.R[k]), R, atol=1e-10)
        np.testing.assert_allclose(np.asarray(p.t[k]), t, atol=1e-10)


def test_odometry_spanning_tree_without_chain():
    g, Rg, tg = random_graph(30, 2, 10, seed=7, noise=0.0, chain=False)
    p = odometry_initialization(g)  # tree edges in both orientations
    np.testing.assert_allclose(np.asarray(p.R), Rg, atol=1e-10)
    np.testing.assert_allclose(np.asarray(p.t), tg, atol=1e-10)


# ---------------------------------------------------------------------------------------------
# dispatcher
# ---------------------------------------------------------------------------------------------


def test_initialize_methods(tmp_path):
    g, Rg, tg = random_graph(12, 2, 6, seed=3, noise=0.01)
    c = initialize(g)
    np.testing.assert_allclose(np.asarray(c.R), np.asarray(chordal_initialization(g).R))
    o = initialize(g, "odometry")
    np.testing.assert_allclose(np.asarray(o.t), np.asarray(odometry_initialization(g).t))
    # a Poses: projected to SO(d)
    noisy = Poses(jnp.asarray(Rg * 1.1), jnp.asarray(tg))
    p = initialize(g, noisy)
    np.testing.assert_allclose(np.asarray(p.R), Rg, atol=1e-12)
    np.testing.assert_allclose(np.asarray(p.t), tg)
    v = initialize(g, "vertices", initial=noisy)
    np.testing.assert_allclose(np.asarray(v.R), Rg, atol=1e-12)
    # .npz file
    f = tmp_path / "init.npz"
    np.savez(f, R=Rg, t=tg)
    for path in (f, str(f)):
        q = initialize(g, path)
        np.testing.assert_allclose(np.asarray(q.t), tg)
    # .g2o file (VERTEX lines)
    from mmpgo_jax._io.g2o import write_g2o

    gf = tmp_path / "init.g2o"
    write_g2o(gf, g, Poses(jnp.asarray(Rg), jnp.asarray(tg)))
    q = initialize(g, gf)
    np.testing.assert_allclose(np.asarray(q.R), Rg, atol=1e-6)
    np.testing.assert_allclose(np.asarray(q.t), tg, atol=1e-6)


def test_initialize_on_the_host_gives_the_same_start():
    """``host=True`` (the host-side solvers' start) returns NumPy arrays equal to the device
    start, for a given start (projected) and a method, with fixed poses applied."""
    from mmpgo_jax._core.gauge import FixedPoses
    from mmpgo_jax._core.pose_graph import HostPoses

    g, Rg, tg = random_graph(12, 3, 6, seed=5, noise=0.01)
    fixed = FixedPoses.from_poses([0, 4], Poses(jnp.asarray(Rg), jnp.asarray(tg)))
    noisy = Poses(jnp.asarray(Rg * 1.1), jnp.asarray(tg))
    for method in (noisy, "chordal", "odometry"):
        for fix in (None, fixed):
            device = initialize(g, method, fixed=fix)
            host = initialize(g, method, fixed=fix, host=True)
            assert isinstance(host, HostPoses) and isinstance(host.R, np.ndarray)
            assert host.R.dtype == np.asarray(device.R).dtype
            np.testing.assert_array_equal(host.R, np.asarray(device.R))
            np.testing.assert_array_equal(host.t, np.asarray(device.t))


def test_initialize_distributed_chordal():
    g, _, _ = random_graph(36, 2, 30, seed=102)  # the shapes of tests/test_distributed_chordal.py
    p = initialize(g, "distributed-chordal", robots=4, rotation_iterations=400, translation_iterations=1500, tol=None)
    c = chordal_initialization(g)
    np.testing.assert_allclose(np.asarray(p.R), np.asarray(c.R), atol=1e-7)
    np.testing.assert_allclose(np.asarray(p.t), np.asarray(c.t), atol=1e-6)


def test_initialize_errors(tmp_path):
    g, Rg, tg = random_graph(12, 2, 6, seed=3)
    with pytest.raises(ValueError, match="unknown initialization"):
        initialize(g, "chordall")
    with pytest.raises(ValueError, match="VERTEX"):
        initialize(g, "vertices")
    with pytest.raises(ValueError, match="shape"):
        initialize(g, Poses(jnp.asarray(Rg[:5]), jnp.asarray(tg[:5])))
    with pytest.raises(ValueError, match="shape"):
        initialize(g, Poses(jnp.asarray(Rg), jnp.asarray(tg[:, :1])))
    with pytest.raises(ValueError, match="shape"):
        initialize(g, "vertices", initial=Poses(jnp.zeros((12, 3, 3)), jnp.zeros((12, 3))))
    with pytest.raises(ValueError, match="does not exist"):
        initialize(g, tmp_path / "missing.npz")
    f = tmp_path / "bad.npz"
    np.savez(f, R=Rg)
    with pytest.raises(ValueError, match="missing"):
        initialize(g, f)
    with pytest.raises(ValueError, match="only apply"):
        initialize(g, "chordal", rotation_iterations=3)
    with pytest.raises(ValueError):
        initialize(g, 3.5)


# ---------------------------------------------------------------------------------------------
# benchmark files: f at the chordal start (docs/conventions.md §5), to 4 significant digits
# ---------------------------------------------------------------------------------------------


def _check_chordal_f(path, name):
    from mmpgo_jax._io.g2o import read_g2o

    g = read_g2o(path).graph
    f = float(cost(g, chordal_initialization(g)))
    ref = CHORDAL_F[name]
    unit = 10.0 ** (np.floor(np.log10(ref)) - 3)  # one unit in the 4th significant digit
    assert abs(f - ref) <= 0.5 * unit, (name, f, ref)
    return g


@pytest.mark.parametrize("name", ["MIT.g2o", "CSAIL.g2o", "intel.g2o"])
def test_chordal_f_small_benchmarks(benchmark_file, name):
    _check_chordal_f(benchmark_file(name), name)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(CHORDAL_F))
def test_chordal_f_all_benchmarks(benchmark_file, name):
    g = _check_chordal_f(benchmark_file(name), name)
    best = min(_timed(chordal_initialization, g) for _ in range(3))
    assert best < 2.0, f"chordal initialization of {name} took {best:.2f} s"


def _timed(fn, *args):
    t = time.perf_counter()
    out = fn(*args)
    np.asarray(out.R)
    return time.perf_counter() - t


# ---------------------------------------------------------------------------------------------
# the nested-dissection sparse path against the former one (SuperLU's minimum-degree order, JAX's
# SVD projection), on the benchmark files: the same chordal start to 1e-10
# ---------------------------------------------------------------------------------------------


def _former_chordal(g):
    """Chordal start as computed before the sparse rewrite (pose 0 held at identity)."""
    import scipy.sparse.linalg as spla

    from mmpgo_jax._core.geometry import project_to_so
    from mmpgo_jax._init.chordal import rotation_connection_laplacian, translation_laplacian, translation_rhs

    def solve(A, B):
        lu = spla.splu(A.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        return lu.solve(np.ascontiguousarray(B))

    n, d = g.num_poses, g.dim
    L = rotation_connection_laplacian(g).tocsr()
    V = np.zeros((d * n, d))
    V[:d] = np.eye(d)
    V[d:] = solve(L[d:, d:], -(L[d:, :d] @ np.eye(d)))
    R = np.array(project_to_so(jnp.asarray(np.swapaxes(V.reshape(n, d, d), 1, 2))))
    Lt = translation_laplacian(g).tocsr()
    b = translation_rhs(g, R)
    t = np.zeros((n, d))
    t[1:] = solve(Lt[1:, 1:], b[1:])
    return R, t


def _check_same_chordal_start(path):
    from mmpgo_jax._io.g2o import read_g2o

    g = read_g2o(path).graph
    R_ref, t_ref = _former_chordal(g)
    X = chordal_initialization(g)
    np.testing.assert_allclose(np.asarray(X.R), R_ref, rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(X.t), t_ref, rtol=0, atol=1e-10 * max(1.0, np.abs(t_ref).max()))


@pytest.mark.parametrize("name", ["MIT.g2o", "intel.g2o", "smallGrid3D.g2o"])
def test_same_chordal_start_as_minimum_degree_small(benchmark_file, name):
    _check_same_chordal_start(benchmark_file(name))


@pytest.mark.slow
@pytest.mark.parametrize("name", ["CSAIL.g2o", "M3500.g2o", "city10000.g2o", "sphere2500.g2o", "torus3D.g2o",
                                  "parking-garage.g2o", "manhattan.g2o", "kitti_00.g2o"])
def test_same_chordal_start_as_minimum_degree_all(benchmark_file, name):
    _check_same_chordal_start(benchmark_file(name))


def _broken_chain_graph(seed, n=60, d=3):
    """Odometry edges (k, k+1) with gaps, random loop closures (some duplicated, both orientations),
    random measurements, and a separate component of poses n-5 .. n-1."""
    rng = np.random.default_rng(seed)
    k = np.flatnonzero(rng.random(n - 6) < 0.7)
    i, j = list(k), list(k + 1)
    for _ in range(n // 2):
        a, b = rng.choice(n - 5, 2, replace=False)
        i.append(int(a)), j.append(int(b))
    i += [n - 5, n - 3, n - 3, n - 1, int(i[-1])]  # the last component, and a duplicate edge
    j += [n - 4, n - 4, n - 2, n - 2, int(j[-1])]
    i, j = np.array(i), np.array(j)
    m = len(i)
    g = PoseGraph.from_arrays(i, j, random_rotations(rng, (m,), d), rng.standard_normal((m, d)),
                              np.ones(m), np.ones(m), num_poses=n, dtype=np.float64)
    return g, rng


def _reference_01_bfs(g, roots):
    """Fewest loop closures (edges with |i - j| != 1) from any root to each pose (pose by pose)."""
    from collections import deque

    n = g.num_poses
    adj = [[] for _ in range(n)]
    for a, b in zip(np.asarray(g.i).tolist(), np.asarray(g.j).tolist(), strict=True):
        w = 0 if abs(a - b) == 1 else 1
        adj[a].append((b, w))
        adj[b].append((a, w))
    dist = [None] * n
    dq = deque((int(r), 0) for r in roots)
    while dq:
        u, du = dq.popleft()
        if dist[u] is not None and dist[u] <= du:
            continue
        dist[u] = du
        for v, w in adj[u]:
            (dq.appendleft if w == 0 else dq.append)((v, du + w))
    return np.array(dist)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_odometry_tree_uses_fewest_loop_closures(seed):
    from mmpgo_jax._core.gauge import FixedPoses, anchor_set
    from mmpgo_jax._init.chordal import _spanning_tree

    g, rng = _broken_chain_graph(seed)
    n = g.num_poses
    fixed = None if seed % 2 == 0 else FixedPoses.identity(np.sort(rng.choice(n - 5, 3, replace=False)), 3)
    roots = anchor_set(g, fixed).index
    parent, parent_edge = _spanning_tree(g, roots)
    I_, J_ = np.asarray(g.i), np.asarray(g.j)
    assert set(np.flatnonzero(parent < 0)) == set(roots.tolist())
    child = np.flatnonzero(parent >= 0)
    e = parent_edge[child]
    assert np.all(((I_[e] == child) & (J_[e] == parent[child])) | ((J_[e] == child) & (I_[e] == parent[child])))
    # loop closures on the tree path to the root (walked pose by pose here) = the 0-1 BFS distance
    loops = np.zeros(n, dtype=np.int64)
    for p in range(n):
        q, steps = p, 0
        while parent[q] >= 0:
            loops[p] += abs(I_[parent_edge[q]] - J_[parent_edge[q]]) != 1
            q, steps = parent[q], steps + 1
            assert steps <= n  # no cycle
        assert q in roots
    np.testing.assert_array_equal(loops, _reference_01_bfs(g, roots))


@pytest.mark.parametrize("seed", [0, 1])
def test_odometry_matches_edge_by_edge_composition(seed):
    """The pointer-doubling composition equals the pose-by-pose fold along the same tree (to round-off)."""
    from mmpgo_jax._core.gauge import FixedPoses, anchor_set
    from mmpgo_jax._init.chordal import _spanning_tree

    g, rng = _broken_chain_graph(seed)
    n, d = g.num_poses, g.dim
    fixed = FixedPoses(np.array([3, 20]), random_rotations(rng, (2,), d), rng.standard_normal((2, d)))
    anchor = anchor_set(g, fixed)
    parent, parent_edge = _spanning_tree(g, anchor.index)
    J_ = np.asarray(g.j)
    Rm, tm = np.asarray(g.R), np.asarray(g.t)
    R, t = np.zeros((n, d, d)), np.zeros((n, d))
    R[anchor.index], t[anchor.index] = anchor.R, anchor.t
    done = parent < 0
    while not done.all():  # one pose at a time, parents first
        p = int(np.flatnonzero(~done & done[np.maximum(parent, 0)])[0])
        q, e = parent[p], parent_edge[p]
        if J_[e] == p:
            R[p], t[p] = R[q] @ Rm[e], t[q] + R[q] @ tm[e]
        else:
            R[p] = R[q] @ Rm[e].T
            t[p] = t[q] - R[p] @ tm[e]
        done[p] = True
    out = odometry_initialization(g, fixed)
    np.testing.assert_allclose(np.asarray(out.R), R, atol=1e-12)
    np.testing.assert_allclose(np.asarray(out.t), t, atol=1e-11)
    np.testing.assert_array_equal(np.asarray(out.R)[[3, 20]], fixed.R)


def test_odometry_tree_with_many_duplicate_edges():
    """256 copies of an odometry edge and 300 of a loop closure: every pose is reached, through the
    lowest-index copy."""
    rng = np.random.default_rng(0)
    i = np.array([0] * 256 + [1, 3, 4] + [0] * 300)
    j = np.array([1] * 256 + [2, 4, 5] + [5] * 300)
    m = len(i)
    g = PoseGraph.from_arrays(i, j, random_rotations(rng, (m,), 3), rng.standard_normal((m, 3)), np.ones(m),
                              np.ones(m), num_poses=6, dtype=np.float64)
    p = odometry_initialization(g)
    Rm, tm = np.asarray(g.R), np.asarray(g.t)
    np.testing.assert_allclose(np.asarray(p.R[1]), Rm[0], atol=1e-12)  # the lowest-index copy
    np.testing.assert_allclose(np.asarray(p.t[5]), tm[259], atol=1e-12)  # 0 -> 5: the first loop closure
