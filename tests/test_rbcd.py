"""RBCD / RBCD++ (mmpgo_jax._baselines.rbcd) against independent references: the block problem is F
with the neighbours fixed (an exact quadratic), its minimiser by SciPy's exact-Hessian trust region in a chart, the block-gradient
norms from the graph's own Riemannian gradient, descent, colour classes, the centralized optimum,
fixed poses, and the same run sharded over two devices. The lifted rank r > d: iterates on the
Stiefel manifold, descent, the lifted gradient against autodiff and finite differences, the rounded
result against the optimum, r = d bit for bit as rank=None; checkpoints; the communication counts."""

import json
import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize

import mmpgo_jax as mm
from mmpgo_jax._baselines.rbcd import RBCD, boundary_poses_sent, rbcd_poses_sent, robot_colouring
from mmpgo_jax._baselines.rbcd_lifted import lift_matrix
from mmpgo_jax._mm.driver import Termination
from mmpgo_jax._mm.majorization import build_gamma_operator, soa_to_gamma, stack, unstack
from mmpgo_jax._mm.solvers import run_chunk
from mmpgo_jax._mm.weighting import gradients

SELECTIONS = ("greedy", "uniform", "round-robin", "parallel")


@pytest.fixture(scope="module")
def cube():
    return mm.cube_dataset(1, num_poses=100, grid=4).graph


@pytest.fixture(scope="module")
def grid():
    return mm.grid_2d_dataset(1, num_poses=120, grid=6).graph


def _setup(graph, robots, solver):
    """(partition, problem, stacked X0, grad F(X0) per block) at the chordal start."""
    part = mm.partition(graph, robots)
    X0s = part.scatter(mm.chordal_initialization(graph))
    problem = solver.build(part, poses=X0s)
    X = stack(X0s)
    return part, problem, X, jax.jit(gradients)(problem, X)[0]


def _F(graph, R, t):
    """F (the 1/2 convention) written from the edges alone."""
    i, j = np.asarray(graph.i), np.asarray(graph.j)
    rot = R[j] - R[i] @ graph.R
    tr = t[j] - t[i] - jnp.einsum("eab,eb->ea", R[i], graph.t)
    return 0.5 * (jnp.sum(graph.kappa * jnp.sum(rot**2, axis=(1, 2))) + jnp.sum(graph.tau * jnp.sum(tr**2, axis=1)))


def _global(part, X):
    P = part.gather(unstack(np.asarray(X)))
    return np.asarray(P.R), np.asarray(P.t)


def test_inter_weight_default_unchanged(cube):
    part = mm.partition(cube, 4)
    a = build_gamma_operator(part.edges, 1e-3, part.max_poses, host=True)
    b = build_gamma_operator(part.edges, 1e-3, part.max_poses, host=True, inter_weight=2.0)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("dataset", ["cube", "grid"])
def test_block_gamma_is_the_exact_block_hessian(dataset, request):
    """F(X + D on robot a's block) - F(X) = <grad_a F, D> + 1/2 <Gamma_b D, D> for ambient D."""
    graph = request.getfixturevalue(dataset)
    part, problem, X, grad = _setup(graph, 3, RBCD())
    gamma = soa_to_gamma(problem.gamma_soa)
    rng = np.random.default_rng(0)
    for a in range(3):
        D = rng.standard_normal(X.shape[1:]) * np.asarray(part.pose_mask[a])[:, None, None]
        Xd = np.asarray(X).copy()
        Xd[a] += D
        lhs = _F(graph, *_global(part, Xd)) - _F(graph, *_global(part, X))
        G = jax.tree.map(lambda x, a=a: x[a], gamma)
        rhs = np.sum(grad[a] * D) + 0.5 * np.sum(G(jnp.asarray(D)) * D)
        np.testing.assert_allclose(lhs, rhs, rtol=1e-10)


def _hat(w, d):
    if d == 2:
        z = jnp.zeros_like(w[:, 0])
        return jnp.stack([jnp.stack([z, -w[:, 0]], -1), jnp.stack([w[:, 0], z], -1)], -2)
    z = jnp.zeros_like(w[:, 0])
    x, y, u = w[:, 0], w[:, 1], w[:, 2]
    return jnp.stack([jnp.stack([z, -u, y], -1), jnp.stack([u, z, -x], -1), jnp.stack([-y, x, z], -1)], -2)


def _block_minimiser(graph, R0, t0, poses):
    """argmin of F over the given poses (the others fixed) by an exact-Hessian trust region (SciPy) in the
    Cayley chart R0 (I - hat w)^-1 (I + hat w), t0 + dt."""
    d = graph.dim
    k = d * (d - 1) // 2
    n = len(poses)

    def unpack(z):
        w, dt = z[: n * k].reshape(n, k), z[n * k:].reshape(n, d)
        K, eye = _hat(w, d), jnp.eye(d)
        R = jnp.asarray(R0).at[poses].set(jnp.asarray(R0)[poses] @ jnp.linalg.solve(eye - K, eye + K))  # Cayley
        return R, jnp.asarray(t0).at[poses].add(dt)

    near = graph.select_edges(np.isin(np.asarray(graph.i), poses) | np.isin(np.asarray(graph.j), poses))

    def F(z):  # F up to the constant of the edges away from the block
        return _F(near, *unpack(z))

    fun, hess = jax.jit(jax.value_and_grad(F)), jax.jit(jax.hessian(F))
    out = scipy.optimize.minimize(lambda z: [np.asarray(v) for v in fun(z)], np.zeros(n * (k + d)), jac=True,
                                  hess=lambda z: np.asarray(hess(z)), method="trust-exact", options=dict(gtol=1e-10))
    assert out.success or out.status == 2, out.message  # 2: a step below rounding
    R, t = unpack(out.x)
    return np.asarray(R), np.asarray(t)


EXACT = mm.SubproblemConfig(preconditioner="block-jacobi", gradient_tolerance=1e-13, cg_tolerance=1e-13, max_steps=100,
                            cg_iterations=400)


@pytest.mark.parametrize("dataset", ["cube", "grid"])
def test_block_update_is_the_exact_block_minimiser(dataset, request):
    graph = request.getfixturevalue(dataset)
    solver = RBCD("round-robin", inner=EXACT)
    part, problem, X, grad = _setup(graph, 3, solver)
    robot = 1
    selected = jnp.arange(3) == robot
    Xn = jax.jit(solver.block_update)(problem, X, grad, selected)
    np.testing.assert_array_equal(np.asarray(Xn)[[0, 2]], np.asarray(X)[[0, 2]])  # the others keep their poses
    R0, t0 = _global(part, X)
    poses = np.flatnonzero(np.asarray(part.robot_of_pose) == robot)
    R_ref, t_ref = _block_minimiser(graph, R0, t0, poses)
    R, t = _global(part, Xn)
    f, f_ref, f0 = (float(_F(graph, *p)) for p in ((R, t), (R_ref, t_ref), (R0, t0)))
    assert f < f0 - 1e-3 * f0  # the block had work to do
    np.testing.assert_allclose(f, f_ref, rtol=1e-11)
    np.testing.assert_allclose(R, R_ref, atol=1e-6)
    np.testing.assert_allclose(t, t_ref, atol=1e-6)


@pytest.mark.parametrize("accelerated", [False, True])
@pytest.mark.parametrize("selection", SELECTIONS)
def test_f_is_non_increasing(cube, selection, accelerated):
    r = mm.solve(cube, 4, solver=RBCD(selection, accelerated=accelerated),
                 termination=Termination(40, 40, stop_when_stalled=False))
    f = r.history.f
    assert np.all(np.isfinite(f)) and f[-1] < 0.7 * f[0]
    assert np.all(np.diff(f) <= 1e-12 * f[0]), np.diff(f).max()
    if not accelerated:
        assert not r.history.restarts.any()
    assert r.solver.name == ("rbcd++" if accelerated else "rbcd")


def test_fixed_interval_restart_is_dpgos_rule(cube):
    """``restart="fixed"``: the momentum restarts after every ``restart_interval``-th iteration and at
    no other (no redo); before the first restart it is the adaptive rule's first pass whenever that
    one did not restart."""
    term = Termination(40, 40, stop_when_stalled=False)
    fixed = mm.solve(cube, 4, solver=RBCD(accelerated=True, restart="fixed", restart_interval=15), termination=term)
    adaptive = mm.solve(cube, 4, solver=RBCD(accelerated=True), termination=term)
    restarts = fixed.history.restarts.any(axis=1)
    assert np.flatnonzero(restarts).tolist() == [15, 30]  # history index k + 1: iterations 15 and 30
    f = fixed.history.f
    assert np.all(np.isfinite(f)) and f[-1] < 0.7 * f[0]
    first = int(np.argmax(adaptive.history.restarts.any(axis=1))) or len(f)
    upto = min(first, 15)  # the same iterates until one of the two rules restarts
    np.testing.assert_allclose(f[:upto], adaptive.history.f[:upto], rtol=1e-12)
    with pytest.raises(ValueError, match="restart"):
        RBCD(accelerated=True, restart="sometimes")
    with pytest.raises(ValueError, match="restart_interval"):
        RBCD(accelerated=True, restart="fixed", restart_interval=0)


def test_greedy_picks_the_largest_block_gradient(cube):
    solver = RBCD("greedy")
    part, problem, X, grad = _setup(cube, 5, solver)
    R0, t0 = _global(part, X)
    rgrad = mm.riemannian_gradient(cube, mm.Poses(jnp.asarray(R0), jnp.asarray(t0)))
    per_pose = np.sum(np.asarray(rgrad.R) ** 2, axis=(1, 2)) + np.sum(np.asarray(rgrad.t) ** 2, axis=1)
    norms2 = np.bincount(np.asarray(part.robot_of_pose), weights=per_pose, minlength=5)
    state, _ = solver.init(problem, unstack(X))
    new, rec = jax.jit(solver.step)(problem, state)
    moved = np.any(np.asarray(new.X) != np.asarray(X), axis=(1, 2, 3))
    np.testing.assert_array_equal(moved, np.arange(5) == np.argmax(norms2))
    np.testing.assert_allclose(rec.f, 2 * _F(cube, *_global(part, new.X)), rtol=1e-12)


def test_selection_rules(cube):
    part, problem, X, grad = _setup(cube, 5, RBCD())
    z = jnp.zeros(5)
    for k in range(7):
        np.testing.assert_array_equal(RBCD("round-robin").select(problem, k, z), np.arange(5) == k % 5)
    drawn = [int(np.flatnonzero(RBCD("uniform", seed=3).select(problem, k, z))[0]) for k in range(60)]
    assert set(drawn) == set(range(5))
    assert drawn == [int(np.flatnonzero(RBCD("uniform", seed=3).select(problem, k, z))[0]) for k in range(60)]
    assert drawn != [int(np.flatnonzero(RBCD("uniform", seed=4).select(problem, k, z))[0]) for k in range(60)]


def test_parallel_classes_equal_a_sequential_order(grid):
    """Colour classes hold no two neighbouring robots, and one class's update at once equals its
    robots' updates one after the other (each reading the others' latest poses)."""
    A = 8
    parallel = RBCD("parallel", inner=EXACT)
    part, problem, X, grad = _setup(grid, A, parallel)
    colour = robot_colouring(part)
    e = part.edges
    inter = np.asarray(e.local_i) ^ np.asarray(e.local_j)
    ri, rj = np.asarray(e.robot_i)[inter], np.asarray(e.robot_j)[inter]
    assert len(ri) and np.all(colour[ri] != colour[rj])
    np.testing.assert_array_equal(problem.colour, colour)
    largest = np.argmax(np.bincount(colour))
    members = np.flatnonzero(colour == largest)
    assert len(members) >= 2
    Xp = jax.jit(parallel.block_update)(problem, X, grad, jnp.asarray(colour == largest))
    sequential = RBCD("round-robin", inner=EXACT)
    update = jax.jit(sequential.block_update)
    Xs, gs = X, grad
    for a in members[::-1]:
        Xs = update(problem, Xs, gs, jnp.arange(A) == a)
        gs = gradients(problem, Xs)[0]
    np.testing.assert_allclose(Xp, Xs, rtol=0, atol=1e-11)
    assert not np.allclose(Xp, X)


def test_converges_to_the_centralized_optimum(cube):
    fstar = mm.centralized_optimum(cube).f
    r = mm.solve(cube, 4, solver=RBCD("greedy", accelerated=True),
                 termination=Termination(2000, 50, f_target=fstar * (1 + 1e-7)))
    assert r.result is mm.RESULTS.f_target, r.history.f[-1] / fstar - 1
    assert abs(r.history.f[-1] - fstar) <= 1e-6 * fstar


@pytest.mark.slow  # 9 s: a 400-pose comparison (the default run keeps RBCD++'s descent and optimum tests)
def test_acceleration_needs_fewer_iterations():
    """Measured (cube, 400 poses, 8 robots, chordal start): gap 1e-3 after 422 RBCD / 131 RBCD++ greedy
    iterations; 2D grid (400 poses, 8 robots): > 1500 / 253. Asserted: RBCD++ needs at most half."""
    graph = mm.cube_dataset(2, num_poses=400, grid=6).graph
    target = mm.centralized_optimum(graph).f * (1 + 1e-3)
    k = {}
    for acc in (False, True):
        r = mm.solve(graph, 8, solver=RBCD("greedy", accelerated=acc),
                     termination=Termination(600, 50, f_target=target))
        k[acc] = r.history.first_below(target)
    assert k[True] is not None and (k[False] is None or k[True] <= 0.5 * k[False]), k


def test_fixed_poses_do_not_move(cube):
    start = mm.chordal_initialization(cube)
    index = np.array([0, 57])
    fixed = mm.FixedPoses(index, np.asarray(start.R)[index], np.asarray(start.t)[index])
    for solver in (RBCD("greedy", accelerated=True), RBCD("parallel")):
        r = mm.solve(cube, 4, solver=solver, fixed=fixed, termination=Termination(30, 30, stop_when_stalled=False))
        assert r.history.f[-1] < 0.8 * r.history.f[0]
        np.testing.assert_array_equal(np.asarray(r.poses.R)[index], fixed.R)
        np.testing.assert_array_equal(np.asarray(r.poses.t)[index], fixed.t)


def test_arguments_are_checked(cube):
    with pytest.raises(ValueError, match="selection"):
        RBCD("random")
    with pytest.raises(ValueError, match="at least d = 3"):
        mm.solve(cube, 2, solver=RBCD(rank=2), iterations=1)
    with pytest.raises(ValueError, match="block-Jacobi only"):
        mm.solve(cube, 2, solver=RBCD(rank=5, inner=mm.SubproblemConfig()), iterations=1)
    with pytest.raises(ValueError, match="least-squares"):
        mm.solve(cube, 2, solver=RBCD(), loss="cauchy", iterations=1)


_CHILD = textwrap.dedent("""
    import json
    import jax
    jax.config.update("jax_enable_x64", True)
    import mmpgo_jax as mm
    from mmpgo_jax.sharding import Sharded
    from mmpgo_jax._mm.driver import Termination

    graph = mm.cube_dataset(3, num_poses=150, grid=4).graph
    out = {}
    for name, solver in [("greedy++", mm.RBCD("greedy", accelerated=True)), ("parallel", mm.RBCD("parallel")),
                         ("uniform", mm.RBCD("uniform", seed=2)), ("lifted", mm.RBCD("greedy", accelerated=True, rank=5))]:
        for layout in (None, Sharded(devices=2)):
            r = mm.solve(graph, 4, solver=solver, layout=layout,
                         termination=Termination(30, 10, stop_when_stalled=False))
            out[name + ("/sharded" if layout else "")] = dict(f=r.history.f.tolist(), devices=r.stats.get("devices"),
                                                             restarts=int(r.history.restarts.sum()))
    print(json.dumps(out))
""")


@pytest.mark.slow  # 30 s: a child process with two devices (test_one_solve_path checks the layouts by default)
def test_sharded_run_gives_the_same_history():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    proc = subprocess.run([sys.executable, "-c", _CHILD], capture_output=True, text=True, env=env, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    for name in ("greedy++", "parallel", "uniform", "lifted"):
        one, sharded = out[name], out[name + "/sharded"]
        assert sharded["devices"] == 2 and len(one["f"]) == 31
        np.testing.assert_allclose(sharded["f"], one["f"], rtol=1e-10, atol=0, err_msg=name)
        assert sharded["restarts"] == one["restarts"]


# --- the lifted rank r > d ---------------------------------------------------------------------

LIFTED = [("cube", 5), ("grid", 3)]  # (dataset, r): d = 3 lifted to 5, d = 2 to 3


@pytest.mark.parametrize(("dataset", "rank"), LIFTED)
def test_lifted_iterates_stay_on_the_stiefel_manifold_and_descend(dataset, rank, request):
    graph = request.getfixturevalue(dataset)
    d = graph.dim
    solver = RBCD("round-robin", rank=rank)
    part, problem, X, _ = _setup(graph, 4, solver)
    state, rec0 = jax.jit(solver.init)(problem, unstack(X))
    state, recs = run_chunk(solver, problem, state, 30)
    mask = np.asarray(part.pose_mask)
    Y = np.asarray(state.X)[mask]
    assert Y.shape[1:] == (rank, d + 1)
    R = Y[..., 1:]
    np.testing.assert_allclose(np.swapaxes(R, -1, -2) @ R, np.broadcast_to(np.eye(d), (len(R), d, d)), rtol=0,
                               atol=1e-10)
    f = np.concatenate([[float(rec0.f)], np.asarray(recs.f)])
    np.testing.assert_allclose(f[0], 2 * _F(graph, *_global(part, X)), rtol=1e-12)  # the lift keeps f
    np.testing.assert_allclose(f[-1], 2 * _F(graph, *_global(part, state.X)), rtol=1e-12)  # F on lifted poses
    assert np.all(np.diff(f) <= 1e-12 * f[0]), np.diff(f).max()
    assert f[-1] < 0.8 * f[0]


@pytest.mark.parametrize(("dataset", "rank"), LIFTED)
def test_lifted_gradient(dataset, rank, request):
    """grad F on lifted poses (the solver's gradients) equals autodiff of F written from the edges, and
    central differences of F along random directions (F is quadratic: exact up to rounding)."""
    graph = request.getfixturevalue(dataset)
    d = graph.dim
    part, problem, X, _ = _setup(graph, 3, RBCD(rank=rank))
    rng = np.random.default_rng(1)
    Q, _ = np.linalg.qr(rng.standard_normal((*X.shape[:2], rank, d)))  # random Stiefel blocks
    Y = np.concatenate([rng.standard_normal((*X.shape[:2], rank, 1)), Q], axis=-1)
    Y = np.where(np.asarray(part.pose_mask)[..., None, None], Y, 0.0)
    grad = np.asarray(jax.jit(gradients)(problem, jnp.asarray(Y))[0])
    R, t = _global(part, Y)
    gR, gt = jax.grad(_F, argnums=(1, 2))(graph, jnp.asarray(R), jnp.asarray(t))
    Pg = part.gather(unstack(grad))
    np.testing.assert_allclose(Pg.R, gR, rtol=0, atol=1e-10 * np.abs(gR).max())
    np.testing.assert_allclose(Pg.t, gt, rtol=0, atol=1e-10 * np.abs(gt).max())
    for _ in range(3):
        D = rng.standard_normal(Y.shape) * np.asarray(part.pose_mask)[..., None, None]
        h = 1e-3
        fd = (_F(graph, *_global(part, Y + h * D)) - _F(graph, *_global(part, Y - h * D))) / (2 * h)
        np.testing.assert_allclose(fd, np.sum(grad * D), rtol=1e-8)


@pytest.mark.parametrize(("dataset", "rank"), LIFTED)
def test_rounded_result_is_near_the_optimum(dataset, rank, request):
    graph = request.getfixturevalue(dataset)
    fstar = mm.centralized_optimum(graph).f
    r = mm.solve(graph, 4, solver=RBCD("greedy", accelerated=True, rank=rank),
                 termination=Termination(600, 50, f_target=fstar * (1 + 1e-6)))
    lifted, rounded = r.stats["rbcd_lifted_f"], r.stats["rbcd_rounded_f"]
    np.testing.assert_allclose(lifted, r.history.f[-1], rtol=1e-12)
    R, t = np.asarray(r.poses.R), np.asarray(r.poses.t)
    assert R.shape[-2:] == (graph.dim, graph.dim) and t.shape[-1] == graph.dim
    np.testing.assert_allclose(rounded, 2 * _F(graph, R, t), rtol=1e-12)
    np.testing.assert_allclose(np.swapaxes(R, -1, -2) @ R, np.broadcast_to(np.eye(graph.dim), R.shape), atol=1e-12)
    assert np.all(np.linalg.det(R) > 0)
    # the iterates keep the lift's rank d, so rounding loses nothing but the iterates' rounding errors
    assert rounded >= lifted * (1 - 1e-9), (rounded, lifted)
    assert rounded <= fstar * (1 + 1e-5), rounded / fstar - 1


@pytest.mark.parametrize("accelerated", [False, True])
def test_rank_d_is_rank_none_bit_for_bit(cube, accelerated):
    term = Termination(25, 25, stop_when_stalled=False)
    a = mm.solve(cube, 4, solver=RBCD("greedy", accelerated=accelerated), termination=term)
    b = mm.solve(cube, 4, solver=RBCD("greedy", accelerated=accelerated, rank=3), termination=term)
    np.testing.assert_array_equal(a.history.f, b.history.f)
    np.testing.assert_array_equal(a.poses.R, b.poses.R)
    np.testing.assert_array_equal(a.poses.t, b.poses.t)
    assert not any(k.startswith("rbcd_") for k in b.stats)


def test_lift_matrix_is_fixed_and_orthonormal():
    P = lift_matrix(5, 3)
    np.testing.assert_allclose(P.T @ P, np.eye(3), atol=1e-15)
    np.testing.assert_array_equal(P, lift_matrix(5, 3))


@pytest.mark.parametrize("rank", [None, 5])
def test_resumed_rbcd_plus_plus_equals_the_uninterrupted_run(tmp_path, cube, rank):
    """As tests/test_checkpoint.py does for MM: stopped after 30 iterations (checkpoints every 20),
    resumed from the checkpoint, the f history and the poses equal the uninterrupted run's."""
    ck = tmp_path / "rbcd.ckpt"
    opts = dict(solver=RBCD("greedy", accelerated=True, rank=rank), iterations=50, chunk_size=10)
    full = mm.solve(cube, 4, **opts)
    cut = mm.solve(cube, 4, callback=lambda k, f: k >= 30, checkpoint=ck, checkpoint_every=2, **opts)
    assert cut.iterations == 30 and cut.stop_reason == "callback"
    resumed = mm.solve(cube, 4, resume=ck, **opts)
    assert resumed.iterations == full.iterations
    np.testing.assert_array_equal(resumed.history.f, full.history.f)
    np.testing.assert_array_equal(resumed.history.restarts, full.history.restarts)
    np.testing.assert_array_equal(resumed.poses.R, full.poses.R)
    np.testing.assert_array_equal(resumed.poses.t, full.poses.t)


def test_poses_sent(grid):
    part = mm.partition(grid, 6)
    sent = boundary_poses_sent(part)
    np.testing.assert_array_equal(sent, mm.partition_stats(grid, part.robot_of_pose).sent_poses)
    total = sent.sum()
    assert rbcd_poses_sent(part, "round-robin") == total / 6 == rbcd_poses_sent(part, "greedy")
    C = robot_colouring(part).max() + 1
    assert rbcd_poses_sent(part, "parallel") == total / C
    assert rbcd_poses_sent(part, "uniform", accelerated=True) == total / 6 + total


@pytest.mark.parametrize(("r", "d"), [(5, 3), (3, 2)])
def test_stiefel_polar_is_the_svd_polar_factor(r, d):
    from mmpgo_jax._core.lie import stiefel_polar

    M = np.random.default_rng(2).standard_normal((200, r, d)) * 3
    U, _, Vt = np.linalg.svd(M, full_matrices=False)
    P = np.moveaxis(np.asarray(jax.jit(stiefel_polar)(jnp.asarray(np.moveaxis(M, 0, -1)))), -1, 0)
    np.testing.assert_allclose(P, U @ Vt, rtol=0, atol=1e-13)


@pytest.mark.parametrize(("dataset", "rank"), LIFTED)
def test_lifted_preconditioner_inverts_the_diagonal_hessian_blocks(dataset, rank, request):
    """M^-1 H_ss V = V for tangent V at lifted poses, H_ss V = P_Y(V Gamma_ss - [0 | V_R W]) pose by
    pose (Gamma's diagonal blocks alone), W a small symmetric Weingarten term."""
    from mmpgo_jax._baselines.rbcd_lifted import LiftedPreconditioner
    from mmpgo_jax._mm.majorization import soa_bmm, tangent_soa, to_soa

    graph = request.getfixturevalue(dataset)
    d = graph.dim
    part, problem, X, _ = _setup(graph, 3, RBCD(rank=rank))
    state, _ = jax.jit(RBCD(rank=rank).init)(problem, unstack(X))
    Y = to_soa(state.X[0])
    diag = problem.gamma_soa.diag[0]
    rng = np.random.default_rng(3)
    W = rng.standard_normal((d, d, Y.shape[-1])) * 0.05
    W = jnp.asarray(W + np.swapaxes(W, 0, 1))
    pre = LiftedPreconditioner(jax.tree.map(lambda a: a[0], problem.newton.without_coarse()), diag)

    @jax.jit
    def M_H(V):
        VG = soa_bmm(V, diag)
        return pre.at(Y, W)(tangent_soa(Y, jnp.concatenate([VG[:, :1], VG[:, 1:] - soa_bmm(V[:, 1:], W)], axis=1)))

    V = tangent_soa(Y, jnp.asarray(rng.standard_normal(Y.shape)))
    np.testing.assert_allclose(M_H(V), V, rtol=0, atol=1e-10 * float(jnp.abs(V).max()))


def test_lifted_fixed_poses_keep_their_values(cube):
    """Fixed poses stay at their lifted values; the rounded result is moved back onto them (to rounding)."""
    start = mm.chordal_initialization(cube)
    index = np.array([0, 57])
    fixed = mm.FixedPoses(index, np.asarray(start.R)[index], np.asarray(start.t)[index])
    r = mm.solve(cube, 4, solver=RBCD("greedy", rank=5), fixed=fixed,
                 termination=Termination(20, 20, stop_when_stalled=False))
    assert r.history.f[-1] < 0.8 * r.history.f[0]
    np.testing.assert_allclose(np.asarray(r.poses.R)[index], fixed.R, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(r.poses.t)[index], fixed.t, rtol=0, atol=1e-12 * np.abs(fixed.t).max())
    np.testing.assert_allclose(r.stats["rbcd_rounded_f"], r.stats["rbcd_lifted_f"], rtol=1e-9)
