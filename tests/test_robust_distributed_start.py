"""The distributed robust start (mmpgo_jax/_init/robust_distributed.py): each robot's own GNC, the
frames of the robots from their inter-robot closures, what it accepts and what it reports."""

from __future__ import annotations

import functools

import numpy as np
import pytest

import mmpgo_jax as mm
from mmpgo_jax._core.gauge import FixedPoses, express_in_frame
from mmpgo_jax._core.pose_graph import HostPoses, PoseGraph, host_graph
from mmpgo_jax._init.robust_distributed import (
    _grounded_resistances,
    chain_variances,
    closure_variances,
    distributed_robust_initialization,
    pair_average,
    variance_factor,
)
from mmpgo_jax._init.robust_start import gnc_chordal_initialization
from mmpgo_jax._init.start import initialize


@functools.cache
def _team(robots=4, poses=40, intra=2, inter=10, noise=0.0, seed=0):
    return mm.robot_team_dataset(robots, poses, intra_closures=intra, inter_closures=inter, seed=seed,
                                 sigma_t=noise, sigma_R=noise)


def _in_pose0_frame(poses) -> HostPoses:
    """Poses moved rigidly so that pose 0 is the identity (the starts' gauge)."""
    p = HostPoses(np.asarray(poses.R, np.float64), np.asarray(poses.t, np.float64))
    return express_in_frame(p, FixedPoses.identity(0, p.R.shape[-1]))


def _ate(poses, reference) -> float:
    return mm.trajectory_accuracy(mm.Poses(np.asarray(poses.R), np.asarray(poses.t)), reference).ate


def _with_edges(graph, i, j, R, t):
    """``graph`` with edges (i, j, R, t) appended (weights of its first loop closure)."""
    g = host_graph(graph)
    k = int(np.flatnonzero(np.abs(g.i - g.j) > 1)[0])
    m = len(i)
    return PoseGraph(np.concatenate([g.i, i]), np.concatenate([g.j, j]), np.concatenate([g.R, R]),
                     np.concatenate([g.t, t]), np.concatenate([g.kappa, np.full(m, g.kappa[k])]),
                     np.concatenate([g.tau, np.full(m, g.tau[k])]), num_poses=g.num_poses)


@pytest.mark.parametrize("frames", ["graph", "tree"])
def test_noise_free_team_equals_centralized_start_and_truth(frames):
    ds = _team()
    rop = ds.robot_of_pose
    st = distributed_robust_initialization(ds.graph, rop, frames=frames)
    central = gnc_chordal_initialization(ds.graph)
    truth = _in_pose0_frame(ds.ground_truth)
    for ref in (central.poses, truth):
        np.testing.assert_allclose(st.poses.R, np.asarray(ref.R), atol=1e-9)
        np.testing.assert_allclose(st.poses.t, np.asarray(ref.t), atol=1e-9)
    # every map placed, every closure accepted; the frames are the true poses of the maps' first poses
    assert st.placed.all() and st.unplaced_robots.size == 0
    assert st.accepted.sum() == ds.inter_robot.sum() and np.all(st.weights == 1.0)
    firsts = np.searchsorted(rop, np.arange(rop.max() + 1))
    np.testing.assert_array_equal(st.map_of_pose[firsts], np.arange(len(firsts)))
    np.testing.assert_allclose(st.frames.R, truth.R[firsts], atol=1e-9)
    np.testing.assert_allclose(st.frames.t, truth.t[firsts], atol=1e-9)
    # through initialize, and with a fixed pose: the same poses in the fixed pose's frame
    X = initialize(ds.graph, "distributed-robust", robots=rop, host=True, frames=frames)
    np.testing.assert_allclose(X.t, st.poses.t, atol=1e-12)
    fixed = FixedPoses.from_poses([7], ds.ground_truth)
    Xf = initialize(ds.graph, "distributed-robust", robots=rop, fixed=fixed, host=True)
    np.testing.assert_allclose(Xf.t, np.asarray(ds.ground_truth.t), atol=1e-9)


def test_planted_wrong_inter_robot_closures_are_rejected():
    """Low noise, 4 robots, 10 correct inter-robot closures and 5 wrong ones (random poses of
    different robots, random rotations, translations the size of the map): the frame graph's GNC
    rejects every wrong one, keeps every correct one, and the start is as accurate as the
    outlier-free start."""
    ds = _team(noise=0.005, seed=1)
    rop = ds.robot_of_pose
    c = mm.add_outlier_loop_closures(ds.graph, 5 / (ds.num_edges - ds.graph.num_poses + 4 + 5),
                                     reference=ds.ground_truth, seed=3, robot_of_pose=rop, inter_robot_only=True)
    assert c.num_outliers == 5
    st = distributed_robust_initialization(c.graph, rop)
    inter = st.inter
    assert not (st.accepted & c.outlier).any()
    assert st.accepted[inter & ~c.outlier].all()
    clean = distributed_robust_initialization(ds.graph, rop)
    assert _ate(st.poses, ds.ground_truth) < 1.5 * _ate(clean.poses, ds.ground_truth) + 1e-3
    assert _ate(st.poses, ds.ground_truth) < 0.05
    # the least-squares chordal start is bent by them
    assert _ate(initialize(c.graph, "chordal"), ds.ground_truth) > 5 * _ate(st.poses, ds.ground_truth)


def test_a_pair_s_only_wrong_closure_is_rejected_by_a_cycle_of_robots():
    """Robots 0-1 share their only closure, and it is wrong; the other pairs close cycles through both
    robots: the frame graph rejects it (pair averaging alone cannot: one closure is its own mean)."""
    ds = _team(robots=3, poses=40, intra=2, inter=8, seed=0)
    rop = ds.robot_of_pose
    g = host_graph(ds.graph)
    inter = rop[g.i] != rop[g.j]
    pair01 = inter & (np.minimum(rop[g.i], rop[g.j]) == 0) & (np.maximum(rop[g.i], rop[g.j]) == 1)
    graph = g.select_edges(~pair01)
    quarter_turn = np.array([[[0.0, -1.0], [1.0, 0.0]]])
    graph = _with_edges(graph, np.array([5]), np.array([45]), quarter_turn, np.array([[3.0, -4.0]]))
    # noise-free data carries weights 1 (information of 0.7 rad per step): the closures' own
    # information is the right test here, the odometry's drift would accept anything
    st = distributed_robust_initialization(graph, rop, map_sigma=(0.0, 0.0))
    assert not st.weights[-1]  # the wrong closure
    assert st.accepted.sum() == (inter & ~pair01).sum()
    assert st.placed.all()
    np.testing.assert_allclose(st.poses.t, _in_pose0_frame(ds.ground_truth).t, atol=1e-9)
    # its pair average accepted it: one hypothesis, nothing to compare with
    p = st.pairs
    row = np.flatnonzero((p.pairs[:, 0] == 0) & (p.pairs[:, 1] == 1))[0]
    assert p.closures[row] == 1 and p.inliers[row] == 1


def test_robot_without_usable_closures_is_reported():
    ds = _team(robots=4, poses=40, intra=2, inter=10, seed=0)
    rop = ds.robot_of_pose
    g = host_graph(ds.graph)
    touches3 = (rop[g.i] == 3) | (rop[g.j] == 3)
    inter = rop[g.i] != rop[g.j]
    graph = g.select_edges(~(touches3 & inter))
    st = distributed_robust_initialization(graph, rop)
    np.testing.assert_array_equal(st.unplaced_robots, [3])
    assert st.placed.tolist() == [True, True, True, False]
    # robot 3 stays in its local frame (its first pose at the identity), its map unchanged
    first3 = int(np.searchsorted(rop, 3))
    np.testing.assert_allclose(st.poses.R[first3], np.eye(2), atol=1e-12)
    np.testing.assert_allclose(st.poses.t[rop == 3], st.local.t[rop == 3], atol=1e-12)
    with pytest.warns(UserWarning, match=r"robots \[3\] share no accepted"):
        initialize(graph, "distributed-robust", robots=rop)
    # min_inliers: pairs with fewer accepted closures are not used; robots left without one are reported
    st2 = distributed_robust_initialization(ds.graph, rop, min_inliers=100)
    assert not st2.placed[1:].any() and st2.unplaced_robots.tolist() == [1, 2, 3]
    assert st2.accepted.sum() == 0


def test_excluded_edges_are_left_out_of_every_step():
    """``excluded``: the start of the graph without those edges (an accepted wrong closure, a correct
    one and an intra-robot closure), its per-edge arrays in the whole graph's order with weight 0 there."""
    ds = _team(noise=0.005, seed=1)
    rop = ds.robot_of_pose
    c = mm.add_outlier_loop_closures(ds.graph, 5 / (ds.num_edges - ds.graph.num_poses + 4 + 5),
                                     reference=ds.ground_truth, seed=3, robot_of_pose=rop, inter_robot_only=True)
    g = host_graph(c.graph)
    inter = rop[g.i] != rop[g.j]
    intra_closure = ~inter & (np.abs(g.i - g.j) > 1)
    excluded = np.zeros(g.num_edges, bool)
    excluded[[np.flatnonzero(c.outlier)[0], np.flatnonzero(inter & ~c.outlier)[2], np.flatnonzero(intra_closure)[0]]] = True
    st = distributed_robust_initialization(c.graph, rop, excluded=excluded)
    ref = distributed_robust_initialization(g.select_edges(~excluded), rop)
    np.testing.assert_array_equal(st.poses.t, ref.poses.t)
    np.testing.assert_array_equal(st.weights[~excluded], ref.weights)
    assert not st.weights[excluded].any() and not st.accepted[excluded].any()
    np.testing.assert_array_equal(st.inter, inter)
    with pytest.raises(ValueError, match="excluded: need one bool per edge"):
        distributed_robust_initialization(c.graph, rop, excluded=excluded[:-1])


def test_the_local_maps_are_solved_once_for_starts_that_differ_in_inter_robot_closures(monkeypatch):
    """A start made again without an inter-robot closure (a revisit) takes the robots' own maps from
    the cache (no second local GNC), equal to a fresh solve; excluding an intra-robot closure changes
    the maps (solved again)."""
    import mmpgo_jax._init.robust_distributed as rd

    ds = _team(noise=0.005, seed=1)
    rop = ds.robot_of_pose
    c = mm.add_outlier_loop_closures(ds.graph, 5 / (ds.num_edges - ds.graph.num_poses + 4 + 5),
                                     reference=ds.ground_truth, seed=3, robot_of_pose=rop, inter_robot_only=True)
    plain = distributed_robust_initialization(c.graph, rop)
    calls = []
    monkeypatch.setattr(rd, "gnc_chordal_initialization",
                        lambda *a, **k: calls.append(k.get("scale")) or gnc_chordal_initialization(*a, **k))
    without = np.zeros(c.graph.num_edges, bool)
    without[np.flatnonzero(c.outlier)[0]] = True
    st = distributed_robust_initialization(c.graph, rop, excluded=without)
    np.testing.assert_array_equal(st.local.t, plain.local.t)
    local_solves = functools.partial(calls.count, None)  # the local maps' call has the default scale; the frames' not
    assert calls and local_solves() == 0  # the frame graph's solves only: the local maps came from the cache
    rd._LOCAL_MAPS.clear()
    fresh = distributed_robust_initialization(c.graph, rop, excluded=without)
    np.testing.assert_array_equal(fresh.local.t, st.local.t)
    np.testing.assert_array_equal(fresh.weights, st.weights)
    assert local_solves() == 1  # the local maps solved again
    g = host_graph(c.graph)
    excluded = np.zeros(g.num_edges, bool)
    excluded[np.flatnonzero((rop[g.i] == rop[g.j]) & (np.abs(g.i - g.j) > 1))[0]] = True
    distributed_robust_initialization(c.graph, rop, excluded=excluded)
    assert local_solves() == 2  # another robot graph: its maps solved


def test_sampled_frames_are_refitted_to_their_inliers(monkeypatch):
    """The consensus search refits each sampled tree's frames to the hypotheses within c of them
    (LO-RANSAC's local optimisation). A 10 x 500-pose team of long chains, low noise, 13 wrong
    inter-robot closures (30 % of them; the team of benchmarks/robust_teams.md, seed 0): with the refit
    the start sorts every inter-robot closure right; without it, it accepted an outlier and rejected
    four correct closures (the all-correct trees' frames carry the drift of their few closures)."""
    import mmpgo_jax._init.robust_distributed as rd

    ds = mm.robot_team_dataset(10, 500, intra_closures=5, inter_closures=30, dim=2, seed=0, sigma_R=0.005 * np.pi)
    rop = ds.robot_of_pose
    n_loops = int(ds.inter_robot.sum()) + int((ds.edge_kind == 1).sum())
    c = mm.add_outlier_loop_closures(ds.graph, 13 / (n_loops + 13), reference=ds.ground_truth, seed=0,
                                     robot_of_pose=rop, inter_robot_only=True)
    assert c.num_outliers == 13
    st = distributed_robust_initialization(c.graph, rop)
    assert np.array_equal(st.accepted[st.inter], ~c.outlier[st.inter])
    monkeypatch.setattr(rd, "MAX_REFITS", 0)
    without = distributed_robust_initialization(c.graph, rop)
    assert (without.accepted & c.outlier).sum() == 1
    assert (st.inter & ~without.accepted & ~c.outlier).sum() == 4


def _local_closures(seed=2):
    """A 3-robot team with wrong loop closures, intra-robot ones included: (graph, robot of pose,
    outlier flags, the intra-robot edges)."""
    ds = _team(robots=3, poses=60, intra=4, inter=6, noise=0.005, seed=seed)
    rop = ds.robot_of_pose
    c = mm.add_outlier_loop_closures(ds.graph, 0.3, reference=ds.ground_truth, seed=0)
    g = host_graph(c.graph)
    return c.graph, rop, c.outlier, rop[g.i] == rop[g.j]


def test_local_stage_rejects_wrong_intra_robot_closures():
    graph, rop, outlier, own = _local_closures()
    g = host_graph(graph)
    closure = own & (np.abs(g.i - g.j) > 1)
    assert (closure & outlier).sum() >= 3
    st = distributed_robust_initialization(graph, rop)
    rejected = st.weights < 0.5
    assert np.array_equal(rejected & own, closure & outlier)


@pytest.mark.slow
def test_shared_gnc_schedule_against_one_call_per_robot():
    """The local stage solves all robots in one GNC-chordal call (one mu schedule for all): it
    classifies the intra-robot closures at least as well as one call per robot. (Here it does better:
    robot 0 alone starts GNC at its own, larger mu_0 and rejects its 4 correct closures; under the
    shared, smaller mu_0 it keeps them. One call per robot also compiles per robot's shapes, 40 s
    against 2 s for the shared call on this 180-pose team.)"""
    graph, rop, outlier, own = _local_closures()
    g = host_graph(graph)
    local = g.select_edges(own)
    closure = np.abs(local.i - local.j) > 1
    wrong = outlier[own]
    st = distributed_robust_initialization(graph, rop)
    shared = st.weights[own] < 0.5
    alone = np.zeros(local.num_edges, bool)
    for r in range(3):  # a loop over robots in the test only: the reference, one call per robot
        poses = np.flatnonzero(rop == r)
        sel = rop[local.i] == r
        sub = PoseGraph(local.i[sel] - poses[0], local.j[sel] - poses[0], local.R[sel], local.t[sel],
                        local.kappa[sel], local.tau[sel], num_poses=len(poses))
        alone[sel] = gnc_chordal_initialization(sub).weights < 0.5
    assert (shared & wrong & closure).sum() >= (alone & wrong & closure).sum()
    assert (shared & ~wrong).sum() <= (alone & ~wrong).sum()


def test_pair_average_rejects_the_odd_hypothesis_per_pair():
    rng = np.random.default_rng(0)

    def rot(a):
        return np.stack([np.stack([np.cos(a), -np.sin(a)], -1), np.stack([np.sin(a), np.cos(a)], -1)], -2)

    # pair 0: 4 hypotheses near 0.3 rad / (1, 2) and one at 2.0 rad; pair 1: 3 near -1 rad / (5, 0)
    ang = np.array([0.3, 0.301, 0.299, 0.3, 2.0, -1.0, -1.001, -0.999])
    t = np.array([[1, 2], [1, 2.01], [1.01, 2], [1, 2], [7, 7], [5, 0], [5, 0.01], [5.01, 0]], float)
    pair = np.array([0, 0, 0, 0, 0, 1, 1, 1])
    kappa = np.full(8, 1e4)
    tau = np.full(8, 1e4)
    order = rng.permutation(8)  # the segment operations do not need hypotheses grouped by pair
    R, tm, inlier = pair_average(pair[order], rot(ang)[order], t[order], kappa, tau, 2)
    np.testing.assert_array_equal(inlier, (np.arange(8) != 4)[order])
    np.testing.assert_allclose(np.arctan2(R[:, 1, 0], R[:, 0, 0]), [0.3, -1.0], atol=1e-3)
    np.testing.assert_allclose(tm, [[1.0025, 2.0025], [5.0033, 0.0033]], atol=1e-3)


def test_chain_variances_grow_along_the_odometry():
    ds = _team(robots=2, poses=30, intra=1, inter=2, noise=0.01, seed=0)
    g = host_graph(ds.graph)
    rop = ds.robot_of_pose
    st = distributed_robust_initialization(ds.graph, rop)
    vR, vt = chain_variances(g, st.local.t, st.map_of_pose)
    starts = np.searchsorted(rop, [0, 1])
    assert np.all(vR[starts] == 0) and np.all(vt[starts] == 0)
    # var_R: one 1 / (2 kappa) per step; var_t: the steps' 1 / tau plus the lever arms (explicit sum)
    np.testing.assert_allclose(vR[:30], np.arange(30) * 0.5 / g.kappa[0])
    p = 20
    lever = sum(0.5 / g.kappa[0] * np.sum((st.local.t[p] - st.local.t[k]) ** 2) for k in range(p))
    np.testing.assert_allclose(vt[p], p / g.tau[0] + lever, rtol=1e-10)


def test_grounded_resistances_against_a_dense_pseudo_inverse():
    """The Johnson-Lindenstrauss estimate of the effective resistance to each component's anchor
    against the exact one, diag((L restricted to the free nodes)^-1), on a small graph with cycles:
    within its sqrt(2 / probes) accuracy (4000 probes: 2.2 % per node; 8 % = 3.5 of those asked of 28 nodes)."""
    rng = np.random.default_rng(0)
    n = 30
    i = np.concatenate([np.arange(n - 1), rng.integers(0, 15, 8), rng.integers(15, n, 8)])
    j = np.concatenate([np.arange(1, n), rng.integers(0, 15, 8), rng.integers(15, n, 8)])
    keep = (i != j) & ~((i < 15) & (j >= 15) | (i >= 15) & (j < 15)) | (np.abs(i - j) == 1) & (np.minimum(i, j) != 14)
    i, j = i[keep], j[keep]
    cond = rng.uniform(0.5, 2.0, len(i))
    anchors = np.array([0, 15])  # two components: 0..14 and 15..29
    L = np.zeros((n, n))
    np.add.at(L, (i, i), cond)
    np.add.at(L, (j, j), cond)
    np.add.at(L, (i, j), -cond)
    np.add.at(L, (j, i), -cond)
    free = np.setdiff1d(np.arange(n), anchors)
    exact = np.zeros(n)
    exact[free] = np.diag(np.linalg.inv(L[np.ix_(free, free)]))
    est = _grounded_resistances(n, i, j, cond, anchors, 4000, np.random.default_rng(1))
    assert np.all(est[anchors] == 0)
    np.testing.assert_allclose(est[free], exact[free], rtol=0.08)


def test_closure_variances_are_the_chain_s_without_closures_and_smaller_with_them():
    ds = _team(robots=2, poses=30, intra=1, inter=2, noise=0.01, seed=0)
    g = host_graph(ds.graph)
    st = distributed_robust_initialization(ds.graph, ds.robot_of_pose)
    odometry = np.abs(g.i - g.j) == 1
    chain_R, chain_t = chain_variances(g, st.local.t, st.map_of_pose)
    vR, vt = closure_variances(g, st.local.t, st.map_of_pose, odometry, probes=4000)
    np.testing.assert_allclose(vR, chain_R, rtol=0.1, atol=1e-12)
    np.testing.assert_allclose(vt, chain_t, rtol=0.1, atol=1e-12)
    inside = st.map_of_pose[g.i] == st.map_of_pose[g.j]
    wR, wt = closure_variances(g, st.local.t, st.map_of_pose, inside, probes=4000)
    assert np.all(wR <= chain_R * 1.1 + 1e-12) and wR.sum() < 0.9 * chain_R.sum()  # the closures tie the maps
    assert wt.sum() < chain_t.sum()


def test_variance_factor_reads_the_noise_of_the_data():
    """1 where the information matrices are the noise's (its confidence interval holds 1); where the
    noise is 3x smaller than they say (the team's information kept, its noise divided by 3), the
    interval's end nearer to 1, a little above the estimate of about 1 / 9."""
    for noise, expected in [(0.03, 1.0), (0.01, 1.25 / 9.0)]:
        ds = mm.robot_team_dataset(2, 400, intra_closures=60, inter_closures=2, seed=0, sigma_t=noise, sigma_R=noise)
        g = host_graph(ds.graph)
        info = mm.robot_team_dataset(2, 400, intra_closures=60, inter_closures=2, seed=0, sigma_t=0.03,
                                     sigma_R=0.03).graph
        g = PoseGraph(g.i, g.j, g.R, g.t, np.asarray(info.kappa), np.asarray(info.tau), num_poses=g.num_poses)
        st = distributed_robust_initialization(g, ds.robot_of_pose)
        local = g.select_edges(~st.inter)
        assert variance_factor(local, st.local, 2) == pytest.approx(expected, rel=0.2)


def test_options_are_checked():
    ds = _team()
    with pytest.raises(ValueError, match="frames"):
        distributed_robust_initialization(ds.graph, ds.robot_of_pose, frames="star")
    with pytest.raises(ValueError, match="min_inliers"):
        distributed_robust_initialization(ds.graph, ds.robot_of_pose, min_inliers=0)
    with pytest.raises(ValueError, match="map_sigma"):
        distributed_robust_initialization(ds.graph, ds.robot_of_pose, map_sigma=(-1.0, 0.0))
    with pytest.raises(ValueError, match="robots"):
        distributed_robust_initialization(ds.graph, np.zeros(3, int))
    with pytest.raises(ValueError, match="only apply to"):
        initialize(ds.graph, "chordal", frames="graph")


def test_solve_takes_the_start_by_name_with_its_partition():
    """``solve(start="distributed-robust", distributed=True)``: the start gets the run's Partition as
    ``robots``, and ``distributed=True`` refuses only the centralized starts."""
    ds = _team(robots=3, poses=40, intra=2, inter=6, noise=0.005, seed=0)
    rop = ds.robot_of_pose
    X0 = initialize(ds.graph, "distributed-robust", robots=rop, host=True)
    res = mm.solve(ds.graph, rop, loss="tls", start="distributed-robust", iterations=0, distributed=True)
    np.testing.assert_allclose(np.asarray(res.start.t), X0.t, atol=1e-9)


@pytest.mark.slow  # a whole CLI solve (compilation); the start by name is checked in the default run above
def test_cli_init_distributed_robust(tmp_path, capsys):
    """``mmpgo solve FILE --init distributed-robust --loss tls``: the start is a choice of the command
    and its result is the library's (the team's robots are contiguous blocks of 40 poses)."""
    from mmpgo_jax.cli import main

    ds = _team(robots=3, poses=40, intra=2, inter=6, noise=0.005, seed=0)
    path = tmp_path / "team.g2o"
    mm.write_g2o(path, ds.graph, ds.ground_truth)
    out = tmp_path / "out.g2o"
    assert main(["solve", str(path), "--robots", "3", "--init", "distributed-robust", "--loss", "tls", "-n", "2",
                 "--no-progress", "--out", str(out)]) == 0
    assert "AMM-PGO" in capsys.readouterr().out
    assert out.is_file()


def _exact_chain(poses: int, dim: int = 2) -> PoseGraph:
    """Poses one unit apart along x, odometry only, exact measurements (f = 0 at the truth)."""
    m = poses - 1
    return PoseGraph(np.arange(m), np.arange(1, m + 1), np.tile(np.eye(dim), (m, 1, 1)),
                     np.tile(np.eye(dim)[0], (m, 1)), np.ones(m), np.ones(m), num_poses=poses)


@pytest.mark.parametrize("poses, robots", [(2, 1), (3, 3)], ids=["one-robot", "one-pose-robots"])
def test_robust_starts_without_edges_to_weigh(poses, robots):
    """Graphs where a GNC stage has no edge: a team of one robot (no inter-robot closure, an empty
    frame graph) and robots of one pose (maps without own edges). Both robust starts and the fully
    distributed robust solve return the exact answer (f = 0) instead of failing inside NumPy."""
    graph = _exact_chain(poses)
    assert gnc_chordal_initialization(graph.select_edges(np.zeros(graph.num_edges, bool))).stages == 0
    start = initialize(graph, "distributed-robust", robots=robots)
    assert float(mm.cost(graph, start)) < 1e-20
    result = mm.solve(graph, robots, loss="tls", distributed=True, iterations=5)
    assert float(mm.cost(graph, result.poses)) < 1e-20
    np.testing.assert_array_equal(result.weights, 1.0)  # nothing rejected
