"""noise_level: the a-posteriori variance factor reads how the data's noise compares with their
information matrices (about 1 when they match, about k^2 when the noise is k times what they say)."""

import numpy as np
import pytest

import mmpgo_jax as mm
from mmpgo_jax._core.pose_graph import PoseGraph, host_graph


def _team(noise: float, claimed: float, dim: int = 2):
    """A 2-robot team whose measurements carry ``noise`` but whose information matrices are those of
    ``claimed`` noise (the same generator and seed), at its optimum."""
    kw = dict(intra_closures=60, inter_closures=10, seed=0, dim=dim)
    g = host_graph(mm.robot_team_dataset(2, 300, sigma_t=noise, sigma_R=noise, **kw).graph)
    info = mm.robot_team_dataset(2, 300, sigma_t=claimed, sigma_R=claimed, **kw).graph
    g = PoseGraph(g.i, g.j, g.R, g.t, np.asarray(info.kappa), np.asarray(info.tau), num_poses=g.num_poses)
    return g, mm.centralized_optimum(g).poses


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("noise, claimed", [(0.03, 0.03), (0.03, 0.01), (0.01, 0.03)])
def test_factor_is_the_ratio_of_the_noise_variance_to_the_claimed_one(dim, noise, claimed):
    g, X = _team(noise, claimed, dim)
    level = mm.noise_level(g, X)
    ratio = (noise / claimed) ** 2
    assert level.factor == pytest.approx(ratio, rel=0.25)
    p = dim * (dim + 1) // 2
    assert level.redundancy == p * (g.num_edges - g.num_poses + 1)
    s = np.asarray(mm.edge_costs(g, X))
    assert level.factor == pytest.approx(s.sum() / level.redundancy, rel=1e-12)
    assert level.low < level.factor < level.high
    if ratio == 1.0:
        assert level.low <= 1.0 <= level.high and level.nearest_one() == 1.0
    else:  # 9x off either way: the 99 % interval excludes 1 and its nearer end is returned
        assert not level.low <= 1.0 <= level.high
        assert level.nearest_one() == (level.low if ratio > 1 else level.high)


def test_no_redundancy_and_bad_confidence():
    g, X = _team(0.03, 0.03)
    chain = g.select_edges(np.abs(np.asarray(g.i) - np.asarray(g.j)) == 1)  # two odometry chains
    level = mm.noise_level(chain, X)
    assert level.redundancy == 0 and np.isnan(level.factor) and level.nearest_one() == 1.0
    with pytest.raises(ValueError, match="confidence must be in"):
        mm.noise_level(g, X, confidence=1.0)


def _cli_noise_line(tmp_path, capsys, g, X) -> str:
    """The ``noise`` line of ``mmpgo solve`` (TLS from the GNC start) on ``g`` written with poses X."""
    from mmpgo_jax.cli import main

    path = tmp_path / "team.g2o"
    mm.write_g2o(path, g, X)
    rc = main(["solve", str(path), "-A", "2", "--loss", "tls", "--init", "gnc-chordal", "-n", "50", "--no-progress"])
    out = capsys.readouterr().out
    assert rc == 0, out
    return next(line for line in out.splitlines() if line.startswith("noise "))


def test_cli_robust_run_prints_the_noise_line(tmp_path, capsys):
    line = _cli_noise_line(tmp_path, capsys, *_team(0.03, 0.01))  # information 9x too confident
    assert "the information matrices understate the noise" in line and "--loss-scale" in line
    assert "in 2D this is also" not in line  # far beyond what SE-Sync's 2D kappa alone reads


def test_cli_noise_line_names_the_2d_reading_of_a_calibrated_file(tmp_path, capsys):
    """A 2D team written with the information its noise has in the g2o sense (I33 = 1 / var(angle):
    kappa doubled against the generator's Langevin concentration) reads between 1 and 2 under SE-Sync's
    model (1.7 here: the angle's share of the residuals counts twice); the CLI's noise line says so and
    gives that file's 0.99 quantile as --loss-scale."""
    g, X = _team(0.03, 0.03)
    g = PoseGraph(g.i, g.j, g.R, g.t, 2.0 * np.asarray(g.kappa), np.asarray(g.tau), num_poses=g.num_poses)
    level = mm.noise_level(g, mm.centralized_optimum(g).poses)
    assert 1.0 < level.low < level.factor < 2.0
    line = _cli_noise_line(tmp_path, capsys, g, X)
    assert "understate the noise" in line and "in 2D this is also what a file" in line and "--loss-scale 4.04" in line
