"""DGS (mmpgo_jax._baselines.dgs) against independent references: dense solves of the whole-graph
chordal system and of the Gauss–Newton system (built here, the latter by automatic differentiation of
the residuals through the matrix exponential), a NumPy block Gauss–Seidel with the flagged first sweep,
and hand-made robot orders."""

import numpy as np
import pytest
from scipy.linalg import expm

import mmpgo_jax as mg
from mmpgo_jax._baselines.dgs import dgs, flagged_order, robot_adjacency

ROBOTS = 3
ITERS = 3000  # one budget for the converging runs: they share their compilations


@pytest.fixture(scope="module")
def graphs():
    return {
        3: mg.cube_dataset(seed=0, grid=3, num_poses=60).graph,
        2: mg.grid_2d_dataset(seed=1, grid=4, num_poses=45).graph,
    }


def _edges(g):
    return (np.asarray(g.i), np.asarray(g.j), np.asarray(g.R, np.float64), np.asarray(g.t, np.float64),
            np.asarray(g.kappa, np.float64), np.asarray(g.tau, np.float64))


def _weights(g, weights):
    _, _, _, _, kappa, tau = _edges(g)
    return (np.ones_like(kappa), np.ones_like(tau)) if weights == "unit" else (kappa, tau)


def _chordal_matrix(g, w, keep=None):
    """Dense (dn x dn) matrix of sum_e w_e ||R_i R~ - R_j||^2 in V = [R_1^T; ...; R_n^T], edge by edge."""
    i, j, Rm, _, _, _ = _edges(g)
    n, d = g.num_poses, g.dim
    L = np.zeros((n * d, n * d))
    for e in range(len(i)) if keep is None else np.flatnonzero(keep):
        a, b = slice(d * i[e], d * i[e] + d), slice(d * j[e], d * j[e] + d)
        L[a, a] += w[e] * Rm[e] @ Rm[e].T
        L[b, b] += w[e] * np.eye(d)
        L[a, b] -= w[e] * Rm[e]
        L[b, a] -= w[e] * Rm[e].T
    return L


def _dense_chordal(g, w, R0):
    """Whole-graph minimiser with pose 0 held at R0 (the anchor)."""
    n, d = g.num_poses, g.dim
    L = _chordal_matrix(g, w)
    free = np.ones(n * d, bool)
    free[:d] = False
    V = np.zeros((n * d, d))
    V[:d] = R0.T
    V[free] = np.linalg.solve(L[np.ix_(free, free)], -L[np.ix_(free, ~free)] @ V[~free])
    return np.swapaxes(V.reshape(n, d, d), 1, 2)


def _hat(omega, d):
    """[omega]_x for (..., d(d-1)/2) vectors."""
    if d == 2:
        w = omega[..., 0]
        return np.stack([np.stack([0 * w, -w], -1), np.stack([w, 0 * w], -1)], -2)
    x, y, z = omega[..., 0], omega[..., 1], omega[..., 2]
    o = 0 * x
    return np.stack([np.stack([o, -z, y], -1), np.stack([z, o, -x], -1), np.stack([-y, x, o], -1)], -2)


def _retract(R, t, delta, d):
    """R expm([omega]_x), t + dt (SciPy's matrix exponential, pose by pose)."""
    k = d * (d - 1) // 2
    E = np.stack([expm(h) for h in _hat(delta[:, :k], d)])
    return np.asarray(R) @ E, np.asarray(t) + delta[:, k:]


def _gauss_newton_system(g, poses, w):
    """(system, retract): ``system(keep)`` = (H, b), the Gauss–Newton model 1/2 x^T H x + b^T x of
    sum_e w_R ||R_i R~ - R_j||^2 + w_t ||R_i t~ + t_i - t_j||^2 over the edges ``keep`` (default all) at
    ``poses``, in the increment R Exp(omega), t + dt. The residuals with Exp(omega) replaced by its
    first-order form I + [omega]_x (the same derivative at 0) are affine in x, so column k of J is
    r(e_k) - r(0), exactly."""
    i, j, Rm, tm, _, _ = _edges(g)
    wr, wt = w
    n, d = g.num_poses, g.dim
    p = d * (d - 1) // 2 + d
    R, t = np.asarray(poses.R, np.float64), np.asarray(poses.t, np.float64)

    def residuals(x):  # (B, n p) -> (B, rows)
        x = x.reshape(len(x), n, p)
        Rn = R @ (np.eye(d) + _hat(x[..., : p - d], d))
        tn = t + x[..., p - d :]
        rot = Rn[:, i] @ Rm - Rn[:, j]
        trans = np.einsum("bmac,mc->bma", Rn[:, i], tm) + tn[:, i] - tn[:, j]
        return np.concatenate([(np.sqrt(wr)[:, None, None] * rot).reshape(len(x), -1),
                               (np.sqrt(wt)[:, None] * trans).reshape(len(x), -1)], 1)

    r = residuals(np.zeros((1, n * p)))[0]
    J = (residuals(np.eye(n * p)) - r).T
    edge_of_row = np.concatenate([np.repeat(np.arange(len(i)), d * d), np.repeat(np.arange(len(i)), d)])

    def system(keep=None):
        rows = np.ones(len(r), bool) if keep is None else keep[edge_of_row]
        return J[rows].T @ J[rows], J[rows].T @ r[rows]

    return system, lambda x: _retract(R, t, x.reshape(n, p), d)


def _dense_gauss_newton(g, poses, w):
    """One Gauss–Newton step from ``poses``, pose 0 held: a dense solve of H x = -b."""
    system, retract = _gauss_newton_system(g, poses, w)
    H, b = system()
    p = H.shape[0] // g.num_poses
    x = np.zeros(H.shape[0])
    x[p:] = np.linalg.solve(H[p:, p:], -b[p:])
    return retract(x)


def _block_gauss_seidel(system, n, p, rop, order, sweeps, seen_first):
    """x after each of ``sweeps`` block Gauss–Seidel sweeps on H x = -b (pose 0 held at 0), robots in
    ``order``; in the first sweep robot a uses only the edges ``seen_first(a)``."""
    x, out = np.zeros(n * p), []
    free = np.ones(n * p, bool)
    free[:p] = False
    for sweep in range(sweeps):
        for a in order:
            H, b = system(seen_first(a) if sweep == 0 else None)
            B = (np.repeat(rop, p) == a) & free
            x[B] = np.linalg.solve(H[np.ix_(B, B)], -b[B] - H[np.ix_(B, ~B)] @ x[~B])
        out.append(x.copy())
    return out


def _seen_in_first_sweep(g, rop, order):
    """Robot a's edges in a stage's first sweep (flagged): its own and those to robots before it."""
    i, j = np.asarray(g.i), np.asarray(g.j)
    position = np.argsort(order)
    return lambda a: np.maximum(position[rop[i]], position[rop[j]]) <= position[a]


@pytest.mark.parametrize(("d", "weights"), [(3, "information"), (2, "unit")])
def test_rotation_stage_fixed_point_is_the_dense_chordal_solution(graphs, d, weights):
    g = graphs[d]
    r = dgs(g, ROBOTS, iterations=ITERS, start="code", weights=weights, rotation_tol=1e-12, pose_iterations=0)
    assert 0 < r.rotation_iterations < ITERS and r.pose_iterations == 0
    start = mg.initialize(g, "odometry")
    ref = _dense_chordal(g, _weights(g, weights)[0], np.asarray(start.R[0]))
    np.testing.assert_allclose(np.asarray(r.relaxed_rotations), ref, atol=1e-8)
    np.testing.assert_allclose(np.asarray(r.poses.R), np.asarray(mg.project_to_so(ref)), atol=1e-8)
    np.testing.assert_array_equal(np.asarray(r.poses.t), 0.0)  # their code's start: translations 0


def test_rotation_sweeps_are_block_gauss_seidel_with_the_flagged_first_sweep(graphs):
    """Sweeps 1..3 against a NumPy block Gauss–Seidel on the whole-graph matrix, robots in the flagged
    order; in the first sweep robot a sees only its own edges and those to robots before it."""
    g = graphs[3]
    n, d = g.num_poses, g.dim
    kappa = _edges(g)[4]
    rop = mg.contiguous_robots(n, ROBOTS)
    order = flagged_order(robot_adjacency(g, rop))
    assert order.tolist() == [0, 2, 1]  # not the natural order
    seen = _seen_in_first_sweep(g, rop, order)
    V = np.swapaxes(np.asarray(mg.initialize(g, "odometry").R), 1, 2).reshape(n * d, d)
    free = np.ones(n * d, bool)
    free[:d] = False
    L = _chordal_matrix(g, kappa)
    for sweep in range(1, 4):
        for a in order:
            M = _chordal_matrix(g, kappa, keep=seen(a)) if sweep == 1 else L
            B = (np.repeat(rop, d) == a) & free
            V[B] = np.linalg.solve(M[np.ix_(B, B)], -M[np.ix_(B, ~B)] @ V[~B])
        r = dgs(g, ROBOTS, iterations=ITERS, start="code", rotation_iterations=sweep, pose_iterations=0,
                rotation_tol=0.0)
        assert r.rotation_iterations == sweep
        np.testing.assert_allclose(np.asarray(r.relaxed_rotations), np.swapaxes(V.reshape(n, d, d), 1, 2),
                                   atol=1e-12)


@pytest.mark.parametrize("d", [3, 2])
def test_pose_stage_fixed_point_is_one_dense_gauss_newton_step(graphs, d):
    """Unit weights, 3 robots: converged sweeps = the dense step (kappa, tau of the synthetic graphs make
    block Gauss–Seidel contract by 0.999 per sweep; the sweeps with them are checked below)."""
    g = graphs[d]
    r = dgs(g, ROBOTS, iterations=ITERS, weights="unit", pose_tol=1e-11)
    assert r.stop_reason == "converged" and r.rotation_iterations == 0 and 0 < r.pose_iterations < ITERS
    R, t = _dense_gauss_newton(g, mg.initialize(g, "chordal"), _weights(g, "unit"))
    np.testing.assert_allclose(np.asarray(r.poses.R), np.asarray(R), atol=1e-8)
    np.testing.assert_allclose(np.asarray(r.poses.t), np.asarray(t), atol=1e-8)


def test_one_robot_solves_the_gauss_newton_step_in_one_sweep(graphs):
    g = graphs[3]
    r = dgs(g, 1, iterations=ITERS, pose_tol=1e-12)
    assert r.stop_reason == "converged" and r.pose_iterations == 2  # the second sweep changes nothing
    R, t = _dense_gauss_newton(g, mg.initialize(g, "chordal"), _weights(g, "information"))
    np.testing.assert_allclose(np.asarray(r.poses.R), np.asarray(R), atol=1e-10)
    np.testing.assert_allclose(np.asarray(r.poses.t), np.asarray(t), atol=1e-10)


def test_pose_sweeps_are_block_gauss_seidel_with_the_flagged_first_sweep(graphs):
    g = graphs[3]
    n, p = g.num_poses, 6
    rop = mg.contiguous_robots(n, ROBOTS)
    order = flagged_order(robot_adjacency(g, rop))
    system, retract = _gauss_newton_system(g, mg.initialize(g, "chordal"), _weights(g, "information"))
    xs = _block_gauss_seidel(system, n, p, rop, order, 3, _seen_in_first_sweep(g, rop, order))
    for k, x in enumerate(xs, 1):
        r = dgs(g, ROBOTS, iterations=ITERS, pose_iterations=k, pose_tol=0.0)
        R, t = retract(x)
        np.testing.assert_allclose(np.asarray(r.poses.R), np.asarray(R), atol=1e-11)
        np.testing.assert_allclose(np.asarray(r.poses.t), np.asarray(t), atol=1e-11)


def test_jacobi_and_gauss_seidel_reach_the_same_fixed_point(graphs):
    """Stage 1 (the rotation system: Jacobi's sweeps contract fast enough there on these graphs)."""
    g = graphs[2]
    runs = [dgs(g, ROBOTS, iterations=ITERS, start="code", weights="unit", rotation_tol=1e-12, pose_iterations=0,
                jacobi=jacobi) for jacobi in (False, True)]
    assert runs[1].rotation_iterations > runs[0].rotation_iterations
    assert all(r.rotation_iterations < ITERS for r in runs)  # both met the change rule
    np.testing.assert_allclose(np.asarray(runs[1].relaxed_rotations), np.asarray(runs[0].relaxed_rotations),
                               atol=1e-9)


def test_history_is_the_projects_f_and_the_budget_is_shared(graphs):
    g = graphs[3]
    start = mg.initialize(g, "odometry")
    r = dgs(g, ROBOTS, iterations=ITERS, start="code", rotation_iterations=5, pose_iterations=7, rotation_tol=0.0,
            pose_tol=0.0)
    assert r.iterations == 12 and r.rotation_iterations == 5 and r.pose_iterations == 7
    np.testing.assert_array_equal(r.stage, [0] + [1] * 5 + [2] * 7)
    assert r.stop_reason == "max_iterations"
    assert r.history[0] == pytest.approx(float(mg.cost(g, mg.Poses(start.R, 0 * start.t))), rel=1e-12)
    assert r.f == pytest.approx(float(mg.cost(g, r.poses)), rel=1e-12)
    assert r.f_at(100) == r.f


def test_robot_adjacency_counts_distinct_remote_poses():
    # robots: poses 0-1 -> 0, 2-3 -> 1, 4 -> 2; two edges reach pose 2 from robot 0: it counts once
    g = mg.PoseGraph.from_arrays([0, 1, 0, 2, 3, 1], [1, 2, 2, 3, 4, 4], np.broadcast_to(np.eye(2), (6, 2, 2)),
                                 np.zeros((6, 2)), np.ones(6), np.ones(6))
    adj = robot_adjacency(g, np.array([0, 0, 1, 1, 2]))
    np.testing.assert_array_equal(adj, [[0, 1, 1], [2, 0, 1], [1, 1, 0]])


def test_flagged_order_by_hand():
    # adj[a, b]: poses of robot b adjacent to robot a
    adj = np.array([
        [0, 0, 2, 2, 0],  # robot 0 -> robots 2 and 3, 2 poses each
        [0, 0, 0, 0, 1],  # robot 1 -> robot 4 only
        [3, 0, 0, 0, 3],  # robot 2 -> 0 (3 poses), 4 (3)
        [1, 0, 0, 0, 1],  # robot 3 -> 0 (1 pose), 4 (1)
        [0, 1, 2, 5, 0],  # robot 4 -> 1, 2, 3
    ])
    # round 1: robots 2 (3) and 3 (1) see robot 0; round 2: robot 4 (2 + 5); round 3: robot 1
    np.testing.assert_array_equal(flagged_order(adj), [0, 2, 3, 4, 1])
    # one robot per round: 2; then 3 (1) vs 4 (2): 4; then 3 (1 + 1) vs 1 (1): 3
    np.testing.assert_array_equal(flagged_order(adj, single=True), [0, 2, 4, 3, 1])
    tie = np.array([[0, 1, 1], [1, 0, 0], [1, 0, 0]])
    np.testing.assert_array_equal(flagged_order(tie), [0, 2, 1])  # ties: the larger index first
    unreachable = np.array([[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, 0, 1], [0, 0, 1, 0]])
    np.testing.assert_array_equal(flagged_order(unreachable), [0, 1, 2, 3])


def test_options_are_checked(graphs):
    g = graphs[2]
    with pytest.raises(ValueError, match="weights"):
        dgs(g, ROBOTS, weights="covariance")
    with pytest.raises(ValueError, match="order"):
        dgs(g, ROBOTS, order=[0, 0, 1])
    with pytest.raises(ValueError, match="start"):
        dgs(g, ROBOTS, start="random")
    with pytest.raises(ValueError, match="connected"):
        dgs(g.select_edges((np.asarray(g.i) != 10) & (np.asarray(g.j) != 10)), ROBOTS)
