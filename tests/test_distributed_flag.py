"""``solve(..., distributed=True)`` and ``mmpgo solve --distributed``: every centralized step refused
with its name, the distributed chordal start (least squares) and the distributed robust start with
its edge weights held first (robust losses) used by default."""

import numpy as np
import pytest

import mmpgo_jax as mm


def _team():
    ds = mm.robot_team_dataset(3, 40, intra_closures=2, inter_closures=6, dim=2, seed=0, sigma_t=0.01,
                               sigma_R=0.01)
    return ds.graph, ds.robot_of_pose


@pytest.mark.parametrize("start", ["chordal", "gnc-chordal", "odometry"])
@pytest.mark.parametrize("keyword", ["start", "init"])
def test_centralized_starts_are_refused_by_name(start, keyword):
    graph, rop = _team()
    with pytest.raises(ValueError, match=f"distributed=True: the start '{start}'") as info:
        mm.solve(graph, rop, distributed=True, **{keyword: start})
    assert "\n" not in str(info.value)


def test_default_start_is_the_distributed_chordal_one_and_the_distributed_robust_one_for_a_robust_loss(monkeypatch):
    import mmpgo_jax._init.start as start_module

    graph, rop = _team()
    ref = mm.solve(graph, rop, start="distributed-chordal", iterations=0)
    # the distributed start converges to the centralized chordal start's poses: what shows which one
    # ran is that the centralized one is never called
    monkeypatch.setattr(start_module, "chordal_initialization",
                        lambda *a, **k: pytest.fail("distributed=True ran the centralized chordal start"))
    r = mm.solve(graph, rop, distributed=True, iterations=0)
    np.testing.assert_array_equal(np.asarray(r.start.t), np.asarray(ref.start.t))
    robust = mm.solve(graph, rop, distributed=True, loss="tls", iterations=0)
    # a robust loss: the distributed robust start with its accepted closures checked at the team's map
    dr = mm.initialize(graph, "distributed-robust", robots=rop, team_check=True)
    np.testing.assert_allclose(np.asarray(robust.start.t), np.asarray(dr.t), atol=1e-12)
    assert not bool(robust.loss.use_gnc) and robust.stats["start_weights_given"]
    unchecked = mm.solve(graph, rop, distributed=True, loss="tls", start="distributed-robust", iterations=0)
    plain = mm.initialize(graph, "distributed-robust", robots=rop)
    np.testing.assert_allclose(np.asarray(unchecked.start.t), np.asarray(plain.t), atol=1e-12)
    assert np.abs(np.asarray(plain.t) - np.asarray(dr.t)).max() > 1e-6  # the check's start is another map
    gnc = mm.solve(graph, rop, distributed=True, loss="tls", gnc=mm.GNCConfig(), iterations=0)  # GNC when asked
    assert bool(gnc.loss.use_gnc) and gnc.stats["start_weights_given"]
    huber = mm.solve(graph, rop, distributed=True, loss="huber", iterations=0)  # the same start
    np.testing.assert_allclose(np.asarray(huber.start.t), np.asarray(dr.t), atol=1e-12)
    given = mm.solve(graph, rop, distributed=True, start="vertices", initial=ref.start, iterations=0)
    np.testing.assert_allclose(np.asarray(given.start.t), np.asarray(ref.start.t), atol=1e-12)


@pytest.mark.parametrize("argv, named", [
    (["--init", "chordal"], "the start 'chordal' gathers the whole graph in one place; use --init distributed-chordal"),
    (["--init", "gnc-chordal"], "the start 'gnc-chordal'"),
    (["--init", "odometry"], "the start 'odometry'"),
    (["--certify"], "--certify"),
    (["--robots-from", "metis"], "--robots-from metis"),
])
def test_cli_refuses_each_centralized_option_in_one_line(tmp_path, capsys, argv, named):
    from mmpgo_jax.cli import main

    graph, _ = _team()
    path = tmp_path / "team.g2o"
    mm.write_g2o(path, graph, mm.initialize(graph, "odometry"))
    rc = main(["solve", str(path), "-A", "3", "--distributed", "--no-progress", *argv])
    err = capsys.readouterr().err.strip()
    assert rc != 0 and f"--distributed: {named}" in err
    assert len([line for line in err.splitlines() if "--distributed" in line]) == 1


def test_cli_distributed_runs_without_a_centralized_step(tmp_path, capsys):
    from mmpgo_jax.cli import main

    graph, _ = _team()
    path = tmp_path / "team.g2o"
    mm.write_g2o(path, graph, mm.initialize(graph, "odometry"))
    rc = main(["solve", str(path), "-A", "3", "--distributed", "--loss", "tls", "-n", "30", "--no-progress"])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "no centralized step: start distributed-robust, its edge weights held first" in out
    assert "exchanged   start " in out and "kB each, boundary poses" in out
    # the run used its 30 iterations and went on from its kept edges' distributed chordal start
    assert "finishing chordal start " in out and "CG iterations)" in out
    # 30 + 30 iterations, then a re-admission round (30 + 30): the start rejects a correct closure of
    # this outlier-free team, and the run from the start that accepts it reaches a lower objective
    assert "start       distributed-robust: f = " in out and "120 iterations" in out
    assert "1 closure it had rejected tried in turn from its result, 1 of those runs kept (lower f): line " in out


def test_robust_start_traffic_counts_every_message():
    """The distributed robust start's bytes, counted independently edge by edge: each inter-robot
    closure's far end (pose and two variances) to the near end's robot, each hypothesis (R, t, two
    weights, two map indices) to every other robot, and the variance factor's two sums per robot."""
    from mmpgo_jax._init.robust_distributed import start_traffic

    graph, rop = _team()
    d, A = graph.dim, 3
    closure_numbers = hypothesis_numbers = 0
    for i, j in zip(np.asarray(graph.i), np.asarray(graph.j), strict=True):
        if rop[i] != rop[j]:
            closure_numbers += d * d + d + 2
            hypothesis_numbers += (d * d + d + 4) * (A - 1)
    traffic = start_traffic(graph, rop)
    assert traffic.closures > 0 and traffic.robots == A
    assert traffic.bytes == 8 * (closure_numbers + hypothesis_numbers + 4 * A)
