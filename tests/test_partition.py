"""Splitting a pose graph among robots: contiguous blocks, the padded layout, per-robot shares and
gradient blocks, padding invariance and partition statistics.

References are independent: brute-force loops over the edge list, and the whole-graph objective
and gradient of ``mmpgo_jax._core.pose_graph``.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import mmpgo_jax._core.pose_graph as pg
from mmpgo_jax._core.geometry import random_rotations
from mmpgo_jax._core.partition import contiguous_robots, partition, partition_stats
from mmpgo_jax._core.pose_graph import PoseGraph, Poses
from mmpgo_jax._mm.majorization import gradient_and_share, stack, unstack

SETTINGS = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# Jitted once at module level (eager dispatch recompiles every primitive for each new shape).
objective = jax.jit(pg.objective)
euclidean_gradient = jax.jit(pg.euclidean_gradient)


@functools.partial(jax.jit, static_argnums=2)
def _robots_eval(part, poses, n_max):
    X = stack(part.scatter(poses))
    grad, share, local = jax.vmap(lambda e: gradient_and_share(e, X, n_max))(part.edges)
    grad = unstack(grad)
    return grad, share, local, part.gather(grad)


@jax.jit
def _round_trip(part, poses):
    padded = part.scatter(poses)
    return padded, part.gather(padded)


def check_scatter_gather(part, poses):
    d = poses.R.shape[-1]
    padded, back = _round_trip(part, poses)
    assert padded.R.shape == (part.num_robots, part.max_poses, d, d)
    assert padded.t.shape == (part.num_robots, part.max_poses, d)
    np.testing.assert_array_equal(np.asarray(back.R), np.asarray(poses.R))
    np.testing.assert_array_equal(np.asarray(back.t), np.asarray(poses.t))
    mask = np.asarray(part.pose_mask)
    idx = np.asarray(part.pose_index)
    np.testing.assert_array_equal(np.asarray(padded.R)[mask], np.asarray(poses.R)[idx[mask]])
    np.testing.assert_array_equal(np.asarray(padded.t)[mask], np.asarray(poses.t)[idx[mask]])
    # Padding slots: R = I, t = 0.
    np.testing.assert_array_equal(np.asarray(padded.R)[~mask], np.broadcast_to(np.eye(d), ((~mask).sum(), d, d)))
    np.testing.assert_array_equal(np.asarray(padded.t)[~mask], 0.0)
    # outside a trace: the same on the host, kept there with host=True (NumPy arrays, no transfer)
    host = part.scatter(Poses(np.asarray(poses.R), np.asarray(poses.t)), host=True)
    assert isinstance(host.R, np.ndarray) and isinstance(host.t, np.ndarray)
    np.testing.assert_array_equal(host.R, np.asarray(padded.R))
    np.testing.assert_array_equal(host.t, np.asarray(padded.t))


def robots_eval(part, poses):
    """(per-robot grad blocks, shares G^alpha, local costs, grad blocks gathered to global order)."""
    return _robots_eval(part, poses, part.max_poses)


# ----------------------------------------------------------------------------------------------
# Random problems
# ----------------------------------------------------------------------------------------------

N_POSES = 7  # fixed sizes for the jitted hypothesis tests: few compilations
N_EDGES = 10


def random_graph(rng: np.random.Generator, n: int, m: int, d: int, duplicates: int = 0) -> PoseGraph:
    """m random edges without self-loops (the last ``duplicates`` repeat earlier endpoints)."""
    i = rng.integers(0, n, m)
    j = rng.integers(0, n - 1, m)
    j = j + (j >= i)
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


def random_assignment(rng: np.random.Generator, n: int, A: int) -> np.ndarray:
    """A random robot-of-pose array in which every robot 0..A-1 owns at least one pose."""
    labels = np.concatenate([np.arange(A), rng.integers(0, A, n - A)])
    return rng.permutation(labels)


@st.composite
def partitioned_problems(draw, n=N_POSES, m=N_EDGES):
    """(rng, graph, poses, robots) with robots either a count or a random robot-of-pose array."""
    seed = draw(st.integers(0, 2**32 - 1))
    d = draw(st.sampled_from([2, 3]))
    dup = draw(st.integers(0, 3))
    A = draw(st.integers(1, n))
    as_count = draw(st.booleans())
    rng = np.random.default_rng(seed)
    graph = random_graph(rng, n, m, d, dup)
    poses = random_poses(rng, n, d)
    robots = A if as_count else random_assignment(rng, n, A)
    return rng, graph, poses, robots


def robot_of(robots, n):
    if np.ndim(robots) == 0:
        # Independent of contiguous_robots: robot a gets len(range(a, n, A)) poses, in order.
        A = int(robots)
        sizes = [len(range(a, n, A)) for a in range(A)]
        return np.repeat(np.arange(A), sizes)
    return np.asarray(robots)


def np_graph(graph):
    return (np.asarray(graph.i), np.asarray(graph.j), np.asarray(graph.R), np.asarray(graph.t),
            np.asarray(graph.kappa), np.asarray(graph.tau))


# ----------------------------------------------------------------------------------------------
# contiguous_robots
# ----------------------------------------------------------------------------------------------


def test_contiguous_robots_sizes():
    for n in range(1, 41):
        for A in range(1, n + 1):
            r = contiguous_robots(n, A)
            assert r.shape == (n,)
            assert r[0] == 0 and np.all(np.diff(r) >= 0) and np.all(np.diff(r) <= 1)  # contiguous
            sizes = np.bincount(r, minlength=A)
            assert len(sizes) == A
            expected = [n // A + 1 if a < n % A else n // A for a in range(A)]
            assert sizes.tolist() == expected
            assert sizes.sum() == n


@pytest.mark.parametrize("n, A", [(5, 6), (1, 2), (5, 0), (5, -1), (0, 1)])
def test_contiguous_robots_invalid(n, A):
    with pytest.raises(ValueError):
        contiguous_robots(n, A)


def test_contiguous_robots_example():
    # 10 robots on 23 poses: 3 robots of 3, then 7 robots of 2.
    r = contiguous_robots(23, 10)
    assert np.bincount(r).tolist() == [3, 3, 3] + [2] * 7
    assert r.tolist()[:9] == [0, 0, 0, 1, 1, 1, 2, 2, 2]


# ----------------------------------------------------------------------------------------------
# partition: layout
# ----------------------------------------------------------------------------------------------


def check_layout(graph, part, rob):
    """Host-side check of a Partition against a brute-force reading of the edge list."""
    n = graph.num_poses
    I, J, Rm, tm, kap, tau = np_graph(graph)
    A, n_max, e_max = part.num_robots, part.max_poses, part.max_edges
    pose_index = np.asarray(part.pose_index)
    mask = np.asarray(part.pose_mask)
    rop = np.asarray(part.robot_of_pose)
    sop = np.asarray(part.slot_of_pose)
    assert part.num_poses == n
    np.testing.assert_array_equal(rop, rob)
    # Every pose in exactly one (robot, slot) with mask True.
    seen = {}
    for a in range(A):
        for s in range(n_max):
            if mask[a, s]:
                p = int(pose_index[a, s])
                assert p not in seen
                seen[p] = (a, s)
    assert sorted(seen) == list(range(n))
    for p, (a, s) in seen.items():
        assert rob[p] == a and rop[p] == a and sop[p] == s
    # Slots are the rank among the robot's poses in global order (and fill a prefix).
    for a in range(A):
        owned = np.flatnonzero(rob == a)
        assert mask[a].sum() == len(owned)
        np.testing.assert_array_equal(pose_index[a, : len(owned)], owned)
        assert not mask[a, len(owned):].any()

    E = part.edges
    arr = {k: np.asarray(getattr(E, k)) for k in
           ["robot_i", "slot_i", "robot_j", "slot_j", "local_i", "local_j", "R", "t", "kappa", "tau"]}
    for k in ["robot_i", "slot_i", "local_i", "kappa"]:
        assert arr[k].shape == (A, e_max)
    assert arr["R"].shape == (A, e_max, graph.dim, graph.dim)
    assert arr["t"].shape == (A, e_max, graph.dim)
    real = (arr["kappa"] != 0) | (arr["tau"] != 0)

    def key(owner, gi, gj, li, lj, R, t, k, w):
        return (int(owner), int(gi), int(gj), bool(li), bool(lj), float(k), float(w),
                tuple(np.asarray(R).ravel().tolist()), tuple(np.asarray(t).ravel().tolist()))

    expected = []
    for e in range(len(I)):
        a, b = rob[I[e]], rob[J[e]]
        if a == b:
            expected.append(key(a, I[e], J[e], True, True, Rm[e], tm[e], kap[e], tau[e]))
        else:
            expected.append(key(a, I[e], J[e], True, False, Rm[e], tm[e], kap[e], tau[e]))
            expected.append(key(b, I[e], J[e], False, True, Rm[e], tm[e], kap[e], tau[e]))
    actual = []
    for a in range(A):
        for k in range(e_max):
            if not real[a, k]:
                continue
            ri, si, rj, sj = (arr[x][a, k] for x in ["robot_i", "slot_i", "robot_j", "slot_j"])
            # Real endpoints address real slots.
            assert mask[ri, si] and mask[rj, sj]
            gi, gj = pose_index[ri, si], pose_index[rj, sj]
            assert arr["local_i"][a, k] == (ri == a) and arr["local_j"][a, k] == (rj == a)
            assert arr["local_i"][a, k] or arr["local_j"][a, k]
            actual.append(key(a, gi, gj, arr["local_i"][a, k], arr["local_j"][a, k],
                              arr["R"][a, k], arr["t"][a, k], arr["kappa"][a, k], arr["tau"][a, k]))
    assert sorted(actual) == sorted(expected)
    # Padding edges carry zero weights only; every local endpoint of a real edge is a real slot,
    # so padding slots only ever meet zero-weight edges.
    assert (~real).sum() == A * e_max - len(expected)
    assert np.all(arr["kappa"][~real] == 0) and np.all(arr["tau"][~real] == 0)
    for a in range(A):
        for k in range(e_max):
            for loc, slot in (("local_i", "slot_i"), ("local_j", "slot_j")):
                if arr[loc][a, k] and not mask[a, arr[slot][a, k]]:
                    assert not real[a, k]
    # is_inter flag
    np.testing.assert_array_equal(np.asarray(E.is_inter)[real],
                                  (arr["local_i"] != arr["local_j"])[real])
    assert np.all(np.asarray(E.is_inter)[real] == (arr["robot_i"] != arr["robot_j"])[real])


@SETTINGS
@given(st.integers(0, 2**32 - 1), st.sampled_from([2, 3]), st.integers(1, 9), st.integers(1, 14),
       st.integers(0, 3), st.booleans(), st.data())
def test_partition_layout(seed, d, n, m, dup, as_count, data):
    n = max(n, 2)
    rng = np.random.default_rng(seed)
    graph = random_graph(rng, n, m, d, dup)
    A = data.draw(st.integers(1, n))
    robots = A if as_count else random_assignment(rng, n, A)
    rob = robot_of(robots, n)
    part = partition(graph, robots)
    assert part.num_robots == A
    assert part.max_poses == np.bincount(rob).max()
    check_layout(graph, part, rob)
    # Padded to larger common shapes: the same layout.
    big = partition(graph, robots, min_max_poses=part.max_poses + 3, min_max_edges=part.max_edges + 5,
                    num_robots=A + 2)
    assert (big.num_robots, big.max_poses, big.max_edges) == (A + 2, part.max_poses + 3, part.max_edges + 5)
    check_layout(graph, big, rob)
    assert not np.asarray(big.pose_mask)[A:].any()


def test_partition_invalid_robot_arrays():
    rng = np.random.default_rng(0)
    g = random_graph(rng, 5, 6, 2)
    with pytest.raises(ValueError):
        partition(g, np.array([0, 0, 2, 2, 2]))  # robot 1 owns nothing
    with pytest.raises(ValueError):
        partition(g, np.array([0, -1, 1, 1, 0]))
    with pytest.raises(ValueError):
        partition(g, np.array([0, 1, 1, 0]))  # wrong shape
    with pytest.raises(ValueError):
        partition(g, np.array([0, 1, 2, 1, 0]), num_robots=2)
    with pytest.raises(ValueError):
        partition(g, 6)  # more robots than poses


# ----------------------------------------------------------------------------------------------
# Shares and gradient blocks
# ----------------------------------------------------------------------------------------------


def reference_shares(graph, poses, rob, A):
    """Brute force: share = own edges F_e + 1/2 inter F_e; local = every incident F_e."""
    I, J, Rm, tm, kap, tau = np_graph(graph)
    R, t = np.asarray(poses.R), np.asarray(poses.t)
    share, local = np.zeros(A), np.zeros(A)
    for e in range(len(I)):
        Fe = 0.5 * (kap[e] * np.sum((R[I[e]] @ Rm[e] - R[J[e]]) ** 2)
                    + tau[e] * np.sum((R[I[e]] @ tm[e] + t[I[e]] - t[J[e]]) ** 2))
        a, b = rob[I[e]], rob[J[e]]
        if a == b:
            share[a] += Fe
            local[a] += Fe
        else:
            share[a] += 0.5 * Fe
            share[b] += 0.5 * Fe
            local[a] += Fe
            local[b] += Fe
    return share, local


def check_shares_and_gradient(graph, poses, part, rob, n_real_robots):
    check_scatter_gather(part, poses)
    grad, share, local, gathered = robots_eval(part, poses)
    share, local = np.asarray(share), np.asarray(local)
    F = float(objective(graph, poses))
    assert share.sum() == pytest.approx(F, rel=1e-12, abs=1e-12)
    ref_share, ref_local = reference_shares(graph, poses, rob, n_real_robots)
    np.testing.assert_allclose(share[:n_real_robots], ref_share, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(local[:n_real_robots], ref_local, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(share[n_real_robots:], 0.0)
    eg = euclidean_gradient(graph, poses)
    np.testing.assert_allclose(np.asarray(gathered.R), np.asarray(eg.R), rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(gathered.t), np.asarray(eg.t), rtol=0, atol=1e-10)
    # Padding slots get a zero gradient.
    mask = np.asarray(part.pose_mask)
    np.testing.assert_array_equal(np.asarray(grad.R)[~mask], 0.0)
    np.testing.assert_array_equal(np.asarray(grad.t)[~mask], 0.0)
    return grad, share, gathered


@SETTINGS
@given(partitioned_problems())
def test_shares_sum_to_objective_and_gradient_blocks(problem):
    """Sum_alpha Gbar^alpha(X) = F(X), and the robots' gradient blocks assemble grad F(X).

    Partitions are padded to one common shape (A = n_max = n, e_max = m) to bound compilation;
    test_padding_invariance compares unpadded partitions with padded ones.
    """
    _, graph, poses, robots = problem
    n, m = graph.num_poses, graph.num_edges
    rob = robot_of(robots, n)
    part = partition(graph, robots, min_max_poses=n, min_max_edges=m, num_robots=n)
    check_shares_and_gradient(graph, poses, part, rob, int(rob.max()) + 1)


@pytest.mark.parametrize("seed, d, A, as_count", [(1, 2, 3, True), (2, 3, 4, False), (3, 2, 1, True),
                                                  (4, 3, N_POSES, False)])
def test_padding_invariance(seed, d, A, as_count):
    rng = np.random.default_rng(seed)
    graph = random_graph(rng, N_POSES, N_EDGES, d, duplicates=2)
    poses = random_poses(rng, N_POSES, d)
    robots = A if as_count else random_assignment(rng, N_POSES, A)
    rob = robot_of(robots, N_POSES)
    part = partition(graph, robots)
    _, s0, g0 = check_shares_and_gradient(graph, poses, part, rob, A)
    big = partition(graph, robots, min_max_poses=part.max_poses + 7, min_max_edges=part.max_edges + 11,
                    num_robots=A + 2)
    _, s1, g1 = check_shares_and_gradient(graph, poses, big, rob, A)
    np.testing.assert_allclose(s1[:A], s0, rtol=1e-13, atol=1e-14)
    np.testing.assert_array_equal(s1[A:], 0.0)
    np.testing.assert_allclose(np.asarray(g1.R), np.asarray(g0.R), rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(np.asarray(g1.t), np.asarray(g0.t), rtol=1e-13, atol=1e-14)


# ----------------------------------------------------------------------------------------------
# partition_stats
# ----------------------------------------------------------------------------------------------


def brute_stats(graph, rob):
    I, J = np.asarray(graph.i), np.asarray(graph.j)
    A = int(rob.max()) + 1
    poses = [int(np.sum(rob == a)) for a in range(A)]
    own = [0] * A
    inter = [0] * A
    nbrs = [set() for _ in range(A)]
    remote = [set() for _ in range(A)]
    for a_, b_ in zip(I, J, strict=True):
        a, b = rob[a_], rob[b_]
        if a == b:
            own[a] += 1
        else:
            inter[a] += 1
            inter[b] += 1
            nbrs[a].add(b)
            nbrs[b].add(a)
            remote[a].add(b_)
            remote[b].add(a_)
    return poses, own, inter, [sorted(s) for s in nbrs], [len(s) for s in remote]


def check_stats(graph, rob):
    st_ = partition_stats(graph, rob)
    poses, own, inter, nbrs, received = brute_stats(graph, rob)
    assert st_.poses.tolist() == poses
    assert st_.own_edges.tolist() == own
    assert st_.inter_edges.tolist() == inter
    assert [np.asarray(x).tolist() for x in st_.neighbours] == nbrs
    assert st_.received_poses.tolist() == received
    assert st_.total_inter_edges == sum(inter) // 2
    assert sum(own) + st_.total_inter_edges == graph.num_edges
    return st_


@SETTINGS
@given(st.integers(0, 2**32 - 1), st.integers(2, 12), st.integers(1, 25), st.integers(0, 4),
       st.booleans(), st.data())
def test_partition_stats_brute_force(seed, n, m, dup, as_count, data):
    rng = np.random.default_rng(seed)
    graph = random_graph(rng, n, m, 2, dup)
    A = data.draw(st.integers(1, n))
    rob = contiguous_robots(n, A) if as_count else random_assignment(rng, n, A)
    check_stats(graph, rob)


@pytest.mark.parametrize("d", [2, 3])
def test_partition_stats_edge_cases(d):
    rng = np.random.default_rng(7)
    n, m = 9, 20
    graph = random_graph(rng, n, m, d, duplicates=3)
    I, J = np.asarray(graph.i), np.asarray(graph.j)
    # A = 1: no inter edges.
    s1 = check_stats(graph, contiguous_robots(n, 1))
    assert s1.own_edges.tolist() == [m] and s1.inter_edges.tolist() == [0]
    assert s1.total_inter_edges == 0 and s1.received_poses.tolist() == [0]
    assert [x.tolist() for x in s1.neighbours] == [[]]
    # A = n: one pose per robot, every edge is inter-robot (no self-loops).
    sn = check_stats(graph, contiguous_robots(n, n))
    assert sn.own_edges.tolist() == [0] * n and sn.total_inter_edges == m
    deg = np.bincount(I, minlength=n) + np.bincount(J, minlength=n)
    assert sn.inter_edges.tolist() == deg.tolist()
    for p in range(n):
        adj = sorted(set(J[p == I].tolist()) | set(I[p == J].tolist()))
        assert sn.neighbours[p].tolist() == adj
        assert sn.received_poses[p] == len(adj)
    # The padded partitions agree: no inter edge at A = 1, every stored edge inter at A = n.
    p1, pn = partition(graph, 1), partition(graph, n)
    real1 = np.asarray(p1.edges.kappa) > 0
    realn = np.asarray(pn.edges.kappa) > 0
    assert not np.asarray(p1.edges.is_inter)[real1].any() and real1.sum() == m
    assert np.asarray(pn.edges.is_inter)[realn].all() and realn.sum() == 2 * m
