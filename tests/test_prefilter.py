"""PCM as a pre-filter of solve and sweep (mmpgo_jax/_solve/prefilter.py), ``mmpgo solve / sweep --pcm``, and the
robot-team generator it is measured on (benchmarks/robust_teams.md)."""

import numpy as np
import pytest

import mmpgo_jax as mm
from mmpgo_jax._core.pose_graph import PoseGraph


def _team(seed: int = 0, **kw):
    kw = dict(robots=3, poses_per_robot=60, intra_closures=3, inter_closures=9, dim=2, seed=seed,
              sigma_t=0.01, sigma_R=0.01, **kw)
    return mm.robot_team_dataset(**kw)


def _append(graph: PoseGraph, i, j, R, t) -> PoseGraph:
    """``graph`` with closures appended (the median weights), edge e < m keeping its index."""
    k, tau = np.median(np.asarray(graph.kappa)), np.median(np.asarray(graph.tau))
    return PoseGraph.from_arrays(np.r_[np.asarray(graph.i), i], np.r_[np.asarray(graph.j), j],
                                 np.concatenate([np.asarray(graph.R), R]), np.concatenate([np.asarray(graph.t), t]),
                                 np.r_[np.asarray(graph.kappa), np.full(len(i), k)],
                                 np.r_[np.asarray(graph.tau), np.full(len(i), tau)], num_poses=graph.num_poses,
                                 dtype=np.float64)


def _planted():
    """A 3-robot team with one wrong closure appended between robots 0 and 1 (which share >= 2
    correct ones, so the wrong one is outvoted): (graph, robot_of_pose, planted mask)."""
    ds = _team()
    rop = ds.robot_of_pose
    i, j = np.asarray(ds.graph.i), np.asarray(ds.graph.j)
    pair01 = ds.inter_robot & (np.minimum(rop[i], rop[j]) == 0) & (np.maximum(rop[i], rop[j]) == 1)
    assert pair01.sum() >= 2  # the set-up the test relies on
    c = np.cos(2.0)
    R = np.array([[[c, -np.sin(2.0)], [np.sin(2.0), c]]])
    graph = _append(ds.graph, np.array([10]), np.array([60 + 30]), R, np.array([[5.0, -3.0]]))
    planted = np.zeros(graph.num_edges, bool)
    planted[-1] = True
    return graph, rop, planted


def test_pcm_removes_the_planted_closure_and_solves_the_graph_without_it():
    graph, rop, planted = _planted()
    r = mm.solve(graph, rop, prefilter="pcm", iterations=200)
    np.testing.assert_array_equal(r.prefiltered, planted)  # removed, and every consistent closure kept
    np.testing.assert_array_equal(r.inliers, ~planted)  # least squares: inliers = ~prefiltered
    assert r.weights is None and r.loss is None
    assert r.stats["pcm_rejected"] == 1 and r.stats["pcm_components"] == 1 and r.stats["pcm_confidence"] == 0.99
    ref = mm.solve(graph.select_edges(~planted), rop, iterations=200)
    assert r.f == ref.f and r.iterations == ref.iterations
    np.testing.assert_allclose(np.asarray(r.poses.t), np.asarray(ref.poses.t), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(r.poses.R), np.asarray(ref.poses.R), rtol=0, atol=1e-12)
    plain = mm.solve(graph, rop, iterations=5)
    assert plain.prefiltered is None and plain.inliers is None and "pcm_rejected" not in plain.stats


def test_pcm_with_a_robust_loss_reports_in_the_original_edge_order():
    graph, rop, planted = _planted()
    r = mm.solve(graph, rop, prefilter=mm.PCM(confidence=0.999), loss="tls", start="gnc-chordal", iterations=100)
    assert r.weights.shape == r.inliers.shape == r.prefiltered.shape == (graph.num_edges,)
    assert r.weights[planted] == 0.0 and not r.inliers[planted]
    np.testing.assert_array_equal(r.prefiltered, planted)
    assert r.stats["pcm_confidence"] == 0.999
    assert r.outliers[planted].all()


def test_the_edges_named_in_starts_stats_are_reported_in_the_original_edge_order():
    """A robust run after the pre-filter names edges of the filtered graph in stats["starts"] (the
    edge a revisit left out, the closure a re-admission admitted or a removal left out, those an
    exchange admitted and left out): put back in the original order."""
    import dataclasses

    from mmpgo_jax._solve.prefilter import Prefiltered

    rejected = np.array([False, True, False, True, False, False])  # kept edges 0, 2, 4, 5
    pre = Prefiltered(graph=None, rejected=rejected, robot_of_pose=np.zeros(3, np.int64), stats={"pcm_rejected": 2})
    starts = [dict(start="gnc-chordal", revisits=[], readmissions=[], removals=[], exchanges=[]),
              dict(start="distributed-robust", revisits=[dict(excluded=1, kept=True)],
                   readmissions=[dict(admitted=2, kept=True), dict(admitted=3, kept=False)],
                   removals=[dict(removed=3, kept=False)],
                   exchanges=[dict(moves=[(1, None)], kept=True), dict(moves=[(0, 2), (3, None)], kept=False)])]

    @dataclasses.dataclass(frozen=True)
    class Result:
        inliers: np.ndarray
        weights: np.ndarray | None
        start_weights: np.ndarray | None
        prefiltered: np.ndarray | None
        stats: dict

    out = pre.report(Result(np.ones(4, bool), None, None, None, dict(starts=starts)))
    gnc, dist = out.stats["starts"]
    assert gnc == starts[0] and out.stats["pcm_rejected"] == 2
    assert [r["excluded"] for r in dist["revisits"]] == [2]
    assert [(r["admitted"], r["kept"]) for r in dist["readmissions"]] == [(4, True), (5, False)]
    assert [(r["removed"], r["kept"]) for r in dist["removals"]] == [(5, False)]
    assert [r["moves"] for r in dist["exchanges"]] == [[(2, None)], [(0, 4), (5, None)]]
    assert starts[1]["readmissions"][0]["admitted"] == 2  # the run's own stats are not changed in place


def test_prefilter_arguments_are_checked():
    graph, rop, _ = _planted()
    with pytest.raises(ValueError, match="prefilter"):
        mm.solve(graph, rop, prefilter="ransac")
    with pytest.raises(ValueError, match="confidence"):
        mm.PCM(confidence=1.5)
    with pytest.raises(ValueError, match="min_clique_size"):
        mm.PCM(min_clique_size=0)
    with pytest.raises(ValueError, match="ties"):
        mm.PCM(ties="all")


def test_a_robot_cut_off_by_pcm_is_solved_in_its_own_frame():
    """Robot 2 tied to the others by one closure: PCM with min_clique_size=2 removes it, the graph
    falls apart in two components; the run still succeeds (each component anchored by the start)."""
    ds = _team()
    rop = ds.robot_of_pose
    i, j = np.asarray(ds.graph.i), np.asarray(ds.graph.j)
    to_two = ds.inter_robot & ((rop[i] == 2) | (rop[j] == 2))
    keep = ~to_two
    keep[np.flatnonzero(to_two)[0]] = True
    graph = ds.graph.select_edges(keep)
    r = mm.solve(graph, rop, prefilter=mm.PCM(min_clique_size=2), iterations=100)
    assert r.stats["pcm_components"] == 2
    assert r.prefiltered[np.flatnonzero(to_two[keep])[0]]
    assert np.isfinite(r.f) and np.all(np.isfinite(np.asarray(r.poses.t)))


@pytest.mark.slow  # about 25 s on 2 cores; the CLI test below runs sweep --pcm in the default run
def test_sweep_prefilter_equals_solve_per_robot_count():
    """sweep(prefilter=) filters per robot count (PCM's pairs follow the split) and equals solve(prefilter=)
    configuration by configuration, in the given graph's edge order."""
    graph, _, planted = _planted()
    res = mm.sweep({"team": graph}, [2, 3], "mm", 20, prefilter="pcm", loss="tls")
    for a in (2, 3):
        key = ("team", a, "mm")
        ref = mm.solve(graph, a, method="mm", prefilter="pcm", loss="tls", iterations=20, stop_when_stalled=False)
        got = res.results[key]
        np.testing.assert_array_equal(got.prefiltered, ref.prefiltered)
        np.testing.assert_array_equal(res.inliers[key], ref.inliers)
        np.testing.assert_allclose(res.weights[key], ref.weights, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(res.histories[key], ref.history.f, rtol=1e-9, atol=0)
        row = next(r for r in res.configs if r["robots"] == a)
        assert row["pcm_rejected"] == int(ref.prefiltered.sum()) == ref.stats["pcm_rejected"]
    assert res.results[("team", 3, "mm")].prefiltered[planted].all()  # the planted closure, between robots 0 and 1
    ls = mm.sweep(graph, [3], "mm", 0, prefilter=mm.PCM(confidence=0.99))
    (key,) = ls.histories
    np.testing.assert_array_equal(ls.inliers[key], ~planted)  # least squares: inliers = ~prefiltered
    assert key not in ls.weights and ls.configs[0]["pcm_rejected"] == 1
    kept = mm.solve(graph.select_edges(~planted), 3, iterations=0)
    np.testing.assert_allclose(ls.histories[key], kept.history.f, rtol=1e-12)
    assert "pcm_rejected" not in mm.sweep(graph, [3], "mm", 0).configs[0]
    with pytest.raises(ValueError, match="prefilter"):
        mm.sweep(graph, [3], "mm", 0, prefilter="ransac")


def test_cli_pcm_prints_the_count_and_the_lines(tmp_path, capsys):
    from mmpgo_jax import read_g2o, write_g2o
    from mmpgo_jax.cli import main

    graph, rop, planted = _planted()
    path = tmp_path / "team.g2o"
    write_g2o(path, graph, mm.initialize(graph, "odometry"))
    line = int(read_g2o(path).edge_line[np.flatnonzero(planted)[0]])
    out = tmp_path / "kept.g2o"
    rc = main(["solve", str(path), "-A", "3", "--pcm", "-n", "50", "--drop-outliers", "--out", str(out),
               "--no-progress"])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert f"1 of {int(np.sum(rop[np.asarray(graph.i)] != rop[np.asarray(graph.j)]))} inter-robot" in text
    assert f"line {line} of team.g2o" in text
    assert read_g2o(out).graph.num_edges == graph.num_edges - 1
    rc = main(["solve", str(path), "-A", "3", "--pcm-confidence", "0.9", "--no-progress"])
    assert rc != 0 and "--pcm-confidence applies with --pcm" in capsys.readouterr().err
    rc = main(["sweep", str(path), "-A", "3", "--pcm", "-n", "5", "--methods", "mm", "--no-progress"])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "PCM rejected" in text and text.splitlines()[-1].split("|")[-5].strip() == "1"  # its column
    rc = main(["sweep", str(path), "-A", "3", "--pcm-confidence", "0.9"])
    assert rc != 0 and "--pcm-confidence applies with --pcm" in capsys.readouterr().err
    rc = main(["solve", str(path), "-A", "3", "--pcm-ties", "keep", "--no-progress"])
    assert rc != 0 and "--pcm-ties applies with --pcm" in capsys.readouterr().err
    # ties kept: the planted closure is outvoted by its pair's consistent ones, so it still goes
    rc = main(["sweep", str(path), "-A", "3", "--pcm", "--pcm-ties", "keep", "-n", "5", "--methods", "mm",
               "--no-progress"])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert text.splitlines()[-1].split("|")[-5].strip() == "1"


def test_robot_team_dataset():
    ds = mm.robot_team_dataset(4, 200, intra_closures=3, inter_closures=6, dim=3, seed=1)
    g, rop = ds.graph, ds.robot_of_pose
    assert g.num_poses == 800 and rop.shape == (800,) and np.array_equal(np.bincount(rop), [200] * 4)
    i, j = np.asarray(g.i), np.asarray(g.j)
    kind = ds.edge_kind
    assert np.array_equal(np.bincount(kind), [4 * 199, 12, 6])
    assert np.all((j[kind == 0] == i[kind == 0] + 1) & (rop[i[kind == 0]] == rop[j[kind == 0]]))
    assert np.all(rop[i[kind == 1]] == rop[j[kind == 1]]) and np.all(rop[i[kind == 2]] != rop[j[kind == 2]])
    assert len(mm.connected_components(g.num_poses, i, j)) == 1  # the spanning closures tie the team
    again = mm.robot_team_dataset(4, 200, intra_closures=3, inter_closures=6, dim=3, seed=1)
    np.testing.assert_array_equal(np.asarray(again.graph.t), np.asarray(g.t))
    # measurements = ground truth relative poses + noise of the stated level
    cost = float(mm.cost(g, ds.ground_truth))
    assert 0.5 < cost / ds.expected_ground_truth_cost() < 1.5
