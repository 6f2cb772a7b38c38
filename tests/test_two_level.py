"""The two-level preconditioner: its coarse matrix and application against dense linear algebra,
its coarse space against Gamma's null space, and its effect on CG where block-Jacobi is weak."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mmpgo_jax as mg
from mmpgo_jax._mm.majorization import from_soa, stack, to_soa
from mmpgo_jax._mm.outer import start_state
from mmpgo_jax._mm.subproblem import SubproblemConfig, subproblem_steps
from mmpgo_jax._mm.two_level import aggregate_size


def _dense_gamma(problem, robot):
    """Gamma^alpha of one robot as a dense (n k) x (n k) matrix acting on one row of the stacked
    poses, built by applying the block-sparse operator to unit vectors."""
    gamma = jax.tree.map(lambda x: x[robot], problem.gamma_soa)
    n = problem.partition.max_poses
    k = gamma.diag.shape[0]
    units = np.eye(n * k).reshape(n * k, n, k)  # unit row vectors, pose-major
    Y = jnp.asarray(np.repeat(units[:, None], k - 1, axis=1))  # (N, d, n, k): every row the same
    out = jax.vmap(lambda y: from_soa(gamma(to_soa(jnp.moveaxis(y, 0, 1)))))(Y)  # (N, n, d, k)
    return np.asarray(out)[:, :, 0, :].reshape(n * k, n * k)


def _dense_prolongation(X0, mask, b):
    """P (n k) x (m k): on aggregate a, column a k + 0 is the translation shift, a k + 1 + r the
    r-th row of [t_s - mean t | R_s] at the aggregate's slots s (zero on padding slots)."""
    n, d, k = X0.shape
    m = -(-n // b)
    P = np.zeros((n, k, m, k))
    for a in range(m):
        slots = [s for s in range(a * b, min(n, (a + 1) * b)) if mask[s]]
        if not slots:
            continue
        mean = X0[slots, :, 0].mean(axis=0)
        for s in slots:
            P[s, 0, a, 0] = 1.0
            for r in range(d):
                P[s, :, a, 1 + r] = X0[s, r]
                P[s, 0, a, 1 + r] -= mean[r]
    return P.reshape(n * k, m * k)


@pytest.fixture(scope="module")
def chain():
    """A long, precise chain with few loop closures (55), 2 robots (300 slots each: many
    aggregates), two MM iterations from the chordal start (the state of an early outer iteration)."""
    data = mg.grid_2d_dataset(3, grid=30, num_poses=600, loop_closure_prob=0.02, sigma_R=0.005, sigma_t=0.01)
    warm = mg.solve(data.graph, 2, method="mm", iterations=2)
    part = warm.partition
    X0 = part.scatter(warm.poses)
    problem = mg.MMProblem.build(part, 1e-3, poses=X0)
    return data, part, X0, problem


def test_coarse_matrix_and_application_match_dense_algebra(chain):
    """M^{-1} = blockdiag(Gamma)^{-1} + P (P^T Gamma P)^+ P^T, entry by entry, for every robot."""
    _, part, X0, problem = chain
    pre = problem.two_level
    b = pre.aggregate
    assert b == aggregate_size(part.max_poses, 3)
    X0s = np.asarray(stack(X0))
    mask = np.asarray(part.pose_mask)
    n, k = part.max_poses, 3
    rng = np.random.default_rng(0)
    for robot in range(part.num_robots):
        G = _dense_gamma(problem, robot)
        P = _dense_prolongation(X0s[robot], mask[robot], b)
        coarse = P.T @ G @ P
        np.testing.assert_allclose(np.linalg.pinv(np.asarray(pre.coarse_inverse[robot])), coarse,
                                   rtol=1e-7, atol=1e-9 * np.abs(coarse).max())
        blocks = np.zeros_like(G)
        for s in range(n):
            blocks[s * k:(s + 1) * k, s * k:(s + 1) * k] = np.linalg.inv(G[s * k:(s + 1) * k, s * k:(s + 1) * k])
        # (the coarse matrix is checked above; its pseudo-inverse is ill-conditioned to compare)
        Minv = blocks + P @ np.asarray(pre.coarse_inverse[robot]) @ P.T
        V = rng.standard_normal((2, n, k))  # d = 2 rows of stacked poses
        one = jax.tree.map(lambda x: x[robot], pre)
        out = np.asarray(from_soa(one(to_soa(jnp.asarray(np.moveaxis(V, 0, 1))))))  # (n, d, k)
        expected = np.einsum("ri,ij->rj", V.reshape(2, n * k), Minv).reshape(2, n, k)
        np.testing.assert_allclose(np.moveaxis(out, 1, 0), expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max())


def test_coarse_space_holds_gammas_null_space():
    """Noise-free measurements, X^0 = the truth, one robot and xi = 0: the shift and the rows of X^0
    cost nothing, so P^T Gamma P has exactly d + 1 zero eigenvalues (the gauge), whose eigenvectors,
    prolonged, are null vectors of Gamma itself; the library's basis is that P."""
    data = mg.grid_2d_dataset(5, grid=12, num_poses=120, loop_closure_prob=0.1, sigma_t=0.0, sigma_R=0.0)
    part = mg.partition(data.graph, 1)
    X0 = part.scatter(data.ground_truth)
    problem = mg.MMProblem.build(part, 0.0, poses=X0)
    b = problem.two_level.aggregate
    n, k = part.max_poses, 3
    P = _dense_prolongation(np.asarray(stack(X0))[0], np.asarray(part.pose_mask)[0], b)
    basis = np.asarray(problem.two_level.basis[0])  # (q, c, slot)
    P_lib = np.zeros((n, k, -(-n // b), k))
    P_lib[np.arange(n), :, np.arange(n) // b, :] = np.moveaxis(basis, -1, 0)
    np.testing.assert_allclose(P_lib.reshape(P.shape), P, atol=1e-12)
    G = _dense_gamma(problem, 0)
    w, V = np.linalg.eigh(P.T @ G @ P)
    scale = np.abs(w).max()
    assert np.all(np.abs(w[:3]) < 1e-9 * scale) and w[3] > 1e-7 * scale, w[:5]
    fine = P @ V[:, :3]
    assert np.abs(G @ fine).max() < 1e-9 * np.abs(G).max() * np.abs(fine).max()
    # and the library's coarse inverse is a generalized inverse of it: C C^+ C = C
    C, Cp = P.T @ G @ P, np.asarray(problem.two_level.coarse_inverse[0])
    np.testing.assert_allclose(C @ Cp @ C, C, atol=1e-8 * scale)


def test_two_level_needs_far_fewer_cg_iterations_on_a_long_chain(chain):
    """Where block-Jacobi leaves the chain's smooth modes to CG, the coarse level removes them:
    the same subproblems, solved to the same criterion, take a fraction of the CG iterations and
    end at least as low."""
    _, part, X0, problem = chain
    state, _ = start_state(problem, X0, mg.MMConfig())
    out = {}
    for kind, pre in (("two-level", problem.two_level), ("block-jacobi", problem.block_jacobi_soa)):
        sub = SubproblemConfig(preconditioner=kind, max_steps=10, cg_iterations=500, gradient_tolerance=1e-3)
        solve = jax.jit(jax.vmap(lambda G, P, x, g, sub=sub: subproblem_steps(G, P, x, x, g, sub)))
        out[kind] = solve(problem.gamma_soa, pre, state.X, state.grad)
    cg_two, cg_bj = np.asarray(out["two-level"].cg), np.asarray(out["block-jacobi"].cg)
    assert np.all(cg_two * 3 <= cg_bj), (cg_two, cg_bj)
    v_two, v_bj = np.asarray(out["two-level"].value), np.asarray(out["block-jacobi"].value)
    assert np.all(v_two <= v_bj + 1e-6 * np.abs(v_bj)), (v_two, v_bj)


def test_build_needs_the_start_poses_for_the_default(chain):
    _, part, X0, _ = chain
    with pytest.raises(ValueError, match="made of the start poses"):
        mg.MMProblem.build(part, config=mg.MMConfig())
    assert mg.MMProblem.build(part, config=mg.MMConfig(), poses=X0).preconditioners == ("two-level",)


def test_padding_does_not_change_the_preconditioner(chain):
    """A partition padded to more slots and robots (to batch it with others) gets the same
    aggregates and the same M^{-1} on its real slots."""
    data, part, X0, problem = chain
    padded = mg.partition(data.graph, 2, min_max_poses=part.max_poses + 37, num_robots=3)
    Xp = padded.scatter(part.gather(X0))
    pre_p = mg.MMProblem.build(padded, 1e-3, poses=Xp).two_level
    assert pre_p.aggregate == problem.two_level.aggregate
    n = part.max_poses
    V = np.random.default_rng(1).standard_normal((2, 2, 3, n))
    Vp = np.zeros((3, 2, 3, padded.max_poses))
    Vp[:2, ..., :n] = V
    out = np.asarray(jax.vmap(lambda p, v: p(v))(problem.two_level, jnp.asarray(V)))
    out_p = np.asarray(jax.vmap(lambda p, v: p(v))(pre_p, jnp.asarray(Vp)))
    np.testing.assert_allclose(out_p[:2, ..., :n], out, rtol=1e-10, atol=1e-12 * np.abs(out).max())
    np.testing.assert_array_equal(out_p[2], 0.0)
