"""The robot subproblem solver and the MM / AMM outer loops (paper §V-VI, Algorithms 1-2, Props. 2-3).

Small random problems (chain + loop closures, noisy measurements) and random partitions. Compiles
are the expensive part (several seconds each on two cores), so shapes and configurations are
reused: most tests read the cached runs of the module-scoped ``runs`` fixture.
"""

import logging

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mmpgo_jax import PoseGraph, Poses, cost, riemannian_gradient_norm
from mmpgo_jax._core.geometry import random_rotations, rotation_2d, sym
from mmpgo_jax._core.partition import partition
from mmpgo_jax._mm.majorization import (
    from_soa,
    gamma_diagonal_blocks,
    gradient_and_share,
    majorizer_decrease,
    soa_bmm,
    soa_T,
    stack,
    sym0,
    to_soa,
    unstack,
)
from mmpgo_jax._mm.outer import MMConfig, MMProblem, _mm_update, init_state, run
from mmpgo_jax._mm.subproblem import SubproblemConfig, majorizer_value, solve_subproblem, tangent_projection

N = 16  # poses of the main 2-D problem
LOOPS = 8
NUM_ROBOTS = 4
CHUNK = 100  # iterations per run() call (one compile per configuration)
XI = MMConfig().xi

CONVERGE = SubproblemConfig(max_steps=50, cg_iterations=200, gradient_tolerance=1e-9, cg_tolerance=1e-10,
                            decrease_tolerance=0.0)


def COMMON_PADDING(graph):
    """Padding that gives every partition of ``graph`` the same problem shape."""
    n, m = graph.num_poses, graph.num_edges
    return dict(min_max_poses=n, min_max_edges=m, num_robots=n, min_couplings=2 * m)


# ----------------------------------------------------------------------------- problem builders


def _small_rotations(rng, d, sigma, size):
    if d == 2:
        return np.asarray(rotation_2d(sigma * rng.standard_normal(size)))
    return Rotation.from_rotvec(sigma * rng.standard_normal((size, 3))).as_matrix()


def make_problem(seed, n, d, loops, sigma_r=0.05, sigma_t=0.05, init_r=0.2, init_t=0.3):
    """Random graph (chain + loop closures, noisy measurements) and perturbed initial poses."""
    rng = np.random.default_rng(seed)
    R = random_rotations(rng, (n,), d)
    t = 3.0 * rng.standard_normal((n, d))
    I, J = list(range(n - 1)), list(range(1, n))
    while len(I) < n - 1 + loops:
        a, b = (int(v) for v in rng.integers(0, n, 2))
        if abs(a - b) > 1:
            I.append(a)
            J.append(b)
    I, J = np.array(I), np.array(J)
    m = len(I)
    Rm = np.swapaxes(R[I], 1, 2) @ R[J] @ _small_rotations(rng, d, sigma_r, m)
    tm = np.einsum("mba,mb->ma", R[I], t[J] - t[I]) + sigma_t * rng.standard_normal((m, d))
    kappa = rng.uniform(0.5, 5.0, m)
    tau = rng.uniform(0.5, 5.0, m)
    graph = PoseGraph.from_arrays(I, J, Rm, tm, kappa, tau, num_poses=n)
    X0 = Poses(jnp.asarray(R @ _small_rotations(rng, d, init_r, n)), jnp.asarray(t + init_t * rng.standard_normal((n, d))))
    return graph, X0


def random_robots(rng, n, A):
    """Random robot-of-pose array using every robot 0..A-1 (robots get unequal pose counts)."""
    r = rng.integers(0, A, n)
    r[rng.permutation(n)[:A]] = np.arange(A)
    return r


_scatter = eqx.filter_jit(lambda part, X: part.scatter(X))
_cost = jax.jit(cost)
_grad_norm = jax.jit(riemannian_gradient_norm)
_init = eqx.filter_jit(init_state)


def setup_mm(graph, X0, robots, config, min_couplings=0, **padding):
    part = partition(graph, robots, **padding)
    X0 = _scatter(part, X0)
    problem = MMProblem.build(part, config.xi, min_couplings=min_couplings, poses=X0)
    state = _init(problem, X0, config)
    return part, problem, state


def run_chunks(problem, config, state, chunks, length=CHUNK):
    """``chunks`` calls of run(.., length); returns final state, the state after each chunk, records."""
    states, fs, gs, rs = [], [], [], []
    for _ in range(chunks):
        state, rec = run(problem, config, state, length)
        states.append(state)
        fs.append(np.asarray(rec.f))
        gs.append(np.asarray(rec.grad_norm))
        rs.append(np.asarray(rec.restarted))
    return dict(state=state, states=states, f=np.concatenate(fs), grad_norm=np.concatenate(gs), restarted=np.concatenate(rs))


# ----------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def problem2d():
    graph, X0 = make_problem(0, N, 2, LOOPS)
    robots = random_robots(np.random.default_rng(1), N, NUM_ROBOTS)
    assert len(set(np.bincount(robots))) > 1  # unequal robots: some have padding slots
    return dict(graph=graph, X0=X0, robots=robots, f0=float(_cost(graph, X0)))


class _Runs:
    """Lazily computed, cached runs on the main 2-D problem (shared by several tests)."""

    def __init__(self, p):
        self.p = p
        self._cache = {}

    def get(self, key):
        if key not in self._cache:
            self._cache[key] = getattr(self, "_" + key)()
        return self._cache[key]

    def _mm(self):
        cfg = MMConfig(method="mm")
        part, problem, st0 = setup_mm(self.p["graph"], self.p["X0"], self.p["robots"], cfg)
        out = run_chunks(problem, cfg, st0, 10)
        out.update(part=part, problem=problem, state0=st0, config=cfg)
        return out

    def _amm_paper(self):
        cfg = MMConfig(method="amm", restart="paper")
        _, problem, st0 = setup_mm(self.p["graph"], self.p["X0"], self.p["robots"], cfg)
        return dict(run_chunks(problem, cfg, st0, 1), state0=st0, config=cfg)

    def _amm_adaptive(self):
        cfg = MMConfig(method="amm", restart="adaptive")
        _, problem, st0 = setup_mm(self.p["graph"], self.p["X0"], self.p["robots"], cfg)
        return dict(run_chunks(problem, cfg, st0, 1), state0=st0, config=cfg)

    def _amm_average(self):
        cfg = MMConfig(method="amm", restart="average")
        _, problem, st0 = setup_mm(self.p["graph"], self.p["X0"], self.p["robots"], cfg)
        return dict(run_chunks(problem, cfg, st0, 1), state0=st0, config=cfg, problem=problem)

    def _extremes(self):
        """A = 1 (centralized) and A = n (one pose per robot), 600 iterations each, both padded to
        one common shape (one compile)."""
        g, n = self.p["graph"], N
        # A = 1 must reach a critical point to 1e-8: subproblems solved to the gradient criterion, without
        # the rule that stops them once 1e-8 of F is left to gain (test_trust_region.py covers that rule)
        cfg = MMConfig(method="mm", subproblem=SubproblemConfig(decrease_tolerance=0.0))
        out = {}
        for name, robots in (("A=1", np.zeros(n, int)), ("A=n", np.arange(n))):
            _, problem, st0 = setup_mm(g, self.p["X0"], robots, cfg, **COMMON_PADDING(g))
            out[name] = run_chunks(problem, cfg, st0, 6)
        return out


@pytest.fixture(scope="module")
def runs(problem2d):
    return _Runs(problem2d)


# ----------------------------------------------------------------------------- subproblem


def edge_roles(graph, robots, num_robots):
    """Per robot (A, m) masks of its own edges, inter-robot edges where it holds the tail, and
    inter-robot edges where it holds the head; and each endpoint's local slot (rank of the pose
    among its robot's poses)."""
    I, J = np.asarray(graph.i), np.asarray(graph.j)
    ra, rb = robots[I], robots[J]
    alpha = np.arange(num_robots)[:, None]
    own = (ra == alpha) & (rb == alpha)
    tail = (ra == alpha) & (rb != alpha)
    head = (rb == alpha) & (ra != alpha)
    slots = np.zeros(len(robots), int)
    for a in range(num_robots):
        slots[robots == a] = np.arange(np.sum(robots == a))
    return jnp.asarray(own), jnp.asarray(tail), jnp.asarray(head), jnp.asarray(slots[I]), jnp.asarray(slots[J])


def explicit_G(graph, own, tail, head, si, sj, xi, Y: Poses, C: Poses, g: Poses):
    """G^α(Y | C) − const written out per edge (the quadratic part of Eq. (10) plus ξ/2‖D‖²), with
    the linear term ⟨g, Y − C⟩. Y, C, g are the robot's padded local poses (n_max slots)."""
    D = Y - C
    DRi, Dti, DRj, Dtj = D.R[si], D.t[si], D.R[sj], D.t[sj]
    Rm, tm, kap, tau = graph.R, graph.t, graph.kappa, graph.tau
    sq = lambda v: jnp.sum(v * v, axis=tuple(range(1, v.ndim)))
    rot_i = DRi @ Rm
    tr_i = jnp.einsum("eab,eb->ea", DRi, tm) + Dti
    q_own = 0.5 * (kap * sq(rot_i - DRj) + tau * sq(tr_i - Dtj))
    q_tail = kap * sq(rot_i) + tau * sq(tr_i)
    q_head = kap * sq(DRj) + tau * sq(Dtj)
    Q = jnp.sum(jnp.where(own, q_own, 0.0) + jnp.where(tail, q_tail, 0.0) + jnp.where(head, q_head, 0.0))
    Q = Q + 0.5 * xi * (jnp.sum(D.R**2) + jnp.sum(D.t**2))
    return Q + jnp.sum(g.R * D.R) + jnp.sum(g.t * D.t)


def riemannian_grad_norm(f, Y: Poses):
    """‖grad f(Y)‖ on R^{d×n} × SO(d)^n: jax.grad, then the tangent projection R ↦ G − R sym(RᵀG)."""
    e = jax.grad(f)(Y)
    gR = e.R - Y.R @ sym(jnp.swapaxes(Y.R, -1, -2) @ e.R)
    return jnp.sqrt(jnp.sum(gR**2) + jnp.sum(e.t**2))


@jax.jit
def _explicit_check(graph, roles, xi, Y, S, C, g):
    """Per robot (stacked inputs with a robot axis): G^α(Y) − G^α(S), ‖grad G^α(Y)‖, ‖grad G^α(S)‖."""
    own, tail, head, si, sj = roles

    def one(o, t, h, Ya, Sa, Ca, ga):
        G = lambda Z: explicit_G(graph, o, t, h, si, sj, xi, Z, unstack(Ca), unstack(ga))
        Ya, Sa = unstack(Ya), unstack(Sa)
        return G(Ya) - G(Sa), riemannian_grad_norm(G, Ya), riemannian_grad_norm(G, Sa)

    return jax.vmap(one)(own, tail, head, Y, S, C, g)


@eqx.filter_jit
def _solve_all(gamma, precond, start, center, g, config):
    """solve_subproblem for every robot (stacked layout), plus the majorizer value at the start."""
    v0 = jax.vmap(majorizer_value)(gamma, start, center, g)
    Y, v = jax.vmap(lambda G, B, s, c, gg: solve_subproblem(G, B, s, c, gg, config))(gamma, precond, start, center, g)
    return Y, v, v0


def _precond(problem, subconfig):
    """The batched preconditioner the outer loop hands to solve_subproblem for this budget."""
    return problem.preconditioner(MMConfig(subproblem=subconfig))


@eqx.filter_jit
def _grads(part, X):
    """(grad F blocks as Poses, shares, local costs) at padded poses X (Poses)."""
    grad, share, local = jax.vmap(lambda e: gradient_and_share(e, stack(X), part.max_poses))(part.edges)
    return unstack(grad), share, local


@pytest.fixture(scope="module", params=[2, 3], ids=["2d", "3d"])
def subproblem_setup(request):
    d = request.param
    n = 12
    graph, X0 = make_problem(20 + d, n, d, 6)
    robots = random_robots(np.random.default_rng(30 + d), n, 3)
    part = partition(graph, robots)
    X = _scatter(part, X0)
    grad, _, _ = _grads(part, X)
    return dict(d=d, graph=graph, robots=robots, part=part, X=X, grad=grad)


def _project_so(M):
    U, _, Vt = np.linalg.svd(M)
    fix = np.ones(M.shape[:-1])
    fix[..., -1] = np.linalg.det(U @ Vt)
    return (U * fix[..., None, :]) @ Vt


def _random_trials(rng, X, grad, mask):
    """(start, center, g) triples, stacked layout (A, n_max, d, d+1): MM-like (start = center = X^k,
    true gradient), AMM-like (ambient extrapolated center, start its projection), random ones."""
    X, grad = np.asarray(X), np.asarray(grad)

    def noise(scale):
        return np.where(mask[..., None, None], scale * rng.standard_normal(X.shape), 0.0)

    def proj(Y):
        out = Y.copy()
        out[..., 1:] = _project_so(Y[..., 1:])
        return out

    trials = [(X, X, grad)]
    C = X + noise(0.1)
    trials.append((proj(C), C, grad + noise(0.5)))
    C = proj(X + noise(0.3))
    trials.append((proj(C + noise(0.3)), C, noise(3.0)))
    return [tuple(jnp.asarray(P) for P in tr) for tr in trials]


def test_subproblem_decreases_and_converges(subproblem_setup):
    """Assumption 1: G^α never increases (any budget); with a large budget the result is a
    critical point of G^α (explicit G^α, jax.grad and tangent projection)."""
    s = subproblem_setup
    part, graph, robots = s["part"], s["graph"], s["robots"]
    mask = np.asarray(part.pose_mask)
    roles = edge_roles(graph, robots, part.num_robots)
    np.testing.assert_array_equal(np.asarray(part.slot_of_pose)[np.asarray(graph.i)], np.asarray(roles[3]))
    rng = np.random.default_rng(5)
    for xi in (XI, 0.5):
        problem = MMProblem.build(part, xi, poses=s["X"])
        for start, center, g in _random_trials(rng, stack(s["X"]), stack(s["grad"]), mask):
            for config in (SubproblemConfig(), CONVERGE):
                Y, v, v0 = _solve_all(problem.gamma, _precond(problem, config), start, center, g, config)
                v, v0 = np.asarray(v), np.asarray(v0)
                assert np.all(v <= v0 + 1e-13 * np.maximum(1.0, np.abs(v0))), (v, v0)
                assert np.all(v < v0)  # and it does make progress from these starts
                # On the manifold; padding slots untouched.
                R = np.asarray(Y)[..., 1:]
                RtR = np.swapaxes(R, -1, -2) @ R
                np.testing.assert_allclose(RtR, np.broadcast_to(np.eye(s["d"]), RtR.shape), atol=1e-12)
                np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
                np.testing.assert_array_equal(np.asarray(Y)[~mask], np.asarray(start)[~mask])
                if config is not CONVERGE:
                    continue
                dG, g_end, g_start = (np.asarray(x) for x in _explicit_check(graph, roles, xi, Y, start, center, g))
                # The explicit G^α and the library's value agree up to the constant.
                np.testing.assert_allclose(dG, v - v0, rtol=1e-9, atol=1e-12 * max(1.0, np.abs(v0).max()))
                assert np.all(g_end <= 1e-6 * g_start), (xi, g_start, g_end)


@eqx.filter_jit
def _decreases(problem, X_new, X, grad):
    """G^α(X_new^α | X) − Ḡ^α(X) per robot, by the edge-based ``majorizer_decrease`` (independent
    of the block-sparse Γ operator the solver uses)."""
    f = lambda e, D, g: majorizer_decrease(e, problem.xi, unstack(D), unstack(g))
    return jax.vmap(f)(problem.partition.edges, X_new - X, grad)


def test_vmapped_update_matches_per_robot_loop(runs):
    """The vmapped MM update (Algorithm 1 line 6) equals solve_subproblem called robot by robot;
    and every robot's G^α does not increase in that iteration."""
    r = runs.get("mm")
    problem, st, cfg = r["problem"], r["state0"], r["config"]
    X1 = eqx.filter_jit(_mm_update)(problem, cfg, st.X, st.grad)
    solve_one = eqx.filter_jit(solve_subproblem)
    for a in range(problem.partition.num_robots):
        gamma_a = jax.tree.map(lambda x: x[a], problem.gamma)
        precond_a = jax.tree.map(lambda x: x[a], _precond(problem, cfg.subproblem))
        Ya, _ = solve_one(gamma_a, precond_a, st.X[a], st.X[a], st.grad[a], cfg.subproblem)
        np.testing.assert_allclose(np.asarray(Ya), np.asarray(X1[a]), rtol=0, atol=1e-12)
    dec = np.asarray(_decreases(problem, X1, st.X, st.grad))
    assert np.all(dec <= 1e-12 * np.maximum(1.0, np.asarray(st.share))), dec
    assert np.all(dec < 0)  # every robot moves in the first iteration
    # run() performs the same first iteration.
    _, share, _ = _grads(problem.partition, unstack(X1))
    np.testing.assert_allclose(r["f"][0], 2 * float(jnp.sum(share)), rtol=1e-12)


# ----------------------------------------------------------------------------- MM / AMM


def test_mm_problem_gamma_and_preconditioners(runs):
    """MMProblem.build: Γ^α's diagonal blocks match the edge-based ones; both preconditioner kinds are
    symmetric positive definite on the tangent space at the iterate, as PCG requires
    (tests/test_preconditioner.py checks them entry by entry against dense algebra)."""
    r = runs.get("mm")
    problem = r["problem"]
    part = problem.partition
    blocks = eqx.filter_jit(lambda e: jax.vmap(lambda ea: gamma_diagonal_blocks(ea, problem.xi, part.max_poses))(e))
    blocks = np.asarray(blocks(part.edges))
    np.testing.assert_allclose(np.asarray(problem.gamma.diag), blocks, rtol=1e-12, atol=1e-14)
    d = blocks.shape[-1] - 1
    shape = (part.max_poses, d, d + 1)
    X, grad = r["state0"].X, r["state0"].grad
    basis = jnp.eye(int(np.prod(shape))).reshape((-1,) + shape)

    @eqx.filter_jit
    def dense(pre, y, g):
        """M^-1 at the pose y (its Weingarten term from the gradient g) on tangent inputs, and the
        tangent projection, as dense matrices (stacked layout, one robot)."""
        Y = to_soa(y)
        W = sym0(soa_bmm(soa_T(Y[:, 1:]), to_soa(g)[:, 1:]))
        op = pre.at(Y, W)
        M = jax.vmap(lambda B: from_soa(op(to_soa(tangent_projection(y, B)))).reshape(-1))(basis).T
        T = jax.vmap(lambda B: tangent_projection(y, B).reshape(-1))(basis).T
        return M, T

    for kind in ("two-level", "block-jacobi"):
        pre = _precond(problem, SubproblemConfig(preconditioner=kind))
        for a in range(part.num_robots):
            M, T = (np.asarray(x) for x in dense(jax.tree.map(lambda x: x[a], pre), X[a], grad[a]))
            w, U = np.linalg.eigh(T)
            Q = U[:, w > 0.5]
            Mt = Q.T @ M @ Q
            np.testing.assert_allclose(Mt, Mt.T, atol=1e-10 * np.abs(Mt).max(), err_msg=kind)
            assert np.linalg.eigvalsh(0.5 * (Mt + Mt.T)).min() > 0, kind


def test_mm_monotone(runs, problem2d):
    """Proposition 2 (1): F(X^k) non-increasing (records.f = 2F after each iteration)."""
    r = runs.get("mm")
    f = np.concatenate([[problem2d["f0"]], r["f"]])
    np.testing.assert_allclose(2 * float(jnp.sum(r["state0"].share)), problem2d["f0"], rtol=1e-12)
    assert np.all(np.diff(f) <= 1e-10 * f[:-1]), np.diff(f).max()
    assert f[-1] < 0.01 * f[0]
    assert not r["restarted"].any()


def test_mm_each_robot_majorizer_decreases(runs):
    """G^α(X^{α,k+1} | X^k) − Ḡ^α(k) ≤ 0 for every robot, at the iterations ending each chunk."""
    r = runs.get("mm")
    for st in r["states"][:3]:
        dec = np.asarray(_decreases(r["problem"], st.X, st.X_prev, st.grad_prev))
        assert np.all(dec <= 1e-12 * np.maximum(1.0, np.asarray(st.share))), dec


def test_mm_gradient_vanishes(runs, problem2d):
    """Proposition 2 (6): grad F → 0 (ξ > 0): 1000 MM iterations shrink ‖grad F‖ by ≥ 1e4."""
    r = runs.get("mm")
    g0 = float(_grad_norm(problem2d["graph"], problem2d["X0"]))
    gn = r["grad_norm"]
    assert len(gn) >= 500
    assert gn[-1] <= 1e-4 * gn[0], (gn[0], gn[-1])
    assert gn[-1] <= 1e-4 * g0
    # The record is the Riemannian gradient norm of F at the final iterate.
    part = r["part"]
    X = part.gather(unstack(r["state"].X))
    np.testing.assert_allclose(gn[-1], float(_grad_norm(problem2d["graph"], X)), rtol=1e-8)
    np.testing.assert_allclose(r["f"][-1], float(_cost(problem2d["graph"], X)), rtol=1e-12)


def test_amm_paper_restart_monotone(runs, problem2d):
    """Proposition 3 (1): AMM with Algorithm 2's restart test keeps F non-increasing."""
    r = runs.get("amm_paper")
    f = np.concatenate([[problem2d["f0"]], r["f"]])
    assert np.all(np.diff(f) <= 1e-10 * f[:-1]), np.diff(f).max()
    assert f[-1] < 0.01 * f[0]


def test_amm_adaptive_bounded_and_faster(runs, problem2d):
    """Adaptive restart: F(X^{k+1}) ≤ F(X^k) + Σ_α slack_k^α, so f ≤ f(X^0) + 2 Σ slack (bounded);
    and it ends below MM after the same number of iterations."""
    r = runs.get("amm_adaptive")
    cfg, st0 = r["config"], r["state0"]
    f = np.concatenate([[problem2d["f0"]], r["f"]])
    k = np.arange(len(r["f"]))
    slack = float(jnp.sum(st0.slack)) * (1.0 - cfg.slack_decay) ** k  # Σ_α slack_k^α (F units)
    assert float(jnp.sum(st0.slack)) > 0
    assert np.all(np.diff(f) <= 2 * slack + 1e-10 * f[:-1])
    assert np.all(f[1:] <= f[0] + 2 * np.cumsum(slack) + 1e-10 * f[0])
    mm = runs.get("mm")["f"][: len(r["f"])]
    assert r["f"][-1] < mm[-1], (r["f"][-1], mm[-1])


def test_amm_average_bounded_and_faster(runs, problem2d):
    """Moving-average restart: its hard test includes the vanishing slack, so the same bound as the
    adaptive rule holds; it still ends below MM."""
    r = runs.get("amm_average")
    cfg, st0 = r["config"], r["state0"]
    f = np.concatenate([[problem2d["f0"]], r["f"]])
    k = np.arange(len(r["f"]))
    slack = float(jnp.sum(st0.slack)) * (1.0 - cfg.slack_decay) ** k
    assert np.all(np.diff(f) <= 2 * slack + 1e-10 * f[:-1])
    mm = runs.get("mm")["f"][: len(r["f"])]
    assert r["f"][-1] < mm[-1], (r["f"][-1], mm[-1])
    # the averages track the shares: after the run the fast one is closer to the current share
    st = r["state"]
    assert np.all(np.abs(st.share_fast - st.share) <= np.abs(st.share_slow - st.share) + 1e-12)


def _spread_weights_graph():
    """A 40-pose planar grid walk whose measurement weights (kappa and tau of every edge) spread over
    nine orders of magnitude, 1e-3 to 1e6: the kind of graph on which AMM's adaptive slack let F climb
    to 2.5x its start (benchmarks/restart_rules.md)."""
    import mmpgo_jax as mm

    g = mm.grid_2d_dataset(6, grid=6, num_poses=40, loop_closure_prob=0.3).graph
    rng = np.random.default_rng(6)
    kappa, tau = (jnp.asarray(10.0 ** rng.uniform(-3, 6, g.num_edges)) for _ in range(2))
    return PoseGraph(g.i, g.j, g.R, g.t, kappa, tau, g.num_poses)


def test_momentum_guard_restarts_every_robot_when_f_gives_back_progress(problem2d):
    """MMConfig.rise_limit, the mechanism: a state with strong momentum (s large, X^{k-1} far from
    X^k, a slack that lets any step through) whose run had brought F down to 1 % of its start takes a
    step that ends far above that; the guard then sets every robot's s to 1, halves the slack and
    counts a reset, where with ``rise_limit=inf`` the momentum and the slack go on as before."""
    from mmpgo_jax._mm.outer import step

    part = partition(problem2d["graph"], problem2d["robots"])
    X0 = _scatter(part, problem2d["X0"])
    out = {}
    for lim in (MMConfig().rise_limit, float("inf")):
        cfg = MMConfig(rise_limit=lim)
        problem = MMProblem.build(part, config=cfg, poses=X0)
        st = _init(problem, X0, cfg)
        far = st.X.at[..., 0].add(50.0)  # X^{k-1}: every translation 50 away
        # as if the run had brought F down to 1 % of its start: any F above 1.1 % gives back too much
        F0 = st.f_start
        st = eqx.tree_at(lambda s: (s.X_prev, s.s, s.slack, s.f_start, s.f_best), st,
                         (far, jnp.full_like(st.s, 40.0), 1e12 * jnp.ones_like(st.slack), 0.02 * F0, 0.01 * F0))
        new, rec = jax.jit(step, static_argnums=1)(problem, cfg, st)
        out[lim] = (st, new, float(rec.f))
    (st, guarded, f), (_, free, f_free) = out.values()
    assert f == f_free > 2 * 0.011 * float(F0)  # the same step either way (f = 2F), far above that
    np.testing.assert_array_equal(np.asarray(guarded.s), 1.0)
    np.testing.assert_allclose(np.asarray(guarded.slack), 0.5 * np.asarray(st.slack))
    assert int(guarded.resets) == 1 and int(free.resets) == 0
    assert np.all(np.asarray(free.s) > 1.0)
    np.testing.assert_allclose(np.asarray(free.slack), (1.0 - MMConfig().slack_decay) * np.asarray(st.slack))


def test_momentum_guard_on_spread_weights():
    """On a graph whose weights spread over nine orders of magnitude (where, without the guard and with
    XLA's default code generation, the adaptive slack let F climb to 2.5x its start in a run of this
    length, benchmarks/restart_rules.md; the tests' quicker code generation rounds differently) the
    default AMM never rises above its start and ends at the optimum (1 robot: the majorizer is F
    itself, so only the momentum can raise F)."""
    import mmpgo_jax as mm

    g = _spread_weights_graph()
    guarded = mm.solve(g, 1, iterations=300, stop_when_stalled=False)
    f = np.asarray(guarded.history.f)
    assert f.max() <= f[0] * (1 + 1e-12)
    f_opt = mm.centralized_optimum(g).f
    assert guarded.f <= f_opt * (1 + 1e-3), (guarded.f, f_opt)


def test_momentum_guard_is_inert_while_f_falls():
    """On a graph of ordinary weights the guard never acts: the run is the unguarded one bit for bit."""
    import mmpgo_jax as mm

    g = mm.grid_2d_dataset(1, grid=6, num_poses=60).graph
    runs_ = [mm.solve(g, 4, solver=mm.AMM(rise_limit=lim), iterations=200, stop_when_stalled=False)
             for lim in (MMConfig().rise_limit, float("inf"))]
    assert [r.stats["momentum_resets"] for r in runs_] == [0, 0]
    np.testing.assert_array_equal(np.asarray(runs_[0].history.f), np.asarray(runs_[1].history.f))


@pytest.mark.slow  # keeps the default run under 15 minutes
def test_amm_average_hard_and_soft_restarts(runs):
    """Hard restart (value above the slow average) takes the MM step; a soft restart keeps the
    momentum step Z but resets s to 1 after ``soft_restart_hits`` consecutive hits."""
    from mmpgo_jax._mm.outer import step

    r = runs.get("amm_average")
    cfg, problem = r["config"], r["problem"]
    st, _ = run(problem, cfg, r["state0"], 5)  # some momentum built up (s > 1)
    assert np.all(np.asarray(st.s) > 1.0)
    A = st.s.shape[0]
    # Hard: slow average far below every share -> every robot falls back to the MM step.
    hard = eqx.tree_at(lambda t: t.share_slow, st, st.share - 1e6)
    new, rec = step(problem, cfg, hard)
    assert np.all(np.asarray(rec.restarted))
    np.testing.assert_allclose(np.asarray(new.X), np.asarray(_mm_update(problem, cfg, st.X, st.grad)), atol=1e-12)
    # Soft: slow average far above (no hard restart), fast average far below, one hit from the limit.
    soft = eqx.tree_at(lambda t: (t.share_slow, t.share_fast, t.soft_hits), st,
                       (st.share + 1e6, st.share - 1e6, jnp.full(A, cfg.soft_restart_hits - 1, jnp.int32)))
    new_soft, rec_soft = step(problem, cfg, soft)
    plain = eqx.tree_at(lambda t: t.share_slow, st, st.share + 1e6)
    new_plain, rec_plain = step(problem, cfg, eqx.tree_at(lambda t: t.share_fast, plain, st.share + 1e6))
    assert not np.any(np.asarray(rec_soft.restarted)) and not np.any(np.asarray(rec_plain.restarted))
    np.testing.assert_array_equal(np.asarray(new_soft.s), np.ones(A))
    assert np.all(np.asarray(new_plain.s) > 1.0) and np.all(np.asarray(new_plain.soft_hits) == 0)
    np.testing.assert_allclose(np.asarray(new_soft.X), np.asarray(new_plain.X), atol=1e-12)  # Z kept
    np.testing.assert_array_equal(np.asarray(new_soft.soft_hits), np.zeros(A))


def test_chunked_run_matches_and_does_not_recompile(runs, caplog):
    """run(.., 50) twice from the returned state equals run(.., 100); the second chunk reuses the
    compiled scan."""
    r = runs.get("mm")
    problem, cfg, st0 = r["problem"], r["config"], r["state0"]
    st, rec1 = run(problem, cfg, st0, 50)
    jax.block_until_ready(rec1)
    with caplog.at_level(logging.WARNING), jax.log_compiles(True):
        caplog.clear()
        st, rec2 = run(problem, cfg, st, 50)
        jax.block_until_ready(rec2)
        compiles = [rec.getMessage() for rec in caplog.records if "Compiling" in rec.getMessage()]
    assert compiles == []
    f = np.concatenate([np.asarray(rec1.f), np.asarray(rec2.f)])
    np.testing.assert_allclose(f, r["f"][:100], rtol=1e-12)
    np.testing.assert_allclose(np.asarray(st.X), np.asarray(r["states"][0].X), rtol=0, atol=1e-12)
    assert int(st.iteration) == 100


def test_padding_invariance(runs, problem2d):
    """Extra pose slots, edge slots and an extra (empty) robot change nothing."""
    r = runs.get("mm")
    part = r["part"]
    cfg = r["config"]
    _, problem, st0 = setup_mm(
        problem2d["graph"],
        problem2d["X0"],
        problem2d["robots"],
        cfg,
        min_max_poses=part.max_poses + 5,
        min_max_edges=part.max_edges + 9,
        num_robots=part.num_robots + 1,
    )
    assert problem.partition.num_robots == NUM_ROBOTS + 1
    padded = run_chunks(problem, cfg, st0, 1)
    np.testing.assert_allclose(padded["f"], r["f"][:CHUNK], rtol=1e-10)
    np.testing.assert_allclose(padded["grad_norm"], r["grad_norm"][:CHUNK], rtol=1e-8)


def test_centralized_and_one_pose_per_robot(runs, problem2d):
    """A = 1 (centralized, Γ̃ = M̃ + ξI) reaches a critical point and a lower-or-equal f than the
    distributed runs; A = n (one pose per robot) is monotone and converges too."""
    c = runs.get("extremes")
    one, alln = c["A=1"], c["A=n"]
    four = runs.get("mm")
    k = len(one["f"])
    assert one["grad_norm"][-1] <= 1e-8
    assert one["f"][-1] <= four["f"][k - 1] * (1 + 1e-12)
    assert one["f"][-1] <= alln["f"][-1] * (1 + 1e-12)
    for out in (one, alln):
        f = np.concatenate([[problem2d["f0"]], out["f"]])
        assert np.all(np.diff(f) <= 1e-10 * f[:-1]), np.diff(f).max()
    assert alln["f"][-1] <= 1.01 * one["f"][-1]
    assert alln["grad_norm"][-1] <= 1e-3 * alln["grad_norm"][0]


def test_padded_partitions_share_problem_shapes(problem2d):
    """Partitions padded to one common shape (min_max_*, min_couplings: batching several
    partitions) give MMProblems of one shape, so run() compiles once for all of them."""
    g = problem2d["graph"]
    pad = COMMON_PADDING(g)
    mc = pad.pop("min_couplings")
    shapes = set()
    for robots in (np.zeros(N, int), problem2d["robots"], np.arange(N)):
        problem = MMProblem.build(partition(g, robots, **pad), XI, min_couplings=mc)
        shapes.add(tuple((x.shape, x.dtype) for x in jax.tree.leaves(problem)))
    assert len(shapes) == 1, shapes


def test_xi_zero_with_padding_slots(subproblem_setup):
    """ξ = 0 is allowed (Prop. 2 (1)-(4)); a robot with padding slots must still decrease G^α, and
    the result must match ξ = 1e-15 (which differs from ξ = 0 by a negligible proximal term)."""
    s = subproblem_setup
    part = s["part"]
    mask = np.asarray(part.pose_mask)
    assert (~mask).any(axis=1).any()  # some robot has padding slots
    X, grad = stack(s["X"]), stack(s["grad"])
    out = {}
    for xi in (0.0, 1e-15):
        problem = MMProblem.build(part, xi, poses=s["X"])
        # solved to convergence: a stopping decision taken at a slightly different point would make
        # the two results differ by the last step, not by xi
        out[xi] = _solve_all(problem.gamma, _precond(problem, CONVERGE), X, X, grad, CONVERGE)
    Y0, v0, _ = out[0.0]
    Y1, v1, _ = out[1e-15]
    assert np.all(np.asarray(v1) < 0)
    np.testing.assert_allclose(np.asarray(v0), np.asarray(v1), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(Y0), np.asarray(Y1), atol=1e-8)


# ----------------------------------------------------------------------------- configs: traced numbers, checks


def _compiles_of_run(fn):
    """(fn's result, number of 'Compiling run' log lines while it ran)."""
    import logging as _logging

    class _Handler(_logging.Handler):
        def __init__(self):
            super().__init__(_logging.DEBUG)
            self.lines = []

        def emit(self, record):
            self.lines.append(record.getMessage())

    handler = _Handler()
    logger = _logging.getLogger("jax")
    logger.addHandler(handler)
    try:
        with jax.log_compiles(True):
            out = fn()
    finally:
        logger.removeHandler(handler)
    return out, sum(1 for m in handler.lines if m.startswith("Compiling") and "jit(run)" in m)


def test_traced_config_numbers_compile_once_and_match_static(problem2d):
    """xi, cg_tolerance, slack_decay and the other restart constants are traced: runs that differ
    only in them share one compilation of run(), and each gives exactly what a compilation with
    the values baked in as constants (the former static fields) gives."""
    from mmpgo_jax._mm.outer import _run

    base = MMConfig(method="amm", restart="average", subproblem=SubproblemConfig(cg_iterations=5))
    variants = {
        "base": base,
        "xi": eqx.tree_at(lambda c: c.xi, base, 0.05),
        "cg_tolerance": eqx.tree_at(lambda c: c.subproblem.cg_tolerance, base, 0.3),
        "slack_decay": eqx.tree_at(lambda c: c.slack_decay, base, 1.0),
        "restart constants": eqx.tree_at(lambda c: (c.slack_scale, c.average_rates, c.soft_restart_hits), base,
                                         (0.01, (0.3, 0.6), 2)),
    }
    part = partition(problem2d["graph"], problem2d["robots"])
    X0 = _scatter(part, problem2d["X0"])
    static_run = eqx.filter_jit(_run)  # Python floats of the config are compile-time constants here
    length = 30
    results, compiles = {}, []
    for name, cfg in variants.items():
        problem = MMProblem.build(part, config=cfg, poses=X0)
        assert float(problem.xi) == cfg.xi
        st0 = _init(problem, X0, cfg)
        (st, rec), n = _compiles_of_run(lambda p=problem, c=cfg, s=st0: jax.block_until_ready(run(p, c, s, length)))
        compiles.append(n)
        st_ref, rec_ref = static_run(problem, cfg, st0, length)
        np.testing.assert_allclose(np.asarray(rec.f), np.asarray(rec_ref.f), rtol=1e-12, atol=0, err_msg=name)
        np.testing.assert_allclose(np.asarray(st.X), np.asarray(st_ref.X), rtol=0, atol=1e-12, err_msg=name)
        results[name] = np.asarray(rec.f)
    assert compiles[0] <= 1 and compiles[1:] == [0] * (len(variants) - 1), compiles
    for name in variants:  # every traced number is read: each changes the run
        if name != "base":
            assert not np.allclose(results[name], results["base"], rtol=1e-10, atol=0), name


@pytest.mark.parametrize(("cls", "kwargs", "message"), [
    (MMConfig, dict(method="gd"), r"MMConfig\.method.*'mm' or 'amm'"),
    (MMConfig, dict(restart="never"), r"MMConfig\.restart.*'paper' or 'adaptive' or 'average'"),
    (MMConfig, dict(xi=-1e-3), r"MMConfig\.xi must be a finite number >= 0"),
    (MMConfig, dict(xi=float("inf")), r"MMConfig\.xi must be a finite number >= 0"),
    (MMConfig, dict(slack_scale=-1.0), r"MMConfig\.slack_scale must be a finite number >= 0"),
    (MMConfig, dict(slack_decay=1.5), r"MMConfig\.slack_decay must be a finite number in \[0, 1\]"),
    (MMConfig, dict(average_rates=(0.1, 2.0)), r"MMConfig\.average_rates\[1\] must be a finite number in \[0, 1\]"),
    (MMConfig, dict(average_rates=(0.1,)), r"MMConfig\.average_rates must be a pair"),
    (MMConfig, dict(soft_restart_hits=0), r"MMConfig\.soft_restart_hits must be an integer >= 1"),
    (MMConfig, dict(rise_limit=-0.1), r"MMConfig\.rise_limit must be a finite number >= 0"),
    (MMConfig, dict(soft_restart_hits=2.5), r"MMConfig\.soft_restart_hits must be an integer >= 1"),
    (SubproblemConfig, dict(preconditioner="ilu"), r"SubproblemConfig\.preconditioner.*'two-level' or 'block-jacobi'"),
    (SubproblemConfig, dict(cg_tolerance=0.0), r"SubproblemConfig\.cg_tolerance must be a finite number in \(0, 1\]"),
    (SubproblemConfig, dict(cg_tolerance=1.5), r"SubproblemConfig\.cg_tolerance must be a finite number in \(0, 1\]"),
    (SubproblemConfig, dict(cg_iterations=0), r"SubproblemConfig\.cg_iterations must be an integer >= 1"),
    (SubproblemConfig, dict(max_steps=0), r"SubproblemConfig\.max_steps must be an integer >= 1"),
    (SubproblemConfig, dict(gradient_tolerance=-0.1), r"SubproblemConfig\.gradient_tolerance must be a finite number in \[0, 1\)"),
    # a tolerance of 1 holds at the start: the robot would never move
    (SubproblemConfig, dict(gradient_tolerance=1.0), r"SubproblemConfig\.gradient_tolerance must be a finite number in \[0, 1\)"),
    (SubproblemConfig, dict(cg_iterations=True), r"SubproblemConfig\.cg_iterations must be an integer >= 1"),
])
def test_config_fields_checked_when_built(cls, kwargs, message):
    with pytest.raises(ValueError, match=message):
        cls(**kwargs)


def test_config_checks_skip_traced_values():
    """Under vmap / jit the traced numbers cannot be checked; building a config there works (a batch
    of configs), and concrete arrays are checked elementwise."""
    xs = jnp.asarray([0.0, 1e-3, 0.5])
    out = jax.vmap(lambda x: MMConfig(xi=x, slack_decay=x, subproblem=SubproblemConfig(cg_tolerance=x + 0.1)).xi)(xs)
    np.testing.assert_array_equal(np.asarray(out), np.asarray(xs))
    assert float(jax.jit(lambda t: SubproblemConfig(cg_tolerance=t).cg_tolerance)(0.25)) == 0.25
    MMConfig(xi=np.asarray([0.0, 1.0]))
    with pytest.raises(ValueError, match=r"MMConfig\.xi"):
        MMConfig(xi=np.asarray([0.0, -1.0]))
    assert MMConfig(xi=None).xi is None


def test_xi_of_config_and_problem_cannot_disagree(problem2d):
    """MMProblem.build takes xi from the config; init_state / run refuse a config whose xi differs
    from the problem's; xi=None defers to the problem."""
    part = partition(problem2d["graph"], problem2d["robots"])
    X0 = _scatter(part, problem2d["X0"])
    cfg = MMConfig(method="mm", xi=0.25)
    problem = MMProblem.build(part, config=cfg, poses=X0)
    assert float(problem.xi) == 0.25
    assert float(MMProblem.build(part, 0.25, config=cfg, poses=X0).xi) == 0.25  # both given, equal: fine
    assert float(MMProblem.build(part).xi) == MMConfig().xi  # the default
    with pytest.raises(ValueError, match=r"differs from config\.xi"):
        MMProblem.build(part, 0.5, config=cfg, poses=X0)
    other = MMConfig(method="mm", xi=1e-3)
    with pytest.raises(ValueError, match=r"MMConfig\.xi = 0\.001 differs from the xi the MMProblem was built with"):
        init_state(problem, X0, other)
    st = init_state(problem, X0, cfg)
    with pytest.raises(ValueError, match=r"MMConfig\.xi = 0\.001 differs"):
        run(problem, other, st, 2)
    with pytest.raises(ValueError, match=r"MMConfig\.xi = 0\.001 differs"):
        run.lower(problem, other, st, 2)
    deferred = MMConfig(method="mm", xi=None)
    a, _ = run(problem, deferred, init_state(problem, X0), 2)
    b, _ = run(problem, cfg, st, 2)
    np.testing.assert_array_equal(np.asarray(a.X), np.asarray(b.X))


def _leaves_run_reads(problem, config, state, length=3):
    """Which leaves of ``problem`` run() reads: dead-code elimination of its jaxpr."""
    from jax._src.interpreters import partial_eval as pe

    leaves, treedef = jax.tree.flatten(problem)
    closed = jax.make_jaxpr(lambda ls: run(jax.tree.unflatten(treedef, ls), config, state, length))(leaves)
    _, used = pe.dce_jaxpr(closed.jaxpr, [True] * len(closed.jaxpr.outvars))
    paths = [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_flatten_with_path(problem)[0]]
    return dict(zip(paths, used[: len(leaves)], strict=True))


def test_mm_problem_holds_only_what_run_reads(problem2d):
    """With a config, MMProblem.build keeps only what that config's run() reads: no stacked-layout
    copy of Γ, and the coarse level only for "two-level". (The partition's pose maps are for
    scatter/gather by callers, and xi is the 0-d record of Γ's ξ.)"""
    part = partition(problem2d["graph"], problem2d["robots"])
    X0 = _scatter(part, problem2d["X0"])
    host_side = {".partition.pose_index", ".partition.pose_mask", ".partition.robot_of_pose",
                 ".partition.slot_of_pose", ".xi"}
    sizes = {}
    for kind in ("two-level", "block-jacobi"):
        cfg = MMConfig(method="amm", subproblem=SubproblemConfig(preconditioner=kind))
        problem = MMProblem.build(part, config=cfg, poses=X0)
        assert problem.newton.has_coarse == (kind == "two-level")
        reads = _leaves_run_reads(problem, cfg, init_state(problem, X0, cfg))
        unread = {p for p, used in reads.items() if not used}
        assert unread == host_side, unread
        sizes[kind] = sum(x.nbytes for x in jax.tree.leaves(problem))
    assert sizes["two-level"] > sizes["block-jacobi"]
    # without a config: the two-level preconditioner when the start poses are given
    assert MMProblem.build(part).preconditioners == ("block-jacobi",)
    both = MMProblem.build(part, poses=X0)
    assert both.preconditioners == ("two-level", "block-jacobi")
    # the stacked-layout view is an exact transposition of what is stored
    np.testing.assert_array_equal(np.asarray(both.gamma.diag), np.moveaxis(np.asarray(both.gamma_soa.diag), -1, -3))
    bj_config = MMConfig(subproblem=SubproblemConfig(preconditioner="block-jacobi"))
    bj = MMProblem.build(part, config=bj_config)
    with pytest.raises(ValueError, match=r"asks for 'two-level'.*poses=partition\.scatter\(X0\)"):
        run(bj, MMConfig(), init_state(bj, X0), 2)
    with pytest.raises(ValueError, match="two-level preconditioner is made of the start poses"):
        MMProblem.build(part, config=MMConfig())
