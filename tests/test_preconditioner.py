"""The Newton preconditioner of the robot subproblem against dense linear algebra: its block-Jacobi
level equals the inverses of the Riemannian Hessian's diagonal blocks on the tangent space, its
coarse matrix B^T Gamma B, and the whole operator is symmetric positive definite there; its coarse
space holds Gamma's null space; it cuts CG iterations where Gamma-only preconditioning is weak."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mmpgo_jax as mg
from mmpgo_jax._mm.majorization import soa_bmm, soa_T, sym0, tangent_soa, to_soa
from mmpgo_jax._mm.outer import start_state
from mmpgo_jax._mm.preconditioner import _tangent_basis, aggregate_size
from mmpgo_jax._mm.subproblem import SubproblemConfig, subproblem_steps


def _robot(tree, a):
    return jax.tree.map(lambda x: x[a], tree)


def _dense(op, shape):
    """A linear map of (d, k, n) arrays as a dense matrix on the flattened layout."""
    eye = jnp.eye(int(np.prod(shape)))
    return np.asarray(jax.vmap(lambda v: op(v.reshape(shape)).reshape(-1))(eye)).T


def _hessian_pieces(problem, state, a):
    """Gamma, the Riemannian Hessian, the tangent projection (dense) and the Weingarten matrices of
    robot ``a``'s MM subproblem at the state's poses."""
    G = _robot(problem.gamma_soa, a)
    Y, egrad = to_soa(state.X[a]), to_soa(state.grad[a])
    W = sym0(soa_bmm(soa_T(Y[:, 1:]), egrad[:, 1:]))
    shape = Y.shape

    def hess(V):
        GV = G(V)
        return tangent_soa(Y, GV.at[:, 1:].add(-soa_bmm(V[:, 1:], W)))

    return Y, W, _dense(G, shape), _dense(hess, shape), _dense(lambda V: tangent_soa(Y, V), shape)


def _reference(Gd, Hd, Pd, shape, frame, real, b, coarse_inverse):
    """Dense M^-1: per slot the inverse of the Hessian's block on the tangent space (Gamma's block
    where that one is not positive definite), plus P_T B C B^T with the given coarse inverse C
    (B^T Gamma B is returned to be checked against it: its pseudo-inverse is too ill-conditioned to
    compare entry by entry)."""
    D = Gd.shape[0]
    idx = np.arange(D).reshape(shape)
    n = shape[-1]
    fine = np.zeros((D, D))
    for s in range(n):
        ii = idx[:, :, s].reshape(-1)
        w, U = np.linalg.eigh(Pd[np.ix_(ii, ii)])
        Q = U[:, w > 0.5]  # orthonormal basis of the tangent space at slot s
        Hs = Q.T @ Hd[np.ix_(ii, ii)] @ Q
        Hs = 0.5 * (Hs + Hs.T)
        if np.linalg.eigvalsh(Hs).min() <= 0:
            Hs = Q.T @ Gd[np.ix_(ii, ii)] @ Q
        fine[np.ix_(ii, ii)] = Q @ np.linalg.inv(Hs) @ Q.T
    if coarse_inverse is None:
        return fine, None
    E = _tangent_basis(np.asarray(frame), np.asarray(real), shape[0])  # (n, c, d, k)
    m, c = -(-n // b), E.shape[1]
    B = np.zeros((D, c * m))
    for s in range(n):
        for i in range(c):
            V = np.zeros(shape)
            V[:, :, s] = E[s, i]
            B[:, i * m + s // b] += V.reshape(-1)
    Ac = B.T @ Gd @ B
    return fine + Pd @ B @ coarse_inverse @ B.T @ Pd, Ac


@pytest.fixture(scope="module", params=[2, 3], ids=["2d", "3d"])
def setup(request):
    """A noisy graph split among 3 robots, after a few AMM iterations (rotations off the start, a
    nonzero gradient: the Weingarten term matters)."""
    if request.param == 2:
        data = mg.grid_2d_dataset(3, grid=8, num_poses=90, loop_closure_prob=0.2, sigma_R=0.05, sigma_t=0.05)
    else:
        data = mg.cube_dataset(4, grid=4, num_poses=72, loop_closure_prob=0.2)
    X0 = mg.solve(data.graph, 3, iterations=0).poses
    warm = mg.solve(data.graph, 3, method="amm", iterations=3, initial=X0)
    part = warm.partition
    problem = mg.MMProblem.build(part, 1e-3, poses=part.scatter(X0))
    state, _ = start_state(problem, part.scatter(warm.poses), mg.MMConfig())
    return data, part, X0, problem, state


def test_operator_matches_dense_algebra_and_is_spd(setup):
    _, part, _, problem, state = setup
    pre = problem.newton
    assert pre.aggregate == aggregate_size(int(np.asarray(part.pose_mask).sum(1).max()), part.edges.t.shape[-1])
    for a in range(part.num_robots):
        Y, W, Gd, Hd, Pd = _hessian_pieces(problem, state, a)
        one = _robot(pre, a)
        fine_ref, Ac = _reference(Gd, Hd, Pd, Y.shape, one.frame, one.real, one.aggregate,
                                  np.asarray(one.coarse_inverse))
        np.testing.assert_allclose(np.linalg.pinv(np.asarray(one.coarse_inverse), hermitian=True), Ac,
                                   rtol=1e-8, atol=1e-10 * np.abs(Ac).max())
        w, U = np.linalg.eigh(Pd)
        Q = U[:, w > 0.5]
        for op, ref in ((one.without_coarse().at(Y, W), _reference(Gd, Hd, Pd, Y.shape, None, None, 0, None)[0]),
                        (one.at(Y, W), fine_ref)):
            M = _dense(op, Y.shape)
            Mt, Rt = Q.T @ M @ Q, Q.T @ ref @ Q
            np.testing.assert_allclose(Mt, Rt, atol=1e-9 * np.abs(Rt).max())
            np.testing.assert_allclose(Pd @ M, M, atol=1e-10 * np.abs(M).max())  # values are tangent
            np.testing.assert_allclose(Mt, Mt.T, atol=1e-10 * np.abs(Mt).max())
            assert np.linalg.eigvalsh(0.5 * (Mt + Mt.T)).min() > 0


def test_indefinite_blocks_fall_back_to_gammas():
    """A pose whose Hessian block is indefinite (a huge Weingarten term) gets Gamma's block: the
    operator stays positive definite; elsewhere the Hessian's block is used."""
    data = mg.grid_2d_dataset(1, grid=6, num_poses=30, loop_closure_prob=0.2)
    part = mg.partition(data.graph, 1)
    problem = mg.MMProblem.build(part, 1e-3, preconditioner="block-jacobi")
    X = part.scatter(data.ground_truth)
    state, _ = start_state(problem, X, mg.MMConfig(subproblem=SubproblemConfig(preconditioner="block-jacobi")))
    Y = to_soa(state.X[0])
    n = Y.shape[-1]
    W = jnp.zeros((2, 2, n)).at[:, :, 3].set(1e6 * jnp.eye(2))  # tr W huge at slot 3: S < 0 there
    op = _robot(problem.newton, 0).at(Y, W)
    ref = _robot(problem.newton, 0).at(Y, jnp.zeros_like(W))
    V = tangent_soa(Y, jnp.asarray(np.random.default_rng(0).standard_normal(Y.shape)))
    out, out_gamma = np.asarray(op(V)), np.asarray(ref(V))
    np.testing.assert_allclose(out[..., 3], out_gamma[..., 3], rtol=1e-12)
    S_gamma = float(problem.newton.schur[0, 0, 0, 5])  # 2D: S = S_Gamma - tr W; half of it is still PD
    W_half = jnp.zeros((2, 2, n)).at[:, :, 5].set(0.25 * S_gamma * jnp.eye(2))
    out_half = np.asarray(_robot(problem.newton, 0).at(Y, W_half)(V))[..., 5]
    assert not np.allclose(out_half, out_gamma[..., 5], rtol=1e-3)
    M = _dense(op, Y.shape)
    Pd = _dense(lambda U: tangent_soa(Y, U), Y.shape)
    w, U = np.linalg.eigh(Pd)
    Q = U[:, w > 0.5]
    assert np.linalg.eigvalsh(0.5 * (Q.T @ M @ Q + (Q.T @ M @ Q).T)).min() > 0


def test_coarse_space_holds_gammas_null_space():
    """Noise-free measurements, X^0 = the truth, one robot and xi = 0: the rigid motions of the
    whole graph cost nothing, so B^T Gamma B has exactly d(d+1)/2 zero eigenvalues (the gauge) whose
    prolonged eigenvectors are null vectors of Gamma; its pseudo-inverse is a generalized inverse."""
    data = mg.grid_2d_dataset(5, grid=12, num_poses=120, loop_closure_prob=0.1, sigma_t=0.0, sigma_R=0.0)
    part = mg.partition(data.graph, 1)
    X0 = part.scatter(data.ground_truth)
    problem = mg.MMProblem.build(part, 0.0, poses=X0)
    pre = _robot(problem.newton, 0)
    shape = (2, 3, part.max_poses)
    Gd = _dense(_robot(problem.gamma_soa, 0), shape)
    E = _tangent_basis(np.asarray(pre.frame), np.asarray(pre.real), 2)
    n, b = part.max_poses, pre.aggregate
    m = -(-n // b)
    B = np.zeros((Gd.shape[0], 3 * m))
    for s in range(n):
        for i in range(3):
            V = np.zeros(shape)
            V[:, :, s] = E[s, i]
            B[:, i * m + s // b] += V.reshape(-1)
    C = B.T @ Gd @ B
    w, U = np.linalg.eigh(C)
    scale = np.abs(w).max()
    assert np.all(np.abs(w[:3]) < 1e-9 * scale) and w[3] > 1e-7 * scale, w[:5]
    fine = B @ U[:, :3]
    assert np.abs(Gd @ fine).max() < 1e-9 * np.abs(Gd).max() * np.abs(fine).max()
    np.testing.assert_allclose(C @ np.asarray(pre.coarse_inverse) @ C, C, atol=1e-8 * scale)


def test_fewer_cg_iterations_than_gammas_block_jacobi_on_a_long_chain():
    """Where block-Jacobi leaves a long chain's smooth modes to CG, the coarse level removes them:
    the same subproblems, solved to the same criterion, take a fraction of the CG iterations and
    end at least as low."""
    data = mg.grid_2d_dataset(3, grid=30, num_poses=600, loop_closure_prob=0.02, sigma_R=0.005, sigma_t=0.01)
    warm = mg.solve(data.graph, 2, method="mm", iterations=2)
    part = warm.partition
    X0 = part.scatter(warm.poses)
    out = {}
    for kind in ("two-level", "block-jacobi"):
        problem = mg.MMProblem.build(part, 1e-3, poses=X0, preconditioner=kind)
        state, _ = start_state(problem, X0, mg.MMConfig())
        sub = SubproblemConfig(preconditioner=kind, max_steps=10, cg_iterations=500, gradient_tolerance=1e-3)
        solve = jax.jit(jax.vmap(lambda G, P, x, g, sub=sub: subproblem_steps(G, P, x, x, g, sub)))
        out[kind] = solve(problem.gamma_soa, problem.preconditioner(mg.MMConfig(subproblem=sub)), state.X, state.grad)
    cg_two, cg_bj = np.asarray(out["two-level"].cg), np.asarray(out["block-jacobi"].cg)
    assert np.all(cg_two * 3 <= cg_bj), (cg_two, cg_bj)
    v_two, v_bj = np.asarray(out["two-level"].value), np.asarray(out["block-jacobi"].value)
    assert np.all(v_two <= v_bj + 1e-6 * np.abs(v_bj)), (v_two, v_bj)


def test_build_needs_the_start_poses_for_the_default(setup):
    _, part, X0, _, _ = setup
    with pytest.raises(ValueError, match="made of the start poses"):
        mg.MMProblem.build(part, config=mg.MMConfig())
    assert mg.MMProblem.build(part, config=mg.MMConfig(), poses=part.scatter(X0)).preconditioners == (
        "two-level", "block-jacobi")
    assert mg.MMProblem.build(part).preconditioners == ("block-jacobi",)


def test_padding_does_not_change_the_preconditioner(setup):
    """A partition padded to more slots and robots (to batch it with others) gets the same
    aggregates and the same M^{-1} on its real slots."""
    data, part, X0, problem, state = setup
    padded = mg.partition(data.graph, 3, min_max_poses=part.max_poses + 37, num_robots=4)
    pre_p = mg.MMProblem.build(padded, 1e-3, poses=padded.scatter(X0)).newton
    assert pre_p.aggregate == problem.newton.aggregate
    n = part.max_poses
    Y = jax.vmap(to_soa)(state.X)
    W = jax.vmap(lambda y, g: sym0(soa_bmm(soa_T(y[:, 1:]), g[:, 1:])))(Y, jax.vmap(to_soa)(state.grad))
    pad = ((0, 1), (0, 0), (0, 0), (0, padded.max_poses - n))
    Yp = jnp.pad(Y, pad).at[3, :, 1:].set(jnp.eye(Y.shape[1])[:, :, None])  # padding robot: identity rotations
    Yp = Yp.at[:3, :, 1:, n:].set(jnp.eye(Y.shape[1])[:, :, None])
    Wp = jnp.pad(W, pad)
    V = jax.vmap(tangent_soa)(Y, jnp.asarray(np.random.default_rng(1).standard_normal(Y.shape)))
    Vp = jnp.pad(V, pad)
    out = np.asarray(jax.vmap(lambda p, y, w, v: p.at(y, w)(v))(problem.newton, Y, W, V))
    out_p = np.asarray(jax.vmap(lambda p, y, w, v: p.at(y, w)(v))(pre_p, Yp, Wp, Vp))
    np.testing.assert_allclose(out_p[:3, ..., :n], out, rtol=1e-10, atol=1e-12 * np.abs(out).max())
    np.testing.assert_array_equal(out_p[3], 0.0)
