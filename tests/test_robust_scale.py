"""The robust scale c (chi2_scale): the residual a correct edge exceeds with probability 1 - quantile,
under SE-Sync's noise model (the default: s ~ chi^2_p) and, with ``noise="information"``, for g2o
files whose noise is what their information matrices state, read with SE-Sync's weights (2D: kappa =
I33 counts the angle twice, so s = chi^2_2 + 2 chi^2_1)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import mmpgo_jax as mm
from mmpgo_jax._experiments.synthetic import sample_langevin
from mmpgo_jax._mm.robust import correct_edge_sf


def _calibrated_edges(tmp_path, dim: int, count: int, seed: int = 0):
    """A g2o file of two poses and ``count`` measurements of their relative pose, each with noise drawn
    from the covariance its (anisotropic translation, isotropic rotation) information matrix states;
    returns the graph as read and the true poses."""
    rng = np.random.default_rng(seed)
    sig_t, sig_r = 0.05, 0.02
    if dim == 2:
        info = f"{1 / sig_t**2} 0 0 {1 / sig_t**2} 0 {1 / sig_r**2}"
        dx = rng.normal(size=(count, 2)) * sig_t
        da = rng.normal(size=count) * sig_r
        lines = ["VERTEX_SE2 0 0 0 0", "VERTEX_SE2 1 1 2 0.5"]
        # pose 0 is the identity, so the relative pose is pose 1's: (1, 2, 0.5)
        lines += [f"EDGE_SE2 0 1 {1 + x[0]:.17g} {2 + x[1]:.17g} {0.5 + a:.17g} {info}" for x, a in zip(dx, da, strict=True)]
    else:
        upper = [1 / sig_t**2 if a == b and a < 3 else 1 / sig_r**2 if a == b else 0.0
                 for a in range(6) for b in range(a, 6)]
        info = " ".join(f"{v:.17g}" for v in upper)
        dx = rng.normal(size=(count, 3)) * sig_t
        q = Rotation.from_rotvec(rng.normal(size=(count, 3)) * sig_r).as_quat()  # R_1 = I: the noise itself
        lines = ["VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1", "VERTEX_SE3:QUAT 1 1 2 3 0 0 0 1"]
        lines += [f"EDGE_SE3:QUAT 0 1 {1 + x[0]:.17g} {2 + x[1]:.17g} {3 + x[2]:.17g} {r[0]:.17g} {r[1]:.17g} {r[2]:.17g} {r[3]:.17g} {info}"
                  for x, r in zip(dx, q, strict=True)]
    path = tmp_path / f"edges{dim}.g2o"
    path.write_text("\n".join(lines) + "\n")
    data = mm.read_g2o(path)
    return data.graph, mm.Poses(data.vertex_R, data.vertex_t)


def _share_within_binomial(s, c, q):
    share = float(np.mean(s > c * c))
    return abs(share - (1 - q)) < 4 * np.sqrt(q * (1 - q) / len(s)), share


@pytest.mark.parametrize("dim", [2, 3])
def test_default_scale_under_se_syncs_noise_model(dim):
    """20 000 measurements with SE-Sync's noise (Langevin rotations of concentration kappa, Gaussian
    translations of precision tau; the generator's sampler): s = kappa ||R - I||^2 + tau ||t||^2 exceeds
    the default c^2 at the rate 1 - quantile (four binomial standard deviations), at 0.99 and 0.9."""
    rng = np.random.default_rng(1)
    kappa, tau, m = 400.0, 300.0, 20_000
    R = sample_langevin(rng, kappa, m, dim)
    t = rng.normal(size=(m, dim)) / np.sqrt(tau)
    s = kappa * np.sum((R - np.eye(dim)) ** 2, axis=(1, 2)) + tau * np.sum(t**2, axis=1)
    for q in (0.99, 0.9):
        ok, share = _share_within_binomial(s, mm.chi2_scale(dim, q), q)
        assert ok, (q, share)


@pytest.mark.parametrize("dim", [2, 3])
def test_information_scale_for_files_whose_noise_is_their_information(tmp_path, dim):
    """20 000 calibrated g2o measurements read back, costs at the true poses: ``noise="information"``'s
    c is exceeded at the rate 1 - quantile; in 2D the default c (chi^2_3's) at 0.042 instead of 0.01,
    in 3D the two scales are one."""
    graph, truth = _calibrated_edges(tmp_path, dim, 20_000)
    s = np.asarray(mm.edge_costs(graph, truth))
    for q in (0.99, 0.9):
        ok, share = _share_within_binomial(s, mm.chi2_scale(dim, q, noise="information"), q)
        assert ok, (q, share)
    if dim == 2:
        assert mm.chi2_scale(2) == pytest.approx(np.sqrt(11.344866730144373), rel=1e-12)
        assert 0.035 < np.mean(s > mm.chi2_scale(2) ** 2) < 0.05
    else:
        assert mm.chi2_scale(3, noise="information") == mm.chi2_scale(3)


def test_survival_function_and_quantile_agree():
    """chi2_scale inverts correct_edge_sf; in 3D it is chi^2_6's quantile; the 2D closed form against a
    direct quadrature of P(A + 2B > x) over B."""
    from scipy import integrate, stats

    for q in (1e-6, 0.1, 0.5, 0.9, 0.99, 1 - 1e-9):
        c = mm.chi2_scale(2, q, noise="information")
        assert float(correct_edge_sf(c * c, 2, "information")) == pytest.approx(1 - q, rel=1e-9, abs=1e-15)
        for dim in (2, 3):
            p = dim * (dim + 1) // 2
            assert mm.chi2_scale(dim, q) ** 2 == pytest.approx(stats.chi2.ppf(q, p), rel=1e-12)
            assert float(correct_edge_sf(mm.chi2_scale(dim, q) ** 2, dim)) == pytest.approx(1 - q, rel=1e-9)
    for x in (0.5, 4.0, 11.3, 25.0):
        tail = integrate.quad(lambda b: stats.chi2.pdf(b, 1) * stats.chi2.sf(x - 2 * b, 2), 0, x / 2)[0]
        expected = tail + stats.chi2.sf(x / 2, 1)
        assert float(correct_edge_sf(x, 2, "information")) == pytest.approx(expected, rel=1e-8)
    with pytest.raises(ValueError, match="dim must be 2 or 3"):
        mm.chi2_scale(4)
    with pytest.raises(ValueError, match="noise must be one of"):
        mm.chi2_scale(2, noise="g2o")
