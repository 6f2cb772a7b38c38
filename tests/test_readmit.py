"""Greedy re-admission of rejected loop closures by the robust objective (``readmit_loop_closures``,
``solve(..., readmit=True)``), against the optimum of the right classification computed directly."""

import numpy as np
import pytest

import mmpgo_jax as mm
from mmpgo_jax._experiments.outliers import add_outliers
from mmpgo_jax._mm.robust import robust_objective


def _case(seed=3):
    """A small Cube graph with planted outliers, the TLS loss, and a wrong classification: every
    outlier rejected plus two correct loop closures, the poses at the optimum of the edges kept."""
    ds = mm.cube_dataset(seed, grid=3, num_poses=60)
    bad = add_outliers(ds.graph, 0.2, reference=ds.ground_truth, seed=seed)
    graph = bad.graph
    loop = np.abs(np.asarray(graph.i) - np.asarray(graph.j)) != 1
    correct_loops = np.flatnonzero(loop & ~bad.outlier)
    dropped = correct_loops[[0, len(correct_loops) // 2]]
    kept = ~bad.outlier.copy()
    kept[dropped] = False
    X = mm.centralized_optimum(graph.select_edges(kept)).poses
    loss = mm.RobustLoss("tls").with_defaults(graph.dim)
    return graph, bad.outlier, kept, dropped, X, loss


def test_readmission_finds_the_correct_closures_and_the_optimum_of_the_right_classification():
    graph, outlier, kept, dropped, X, loss = _case()
    r = mm.readmit_loop_closures(graph, kept, X, loss)
    assert sorted(r.readmitted.tolist()) == sorted(dropped.tolist())
    np.testing.assert_array_equal(r.inliers, ~outlier)  # no outlier re-admitted
    ref = mm.centralized_optimum(graph.select_edges(~outlier)).poses
    assert mm.trajectory_accuracy(mm.Poses(r.poses.R, r.poses.t), ref).ate < 1e-6
    assert r.f == pytest.approx(robust_objective(loss, graph, ref), rel=1e-9)
    assert r.f < r.f_before == pytest.approx(robust_objective(loss, graph, X), rel=1e-12)
    # every rejected loop closure was tried in each of the three rounds (two re-admissions, one empty)
    rejected_loops = int((~kept & (np.abs(np.asarray(graph.i) - np.asarray(graph.j)) != 1)).sum())
    assert r.solves == rejected_loops + (rejected_loops - 1) + (rejected_loops - 2)


def test_readmission_leaves_a_right_classification_alone_and_checks_its_input():
    graph, outlier, _, _, _, loss = _case()
    X = mm.centralized_optimum(graph.select_edges(~outlier)).poses
    r = mm.readmit_loop_closures(graph, ~outlier, X, loss)
    assert r.readmitted.size == 0 and r.f == r.f_before
    np.testing.assert_array_equal(r.inliers, ~outlier)
    with pytest.raises(ValueError, match="inliers: expected"):
        mm.readmit_loop_closures(graph, ~outlier[:-1], X, loss)


def test_solve_readmit_runs_from_the_readmitted_optimum_and_refuses_what_it_cannot_do():
    """solve(readmit=True) with the wrong classification given as held start weights: the search
    re-admits the two correct closures and the run from their optimum is kept (the right
    classification, its optimum); least squares and distributed=True are refused in one line."""
    graph, outlier, kept, dropped, X, _ = _case()
    r = mm.solve(graph, 3, loss="tls", start=X, start_weights=kept.astype(float), iterations=200, readmit=True)
    info = r.stats["readmission"]
    assert sorted(info["readmitted"]) == sorted(dropped.tolist()) and info["kept"]
    assert info["f_after"] < info["f_before"]
    np.testing.assert_array_equal(np.asarray(r.inliers, bool), ~outlier)
    ref = mm.centralized_optimum(graph.select_edges(~outlier)).poses
    assert mm.trajectory_accuracy(r.poses, ref).ate < 1e-3
    with pytest.raises(ValueError, match="readmit=True re-admits loop closures a robust loss rejected"):
        mm.solve(graph, 3, readmit=True, iterations=0)
    with pytest.raises(ValueError, match="distributed=True: readmit=True"):
        mm.solve(graph, 3, loss="tls", distributed=True, readmit=True, iterations=0)
    with pytest.raises(ValueError, match="readmit=True may run a second solve: not with checkpoint"):
        mm.solve(graph, 3, loss="tls", readmit=True, iterations=0, checkpoint="never-written.npz")


def test_cli_readmit(tmp_path, capsys):
    """mmpgo solve --loss tls --readmit prints the search's line; without a robust loss and beside
    --distributed it is a one-line error naming the option."""
    from mmpgo_jax.cli import main

    graph, outlier, kept, dropped, X, _ = _case()
    path = tmp_path / "cube.g2o"
    mm.write_g2o(path, graph, X)
    rc = main(["solve", str(path), "-A", "3", "--loss", "tls", "--init", "gnc-chordal", "--readmit", "-n", "50",
               "--no-progress"])
    out = capsys.readouterr().out
    assert rc == 0, out
    line = next(line for line in out.splitlines() if line.startswith("readmit "))
    assert "re-admitted (f " in line and "Newton solves" in line
    for argv, named in ((["--readmit"], "--readmit re-admits loop closures a robust --loss rejected"),
                        (["--loss", "tls", "--readmit", "--distributed"], "--distributed: --readmit re-solves")):
        rc = main(["solve", str(path), "-A", "3", "-n", "5", "--no-progress", *argv])
        err = capsys.readouterr().err
        assert rc != 0 and named in err and len(err.strip().splitlines()) == 1, err


def test_readmission_warns_where_the_information_overstates_the_noise():
    """The kept edges' residuals 1/9 of what their information predicts (noise 3x below the claimed):
    a warning that the scale is loose; none where the information matches the noise."""
    import warnings

    from test_noise import _team

    for noise, claimed, warns in ((0.01, 0.03, True), (0.03, 0.03, False)):
        g, X = _team(noise, claimed)
        kept = np.ones(g.num_edges, bool)
        kept[np.flatnonzero(np.abs(np.asarray(g.i) - np.asarray(g.j)) != 1)[0]] = False
        loss = mm.RobustLoss("tls").with_defaults(g.dim)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            mm.readmit_loop_closures(g, kept, X, loss)
        loose = [w for w in caught if "scale is loose for these data" in str(w.message)]
        assert bool(loose) == warns, [str(w.message) for w in caught]
