"""The check of accepted inter-robot loop closures at the team's chordal map
(:mod:`mmpgo_jax._init.closure_check`)."""

from __future__ import annotations

import numpy as np
import pytest

import mmpgo_jax as mm
from mmpgo_jax._core.pose_graph import host_edge_costs
from mmpgo_jax._init.closure_check import check_inter_robot_closures
from mmpgo_jax._init.distributed_chordal import distributed_chordal_initialization
from mmpgo_jax._init.robust_distributed import distributed_robust_initialization


def _team_with_wrong_closures(count=3, seed=1):
    ds = mm.robot_team_dataset(4, 60, intra_closures=2, inter_closures=12, seed=seed, sigma_t=0.005,
                               sigma_R=0.005)
    rop = ds.robot_of_pose
    loops = int((np.abs(np.asarray(ds.graph.i) - np.asarray(ds.graph.j)) != 1).sum())
    c = mm.add_outlier_loop_closures(ds.graph, count / (loops + count), reference=ds.ground_truth, seed=seed,
                                     robot_of_pose=rop, inter_robot_only=True)
    assert c.num_outliers == count
    return ds, c, rop


def test_planted_wrong_closures_accepted_by_hand_are_dropped():
    """Every edge accepted, three wrong inter-robot closures among them: the check drops all three
    (and here one correct closure, dropped while two wrong ones still bent the chordal map), the
    objective is the TLS one of every edge at each round's map, lowest at the kept round, and the
    start is the distributed chordal map of the edges kept."""
    ds, c, rop = _team_with_wrong_closures()
    scale = float(mm.chi2_scale(2))
    found = check_inter_robot_closures(c.graph, rop, np.ones(c.graph.num_edges, bool), scale, patience=5)
    assert not (found.accepted & c.outlier).any()
    assert int((~found.accepted & ~c.outlier).sum()) <= 1
    assert set(np.flatnonzero(~found.accepted).tolist()) == set(found.removed.tolist())
    kept_round = int(found.rounds[-1]) if found.removed.size else 0
    assert found.objective.min() == found.objective[kept_round]
    assert np.all(np.diff(found.rounds) >= 0) and np.all(np.bincount(found.rounds)[1:] <= 2)
    X, _ = distributed_chordal_initialization(c.graph.select_edges(found.accepted), rop)
    np.testing.assert_allclose(found.poses.t, np.asarray(X.t), atol=1e-9)
    s = host_edge_costs(c.graph, found.poses)
    odometry = np.abs(np.asarray(c.graph.i) - np.asarray(c.graph.j)) == 1
    expected = np.sum(np.where(odometry, s, np.minimum(s, scale**2)))
    assert found.objective[kept_round] == pytest.approx(expected, rel=1e-12)
    # every chordal solve counted (the first map, then one to three per round), each with CG iterations
    assert len(found.objective) <= len(found.cg_iterations) <= 1 + 3 * (len(found.objective) - 1)
    assert (found.cg_iterations > 0).all()


def test_without_wrong_closures_nothing_is_dropped():
    ds, _, rop = _team_with_wrong_closures()
    found = check_inter_robot_closures(ds.graph, rop, np.ones(ds.graph.num_edges, bool), float(mm.chi2_scale(2)),
                                       patience=3)
    # every closure fits within c at the team's chordal map: no suspect, no round
    assert found.removed.size == 0 and found.accepted.all() and len(found.objective) == 1
    s = host_edge_costs(ds.graph, found.poses)
    assert s[np.abs(np.asarray(ds.graph.i) - np.asarray(ds.graph.j)) != 1].max() <= float(mm.chi2_scale(2)) ** 2


def test_a_closure_whose_removal_splits_the_team_stays():
    """Robots joined by one closure each (a chain of robots): no closure can be dropped."""
    ds = mm.robot_team_dataset(3, 30, intra_closures=1, inter_closures=0, seed=0, sigma_t=0.005, sigma_R=0.005)
    rop = ds.robot_of_pose
    g = ds.graph  # contiguous robots: the consecutive-pose edges between robots are odometry, trusted
    found = check_inter_robot_closures(g, rop, np.ones(g.num_edges, bool), 3.0, patience=2,
                                       trusted=np.zeros(g.num_edges, bool) | (rop[np.asarray(g.i)] == rop[np.asarray(g.j)]))
    assert found.accepted.all() and found.removed.size == 0


def test_the_distributed_robust_start_with_the_check():
    ds, c, rop = _team_with_wrong_closures()
    plain = distributed_robust_initialization(c.graph, rop)
    checked = distributed_robust_initialization(c.graph, rop, team_check=True, patience=5)
    assert plain.team_check is None and checked.team_check is not None
    # the check only drops closures the frame test accepted
    assert not (checked.accepted & ~plain.accepted).any()
    assert not (checked.accepted & c.outlier).any()
    np.testing.assert_array_equal(checked.weights, checked.team_check.accepted.astype(float))
    with pytest.raises(ValueError, match="patience"):
        check_inter_robot_closures(c.graph, rop, np.ones(c.graph.num_edges, bool), 3.0, patience=0)


def test_solve_takes_the_check_as_a_named_start_s_option(monkeypatch):
    """``start=NamedStart("distributed-robust", {"team_check": True})``: the fully distributed
    pipeline's start runs the check (and so does every start its search makes again)."""
    import mmpgo_jax._init.robust_distributed as robust_distributed

    calls = []

    def counted(*args, **kwargs):
        calls.append(kwargs.get("patience"))
        return check_inter_robot_closures(*args, **kwargs)

    monkeypatch.setattr(robust_distributed, "check_inter_robot_closures", counted)
    ds, c, rop = _team_with_wrong_closures()
    res = mm.solve(c.graph, rop, loss="tls", distributed=True, iterations=200,
                   start=mm.NamedStart("distributed-robust", {"team_check": True, "patience": 4}))
    assert calls and set(calls) == {4}
    assert len(calls) == 1 + sum(len(row["revisits"]) for row in res.stats["starts"])
    assert not (np.asarray(res.inliers, bool) & c.outlier).any()


def test_cli_team_check(tmp_path, capsys, monkeypatch):
    """``mmpgo solve FILE --loss tls --distributed --team-check`` runs the check, as ``--distributed``
    does by default and ``--no-team-check`` does not (and the default's two starts take it on the
    distributed one); without a robust loss, or with a start other than the distributed robust one,
    it is a one-line error."""
    import mmpgo_jax._init.robust_distributed as robust_distributed
    from mmpgo_jax.cli import main

    calls = []

    def counted(*args, **kwargs):
        calls.append(1)
        return check_inter_robot_closures(*args, **kwargs)

    monkeypatch.setattr(robust_distributed, "check_inter_robot_closures", counted)
    ds, c, _ = _team_with_wrong_closures()
    path = tmp_path / "team.g2o"
    mm.write_g2o(path, c.graph, ds.ground_truth)
    common = [str(path), "--robots", "4", "-n", "20", "--no-progress"]
    assert main(["solve", *common, "--loss", "tls", "--distributed", "--team-check"]) == 0
    assert calls
    calls.clear()
    capsys.readouterr()
    assert main(["solve", *common, "--loss", "tls", "--distributed"]) == 0  # on by default with --distributed
    assert calls
    (line,) = [x for x in capsys.readouterr().out.splitlines() if x.startswith("exchanged")]
    assert "team check" in line and "distributed chordal solve" in line
    calls.clear()
    assert main(["solve", *common, "--loss", "tls", "--distributed", "--no-team-check"]) == 0
    assert not calls
    assert main(["solve", *common, "--loss", "tls", "--team-check"]) == 0
    assert calls
    capsys.readouterr()
    assert main(["solve", *common, "--team-check"]) != 0
    assert "--team-check" in capsys.readouterr().err
    assert main(["solve", *common, "--loss", "tls", "--init", "gnc-chordal", "--team-check"]) != 0
    assert "--init distributed-robust" in capsys.readouterr().err


def _round_with(objectives: dict, split=()):
    """One round of the check's decision on three candidate closures (residuals 9, 8, 1) with a
    chordal map stubbed as the set of edges dropped and the objective of each such map given."""
    from mmpgo_jax._init.closure_check import _next_drop

    acc = np.ones(3, bool)

    def chordal_map(keep):
        dropped = frozenset(np.flatnonzero(~keep).tolist())
        return None if dropped in split else dropped

    return _next_drop(acc, np.array([9.0, 8.0, 1.0]), np.ones(3, bool), np.zeros(3, bool), chordal_map,
                      lambda dropped: objectives[dropped], 4.0), acc


def test_a_round_drops_the_trial_of_lower_objective_or_both_when_tied():
    """The two largest residuals are each dropped on trial: the lower objective goes (the second
    residual here), both go when their objectives differ by less than c^2 (4 here), and a tie whose
    double removal would split the team drops the lower one alone."""
    (dropped, X), acc = _round_with({frozenset({0}): 50.0, frozenset({1}): 20.0})
    assert dropped == [1] and X == frozenset({1}) and acc.tolist() == [True, False, True]
    (dropped, X), acc = _round_with({frozenset({0}): 21.0, frozenset({1}): 20.0, frozenset({0, 1}): 5.0})
    assert dropped == [0, 1] and X == frozenset({0, 1}) and acc.tolist() == [False, False, True]
    (dropped, X), acc = _round_with({frozenset({0}): 21.0, frozenset({1}): 20.0}, split={frozenset({0, 1})})
    assert dropped == [1] and acc.tolist() == [True, False, True]
