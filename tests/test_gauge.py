"""Fixed poses (g2o FIX) and the frame of results (mmpgo_jax._core.gauge).

Independent references: the relaxed chordal problems' optimality conditions (autodiff gradient of
the relaxed costs on the free blocks), the cost's invariance under rigid motions, and the
unconstrained optimum (one fixed pose only fixes the gauge, so f* is unchanged).
"""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import mmpgo_jax as mm
from mmpgo_jax._core.geometry import random_rotations
from mmpgo_jax._init.chordal import (
    chordal_relaxed_rotations,
    translations_given_rotations,
)


def _graph(d: int, n: int = 14, loops: int = 6, seed: int = 0) -> mm.PoseGraph:
    rng = np.random.default_rng(seed)
    R = random_rotations(rng, (n,), d)
    t = rng.normal(size=(n, d)) * 2
    pairs = [(k, k + 1) for k in range(n - 1)]
    while len(pairs) < n - 1 + loops:
        i, j = sorted(rng.choice(n, 2, replace=False))
        if j - i > 1 and (i, j) not in pairs:
            pairs.append((int(i), int(j)))
    i, j = np.array(pairs).T
    Rm = np.einsum("mba,mbc->mac", R[i], R[j])
    if d == 3:
        Rm = Rm @ Rotation.from_rotvec(0.05 * rng.normal(size=(len(i), 3))).as_matrix()
    tm = np.einsum("mba,mb->ma", R[i], t[j] - t[i]) + 0.05 * rng.normal(size=(len(i), d))
    return mm.PoseGraph.from_arrays(i, j, Rm, tm, np.full(len(i), 5.0), np.full(len(i), 20.0), n)


def _fixed(graph, index, seed=3) -> mm.FixedPoses:
    d = graph.dim
    rng = np.random.default_rng(seed)
    R = random_rotations(rng, (len(index),), d)
    t = rng.normal(size=(len(index), d))
    return mm.FixedPoses(np.asarray(index), R, t)


def _assert_fixed(poses, fixed, tol=1e-12):
    np.testing.assert_allclose(np.asarray(poses.R)[fixed.index], fixed.R, atol=tol, rtol=0)
    np.testing.assert_allclose(np.asarray(poses.t)[fixed.index], fixed.t, atol=tol, rtol=0)


@pytest.mark.parametrize("d", [2, 3])
def test_chordal_with_fixed_poses_is_the_constrained_minimiser(d):
    g = _graph(d)
    fixed = _fixed(g, [4, 9])
    V = chordal_relaxed_rotations(g, fixed)
    np.testing.assert_allclose(V[fixed.index], fixed.R, atol=1e-12)
    free = np.setdiff1d(np.arange(g.num_poses), fixed.index)

    def relaxed(Rf):
        Rall = jnp.asarray(V).at[free].set(Rf)
        res = Rall[g.i] @ g.R - Rall[g.j]
        return jnp.sum(g.kappa[:, None, None] * res**2)

    grad = jax.grad(relaxed)(jnp.asarray(V[free]))
    assert float(jnp.max(jnp.abs(grad))) < 1e-9
    R = np.asarray(mm.chordal_initialization(g, fixed).R)
    t = translations_given_rotations(g, R, fixed)
    np.testing.assert_allclose(t[fixed.index], fixed.t, atol=1e-12)

    def trans(tf):
        tall = jnp.asarray(t).at[free].set(tf)
        res = jnp.einsum("mab,mb->ma", jnp.asarray(R)[g.i], g.t) + tall[g.i] - tall[g.j]
        return jnp.sum(g.tau[:, None] * res**2)

    assert float(jnp.max(jnp.abs(jax.grad(trans)(jnp.asarray(t[free]))))) < 1e-9


@pytest.mark.parametrize("init", ["chordal", "odometry", "distributed-chordal"])
def test_every_initialization_holds_fixed_poses(init):
    g = _graph(3)
    fixed = _fixed(g, [0, 7])
    X0 = mm.initialize(g, init, robots=3, fixed=fixed)
    _assert_fixed(X0, fixed, tol=1e-12)
    if init == "distributed-chordal":  # the robots' sparse factors hold them too, at the same start
        Xs = mm.initialize(g, init, robots=3, fixed=fixed, factorization="sparse")
        _assert_fixed(Xs, fixed, tol=1e-12)
        np.testing.assert_allclose(np.asarray(Xs.t), np.asarray(X0.t), atol=1e-6 * float(jnp.abs(X0.t).max()))


def test_initialize_from_poses_sets_fixed_values():
    g = _graph(2)
    fixed = _fixed(g, [5])
    X0 = mm.initialize(g, mm.odometry_initialization(g), fixed=fixed)
    _assert_fixed(X0, fixed)


@pytest.mark.parametrize("method", ["mm", "amm"])
def test_fixed_poses_do_not_move(method):
    g = _graph(3)
    fixed = _fixed(g, [2, 11])
    res = mm.solve(g, 3, method=method, iterations=60, fixed=fixed, chunk_size=30)
    _assert_fixed(res.poses, fixed, tol=1e-12)
    f = res.history.f
    assert f[-1] < f[0]
    if method == "mm":  # Proposition 2 holds on the constrained problem too
        assert np.all(np.diff(f) <= 1e-9 * f[0])
    # the reported f is the cost of the returned poses
    assert abs(float(mm.cost(g, res.poses)) - res.f) < 1e-9 * res.f


def test_one_fixed_pose_only_fixes_the_gauge():
    g = _graph(2, seed=5)
    free = mm.centralized_optimum(g, grad_tol=1e-9)
    fixed = mm.FixedPoses.from_poses([6], free.poses)
    pinned = mm.centralized_optimum(g, grad_tol=1e-9, fixed=fixed)
    _assert_fixed(pinned.poses, fixed)
    assert abs(pinned.f - free.f) < 1e-9 * free.f
    # the same poses: the fixed pose already sits at its optimal value
    np.testing.assert_allclose(np.asarray(pinned.poses.t), np.asarray(free.poses.t), atol=1e-6)


def test_two_fixed_poses_constrain_the_problem():
    g = _graph(2, seed=6)
    free = mm.centralized_optimum(g, grad_tol=1e-9)
    at_opt = mm.FixedPoses.from_poses([0, 13], free.poses)
    # pose 0 moved away from its optimal place relative to pose 13: the constrained optimum is worse
    fixed = mm.FixedPoses(at_opt.index, at_opt.R, at_opt.t + np.array([[0.3, -0.2], [0.0, 0.0]]))
    pinned = mm.centralized_optimum(g, grad_tol=1e-8, fixed=fixed)
    _assert_fixed(pinned.poses, fixed)
    assert pinned.stop_reason == "grad_tol"  # stationary on the free poses
    assert pinned.f > free.f * (1 + 1e-6)


def test_sweep_and_sharded_solve_hold_fixed_poses():
    from mmpgo_jax.sharding import solve_sharded

    g = _graph(2, seed=2)
    fixed = _fixed(g, [3])
    res = mm.sweep({"g": g}, robots=[2, 3], methods="mm", iterations=20, fixed={"g": fixed})
    for a in (2, 3):
        _assert_fixed(res.poses[("g", a, "mm")], fixed)
        one = mm.solve(g, a, method="mm", iterations=20, fixed=fixed)
        # padded to a common shape: equal within the default inner solver's rounding sensitivity
        np.testing.assert_allclose(res.history("g", a, "mm"), one.history.f, rtol=1e-6)
    sh = solve_sharded(g, 3, devices=1, method="amm", iterations=20, fixed=fixed)
    _assert_fixed(sh.poses, fixed)
    one = mm.solve(g, 3, method="amm", iterations=20, fixed=fixed)
    np.testing.assert_allclose(sh.history.f, one.history.f, rtol=1e-10)


def test_result_frame():
    g = _graph(3, seed=4)
    raw = mm.solve(g, 3, iterations=30, frame="raw")
    default = mm.solve(g, 3, iterations=30)
    target = _fixed(g, [0], seed=11)
    moved = mm.solve(g, 3, iterations=30, frame=target)
    # same run, other frames: same f, poses related by one rigid motion
    assert raw.f == default.f == moved.f
    np.testing.assert_allclose(np.asarray(default.poses.R)[0], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(np.asarray(default.poses.t)[0], 0.0, atol=1e-12)
    _assert_fixed(moved.poses, target)
    assert not np.allclose(np.asarray(raw.poses.t)[0], 0.0)
    for p in (default.poses, moved.poses):
        assert abs(float(mm.cost(g, p)) - float(mm.cost(g, raw.poses))) < 1e-9 * raw.f
    again = mm.express_in_frame(raw.poses, target)
    np.testing.assert_allclose(np.asarray(again.t), np.asarray(moved.poses.t), atol=1e-12)


def test_frame_already_met_returns_the_poses_and_the_origin_is_shared():
    """Poses whose reference pose already has the frame's value are returned as they are (the
    rigid motion would be the identity exactly), on the device or the host; FixedPoses.identity
    of pose 0 alone is one shared instance whose arrays cannot be changed."""
    from mmpgo_jax._core.pose_graph import HostPoses

    rng = np.random.default_rng(3)
    R = random_rotations(rng, (5,), 3)
    R[0] = np.eye(3)
    t = rng.normal(size=(5, 3))
    t[0] = 0.0
    origin = mm.FixedPoses.identity([0], 3)
    assert mm.FixedPoses.identity(np.array([0]), 3) is origin and not origin.R.flags.writeable
    with pytest.raises(ValueError):
        origin.t[0, 0] = 1.0
    for poses in (HostPoses(R, t), mm.Poses(jnp.asarray(R), jnp.asarray(t))):
        assert mm.express_in_frame(poses, origin) is poses
    moved = mm.express_in_frame(HostPoses(R, t + 1.0), origin)  # not in the frame: moved, on the host
    assert isinstance(moved, HostPoses)
    np.testing.assert_allclose(moved.t, t, atol=1e-14)
    np.testing.assert_allclose(moved.R, R, atol=1e-14)


def test_fixed_poses_validation():
    with pytest.raises(ValueError, match="distinct"):
        mm.FixedPoses([1, 1], np.stack([np.eye(2)] * 2), np.zeros((2, 2)))
    with pytest.raises(ValueError, match="finite"):
        mm.FixedPoses([1], np.eye(2)[None], np.full((1, 2), np.nan))
    g = _graph(2)
    with pytest.raises(ValueError, match="out of range"):
        mm.initialize(g, "chordal", fixed=mm.FixedPoses.identity([99], 2))
    with pytest.raises(ValueError, match="3D"):
        mm.initialize(g, "chordal", fixed=mm.FixedPoses.identity([1], 3))


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(iterations=-1), "iterations"),
        (dict(chunk_size=0), "chunk_size"),
        (dict(xi=float("nan")), "xi"),
        (dict(xi=float("inf")), "xi"),
        (dict(xi=-1.0), "xi"),
        (dict(grad_tol=0.0), "grad_tol"),
        (dict(rel_decrease_tol=-1.0), "rel_decrease_tol"),
    ],
)
def test_solve_validates_numbers(kwargs, name):
    with pytest.raises(ValueError, match=name):
        mm.solve(_graph(2), 2, **kwargs)


def test_non_finite_objective_stops_with_a_clear_error():
    g = _graph(2)
    huge = mm.PoseGraph.from_arrays(g.i, g.j, g.R, g.t * 1e200, g.kappa, g.tau, g.num_poses)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # the error alone, no NumPy overflow warnings
        with pytest.raises(mm.NonFiniteError, match="nothing was written"):
            mm.solve(huge, 2, iterations=10, init="odometry")


def test_poses_are_matched_by_vertex_id(tmp_path):
    from mmpgo_jax._init.chordal import load_poses

    g = _graph(2)
    X = mm.odometry_initialization(g)
    ids = np.arange(g.num_poses) * 3 + 10  # non-contiguous ids, as in real files
    rng = np.random.default_rng(0)
    perm = rng.permutation(g.num_poses)
    path = tmp_path / "poses.npz"
    np.savez(path, R=np.asarray(X.R)[perm], t=np.asarray(X.t)[perm], vertex_ids=ids[perm])
    got = load_poses(g, path, vertex_ids=ids)
    np.testing.assert_allclose(np.asarray(got.t), np.asarray(X.t), atol=1e-12)
    with pytest.raises(ValueError, match=r"missing vertex ids 110, 113, 116, 119, 122, \.\.\. \(14 in all\); "
                                         r"vertex ids not in the graph 10, 13"):
        load_poses(g, path, vertex_ids=ids + 100)
    np.savez(path, R=np.asarray(X.R), t=np.asarray(X.t), vertex_ids=np.append(ids[:-1], 999))
    with pytest.raises(ValueError, match=r"missing vertex ids 49; vertex ids not in the graph 999"):
        load_poses(g, path, vertex_ids=ids)


DATA = __import__("pathlib").Path(__file__).parent / "data"


def test_g2o_fix_lines_and_frame():
    f = mm.read_g2o(DATA / "fix2d.g2o")
    fixed = f.fixed_poses
    assert fixed.index.tolist() == [5] and f.vertex_ids[5] == 110
    np.testing.assert_allclose(fixed.R, f.vertex_R[[5]], atol=0)
    assert f.frame is not None and f.frame.index.tolist() == [5]
    res = mm.solve(f.graph, 3, iterations=40, fixed=fixed, frame=f.frame)
    _assert_fixed(res.poses, fixed)
    g = mm.read_g2o(DATA / "frame2d.g2o")
    assert g.fixed_poses is None and g.frame.index.tolist() == [0]
    res = mm.solve(g.graph, 3, iterations=40, frame=g.frame)
    # the result overlays the input: its first pose is at its VERTEX value (2, 1, 0.5 rad)
    np.testing.assert_allclose(np.asarray(res.poses.t)[0], [2.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(np.asarray(res.poses.R)[0], np.asarray(mm.rotation_2d(0.5)), atol=1e-12)
