"""The rotation groups of mmpgo_jax._core.lie: properties of each group's maps, for NumPy and JAX
inputs, with the coordinate axes last and first, over several batch shapes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st
from lie_cases import each_dim

from mmpgo_jax._core.geometry import random_rotations
from mmpgo_jax._core.lie import GROUPS, SO2, SO3, project_svd, so

BATCHES = [(), (1,), (5,), (2, 3)]
BACKENDS = pytest.mark.parametrize("xp", [np, jnp], ids=["numpy", "jax"])
examples = settings(max_examples=15, deadline=None)
seeds = st.integers(0, 2**32 - 1)
batches = st.sampled_from(BATCHES)


def _vectors(rng, batch, p, radius):
    """Tangent vectors (batch..., p) with norms uniform in [0, radius)."""
    w = rng.standard_normal((*batch, p))
    w /= np.linalg.norm(w, axis=-1, keepdims=True)
    return w * rng.uniform(0, radius, (*batch, 1))


def _first(x, k):
    """The last k axes moved to the front (the solver's layout)."""
    return np.moveaxis(x, tuple(range(x.ndim - k, x.ndim)), tuple(range(k)))


def test_so_is_the_one_dimension_switch():
    assert so(2) is SO2 and so(3) is SO3 and dict(GROUPS) == {2: SO2, 3: SO3}
    for group in (SO2, SO3):
        assert group.tangent_dim == group.dim * (group.dim - 1) // 2
    with pytest.raises(ValueError, match="dimension 2 or 3"):
        so(4)


@each_dim
@BACKENDS
@examples
@given(seed=seeds, batch=batches)
def test_hat_and_vee_are_inverse(d, xp, seed, batch):
    G, rng = so(d), np.random.default_rng(seed)
    w = xp.asarray(rng.standard_normal((*batch, G.tangent_dim)))
    W = G.hat(w)
    assert type(W) is type(w) and W.shape == (*batch, d, d)
    np.testing.assert_array_equal(G.vee(W), w)
    np.testing.assert_array_equal(W, -np.swapaxes(W, -1, -2))  # skew
    np.testing.assert_array_equal(G.hat(G.vee(W)), W)
    np.testing.assert_allclose(G.dual(W), 2 * np.asarray(w), rtol=1e-15)
    np.testing.assert_allclose(W, np.einsum("...q,qab->...ab", w, G.generators()), rtol=1e-15)
    # the entries-first layout computes the same numbers
    np.testing.assert_array_equal(G.hat(xp.asarray(_first(np.asarray(w), 1)), first=True), _first(np.asarray(W), 2))
    np.testing.assert_array_equal(G.vee(xp.asarray(_first(np.asarray(W), 2)), first=True), _first(np.asarray(w), 1))


@each_dim
@BACKENDS
@examples
@given(seed=seeds, batch=batches)
def test_exp_of_hat_is_a_rotation_and_the_matrix_exponential(d, xp, seed, batch):
    G, rng = so(d), np.random.default_rng(seed)
    w = _vectors(rng, batch, G.tangent_dim, 10.0)
    R = G.exp(xp.asarray(w))
    assert type(R) is type(xp.asarray(w)) and R.shape == (*batch, d, d)
    R = np.asarray(R)
    np.testing.assert_allclose(np.swapaxes(R, -1, -2) @ R, np.broadcast_to(np.eye(d), R.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)
    expm = np.array([scipy.linalg.expm(W) for W in G.hat(w).reshape(-1, d, d)]).reshape(R.shape)
    np.testing.assert_allclose(R, expm, atol=1e-13)


@each_dim
@BACKENDS
@examples
@given(seed=seeds, batch=batches)
def test_exp_of_log_is_the_identity(d, xp, seed, batch):
    G, rng = so(d), np.random.default_rng(seed)
    R = random_rotations(rng, batch, d)
    np.testing.assert_allclose(G.exp(G.log(xp.asarray(R))), R, atol=1e-13)
    # near the identity and near pi (3D: the axis from the symmetric part)
    for angle in (0.0, 1e-9, 1e-5, np.pi - 1e-5, np.pi - 1e-9):
        w = _vectors(rng, batch, G.tangent_dim, 1.0)
        w *= angle / np.maximum(np.linalg.norm(w, axis=-1, keepdims=True), 1e-300)
        R = G.exp(w)
        np.testing.assert_allclose(G.exp(G.log(xp.asarray(R))), R, atol=1e-12)


@each_dim
@BACKENDS
@examples
@given(seed=seeds, batch=batches)
def test_log_of_exp_is_the_identity_within_the_injectivity_radius(d, xp, seed, batch):
    G, rng = so(d), np.random.default_rng(seed)
    w = _vectors(rng, batch, G.tangent_dim, np.pi - 1e-6)
    log = G.log(G.exp(xp.asarray(w)))
    np.testing.assert_allclose(log, w, atol=1e-9)
    np.testing.assert_allclose(G.angle(G.exp(xp.asarray(w))), np.linalg.norm(w, axis=-1), atol=1e-9)


@each_dim
def test_exp_derivative_at_zero_is_the_generators(d):
    G = so(d)
    h = 1e-6
    for q, E in enumerate(G.generators()):
        e = np.eye(G.tangent_dim)[q]
        np.testing.assert_allclose((G.exp(h * e) - G.exp(-h * e)) / (2 * h), E, atol=1e-9)
    assert not G.generators().flags.writeable


@each_dim
@BACKENDS
@examples
@given(seed=seeds, batch=batches)
def test_project_is_the_nearest_rotation(d, xp, seed, batch):
    G, rng = so(d), np.random.default_rng(seed)
    M = rng.standard_normal((*batch, d, d))
    U, _, Vt = np.linalg.svd(M)
    D = np.ones((*batch, d))
    D[..., -1] = np.linalg.det(U @ Vt)
    reference = (U * D[..., None, :]) @ Vt
    P = G.project(xp.asarray(M))
    assert type(P) is type(xp.asarray(M))
    np.testing.assert_allclose(P, reference, atol=1e-12)
    np.testing.assert_allclose(project_svd(xp.asarray(M)), reference, atol=1e-12)
    # no rotation is nearer (a few random ones, and small perturbations of the projection)
    dist = np.linalg.norm(np.asarray(P) - M, axis=(-2, -1))
    for Q in (random_rotations(rng, batch, d), G.exp(0.01 * rng.standard_normal((*batch, G.tangent_dim))) @ P):
        assert np.all(np.linalg.norm(Q - M, axis=(-2, -1)) >= dist - 1e-12)


@each_dim
@examples
@given(seed=seeds, batch=st.sampled_from(BATCHES[1:]))
def test_fast_projection_of_near_rotations_in_both_layouts(d, seed, batch):
    G, rng = so(d), np.random.default_rng(seed)
    M = random_rotations(rng, batch, d) + 0.1 * rng.standard_normal((*batch, d, d))
    reference = G.project(M)
    last = jax.jit(G.project_fast)(jnp.asarray(M))
    first = jax.jit(lambda M: G.project_fast(M, first=True))(jnp.asarray(_first(M, 2)))
    np.testing.assert_allclose(last, reference, atol=1e-12)
    np.testing.assert_allclose(_first(np.asarray(last), 2), first, atol=1e-15)


@each_dim
@BACKENDS
@examples
@given(seed=seeds, batch=batches)
def test_hat_relatives_and_the_adjoint(d, xp, seed, batch):
    G, rng = so(d), np.random.default_rng(seed)
    p = G.tangent_dim
    w, v, u = (rng.standard_normal((*batch, k)) for k in (p, d, d))
    R = random_rotations(rng, batch, d)
    Wv = np.einsum("...ab,...b->...a", G.hat(w), v)
    np.testing.assert_allclose(G.hat_apply(xp.asarray(w), xp.asarray(v)), Wv, atol=1e-14)
    np.testing.assert_allclose(np.einsum("...aq,...q->...a", G.hat_apply_matrix(xp.asarray(v)), w), Wv, atol=1e-14)
    # <hat(w) v, u> = <w, hat_apply_adjoint(v, u)>
    np.testing.assert_allclose(np.sum(Wv * u, -1), np.sum(w * G.hat_apply_adjoint(xp.asarray(v), xp.asarray(u)), -1),
                               atol=1e-13)
    # R hat(w) R^T = hat(Ad_R w)
    Ad_w = np.einsum("...pq,...q->...p", G.adjoint(xp.asarray(R)), w)
    np.testing.assert_allclose(R @ G.hat(w) @ np.swapaxes(R, -1, -2), G.hat(Ad_w), atol=1e-13)
    # entries first: the same numbers
    for f, args in ((G.hat_apply, (w, v)), (G.hat_apply_adjoint, (v, u))):
        np.testing.assert_allclose(f(*(xp.asarray(_first(a, 1)) for a in args), first=True),
                                   _first(np.asarray(f(*(xp.asarray(a) for a in args))), 1), rtol=1e-15)


@each_dim
@BACKENDS
@examples
@given(seed=seeds, batch=batches)
def test_trace_form_and_inverse_spd(d, xp, seed, batch):
    G, rng = so(d), np.random.default_rng(seed)
    p = G.tangent_dim
    A = rng.standard_normal((*batch, d, d))
    M = A + np.swapaxes(A, -1, -2)
    C = G.trace_form(xp.asarray(M), xp.asarray(np.trace(M, axis1=-2, axis2=-1)))
    E = G.generators()
    reference = np.einsum("pba,qbc,...ca->...pq", E, E, M)  # tr(E_p^T E_q M)
    np.testing.assert_allclose(C, reference, atol=1e-13)
    B = rng.standard_normal((*batch, p, p))
    S = B @ np.swapaxes(B, -1, -2) + 0.1 * np.eye(p)
    inv, ok = G.inverse_spd(xp.asarray(S))
    assert np.all(ok)
    np.testing.assert_allclose(np.asarray(inv) @ S, np.broadcast_to(np.eye(p), S.shape), atol=1e-9)
    _, ok = G.inverse_spd(xp.asarray(-S))
    assert not np.any(ok)
    inv_first, _ = G.inverse_spd(xp.asarray(_first(S, 2)), first=True)
    np.testing.assert_array_equal(inv_first, _first(np.asarray(inv), 2))


@each_dim
@examples
@given(seed=seeds, batch=batches)
def test_V_inverse_gives_the_translation_coordinates_of_SE_log(d, seed, batch):
    G, rng = so(d), np.random.default_rng(seed)
    w = _vectors(rng, batch, G.tangent_dim, 3.0)
    rho = rng.standard_normal((*batch, d))
    A = np.zeros((*batch, d + 1, d + 1))
    A[..., :d, :d], A[..., :d, d] = G.hat(w), rho
    T = np.array([scipy.linalg.expm(a) for a in A.reshape(-1, d + 1, d + 1)]).reshape(A.shape)
    np.testing.assert_allclose(G.apply_V_inverse(w, T[..., :d, d]), rho, atol=1e-10)


def test_methods_are_jittable():
    w = jnp.asarray(np.random.default_rng(0).standard_normal((4, 3)))
    for G, x in ((SO2, w[:, :1]), (SO3, w)):
        R = jax.jit(G.exp)(x)
        np.testing.assert_allclose(jax.jit(G.log)(R), x, atol=1e-12)
        np.testing.assert_allclose(jax.jit(G.angle)(R), np.linalg.norm(np.asarray(x), axis=-1), atol=1e-12)
