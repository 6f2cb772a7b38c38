"""Synthetic Cube / planar-grid datasets: determinism, structure, noise model and kappa/tau."""

import itertools
import math

import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate

from mmpgo_jax import connected_components, cost
from mmpgo_jax._experiments.synthetic import (
    _loop_closure_candidates,
    cube_dataset,
    expected_edge_cost,
    grid_2d_dataset,
    kappa_tau_from_rmse,
    langevin_expected_sq_angle,
    langevin_expected_trace,
    lattice_dataset,
    max_angular_rmse,
    rotation_angle,
    sample_langevin,
)

SIGMA_T = 0.02
SIGMA_R = 0.02 * np.pi


@pytest.fixture(scope="module")
def cube():
    return cube_dataset(0)


@pytest.fixture(scope="module")
def grid2d():
    return grid_2d_dataset(0)


def _np(ds):
    g = ds.graph
    return (np.asarray(g.i), np.asarray(g.j), np.asarray(g.R), np.asarray(g.t),
            np.asarray(ds.ground_truth.R), np.asarray(ds.ground_truth.t))


def _noise(ds):
    """Rotation and translation noise of every edge, recovered from the ground truth."""
    I, J, Rm, tm, R, t = _np(ds)
    Rtrue = np.swapaxes(R[I], 1, 2) @ R[J]
    ttrue = np.einsum("mba,mb->ma", R[I], t[J] - t[I])
    return np.swapaxes(Rtrue, 1, 2) @ Rm, tm - ttrue


# ------------------------------------------------------------------------------------ kappa/tau


def test_kappa_tau_paper_values():
    k3, t3 = kappa_tau_from_rmse(SIGMA_T, SIGMA_R, 3)
    k2, t2 = kappa_tau_from_rmse(SIGMA_T, SIGMA_R, 2)
    assert t3 == pytest.approx(7500.0) and t2 == pytest.approx(5000.0)
    assert k3 == pytest.approx(380.288, abs=1e-3)
    assert k2 == pytest.approx(126.902, abs=1e-3)
    # small-noise limit: E theta^2 ~ d(d-1)/2 / (2 kappa)
    assert k3 == pytest.approx(3 / (2 * SIGMA_R**2), rel=2e-3)
    assert k2 == pytest.approx(1 / (2 * SIGMA_R**2), rel=2e-3)
    for d, k in ((2, k2), (3, k3)):
        assert math.sqrt(langevin_expected_sq_angle(k, d)) == pytest.approx(SIGMA_R, rel=1e-10)


@pytest.mark.parametrize("dim", [2, 3])
def test_kappa_inversion_roundtrip_and_limits(dim):
    smax = max_angular_rmse(dim)
    assert langevin_expected_sq_angle(0.0, dim) == pytest.approx(smax**2)
    for s in (1e-5, 1e-3, 0.1, 0.5, 1.0, 0.9 * smax):
        k, _ = kappa_tau_from_rmse(1.0, s, dim)
        assert math.sqrt(langevin_expected_sq_angle(k, dim)) == pytest.approx(s, rel=1e-8)
    ks = [kappa_tau_from_rmse(1.0, s, dim)[0] for s in (0.05, 0.1, 0.5, 1.0)]
    assert all(a > b for a, b in itertools.pairwise(ks))
    assert kappa_tau_from_rmse(0.0, 0.0, dim) == (math.inf, math.inf)
    with pytest.raises(ValueError):
        kappa_tau_from_rmse(0.02, smax * 1.01, dim)


@pytest.mark.parametrize("dim", [2, 3])
def test_expected_trace_closed_form_matches_quadrature(dim):
    for k in (0.05, 0.7, 3.0, 40.0, 380.0):
        def w(th, k=k):
            base = math.exp(2 * k * (math.cos(th) - 1))
            return base if dim == 2 else (1 - math.cos(th)) * base

        tr = (lambda th: 2 * math.cos(th)) if dim == 2 else (lambda th: 1 + 2 * math.cos(th))
        num = integrate.quad(lambda th, tr=tr, w=w: tr(th) * w(th), 0, math.pi, limit=400)[0]
        den = integrate.quad(w, 0, math.pi, limit=400)[0]
        assert langevin_expected_trace(k, dim) == pytest.approx(num / den, rel=1e-9, abs=1e-12)


# ------------------------------------------------------------------------------- the samplers


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("kappa", [0.0, 0.3, 5.0, 1e4])
def test_langevin_sampler_moments(dim, kappa):
    rng = np.random.default_rng(123)
    N = 100_000
    R = sample_langevin(rng, kappa, N, dim)
    assert R.shape == (N, dim, dim)
    assert np.allclose(np.swapaxes(R, 1, 2) @ R, np.eye(dim), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0, atol=1e-12)
    tr = np.trace(R, axis1=1, axis2=2)
    # E tr R (its standard deviation is at most ~1.5 / sqrt(N) for these kappas)
    assert tr.mean() == pytest.approx(langevin_expected_trace(kappa, dim), abs=2e-2)
    th2 = rotation_angle(R) ** 2
    assert th2.mean() == pytest.approx(langevin_expected_sq_angle(kappa, dim), rel=2e-2)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("sigma_R", [SIGMA_R, 0.3, 1.0])
def test_empirical_rmse_matches_sigma(dim, sigma_R):
    """The kappa/tau conversion, checked by sampling: empirical RMSEs are sigma_t and sigma_R."""
    kappa, tau = kappa_tau_from_rmse(SIGMA_T, sigma_R, dim)
    rng = np.random.default_rng(7)
    N = 200_000
    ang_rmse = math.sqrt(np.mean(rotation_angle(sample_langevin(rng, kappa, N, dim)) ** 2))
    assert ang_rmse == pytest.approx(sigma_R, rel=0.01)
    eps = rng.standard_normal((N, dim)) / math.sqrt(tau)
    assert math.sqrt(np.mean(np.sum(eps**2, axis=1))) == pytest.approx(SIGMA_T, rel=0.01)


@pytest.mark.parametrize("dim", [2, 3])
def test_expected_edge_cost_by_sampling(dim):
    kappa, tau = kappa_tau_from_rmse(SIGMA_T, SIGMA_R, dim)
    e = expected_edge_cost(kappa, tau, dim)
    # small noise: one unit per degree of freedom, d + d(d-1)/2
    assert e == pytest.approx(dim + dim * (dim - 1) / 2, rel=2e-3)
    rng = np.random.default_rng(11)
    N = 200_000
    Rn = sample_langevin(rng, kappa, N, dim)
    tn = rng.standard_normal((N, dim)) / math.sqrt(tau)
    c = kappa * np.sum((Rn - np.eye(dim)) ** 2, axis=(1, 2)) + tau * np.sum(tn**2, axis=1)
    assert c.mean() == pytest.approx(e, rel=0.01)
    # large noise: far from the small-noise value, still matched by the closed form
    k2 = kappa_tau_from_rmse(SIGMA_T, 1.0, dim)[0]
    Rn = sample_langevin(rng, k2, N, dim)
    c2 = k2 * np.sum((Rn - np.eye(dim)) ** 2, axis=(1, 2))
    assert c2.mean() == pytest.approx(expected_edge_cost(k2, tau, dim) - dim, rel=0.01)


# ------------------------------------------------------------------------------- the datasets


def test_deterministic_for_seed():
    kw = dict(grid=4, num_poses=300)
    a, b, c = cube_dataset(5, **kw), cube_dataset(5, **kw), cube_dataset(6, **kw)
    for x, y in zip(_np(a), _np(b), strict=True):
        np.testing.assert_array_equal(x, y)
    assert a.seed == 5 and a.name == "cube_seed5"
    assert not np.array_equal(np.asarray(a.graph.R), np.asarray(c.graph.R))
    g1, g2 = grid_2d_dataset(2, num_poses=200), grid_2d_dataset(2, num_poses=200)
    for x, y in zip(_np(g1), _np(g2), strict=True):
        np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("which", ["cube", "grid2d"])
def test_structure(which, request):
    ds = request.getfixturevalue(which)
    d, grid, n = (3, 12, 3600) if which == "cube" else (2, 20, 1000)
    assert ds.dim == d and ds.num_poses == n
    assert ds.graph.num_poses == n and ds.ground_truth.R.shape == (n, d, d)
    I, J, _, _, R, t = _np(ds)
    # proper rotations
    assert np.allclose(np.swapaxes(R, 1, 2) @ R, np.eye(d), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0, atol=1e-12)
    # path along lattice edges, inside the grid, never reversing
    assert t.min() >= 0 and t.max() <= grid
    steps = np.diff(t, axis=0)
    assert np.allclose(np.linalg.norm(steps, axis=1), 1.0)
    assert np.allclose(np.abs(steps).sum(axis=1), 1.0)  # axis-aligned unit moves
    assert np.all(np.sum(steps[1:] * steps[:-1], axis=1) > -0.5)
    # heading: first axis of R_k along the step leaving pose k
    np.testing.assert_allclose(R[:-1, :, 0], steps, atol=1e-12)
    np.testing.assert_allclose(R[-1, :, 0], steps[-1], atol=1e-12)
    # odometry first, then loop closures between nearby non-consecutive poses
    m_odo = ds.num_odometry_edges
    np.testing.assert_array_equal(I[:m_odo], np.arange(n - 1))
    np.testing.assert_array_equal(J[:m_odo], np.arange(1, n))
    li, lj = I[m_odo:], J[m_odo:]
    assert np.all(lj > li + 1)
    assert np.all(np.linalg.norm(t[li] - t[lj], axis=1) <= 1.0 + 1e-9)
    assert len(np.unique(np.stack([li, lj], 1), axis=0)) == len(li)
    # each candidate kept with probability 0.1 (binomial, 5 sigma)
    N = len(_loop_closure_candidates(np.rint(t).astype(np.int64), 1.0))
    assert abs(len(li) - 0.1 * N) < 5 * math.sqrt(N * 0.09)
    assert len(connected_components(n, I, J)) == 1
    # weights are the SE-Sync kappa, tau for the requested RMSEs
    kappa, tau = kappa_tau_from_rmse(SIGMA_T, SIGMA_R, d)
    np.testing.assert_allclose(np.asarray(ds.graph.kappa), kappa)
    np.testing.assert_allclose(np.asarray(ds.graph.tau), tau)
    assert ds.kappa == pytest.approx(kappa) and ds.tau == pytest.approx(tau)


def test_noise_free_measurements_are_consistent():
    ds = cube_dataset(1, grid=5, num_poses=400, sigma_t=0.0, sigma_R=0.0)
    assert float(cost(ds.graph, ds.ground_truth)) < 1e-20
    assert np.all(np.asarray(ds.graph.kappa) == 1.0) and np.all(np.asarray(ds.graph.tau) == 1.0)
    assert ds.expected_ground_truth_cost() == 0.0
    ds2 = grid_2d_dataset(1, grid=5, num_poses=300, sigma_t=0.0, sigma_R=0.0)
    assert float(cost(ds2.graph, ds2.ground_truth)) < 1e-20
    # sigma -> 0: the measurements converge to the ground truth
    ds3 = cube_dataset(1, grid=5, num_poses=400, sigma_t=1e-7, sigma_R=1e-7)
    Rn, tn = _noise(ds3)
    assert np.abs(Rn - np.eye(3)).max() < 1e-5 and np.abs(tn).max() < 1e-5


@pytest.mark.parametrize("which", ["cube", "grid2d"])
def test_dataset_noise_rmse(which, request):
    ds = request.getfixturevalue(which)
    Rn, tn = _noise(ds)
    assert math.sqrt(np.mean(rotation_angle(Rn) ** 2)) == pytest.approx(SIGMA_R, rel=0.05)
    assert math.sqrt(np.mean(np.sum(tn**2, axis=1))) == pytest.approx(SIGMA_T, rel=0.05)


@pytest.mark.parametrize("which", ["cube", "grid2d"])
def test_ground_truth_cost_matches_expectation(which, request):
    ds = request.getfixturevalue(which)
    d, m = ds.dim, ds.num_edges
    f_gt = float(cost(ds.graph, ds.ground_truth))
    e = ds.expected_ground_truth_cost()
    assert e == pytest.approx(m * expected_edge_cost(ds.kappa, ds.tau, d))
    assert e == pytest.approx(m * (d + d * (d - 1) / 2), rel=2e-3)
    # per-edge cost ~ chi^2 with d + d(d-1)/2 dofs: variance ~ 2 (d + d(d-1)/2)
    sd = math.sqrt(2 * (d + d * (d - 1) / 2) * m)
    assert abs(f_gt - e) < 4 * sd


def test_dtype_and_small_lattice():
    ds = lattice_dataset(0, dim=2, grid=1, num_poses=50, dtype=jnp.float32)
    assert ds.graph.R.dtype == jnp.float32 and ds.ground_truth.t.dtype == jnp.float32
    t = np.asarray(ds.ground_truth.t)
    assert set(map(tuple, t.astype(int))) <= {(0, 0), (0, 1), (1, 0), (1, 1)}
    with pytest.raises(ValueError):
        lattice_dataset(0, dim=4, grid=3, num_poses=10)


# --------------------------------------------------------------------------------------------
# the walk and the heading frames against pose-by-pose references
# --------------------------------------------------------------------------------------------


def _walk_reference(rng, dim, grid, num_poses):
    """The walk's definition: one rng.integers call per step with more than one option."""
    steps = np.concatenate([np.eye(dim, dtype=np.int64), -np.eye(dim, dtype=np.int64)])
    pos = np.zeros((num_poses, dim), dtype=np.int64)
    prev = -1  # index into steps of the previous move
    for k in range(1, num_poses):
        nxt = pos[k - 1] + steps
        ok = np.all((nxt >= 0) & (nxt <= grid), axis=1)
        if prev >= 0:
            ok_forward = ok.copy()
            ok_forward[(prev + dim) % (2 * dim)] = False
            if ok_forward.any():
                ok = ok_forward
        choices = np.flatnonzero(ok)
        prev = int(choices[rng.integers(len(choices))]) if len(choices) > 1 else int(choices[0])
        pos[k] = nxt[prev]
    return pos


@pytest.mark.parametrize(("dim", "grid", "n"), [(3, 12, 3000), (3, 1, 200), (2, 1, 300), (2, 3, 2000)])
def test_lattice_walk_is_the_per_step_walk(dim, grid, n):
    """The compiled walk equals one rng.integers call per step, and leaves the generator where
    those calls leave it (grid 1 in 2D has one-option steps, which draw nothing)."""
    from mmpgo_jax._experiments.synthetic import _lattice_walk

    for seed in range(3):
        r1, r2 = np.random.default_rng(seed), np.random.default_rng(seed)
        np.testing.assert_array_equal(_lattice_walk(r1, dim, grid, n), _walk_reference(r2, dim, grid, n))
        assert r1.bit_generator.state == r2.bit_generator.state
        np.testing.assert_array_equal(r1.integers(0, 7, 5), r2.integers(0, 7, 5))  # 32-bit buffer too


class _CraftedDraws:
    """A stand-in for numpy's generator in :func:`_walk_reference`: ``integers(k)`` is numpy's
    bounded integer in [0, k) (Lemire's method) from a given list of 32-bit draws, counting them."""

    def __init__(self, draws):
        self.draws, self.used, self.redraws = list(draws), 0, 0

    def _next(self):
        self.used += 1
        return self.draws[self.used - 1]

    def integers(self, k):
        threshold = (2**32 - k) % k
        m = self._next() * k
        while (m & 0xFFFFFFFF) < threshold:
            m, self.redraws = self._next() * k, self.redraws + 1
        return m >> 32


@pytest.mark.parametrize("dim", [2, 3])
def test_walk_redraws_where_numpy_would(dim):
    """Draws whose product with the option count falls below Lemire's threshold (x = 0 for 3 or 5
    options) are rejected and the next draw taken, as numpy does; the count of draws used says so."""
    from mmpgo_jax._experiments.synthetic import _walk_moves

    rng = np.random.default_rng(1)
    n, grid = 400, 3
    u = rng.integers(0, 2**32, size=n + 40, dtype=np.uint32)
    u[rng.choice(n, 30, replace=False)] = 0
    moves, used = _walk_moves(u, dim, grid, 512, n, u.size)  # padded beyond the walk: the tail neither moves nor draws
    unit = np.concatenate([np.eye(dim, dtype=np.int64), -np.eye(dim, dtype=np.int64)])
    pos = np.concatenate([np.zeros((1, dim), np.int64), np.cumsum(unit[np.asarray(moves)[:n]], axis=0)])

    crafted = _CraftedDraws(u.tolist())
    np.testing.assert_array_equal(pos, _walk_reference(crafted, dim, grid, n + 1))
    assert int(used) == crafted.used and crafted.redraws > 0


@pytest.mark.parametrize("dim", [2, 3])
def test_heading_frames_are_the_pose_by_pose_products(dim):
    from mmpgo_jax._experiments.synthetic import _heading_frames, _lattice_walk

    pos = _lattice_walk(np.random.default_rng(4), dim, 3, 700)
    pos = np.concatenate([pos, pos[-2:-1]])  # end with a reversal (the pi rotation)
    R = _heading_frames(pos)
    heads = np.diff(pos, axis=0).astype(np.float64)
    heads = np.concatenate([heads, heads[-1:]])

    def plane(a, b):  # the rotation taking a to b, fixing the rest, one pair at a time
        if a @ b < -0.5:
            c = np.eye(dim)[int(np.argmax(np.abs(a) < 0.5))]
            return np.eye(dim) - 2.0 * np.outer(a, a) - 2.0 * np.outer(c, c)
        if a @ b > 0.5:
            return np.eye(dim)
        return np.eye(dim) - np.outer(a, a) - np.outer(b, b) + np.outer(b, a) - np.outer(a, b)

    ref = [plane(np.eye(dim)[0], heads[0])]
    for k in range(1, len(pos)):
        ref.append(plane(heads[k - 1], heads[k]) @ ref[-1])
    np.testing.assert_array_equal(R, np.array(ref))
    assert np.all(np.abs(R).sum(axis=1) == 1) and np.all(np.linalg.det(R).round() == 1)
    np.testing.assert_array_equal(np.einsum("kab,b->ka", R, np.eye(dim)[0])[:-1], heads[:-1])
