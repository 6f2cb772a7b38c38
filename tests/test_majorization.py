"""The majorization of distributed PGO (paper §IV-V, Prop. 1, Appendix A; docs/conventions.md §3).

References are independent of the library's per-robot code: the dense data matrix M̃ of Eq. (4)
(``data_matrix``), dense linear algebra, and a per-edge Python loop over Eq. (10) with the
midpoints of Eq. (7) and Eq. (A.3). The library's Γ^α is turned into a dense matrix by applying
``apply_gamma`` to every unit vector of the robot's ambient space.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mmpgo_jax import (
    PoseGraph,
    Poses,
    data_matrix,
    edge_costs,
    matrix_to_poses,
    objective,
    poses_to_matrix,
)
from mmpgo_jax._core.geometry import random_rotations, rotation_2d
from mmpgo_jax._core.partition import partition
from mmpgo_jax._mm.majorization import (
    apply_gamma,
    build_gamma_operator,
    gamma_diagonal_blocks,
    gradient_and_share,
    majorizer_decrease,
    stack,
    unstack,
)

N = 12  # poses per test graph
LOOPS = 8  # loop closures per test graph
XIS = (0.0, 0.25)


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
    """Random robot-of-pose array using every robot 0..A-1."""
    r = rng.integers(0, A, n)
    r[rng.permutation(n)[:A]] = np.arange(A)
    return r


def random_ambient(rng, like: Poses, scale) -> Poses:
    """like + scale * Gaussian, rotations included (NOT on the manifold)."""
    return Poses(
        like.R + scale * jnp.asarray(rng.standard_normal(like.R.shape)),
        like.t + scale * jnp.asarray(rng.standard_normal(like.t.shape)),
    )


def partitions_for(graph, seed):
    """Several partitions of ``graph``, all padded to one common shape (so jitted code compiles once),
    plus one unpadded random partition."""
    n, m = graph.num_poses, graph.num_edges
    rng = np.random.default_rng(seed)
    robot_arrays = {
        "A=1": np.zeros(n, dtype=int),
        "A=3": random_robots(rng, n, 3),
        "A=5": random_robots(rng, n, 5),
        "A=n": rng.permutation(n),
    }
    out = {
        name: (r, partition(graph, r, min_max_poses=n, min_max_edges=m, num_robots=n))
        for name, r in robot_arrays.items()
    }
    r = random_robots(rng, n, 4)
    out["A=4 unpadded"] = (r, partition(graph, r))
    return out


# ----------------------------------------------------------------------------- dense Γ


def _local_to_matrix(V: Poses):
    """Per-robot padded poses (n_max, d, d), (n_max, d) -> d x (d+1) n_max, layout [t_1..t_n R_1..R_n]."""
    n_max, d = V.t.shape
    return jnp.concatenate([V.t.T, jnp.transpose(V.R, (1, 0, 2)).reshape(d, d * n_max)], axis=1)


def _local_from_matrix(X, n_max, d) -> Poses:
    return Poses(jnp.transpose(X[:, n_max:].reshape(d, n_max, d), (1, 0, 2)), X[:, :n_max].T)


@eqx.filter_jit
def _gamma_operator(edges, xi, n_max: int, d: int):
    """The linear map vec(X) -> vec(Γ^α applied to X) for every robot, (A, D, D), D = d (d+1) n_max.

    Row-major vec of the d x (d+1) n_max matrix layout. Column k = image of unit vector k.
    """
    D = d * (d + 1) * n_max
    basis = jnp.eye(D).reshape(D, d, (d + 1) * n_max)

    def one_robot(e):
        def apply(B):
            return _local_to_matrix(apply_gamma(e, xi, _local_from_matrix(B, n_max, d))).reshape(-1)

        return jax.vmap(apply)(basis).T

    return jax.vmap(one_robot)(edges)


@eqx.filter_jit
def _gamma_operator_blocksparse(gamma, n_max: int, d: int):
    """As :func:`_gamma_operator`, for the block-sparse GammaOperator (stacked layout) the solver uses."""
    D = d * (d + 1) * n_max
    basis = jnp.eye(D).reshape(D, d, (d + 1) * n_max)

    def one_robot(G):
        def apply(B):
            return _local_to_matrix(unstack(G(stack(_local_from_matrix(B, n_max, d))))).reshape(-1)

        return jax.vmap(apply)(basis).T

    return jax.vmap(one_robot)(gamma)


def dense_gammas(part, xi):
    """Dense Γ^α ((d+1) n_max square, local layout [t slots, R slots]) for every robot.

    Checks on the way that the operator is X -> X Γ^α, i.e. I_d ⊗ Γ^α in row-major vec form.
    """
    d = part.edges.t.shape[-1]
    n_max = part.max_poses
    L = np.asarray(_gamma_operator(part.edges, jnp.asarray(xi), n_max, d))
    k = (d + 1) * n_max
    gammas = []
    for La in L:
        G = La[:k, :k].T  # row 0 of X e_l-image: X Γ with X = e_0 e_l^T gives row 0 = Γ[l, :]
        np.testing.assert_allclose(La, np.kron(np.eye(d), G.T), rtol=0, atol=1e-12 * max(1.0, np.abs(G).max()))
        gammas.append(G)
    return np.stack(gammas)


def local_indices(n_max, d, slot):
    """Local-layout indices of slot ``slot``: its translation column, then its d rotation columns."""
    return np.concatenate([[slot], n_max + d * slot + np.arange(d)])


def global_indices(n, d, pose):
    return np.concatenate([[pose], n + d * pose + np.arange(d)])


def assemble_global(part, gammas, n, d):
    """Block-diagonal Γ̃ over robots in the paper layout X = [t_1..t_n R_1..R_n]."""
    n_max = part.max_poses
    pose_index = np.asarray(part.pose_index)
    mask = np.asarray(part.pose_mask)
    Gt = np.zeros(((d + 1) * n, (d + 1) * n))
    for a in range(part.num_robots):
        slots = np.flatnonzero(mask[a])
        if len(slots) == 0:
            continue
        li = np.concatenate([local_indices(n_max, d, s) for s in slots])
        gi = np.concatenate([global_indices(n, d, pose_index[a, s]) for s in slots])
        Gt[np.ix_(gi, gi)] += gammas[a][np.ix_(li, li)]
    return Gt


# ----------------------------------------------------------------------------- library G


@eqx.filter_jit
def _diag_blocks(edges, xi, n_max: int):
    return jax.vmap(lambda e: gamma_diagonal_blocks(e, xi, n_max))(edges)


_objective = jax.jit(objective)


def _library_G(part, xi, X: Poses, Xk: Poses):
    """Per robot: (G^α(X^α | X^k), Ḡ^α(k), grad_α F(X^k)) from the library (X, X^k global)."""
    return _library_G_jit(part, jnp.asarray(xi), X, Xk)


@eqx.filter_jit
def _library_G_jit(part, xi, X: Poses, Xk: Poses):
    n_max = part.max_poses
    Xp, Xkp = part.scatter(X), part.scatter(Xk)
    grad, share, _ = jax.vmap(lambda e: gradient_and_share(e, stack(Xkp), n_max))(part.edges)
    grad = unstack(grad)
    dec = jax.vmap(lambda e, D, g: majorizer_decrease(e, xi, D, g))(part.edges, Xp - Xkp, grad)
    return dec + share, share, grad


# ----------------------------------------------------------------------------- Eq. (10) by hand


def eq10_loop(graph, robot_of_pose, X: Poses, Xk: Poses, num_robots, literal_eq8=False):
    """E^α(X^α | X^k) of Eq. (10) for every robot, by a per-edge loop (numpy).

    P = ½ R_i^k R̃ + ½ R_j^k (Eq. (7)); p = ½ (R_i^k t̃ + t_i^k) + ½ t_j^k (Eq. (A.3); the printed
    Eq. (8) drops t_i^k, which ``literal_eq8=True`` reproduces).
    """
    I, J = np.asarray(graph.i), np.asarray(graph.j)
    Rm, tm = np.asarray(graph.R), np.asarray(graph.t)
    kap, tau = np.asarray(graph.kappa), np.asarray(graph.tau)
    R, t = np.asarray(X.R), np.asarray(X.t)
    Rk, tk = np.asarray(Xk.R), np.asarray(Xk.t)
    E = np.zeros(num_robots)
    sq = lambda v: float(np.sum(v * v))
    for e in range(len(I)):
        i, j = I[e], J[e]
        a, b = robot_of_pose[i], robot_of_pose[j]
        if a == b:
            E[a] += 0.5 * (kap[e] * sq(R[i] @ Rm[e] - R[j]) + tau[e] * sq(R[i] @ tm[e] + t[i] - t[j]))
        else:
            P = 0.5 * Rk[i] @ Rm[e] + 0.5 * Rk[j]
            if literal_eq8:
                p = 0.5 * Rk[i] @ tm[e] + 0.5 * tk[j]
            else:
                p = 0.5 * (Rk[i] @ tm[e] + tk[i]) + 0.5 * tk[j]
            E[a] += kap[e] * sq(R[i] @ Rm[e] - P) + tau[e] * sq(R[i] @ tm[e] + t[i] - p)
            E[b] += kap[e] * sq(R[j] - P) + tau[e] * sq(t[j] - p)
    return E


# ----------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module", params=[2, 3], ids=["2d", "3d"])
def setup(request):
    d = request.param
    graph, X0 = make_problem(10 + d, N, d, LOOPS)
    parts = partitions_for(graph, 100 + d)
    M = data_matrix(graph).toarray()
    gammas = {(name, xi): dense_gammas(p, xi) for name, (_, p) in parts.items() for xi in XIS}
    return dict(d=d, graph=graph, X0=X0, parts=parts, M=M, gammas=gammas)


def _scale(M):
    return np.abs(np.linalg.eigvalsh(M)).max()


# ----------------------------------------------------------------------------- tests


def test_data_matrix_reference(setup):
    """The reference itself: F(X) = ½ tr(X M̃ Xᵀ) at random ambient X."""
    g, M = setup["graph"], setup["M"]
    rng = np.random.default_rng(0)
    for X in (setup["X0"], random_ambient(rng, setup["X0"], 1.0)):
        Xm = poses_to_matrix(X)
        np.testing.assert_allclose(0.5 * np.trace(Xm @ M @ Xm.T), float(_objective(g, X)), rtol=1e-12)


@pytest.mark.parametrize("xi", XIS)
def test_gamma_symmetric_and_dominates_data_matrix(setup, xi):
    """Γ^α symmetric PSD; padding slots decoupled (ξ I); Γ̃ − M̃ ⪰ 0 (Prop. 1, Eq. (12))."""
    d, M = setup["d"], setup["M"]
    n = setup["graph"].num_poses
    scale = _scale(M)
    for name, (_, part) in setup["parts"].items():
        gammas = setup["gammas"][(name, xi)]
        n_max = part.max_poses
        mask = np.asarray(part.pose_mask)
        for a, G in enumerate(gammas):
            np.testing.assert_allclose(G, G.T, rtol=0, atol=1e-12 * scale, err_msg=name)
            assert np.linalg.eigvalsh(G).min() >= -1e-9 * scale, name
            pad = np.concatenate([local_indices(n_max, d, s) for s in np.flatnonzero(~mask[a])] + [np.zeros(0, int)])
            real = np.setdiff1d(np.arange(G.shape[0]), pad)
            np.testing.assert_allclose(G[np.ix_(pad, pad)], xi * np.eye(len(pad)), atol=1e-14, err_msg=name)
            np.testing.assert_allclose(G[np.ix_(pad, real)], 0.0, atol=1e-14, err_msg=name)
        Gt = assemble_global(part, gammas, n, d)
        lam = np.linalg.eigvalsh(Gt - M)
        assert lam.min() >= -1e-9 * scale, (name, lam.min())
        if xi > 0:
            assert lam.min() >= xi * (1 - 1e-9), (name, lam.min())
        if name == "A=1":
            # One robot: no inter-robot edge, Γ̃ = M̃ + ξ I exactly.
            np.testing.assert_allclose(Gt, M + xi * np.eye(len(M)), atol=1e-12 * scale)


@pytest.mark.parametrize("xi", XIS)
def test_block_sparse_gamma_operator_matches_dense(setup, xi):
    """The solver's block-sparse Γ^α (build_gamma_operator: diagonal, band, loop-closure list) is
    the same linear map as the edge-based apply_gamma, i.e. I_d ⊗ Γ^α."""
    d = setup["d"]
    for name, (_, part) in setup["parts"].items():
        n_max = part.max_poses
        gammas = setup["gammas"][(name, xi)]
        op = build_gamma_operator(part.edges, xi, n_max)
        L = np.asarray(_gamma_operator_blocksparse(op, n_max, d))
        for a, G in enumerate(gammas):
            # Slots without edges (padding) carry an identity block when xi = 0 (never a zero
            # block, so preconditioners stay invertible); they are decoupled either way.
            pad = ~np.asarray(part.pose_mask[a])
            empty = np.concatenate([pad, np.repeat(pad, d)]) & (np.abs(G).sum(1) == 0)
            G = G + np.diag(empty.astype(float))
            np.testing.assert_allclose(L[a], np.kron(np.eye(d), G.T), rtol=0, atol=1e-12 * max(1.0, np.abs(G).max()), err_msg=name)


@pytest.mark.parametrize("xi", XIS)
def test_gamma_diagonal_blocks_match_dense(setup, xi):
    d = setup["d"]
    for name, (_, part) in setup["parts"].items():
        gammas = setup["gammas"][(name, xi)]
        n_max = part.max_poses
        blocks = np.asarray(_diag_blocks(part.edges, jnp.asarray(xi), n_max))
        assert blocks.shape == (part.num_robots, n_max, d + 1, d + 1)
        for a, G in enumerate(gammas):
            for s in range(n_max):
                idx = local_indices(n_max, d, s)
                np.testing.assert_allclose(blocks[a, s], G[np.ix_(idx, idx)], rtol=1e-12, atol=1e-12, err_msg=name)


@pytest.mark.parametrize("xi", XIS)
def test_majorizer_upper_bound_and_tight(setup, xi):
    """Eq. (14): G(X|X^k) ≥ F(X) at random ambient X, equality at X = X^k; G agrees with the dense
    form ½⟨Γ̃ D, D⟩ + ⟨X^k M̃, D⟩ + F(X^k)."""
    g, M, d = setup["graph"], setup["M"], setup["d"]
    n = g.num_poses
    rng = np.random.default_rng(1)
    Xk_list = [setup["X0"], random_ambient(rng, setup["X0"], 0.5)]  # X^k on and off the manifold
    for name, (_, part) in setup["parts"].items():
        Gt = assemble_global(part, setup["gammas"][(name, xi)], n, d)
        for Xk in Xk_list:
            Fk = float(_objective(g, Xk))
            Gk, share, _ = _library_G(part, xi, Xk, Xk)
            np.testing.assert_allclose(float(jnp.sum(Gk)), Fk, rtol=1e-12, err_msg=name)
            for scale in (1e-3, 0.1, 1.0, 10.0):
                X = random_ambient(rng, Xk, scale)
                G_alpha, _, _ = _library_G(part, xi, X, Xk)
                G = float(jnp.sum(G_alpha))
                F = float(_objective(g, X))
                Dm = poses_to_matrix(X) - poses_to_matrix(Xk)
                Xkm = poses_to_matrix(Xk)
                G_dense = 0.5 * np.sum((Dm @ Gt) * Dm) + np.sum((Xkm @ M) * Dm) + Fk
                np.testing.assert_allclose(G, G_dense, rtol=1e-10, atol=1e-10, err_msg=name)
                assert G >= F - 1e-10 * max(1.0, abs(F)), (name, scale, G, F)


def test_shares_sum_to_objective(setup):
    """(C.3): Σ_α Ḡ^α(k) = F(X^k), and the share is own edges + half of each inter-robot edge."""
    g = setup["graph"]
    rng = np.random.default_rng(2)
    I, J = np.asarray(g.i), np.asarray(g.j)
    for name, (robots, part) in setup["parts"].items():
        for Xk in (setup["X0"], random_ambient(rng, setup["X0"], 1.0)):
            _, share, grad = _library_G(part, 0.0, Xk, Xk)
            np.testing.assert_allclose(float(jnp.sum(share)), float(_objective(g, Xk)), rtol=1e-12, err_msg=name)
            # Per robot against a per-edge count.
            Fe = 0.5 * np.asarray(edge_costs(g, Xk))
            ref = np.zeros(part.num_robots)
            for e in range(len(I)):
                a, b = robots[I[e]], robots[J[e]]
                if a == b:
                    ref[a] += Fe[e]
                else:
                    ref[a] += 0.5 * Fe[e]
                    ref[b] += 0.5 * Fe[e]
            np.testing.assert_allclose(np.asarray(share), ref, rtol=1e-12, atol=1e-13, err_msg=name)
            # The gradient blocks are the blocks of X^k M̃ (∇F, Prop. 1).
            gM = poses_to_matrix(Xk) @ setup["M"]
            gref = matrix_to_poses(gM)
            gathered = part.gather(grad)
            np.testing.assert_allclose(np.asarray(gathered.R), np.asarray(gref.R), rtol=1e-10, atol=1e-10)
            np.testing.assert_allclose(np.asarray(gathered.t), np.asarray(gref.t), rtol=1e-10, atol=1e-10)


def test_eq10_loop_equals_majorizer(setup):
    """Eq. (6)/(9)/(10) by hand: E^α(X|X^k) = G^α(X^α|X^k) with ξ = 0 for every robot (hence
    Σ_α E^α = G), at random ambient X; X^k on the manifold."""
    g = setup["graph"]
    rng = np.random.default_rng(3)
    Xk = setup["X0"]
    for name, (robots, part) in setup["parts"].items():
        for scale in (0.0, 0.05, 1.0):
            X = random_ambient(rng, Xk, scale)
            E = eq10_loop(g, robots, X, Xk, part.num_robots)
            G_alpha, _, _ = _library_G(part, 0.0, X, Xk)
            G_alpha = np.asarray(G_alpha)
            np.testing.assert_allclose(E.sum(), G_alpha.sum(), rtol=1e-11, err_msg=name)
            np.testing.assert_allclose(E, G_alpha, rtol=1e-11, atol=1e-11 * abs(E).max(), err_msg=name)
            assert E.sum() >= float(_objective(g, X)) - 1e-10 * abs(E.sum())


def test_literal_eq8_is_not_tight(setup):
    """Sanity check that the reference is sensitive: the midpoint as printed in Eq. (8) (without
    t_i^k) does not give E(X^k|X^k) = F(X^k) when inter-robot edges exist."""
    g, Xk = setup["graph"], setup["X0"]
    robots, part = setup["parts"]["A=5"]
    F = float(_objective(g, Xk))
    E_fixed = eq10_loop(g, robots, Xk, Xk, part.num_robots).sum()
    E_literal = eq10_loop(g, robots, Xk, Xk, part.num_robots, literal_eq8=True).sum()
    np.testing.assert_allclose(E_fixed, F, rtol=1e-12)
    assert abs(E_literal - F) > 1e-3 * F


# ----------------------------------------------------------------------------- rotation projection


@pytest.mark.parametrize("d", [2, 3, 4])
def test_one_rotation_projection_in_both_layouts(d):
    """project_to_so (SVD), the solver's project_rotations (stacked layout) and _project_soa
    (structure-of-arrays layout) are one projection: near-rotations map to the same rotation
    (d = 2's closed form is exact for any input), and the layouts are transposes of each other."""
    from mmpgo_jax import project_to_so
    from mmpgo_jax._core.geometry import nearest_rotations
    from mmpgo_jax._mm.subproblem import _project_soa, project_rotations

    rng = np.random.default_rng(d)
    M = random_rotations(rng, (5, 7), d) + 0.05 * rng.standard_normal((5, 7, d, d))
    ref = np.asarray(project_to_so(jnp.asarray(M)))
    np.testing.assert_allclose(np.linalg.det(ref), 1.0, atol=1e-12)
    fast = np.asarray(project_rotations(jnp.asarray(M)))
    np.testing.assert_allclose(fast, ref, atol=1e-12)
    soa = np.asarray(_project_soa(jnp.asarray(np.moveaxis(M, (-2, -1), (0, 1)))))
    np.testing.assert_array_equal(np.moveaxis(soa, (0, 1), (-2, -1)), fast)
    svd_first = nearest_rotations(jnp.asarray(np.moveaxis(M, (-2, -1), (0, 1))), layout="blocks-first")
    np.testing.assert_allclose(np.moveaxis(np.asarray(svd_first), (0, 1), (-2, -1)), ref, atol=1e-14)
    if d == 2:  # the closed form is the exact projection of any 2x2 matrix
        W = rng.standard_normal((50, 2, 2))
        np.testing.assert_allclose(np.asarray(project_rotations(jnp.asarray(W))),
                                   np.asarray(project_to_so(jnp.asarray(W))), atol=1e-12)
    with pytest.raises(ValueError, match="layout"):
        nearest_rotations(jnp.asarray(M), layout="rows")


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("distance", [0.2, 1e-3, 1e-7, 0.0])
def test_newton_polar_iteration_stops_at_rounding_accuracy(distance, dtype):
    """The 3D Newton polar iteration stops once a step changes no entry by more than sqrt(eps):
    from near-rotations at any distance (exact rotations included) it lands on the SVD projection
    to rounding, in float64 and float32."""
    from mmpgo_jax import project_to_so
    from mmpgo_jax._core.geometry import nearest_rotations

    rng = np.random.default_rng(3)
    M = random_rotations(rng, (4, 50), 3) + distance * rng.standard_normal((4, 50, 3, 3))
    ref = np.asarray(project_to_so(jnp.asarray(M)))
    got = np.asarray(nearest_rotations(jnp.asarray(M, dtype), method="fast"))
    tol = 1e-13 if dtype == np.float64 else 3e-6
    assert got.dtype == dtype
    np.testing.assert_allclose(got, ref, atol=tol)


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("size", [1e-3, 0.3, 3.0])
def test_retraction_is_the_polar_projection_of_a_tangent_step(d, size):
    """The solver's retraction of a tangent step V = [v | R Omega] (Omega skew) is [t + v | the SVD
    projection of R + R Omega]: for d = 3 by the closed form, for any step size (small steps, and
    steps of several radians)."""
    from mmpgo_jax import project_to_so
    from mmpgo_jax._mm.subproblem import _retract_soa

    rng = np.random.default_rng(int(10 * d + size))
    n = 40
    R = random_rotations(rng, (n,), d)
    S = rng.standard_normal((n, d, d))
    Omega = size * (S - np.swapaxes(S, -1, -2))
    Y = np.concatenate([rng.standard_normal((n, d, 1)), R], axis=-1)
    V = np.concatenate([rng.standard_normal((n, d, 1)), R @ Omega], axis=-1)
    soa = lambda a: jnp.asarray(np.moveaxis(a, 0, -1))
    out = np.moveaxis(np.asarray(_retract_soa(soa(Y), soa(V))), -1, 0)
    np.testing.assert_array_equal(out[..., 0], Y[..., 0] + V[..., 0])
    np.testing.assert_allclose(out[..., 1:], np.asarray(project_to_so(jnp.asarray(R + R @ Omega))), atol=1e-13)
    np.testing.assert_allclose(np.swapaxes(out[..., 1:], -1, -2) @ out[..., 1:], np.broadcast_to(np.eye(d), (n, d, d)),
                               atol=1e-14)
