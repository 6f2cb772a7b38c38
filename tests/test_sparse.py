"""The sparse symmetric solvers: SuperLU in METIS order and MKL PARDISO give the same solutions,
the automatic choice, and errors for systems that are not positive definite."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from mmpgo_jax._core import sparse
from mmpgo_jax._core.sparse import block_order, pardiso_available, pose_order, solve_spd
from mmpgo_jax._init.chordal import chordal_initialization

needs_pardiso = pytest.mark.skipif(not pardiso_available(), reason="pypardiso (the 'large' extra) not installed")


def _random_spd(n, seed):
    """A graph Laplacian plus a positive diagonal: sparse, symmetric positive definite."""
    rng = np.random.default_rng(seed)
    i = rng.integers(0, n, 4 * n)
    j = rng.integers(0, n, 4 * n)
    w = rng.random(4 * n)
    W = sp.coo_matrix((w, (i, j)), shape=(n, n)).tocsr()
    W = W + W.T
    L = sp.diags(np.asarray(W.sum(axis=1)).ravel()) - W
    return (L + sp.diags(0.1 + rng.random(n))).tocsr(), i, j


@pytest.mark.parametrize("backend", ["superlu", "pardiso", "auto"])
def test_solve_spd_matches_dense(backend):
    if backend == "pardiso" and not pardiso_available():
        pytest.skip("pypardiso not installed")
    A, i, j = _random_spd(300, seed=1)
    B = np.random.default_rng(2).standard_normal((300, 3))
    X = solve_spd(A, B, block_order(pose_order(300, i, j), 1), backend=backend)
    np.testing.assert_allclose(X, np.linalg.solve(A.toarray(), B), rtol=0, atol=1e-10)


@needs_pardiso
def test_auto_uses_pardiso_from_the_threshold_and_skips_the_order(monkeypatch):
    A, _, _ = _random_spd(200, seed=3)
    B = np.ones((200, 1))
    used = []
    monkeypatch.setattr(sparse, "_pardiso_solve_spd", lambda A, B: used.append("pardiso") or np.zeros_like(B))

    def order():
        used.append("order")
        return np.arange(200)

    monkeypatch.setattr(sparse, "PARDISO_MIN_SIZE", 201)
    solve_spd(A, B, order)
    assert used == ["order"]  # below the threshold: SuperLU, which needs the order
    monkeypatch.setattr(sparse, "PARDISO_MIN_SIZE", 200)
    solve_spd(A, B, order)
    assert used == ["order", "pardiso"]  # PARDISO orders the matrix itself


@pytest.mark.parametrize("backend", ["superlu", "pardiso"])
def test_not_positive_definite_is_an_error(backend):
    if backend == "pardiso" and not pardiso_available():
        pytest.skip("pypardiso not installed")
    path = sp.csr_matrix(np.array([[1.0, -1, 0], [-1, 2, -1], [0, -1, 1]]))  # unanchored Laplacian
    with pytest.raises(np.linalg.LinAlgError, match="anchored"):
        solve_spd(path, np.ones((3, 1)), backend=backend)
    with pytest.raises(ValueError, match="backend"):
        solve_spd(path, np.ones((3, 1)), backend="cholmod")


def _check_backends_agree(graph):
    a = chordal_initialization(graph, backend="superlu")
    b = chordal_initialization(graph, backend="pardiso")
    np.testing.assert_allclose(np.asarray(b.R), np.asarray(a.R), rtol=0, atol=1e-10)
    # translations to 1e-10 of their scale (both are round-off accurate; the difference is the
    # round-off amplified by the conditioning of the translation system)
    scale = max(1.0, float(np.abs(np.asarray(a.t)).max()))
    np.testing.assert_allclose(np.asarray(b.t), np.asarray(a.t), rtol=0, atol=1e-10 * scale)


@needs_pardiso
@pytest.mark.parametrize("name", ["MIT.g2o", "intel.g2o", "smallGrid3D.g2o"])
def test_pardiso_chordal_start_equals_superlu_small(benchmark_file, name):
    from mmpgo_jax._io.g2o import read_g2o

    _check_backends_agree(read_g2o(benchmark_file(name)).graph)


@needs_pardiso
@pytest.mark.slow
@pytest.mark.parametrize("name", ["CSAIL.g2o", "M3500.g2o", "city10000.g2o", "sphere2500.g2o", "torus3D.g2o",
                                  "parking-garage.g2o", "manhattan.g2o", "kitti_00.g2o"])
def test_pardiso_chordal_start_equals_superlu_all(benchmark_file, name):
    from mmpgo_jax._io.g2o import read_g2o

    _check_backends_agree(read_g2o(benchmark_file(name)).graph)


@needs_pardiso
@pytest.mark.slow
def test_pardiso_chordal_start_equals_superlu_1e5_cube():
    from mmpgo_jax import cube_dataset

    _check_backends_agree(cube_dataset(0, num_poses=100_000, grid=38).graph)


@needs_pardiso
def test_pardiso_cholesky_refactors_one_pattern():
    """One analysis, several numeric factorizations of matrices with the same pattern: each solve
    matches a dense solve; an indefinite matrix of the pattern is reported, not factored."""
    from mmpgo_jax._core.sparse import PardisoCholesky

    A, _, _ = _random_spd(250, seed=4)
    upper = sp.triu(A, format="csr")
    upper.sort_indices()
    chol = PardisoCholesky(upper)
    try:
        with pytest.raises(RuntimeError, match="no successful factorization"):
            chol.solve(np.ones(250))
        rng = np.random.default_rng(5)
        for shift in (0.0, 1.0, 10.0):
            M = (A + shift * sp.eye(250)).tocsr()
            values = sp.triu(M, format="csr")
            values.sort_indices()
            assert chol.factor(values.data)
            b = rng.standard_normal(250)
            np.testing.assert_allclose(chol.solve(b), np.linalg.solve(M.toarray(), b), rtol=0, atol=1e-10)
            B = rng.standard_normal((250, 2))
            np.testing.assert_allclose(chol.solve(B), np.linalg.solve(M.toarray(), B), rtol=0, atol=1e-10)
        indefinite = sp.triu((A - 100.0 * sp.eye(250)).tocsr(), format="csr")
        indefinite.sort_indices()
        assert not chol.factor(indefinite.data)
    finally:
        chol.close()


@needs_pardiso
@pytest.mark.parametrize("name", ["intel.g2o", "smallGrid3D.g2o"])
def test_newton_optimum_same_with_pardiso_and_superlu(benchmark_file, monkeypatch, name):
    """The centralized Newton solve reaches the same optimum, in the same iterations, whether its
    steps are factored by SuperLU (with the inertia test) or by PARDISO's Cholesky."""
    import mmpgo_jax as mm
    from mmpgo_jax._mm import centralized

    g = mm.read_g2o(benchmark_file(name)).graph
    results = {}
    for threshold in (10**12, 0):  # SuperLU, then PARDISO
        monkeypatch.setattr(centralized, "PARDISO_NEWTON_MIN_SIZE", threshold)
        results[threshold] = mm.centralized_optimum(g)
    a, b = results.values()
    assert b.f == pytest.approx(a.f, rel=1e-11, abs=0)
    assert a.iterations == b.iterations and a.stats["factorizations"] == b.stats["factorizations"]
    assert float(b.history.grad_norm[-1]) <= 1e-6


@needs_pardiso
def test_pardiso_solves_are_reproducible():
    """PARDISO runs in its conditional-reproducibility mode: the same system solved again gives the
    same bits. Without it, a 10 000-unknown grid Laplacian with 8 000 random long-range couplings (a
    graph with outlier closures) came back with 2e-16 differences on two of three 2-thread runs, and
    a GNC start built on such solves classified M3500's outliers differently from run to run."""
    rng = np.random.default_rng(0)
    n = 100
    chain = sp.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    m = n * n
    C = sp.coo_matrix((np.full(8000, -0.5), (rng.integers(0, m, 8000), rng.integers(0, m, 8000))), shape=(m, m))
    degree = np.asarray(abs(C).sum(0)).ravel() + np.asarray(abs(C).sum(1)).ravel()
    A = (sp.kronsum(chain, chain) + 1e-3 * sp.eye(m) + C + C.T + sp.diags(degree)).tocsr()
    b = rng.normal(size=m)
    first = solve_spd(A, b, backend="pardiso")
    np.testing.assert_allclose(A @ first, b, atol=1e-8)
    for _ in range(5):
        np.testing.assert_array_equal(solve_spd(A, b, backend="pardiso"), first)


@needs_pardiso
def test_cholesky_fill_counts_the_factor_of_known_patterns():
    """PARDISO's count (of the order of L's and U's entries): a pattern without edges counts about its
    diagonal, a complete graph at least its whole lower triangle, a path a few entries per node, a
    cycle more (it cannot be eliminated without fill), and a few random long-range edges on a grid
    (outlier closures) multiply it."""
    from mmpgo_jax._core.sparse import cholesky_fill

    n = 40
    none = np.array([], dtype=np.int64)
    assert n <= cholesky_fill(n, none, none) <= n + 1
    i, j = np.triu_indices(n, 1)
    assert cholesky_fill(n, i, j) >= n * (n + 1) // 2
    ring = np.arange(n)
    path = cholesky_fill(n, ring[:-1], ring[1:])
    assert 2 * n <= path <= 4 * n
    assert cholesky_fill(n, ring, (ring + 1) % n) > path
    side = 60  # a grid: its factor under nested dissection, and with 300 random long edges added
    grid = np.arange(side * side).reshape(side, side)
    gi = np.concatenate([grid[:, :-1].ravel(), grid[:-1].ravel()])
    gj = np.concatenate([grid[:, 1:].ravel(), grid[1:].ravel()])
    rng = np.random.default_rng(0)
    ri, rj = rng.integers(0, side * side, (2, 1500))
    plain = cholesky_fill(side * side, gi, gj)
    noisy = cholesky_fill(side * side, np.concatenate([gi, ri]), np.concatenate([gj, rj]))
    assert noisy > 3 * plain
