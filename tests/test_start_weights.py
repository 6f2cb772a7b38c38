"""Robust weights given with the start (``solve(start_weights=...)``, and the distributed robust start's
own): held as the first stage, i.e. the weighted least squares of the start's classification, then
the kernel's own weights (mmpgo_jax/_mm/robust.py ``next_weights``)."""

from __future__ import annotations

import functools

import numpy as np
import pytest

import mmpgo_jax as mm
from mmpgo_jax._init.robust_distributed import distributed_robust_initialization
from mmpgo_jax._init.start import initialize_with_weights


@functools.cache
def _team_with_outliers():
    """4 robots x 40 poses, low noise, 10 correct inter-robot closures and 5 wrong ones."""
    ds = mm.robot_team_dataset(4, 40, intra_closures=2, inter_closures=10, seed=1, sigma_t=0.005, sigma_R=0.005)
    rop = ds.robot_of_pose
    c = mm.add_outlier_loop_closures(ds.graph, 5 / (ds.num_edges - ds.graph.num_poses + 4 + 5),
                                     reference=ds.ground_truth, seed=3, robot_of_pose=rop, inter_robot_only=True)
    st = distributed_robust_initialization(c.graph, rop)
    return ds, c, st


def _held_loss():
    """TLS whose held stage cannot end within the test's iterations."""
    return mm.RobustLoss("tls", gnc=mm.GNCConfig(stage_iterations=10_000, stage_tolerance=0.0), use_gnc=False)


def test_the_held_stage_is_the_weighted_least_squares_of_the_start_s_classification():
    """MM with the start's 0/1 weights held = MM on the edges it kept (same start, same iterates up to
    the inner solver's tolerance), and the weights stay the given ones meanwhile."""
    ds, c, st = _team_with_outliers()
    rop = ds.robot_of_pose
    X0 = mm.Poses(np.asarray(st.poses.R), np.asarray(st.poses.t))
    assert not st.accepted[c.outlier].any()  # the start sorted the closures right (test_robust_distributed_start)
    held = mm.solve(c.graph, rop, method="mm", loss=_held_loss(), start=X0, start_weights=st.weights, iterations=15,
                    stop_when_stalled=False)
    kept = mm.solve(c.graph.select_edges(st.weights > 0.5), rop, method="mm", start=X0, iterations=15,
                    stop_when_stalled=False)
    assert held.stats["start_weights_given"] and held.stats["start_weights_held"]
    np.testing.assert_array_equal(held.weights, st.weights)
    # the same iterates: positions agree far below the noise (0.005) and the move from the start
    moved = np.abs(np.asarray(kept.poses.t) - np.asarray(kept.start.t)).max()
    assert moved > 1e-3
    np.testing.assert_allclose(np.asarray(held.poses.t), np.asarray(kept.poses.t), atol=1e-6 * max(1.0, moved))
    np.testing.assert_allclose(np.asarray(held.poses.R), np.asarray(kept.poses.R), atol=1e-6)


def test_without_the_start_s_weights_tls_rejects_the_correct_inter_robot_closures_with_them_it_keeps_them():
    """From the distributed robust start (rigid maps), TLS weights rho'(s) at X^0 reject correct
    inter-robot closures; with the start's weights held first (the default of a robust run from
    start="distributed-robust"), the run keeps every correct closure, rejects every outlier and ends
    where the outlier-free solve ends."""
    ds, c, st = _team_with_outliers()
    rop = ds.robot_of_pose
    inter = st.inter
    default = mm.solve(c.graph, rop, loss="tls", start="distributed-robust", iterations=400)
    assert default.stats["start_weights_given"] and not default.stats["start_weights_held"]
    assert not default.inliers[c.outlier].any()
    assert default.inliers[inter & ~c.outlier].all()
    clean = mm.solve(ds.graph, rop, iterations=400)
    assert mm.trajectory_accuracy(default.poses, clean.poses).ate < 1e-3
    X0 = mm.Poses(np.asarray(st.poses.R), np.asarray(st.poses.t))
    bare = mm.solve(c.graph, rop, loss="tls", start=X0, iterations=0)  # weights rho'(s) of X^0
    assert (bare.weights[inter & ~c.outlier] == 0).sum() > (default.weights[inter & ~c.outlier] == 0).sum()


def test_distributed_robust_loss_defaults_to_the_distributed_robust_start_and_its_weights():
    ds, c, st = _team_with_outliers()
    rop = ds.robot_of_pose
    r = mm.solve(c.graph, rop, loss="tls", distributed=True, iterations=0)  # the start with its team check
    checked = distributed_robust_initialization(c.graph, rop, team_check=True)
    np.testing.assert_allclose(np.asarray(r.start.t), checked.poses.t, atol=1e-9)
    np.testing.assert_array_equal(r.start_weights, checked.weights)
    assert r.stats["start_weights_given"] and not bool(r.loss.use_gnc)
    unchecked = mm.solve(c.graph, rop, loss="tls", distributed=True, start="distributed-robust", iterations=0)
    np.testing.assert_allclose(np.asarray(unchecked.start.t), st.poses.t, atol=1e-9)
    np.testing.assert_array_equal(unchecked.start_weights, st.weights)
    plain = mm.solve(c.graph, rop, distributed=True, iterations=0)  # least squares: the distributed chordal start
    ref = mm.initialize(c.graph, "distributed-chordal", robots=rop)
    np.testing.assert_allclose(np.asarray(plain.start.t), np.asarray(ref.t), atol=1e-12)
    assert "start_weights_given" not in plain.stats


def test_initialize_with_weights_returns_the_classification_of_a_classifying_start_only():
    ds, c, st = _team_with_outliers()
    X, w = initialize_with_weights(c.graph, "distributed-robust", robots=ds.robot_of_pose)
    np.testing.assert_array_equal(w, st.weights)
    for host in (False, True):  # HostPoses is a tuple: it must come back whole, not unpacked
        poses, none = initialize_with_weights(c.graph, "chordal", host=host)
        assert none is None and np.shape(poses.R) == (c.graph.num_poses, 2, 2)
        np.testing.assert_allclose(np.asarray(mm.initialize(c.graph, "chordal", host=host).t), np.asarray(poses.t))


def test_bad_start_weights_are_refused():
    ds, c, _ = _team_with_outliers()
    m, rop = c.graph.num_edges, ds.robot_of_pose
    for loss, weights, match in [("tls", np.ones(m + 1), "one value per edge"), ("tls", np.full(m, 1.5), r"\[0, 1\]"),
                                 ("tls", np.full(m, np.nan), r"\[0, 1\]"), ("l2", np.ones(m), "robust loss")]:
        with pytest.raises(ValueError, match=match):
            mm.solve(c.graph, rop, loss=loss, start_weights=weights, iterations=0)


def test_sweep_holds_the_start_s_weights_as_solve_does():
    ds, c, _ = _team_with_outliers()
    rop = ds.robot_of_pose
    sw = mm.sweep({"team": c.graph}, [4], ("amm",), 20, init="distributed-robust", loss="tls")
    (res,) = sw.results.values()
    one = mm.solve(c.graph, 4, loss="tls", start="distributed-robust", iterations=20, stop_when_stalled=False)
    assert res.stats["start_weights_given"]
    np.testing.assert_allclose(res.history.f, one.history.f, rtol=1e-9)
    assert (rop == np.repeat(np.arange(4), 40)).all()  # the team's robots are sweep's contiguous blocks
