"""The centralized Newton solver's linearization against finite differences of the pulled-back
objective F(R_i Exp(omega_i), t_i + delta_i) on small random graphs (2D and 3D)."""

import numpy as np
import pytest

from mmpgo_jax import PoseGraph, cost
from mmpgo_jax._core.geometry import random_rotations
from mmpgo_jax._core.pose_graph import Poses, riemannian_gradient_norm
from mmpgo_jax._mm.centralized import _Problem


def _graph(d, seed, n=6, extra=5):
    rng = np.random.default_rng(seed)
    i = np.concatenate([np.arange(n - 1), rng.integers(0, n, extra)])
    j = np.concatenate([np.arange(1, n), (i[n - 1:] + rng.integers(1, n, extra)) % n])
    m = i.size
    g = PoseGraph.from_arrays(i, j, random_rotations(rng, (m,), d), rng.normal(size=(m, d)),
                              rng.uniform(0.5, 3.0, m), rng.uniform(0.5, 3.0, m), num_poses=n, dtype=np.float64)
    return g, random_rotations(rng, (n,), d), rng.normal(size=(n, d))


def _array(H):
    return H if isinstance(H, np.ndarray) else H.toarray()


@pytest.mark.parametrize("dense", [False, True], ids=["sparse", "dense"])
@pytest.mark.parametrize("d", [2, 3])
def test_gradient_and_hessian_match_finite_differences(d, dense):
    """Both layouts of the Hessian (sparse in nested-dissection order, dense in pose order)."""
    g, R, t = _graph(d, seed=d)
    pb = _Problem(g, None, dense=dense)
    grad, data = pb.linearize(R, t)
    H = _array(pb.matrix(data))
    free = ~pb.held_rows
    N = free.size

    def F(s):  # F = f / 2 at the retraction of the step s (nested-dissection order)
        Rs, ts = pb.retract(R, t, s)
        return 0.5 * float(cost(pb.graph, Poses(Rs, ts)))

    h = 1e-4
    eye = np.eye(N)
    g_fd = np.array([(F(h * e) - F(-h * e)) / (2 * h) for e in eye])
    H_fd = np.array([[(F(h * (a + b)) - F(h * (a - b)) - F(h * (b - a)) + F(-h * (a + b))) / (4 * h * h)
                      for b in eye] for a in eye])
    np.testing.assert_allclose(grad[free], g_fd[free], atol=1e-6 * max(1, np.abs(g_fd).max()))
    np.testing.assert_allclose(H[np.ix_(free, free)], H_fd[np.ix_(free, free)], atol=1e-5 * np.abs(H_fd).max())
    np.testing.assert_array_equal(H[~free][:, ~free], np.eye((~free).sum()))  # the anchor is held
    # the stopping rule's ||grad F||, from the same gradient, against the Riemannian gradient's norm
    np.testing.assert_allclose(pb.gradient(R, t).norm, float(riemannian_gradient_norm(pb.graph, Poses(R, t))),
                               rtol=1e-12)
    # f from the solver's residual layout against the package's cost
    np.testing.assert_allclose(pb.cost(R, t), float(cost(pb.graph, Poses(R, t))), rtol=1e-14)


@pytest.mark.parametrize("name", ["tinyGrid3D.g2o", "smallGrid3D.g2o"])
def test_dense_and_sparse_factorizations_take_the_same_steps(benchmark_file, name, monkeypatch):
    """The dense path of small problems (LAPACK's Cholesky, poses in their order) and the sparse one
    (nested-dissection order) take the same iterations to the same optimum (same configuration)."""
    import mmpgo_jax as mm
    import mmpgo_jax._mm.centralized as centralized
    from mmpgo_jax._mm.centralized import NewtonConfig, newton_optimum
    from mmpgo_jax._mm.driver import Termination

    g = mm.read_g2o(benchmark_file(name)).graph
    X0 = mm.chordal_initialization(g)
    R0, t0 = np.asarray(X0.R, np.float64), np.asarray(X0.t, np.float64)
    runs = []
    for limit in (10**9, 0):
        monkeypatch.setattr(centralized, "DENSE_NEWTON_MAX_SIZE", limit)
        runs.append(newton_optimum(g, R0, t0, Termination(100, 1, 1e-8), config=NewtonConfig(reuse_contraction=0.0)))
    (R, t, hist, _, stats), (R1, t1, hist1, _, stats1) = runs
    assert hist.iterations == hist1.iterations and stats["factorizations"] == stats1["factorizations"]
    np.testing.assert_allclose(hist.f, hist1.f, rtol=1e-10)
    assert hist.grad_norm[-1] <= 1e-8 and mm.certify(g, Poses(R, t)).certified


def test_centralized_result_builds_its_partition_when_read(benchmark_file):
    """The Newton solver's result carries the one-robot split, built on first use (device arrays)."""
    import dataclasses

    import mmpgo_jax as mm

    g = mm.read_g2o(benchmark_file("tinyGrid3D.g2o")).graph
    res = mm.centralized_optimum(g)
    assert callable(res._partition)
    part = res.partition
    assert part.num_robots == 1 and part.num_poses == g.num_poses and res.partition is part
    assert dataclasses.replace(res, poses=res.poses).partition is part


def test_gtsam_reference_reaches_our_optimum(benchmark_file):
    """GTSAM's Levenberg–Marquardt (the timing reference; skipped without gtsam) from the chordal
    start lands where our Newton solver does, up to the geodesic/chordal objectives' difference."""
    pytest.importorskip("gtsam")
    import mmpgo_jax as mm
    from mmpgo_jax._experiments.gtsam_lm import gtsam_levenberg_marquardt

    g = mm.read_g2o(benchmark_file("smallGrid3D.g2o")).graph
    X0 = mm.chordal_initialization(g)
    ours = mm.centralized_optimum(g, init=X0)
    lm = gtsam_levenberg_marquardt(g, Poses(np.asarray(X0.R), np.asarray(X0.t)))
    f_lm = float(cost(g, Poses(lm.poses.R, lm.poses.t)))
    assert ours.stop_reason == "grad_tol" and lm.iterations >= 1
    assert ours.f <= f_lm <= ours.f * (1 + 1e-3), (ours.f, f_lm)


@pytest.mark.parametrize("dense", [False, True], ids=["sparse", "dense"])
def test_block_pattern_with_several_anchors_matches_finite_differences(dense):
    """The Hessian's pattern is built per pose block: with three held poses (rows and columns of the
    identity) the free part still equals the finite-difference Hessian."""
    from mmpgo_jax._core.gauge import FixedPoses

    g, R, t = _graph(3, seed=7, n=7, extra=6)
    fixed = FixedPoses.identity([0, 2, 5], 3)
    pb = _Problem(g, fixed, dense=dense)
    grad, data = pb.linearize(R, t)
    H = pb.matrix(data)
    assert (dense or H.has_sorted_indices) and pb.held_rows.sum() == 3 * pb.b
    free = ~pb.held_rows
    N = free.size

    def F(s):
        Rs, ts = pb.retract(R, t, s)
        return 0.5 * float(cost(pb.graph, Poses(Rs, ts)))

    h, eye = 1e-4, np.eye(N)
    H_fd = np.array([[(F(h * (a + b)) - F(h * (a - b)) - F(h * (b - a)) + F(-h * (a + b))) / (4 * h * h)
                      for b in eye] for a in eye])
    Hd = _array(H)
    np.testing.assert_allclose(Hd[np.ix_(free, free)], H_fd[np.ix_(free, free)], atol=1e-5 * np.abs(H_fd).max())
    np.testing.assert_array_equal(Hd[~free][:, ~free], np.eye((~free).sum()))
    assert np.all(Hd[np.ix_(free, ~free)] == 0) and np.all(grad[~free] == 0)
    diag = np.zeros(data.size)
    diag[pb.free_diagonal] = 1.0
    np.testing.assert_array_equal(_array(pb.matrix(diag)), np.diag(free.astype(float)))


def test_gauss_newton_start_and_factor_reuse_reach_the_same_optimum(benchmark_file):
    """The default (a Gauss–Newton first step, chord steps reusing a factorization near the
    optimum) and plain damped Newton (neither) stop at the same certified point; the default
    factors fewer matrices."""
    import mmpgo_jax as mm
    from mmpgo_jax._mm.centralized import NewtonConfig, newton_optimum
    from mmpgo_jax._mm.driver import Termination

    g = mm.read_g2o(benchmark_file("smallGrid3D.g2o")).graph
    X0 = mm.chordal_initialization(g)
    R0, t0 = np.asarray(X0.R, np.float64), np.asarray(X0.t, np.float64)
    term = Termination(200, 1, 1e-8)
    runs = [newton_optimum(g, R0, t0, term, config=cfg)
            for cfg in (NewtonConfig(), NewtonConfig(initial_damping=1e-6, gauss_newton_steps=0, reuse_contraction=0))]
    (R, t, hist, res, stats), (R1, t1, hist1, res1, stats1) = runs
    assert hist.grad_norm[-1] <= 1e-8 and hist1.grad_norm[-1] <= 1e-8
    np.testing.assert_allclose(hist.f[-1], hist1.f[-1], rtol=1e-12)
    assert mm.certify(g, Poses(R, t)).certified
    assert stats["factorizations"] < stats1["factorizations"], (stats, stats1)
    with pytest.raises(ValueError, match="reuse_contraction"):
        NewtonConfig(reuse_contraction=1.0)
    with pytest.raises(ValueError, match="gauss_newton_steps"):
        NewtonConfig(gauss_newton_steps=-1)


def test_uncoupled_edges_leave_the_matrix_not_the_objective():
    """Edges left out of the Newton matrix's couplings (``coupled``) keep their diagonal blocks and
    their whole part of the cost and gradient; the matrix is the full one less exactly their
    off-diagonal blocks, and the iterations still reach the full solve's optimum."""
    from mmpgo_jax import cube_dataset
    from mmpgo_jax._init.chordal import chordal_initialization
    from mmpgo_jax._mm.centralized import newton_optimum
    from mmpgo_jax._mm.driver import Termination

    cube = cube_dataset(0, grid=4, num_poses=120).graph
    rng = np.random.default_rng(1)
    coupled = np.ones(cube.num_edges, bool)
    loops = np.flatnonzero(np.abs(np.asarray(cube.i) - np.asarray(cube.j)) != 1)
    coupled[rng.choice(loops, 10, replace=False)] = False
    w = np.where(coupled, 1.0, 1e-4)  # negligible weights, the intended use
    graph = PoseGraph(cube.i, cube.j, cube.R, cube.t, cube.kappa * w, cube.tau * w, num_poses=cube.num_poses)
    X = chordal_initialization(graph)
    R, t = np.asarray(X.R, np.float64), np.asarray(X.t, np.float64)
    full, thin = _Problem(graph, None, dense=False), _Problem(graph, None, dense=False, coupled=coupled)
    g_full, H_full = full.linearize(R, t)
    g_thin, H_thin = thin.linearize(R, t)
    assert thin.cost(R, t) == full.cost(R, t)
    A, B = _array(full.matrix(H_full)), _array(thin.matrix(H_thin))
    np.testing.assert_allclose(g_thin[thin.index], g_full[full.index], rtol=1e-13, atol=1e-12)
    # in pose order: B = A less each uncoupled edge's off-diagonal blocks, and nothing else
    pose = lambda pb, M: M[np.ix_(pb.index.reshape(-1), pb.index.reshape(-1))]
    A, B = pose(full, A), pose(thin, B)
    b = full.b
    diff = A - B
    off = np.zeros_like(diff, dtype=bool)
    for e in np.flatnonzero(~coupled):
        i, j = int(graph.i[e]), int(graph.j[e])
        off[b * i:b * i + b, b * j:b * j + b] = off[b * j:b * j + b, b * i:b * i + b] = True
    assert np.abs(diff[off]).max() > 0
    np.testing.assert_allclose(diff[~off], 0.0, atol=1e-10 * np.abs(A).max())
    stop = Termination(200, 1, 1e-7, stop_when_stalled=False)
    R1, t1, h1, *_ = newton_optimum(graph, R, t, stop)
    R2, t2, h2, *_ = newton_optimum(graph, R, t, stop, coupled=coupled)
    assert h1.grad_norm[-1] <= 1e-7 and h2.grad_norm[-1] <= 1e-7
    assert h2.f[-1] == pytest.approx(h1.f[-1], rel=1e-12)
    np.testing.assert_allclose(t2, t1, atol=1e-7)
    np.testing.assert_allclose(R2, R1, atol=1e-7)


def test_damping_decrease_is_validated():
    from mmpgo_jax._mm.centralized import NewtonConfig

    for bad in (0.0, 1.0, -0.5, float("nan")):
        with pytest.raises(ValueError, match="damping_decrease"):
            NewtonConfig(damping_decrease=bad)
    assert NewtonConfig(damping_decrease=1 / 3).damping_decrease == pytest.approx(1 / 3)
