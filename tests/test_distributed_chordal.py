"""Distributed chordal initialization (paper §VII, Algorithm 3) against the centralized solution."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from test_initialization import dense_relaxed_rotations, random_graph

import mmpgo_jax._init.distributed_chordal as dc
from mmpgo_jax import PoseGraph, cost, read_g2o
from mmpgo_jax._core.partition import partition
from mmpgo_jax._init.chordal import (
    chordal_initialization,
    chordal_relaxed_rotations,
    relaxed_rotation_cost,
    relaxed_translation_cost,
    translations_given_rotations,
)
from mmpgo_jax._init.distributed_chordal import (
    distributed_chordal_initialization,
    distributed_relaxed_rotations,
    distributed_translations,
)

# One budget per stage everywhere, so that the jitted loops compile once per graph shape.
ROT_IT = 400
TRANS_IT = 1500
N, EXTRA, ROBOTS = 36, 30, 4


@pytest.fixture(scope="module", params=[2, 3], ids=["2d", "3d"])
def graph(request):
    d = request.param
    g, _, _ = random_graph(N, d, EXTRA, seed=100 + d)
    return g


def _rel(a, b):
    return abs(a - b) / abs(b)


SCHEMES = pytest.mark.parametrize("scheme", ["cg", "amm"])


@SCHEMES
def test_rotations_reach_centralized_relaxed_solution(graph, scheme):
    Rc = chordal_relaxed_rotations(graph)
    fc = relaxed_rotation_cost(graph, Rc)
    R, hist, k, conv = distributed_relaxed_rotations(graph, ROBOTS, iterations=ROT_IT, tol=None, scheme=scheme)
    assert k == ROT_IT and not conv and hist.shape == (ROT_IT + 1,)
    assert _rel(relaxed_rotation_cost(graph, R), fc) <= 1e-9
    assert _rel(hist[-1], fc) <= 1e-9  # the history is the relaxed objective (2F convention)
    np.testing.assert_allclose(np.asarray(R), Rc, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(R[0]), np.eye(graph.dim))  # anchor never moves
    # history[0] is the objective at the start (all I)
    R0 = np.broadcast_to(np.eye(graph.dim), Rc.shape)
    assert hist[0] == pytest.approx(relaxed_rotation_cost(graph, R0), rel=1e-12)


@SCHEMES
def test_translations_reach_centralized_solution(graph, scheme):
    R = np.asarray(chordal_initialization(graph).R)
    tc = translations_given_rotations(graph, R)
    fc = relaxed_translation_cost(graph, R, tc)
    t, hist, _k, _ = distributed_translations(graph, R, ROBOTS, iterations=TRANS_IT, tol=None, scheme=scheme)
    assert _rel(relaxed_translation_cost(graph, R, np.asarray(t)), fc) <= 1e-9
    assert _rel(hist[-1], fc) <= 1e-9
    np.testing.assert_allclose(np.asarray(t), tc, atol=1e-5)
    np.testing.assert_array_equal(np.asarray(t[0]), np.zeros(graph.dim))


def test_full_initialization_matches_centralized_and_is_in_SOd(graph):
    p, info = distributed_chordal_initialization(
        graph, ROBOTS, rotation_iterations=ROT_IT, translation_iterations=TRANS_IT, tol=None
    )
    c = chordal_initialization(graph)
    R = np.asarray(p.R)
    d = graph.dim
    np.testing.assert_allclose(np.swapaxes(R, 1, 2) @ R, np.broadcast_to(np.eye(d), R.shape), atol=1e-10)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-10)
    np.testing.assert_allclose(R, np.asarray(c.R), atol=1e-6)
    np.testing.assert_allclose(np.asarray(p.t), np.asarray(c.t), atol=1e-5)
    assert _rel(float(cost(graph, p)), float(cost(graph, c))) <= 1e-9
    assert info.rotation_iterations == ROT_IT and info.translation_iterations == TRANS_IT
    assert info.rotation_history.shape == (ROT_IT + 1,) and info.translation_history.shape == (TRANS_IT + 1,)
    assert info.num_robots == ROBOTS and info.scheme == "cg" and not info.restart
    assert p.R.dtype == graph.R.dtype


@pytest.mark.parametrize("scheme", ["amm", "cg"])
def test_padding_invariance(scheme):
    """Padding slots and edges change nothing: AMM-Chordal's iterates to rounding; CG's to its
    float32 preconditioner's rounding (LAPACK factors matrices of another size), so compared at
    convergence."""
    graph, _, _ = random_graph(N, 2, EXTRA, seed=102)
    base = partition(graph, ROBOTS)
    padded = partition(graph, ROBOTS, min_max_poses=base.max_poses + 7, min_max_edges=base.max_edges + 5)
    assert padded.max_poses > base.max_poses
    its, atol, rtol = (40, 1e-12, 1e-12) if scheme == "amm" else (200, 1e-9, 1e-10)
    kw = dict(rotation_iterations=its, translation_iterations=its, tol=None, scheme=scheme)
    p1, i1 = distributed_chordal_initialization(graph, base, **kw)
    p2, i2 = distributed_chordal_initialization(graph, padded, **kw)
    np.testing.assert_allclose(np.asarray(p1.R), np.asarray(p2.R), atol=atol, rtol=0)
    np.testing.assert_allclose(np.asarray(p1.t), np.asarray(p2.t), atol=10 * atol, rtol=0)
    np.testing.assert_allclose(i1.rotation_history[-1], i2.rotation_history[-1], rtol=rtol)
    np.testing.assert_allclose(i1.translation_history[-1], i2.translation_history[-1], rtol=rtol)
    if scheme == "amm":
        np.testing.assert_allclose(i1.rotation_history, i2.rotation_history, rtol=1e-12)
        np.testing.assert_allclose(i1.translation_history, i2.translation_history, rtol=1e-12)


@pytest.mark.parametrize("dim", [2, 3])
def test_first_two_iterations_minimise_the_majorizer_of_eq24(dim):
    """R^1 = argmin G_R(. | R^0) and R^2 = argmin G_R(. | Y^1), Y^1 = R^1 + gamma_1 (R^1 - R^0),
    with G_R of Eq. (24) built explicitly (midpoints P, proximal term) and minimised by lstsq; in 2D
    through the complex (planar) inverse, in 3D through the real one."""
    g, _, _ = random_graph(14, dim, 10, seed=7)
    robots = 3
    xi = 0.3  # large enough to matter
    st = dc._setup(g, robots)
    Ginv = st.gamma_inverse(xi, True)
    assert Ginv.ndim == (4 if dim == 2 else 3)
    R0 = np.asarray(random_graph(14, dim, 0, seed=8)[1])  # arbitrary rotations as R^0
    R0[0] = np.eye(dim)
    R0pad = dc._initial_rotations(st, R0, 14)
    iters = [
        np.asarray(dc._unpad(st, dc._run_rotations(st, Ginv, R0pad, k, None, dc.AMMChordal(restart=False))[0]))
        for k in (1, 2)
    ]
    rob = np.asarray(st.part.robot_of_pose)

    def argmin_majorizer(Y):
        # unknowns: vec(R_1..R_{n-1}) row-major; every term is a weighted linear residual
        n, d = 14, dim
        q = d * d
        rows, rhs = [], []

        def term(w, coeffs, const):
            # residual = sum_p M_p vec(R_p) + const   (R_0 = I folded into const)
            A = np.zeros((q, (n - 1) * q))
            c = np.array(const, dtype=float).ravel()
            for p, M in coeffs:
                if p == 0:
                    c = c + M @ np.eye(d).ravel()
                else:
                    A[:, (p - 1) * q : p * q] += M
            rows.append(np.sqrt(w) * A)
            rhs.append(-np.sqrt(w) * c)

        for e in range(g.num_edges):
            i, j = int(g.i[e]), int(g.j[e])
            Rt, k = np.asarray(g.R[e]), float(g.kappa[e])
            right = np.kron(np.eye(d), Rt.T)  # vec(R Rt) = right vec(R)
            if rob[i] == rob[j]:
                term(0.5 * k, [(i, right), (j, -np.eye(q))], np.zeros(q))
            else:
                P = 0.5 * (Y[i] @ Rt + Y[j])
                term(k, [(i, right)], -P)
                term(k, [(j, np.eye(q))], -P)
        for p in range(1, n):
            term(0.5 * xi, [(p, np.eye(q))], -Y[p])
        x = np.linalg.lstsq(np.concatenate(rows), np.concatenate(rhs), rcond=None)[0]
        return np.concatenate([np.eye(d)[None], x.reshape(n - 1, d, d)])

    np.testing.assert_allclose(iters[0], argmin_majorizer(R0), atol=1e-10)
    s1 = 0.5 * (np.sqrt(5.0) + 1.0)
    gamma1 = (s1 - 1.0) / (0.5 * (np.sqrt(4 * s1**2 + 1) + 1))
    Y1 = iters[0] + gamma1 * (iters[0] - R0)
    np.testing.assert_allclose(iters[1], argmin_majorizer(Y1), atol=1e-10)


def test_algorithm3_without_restart_converges():
    graph, _, _ = random_graph(N, 2, EXTRA, seed=102)
    Rc = chordal_relaxed_rotations(graph)
    R, _, _, _ = distributed_relaxed_rotations(graph, ROBOTS, iterations=ROT_IT, tol=None, scheme="amm",
                                               restart=False)
    assert _rel(relaxed_rotation_cost(graph, R), relaxed_rotation_cost(graph, Rc)) <= 1e-9


@pytest.mark.parametrize("factorization", ["dense", "sparse"])
def test_arbitrary_robot_assignment_and_disconnected_graph(factorization):
    g1, _, _ = random_graph(20, 2, 12, seed=11)
    g2, _, _ = random_graph(12, 2, 8, seed=12)
    g = PoseGraph.from_arrays(
        np.concatenate([g1.i, g2.i + 20]), np.concatenate([g1.j, g2.j + 20]),
        np.concatenate([g1.R, g2.R]), np.concatenate([g1.t, g2.t]),
        np.concatenate([g1.kappa, g2.kappa]), np.concatenate([g1.tau, g2.tau]), 32,
    )  # fmt: skip
    robots = np.random.default_rng(0).permutation(np.arange(32) % 3)
    p, _ = distributed_chordal_initialization(
        g, robots, rotation_iterations=ROT_IT, translation_iterations=TRANS_IT, tol=None, factorization=factorization
    )
    c = chordal_initialization(g)
    np.testing.assert_allclose(np.asarray(p.R), np.asarray(c.R), atol=1e-6)
    np.testing.assert_allclose(np.asarray(p.t), np.asarray(c.t), atol=1e-5)
    np.testing.assert_array_equal(np.asarray(p.R[20]), np.eye(2))  # second component's anchor


def _compiled_programs() -> set:
    """The keys of the driver's compile-once cache (a new shape or structure adds one; the cache is
    bounded, so its size alone would not show a compile once it is full)."""
    from mmpgo_jax._mm import driver

    return set(driver._COMPILED)


def test_tolerance_stop_without_recompiling():
    graph, _, _ = random_graph(N, 3, EXTRA, seed=103)
    traces = []
    Rc = chordal_relaxed_rotations(graph)
    fc = relaxed_rotation_cost(graph, Rc)
    out = {}
    for tol in (1e-6, 1e-12, 1e-13):
        before = _compiled_programs()
        R, hist, k, conv = distributed_relaxed_rotations(graph, ROBOTS, iterations=ROT_IT, tol=tol)
        traces.append(len(_compiled_programs() - before))
        assert conv and 10 <= k < ROT_IT and hist.shape == (k + 1,)
        assert abs(hist[-10] - hist[-1]) <= tol * hist[-1]
        out[tol] = (k, _rel(relaxed_rotation_cost(graph, R), fc))
    assert traces[1:] == [0, 0]  # the same compiled chunk served every tolerance (and the budget)
    assert out[1e-6][0] < out[1e-12][0] <= out[1e-13][0]
    assert out[1e-12][1] <= 1e-9


def test_two_budgets_compile_once():
    """The budget is traced: two budgets run one compiled chunk (from an empty compile-once cache)."""
    from mmpgo_jax._mm import driver

    driver._COMPILED.clear()  # another test of this process may have compiled the same shapes
    graph, _, _ = random_graph(N + 5, 2, EXTRA - 3, seed=104)
    traces = []
    hists = {}
    for budget in (130, 250):
        before = _compiled_programs()
        _, hist, k, conv = distributed_relaxed_rotations(graph, ROBOTS, iterations=budget, tol=None)
        traces.append(len(_compiled_programs() - before))
        assert k == budget and not conv and hist.shape == (budget + 1,) and np.all(np.isfinite(hist))
        hists[budget] = hist
    assert traces[0] >= 1 and traces[1] == 0  # the second budget compiled nothing
    np.testing.assert_array_equal(hists[250][:131], hists[130])  # the same iterates, only more of them


def test_errors():
    graph, _, _ = random_graph(N, 2, EXTRA, seed=102)
    with pytest.raises(ValueError, match="non-negative integer"):
        distributed_chordal_initialization(graph, ROBOTS, rotation_iterations=-1)
    with pytest.raises(ValueError, match="tol"):
        distributed_chordal_initialization(graph, ROBOTS, tol=-1.0)
    with pytest.raises(ValueError, match="initial rotations"):
        distributed_chordal_initialization(graph, ROBOTS, initial_rotations=jnp.zeros((3, 2, 2)))
    with pytest.raises(ValueError, match="initial translations"):
        distributed_chordal_initialization(graph, ROBOTS, initial_translations=jnp.zeros((3, 2)))
    with pytest.raises(ValueError, match="rotations must have shape"):
        distributed_translations(graph, jnp.zeros((3, 2, 2)), ROBOTS)
    other, _, _ = random_graph(N + 1, graph.dim, 3, seed=1)
    with pytest.raises(ValueError, match="partition is for"):
        distributed_chordal_initialization(other, partition(graph, ROBOTS))


def test_dense_reference_is_consistent():
    g, _, _ = random_graph(10, 3, 6, seed=9)
    np.testing.assert_allclose(chordal_relaxed_rotations(g), dense_relaxed_rotations(g), atol=1e-10)


REAL_FILES = [
    pytest.param("MIT.g2o", id="MITb"),
    pytest.param("intel.g2o", id="intel", marks=pytest.mark.slow),
    pytest.param("CSAIL.g2o", id="CSAIL", marks=pytest.mark.slow),
    pytest.param("M3500.g2o", id="M3500", marks=pytest.mark.slow),
    pytest.param("sphere2500.g2o", id="sphere2500", marks=pytest.mark.slow),
    pytest.param("torus3D.g2o", id="torus3D", marks=pytest.mark.slow),
    pytest.param("parking-garage.g2o", id="parking-garage", marks=pytest.mark.slow),
    pytest.param("city10000.g2o", id="city10000", marks=pytest.mark.slow),
]


@pytest.mark.parametrize("name", REAL_FILES)
def test_reaches_centralized_relaxed_solution_on_benchmark(benchmark_file, name):
    """Issue criterion: relaxed objective within 1e-6 of the centralized one with the defaults,
    and f = 2F after projection close to the centralized chordal start."""
    graph = read_g2o(benchmark_file(name)).graph
    f_relaxed = relaxed_rotation_cost(graph, chordal_relaxed_rotations(graph))
    poses, info = distributed_chordal_initialization(graph, 10)
    assert info.rotation_converged and info.translation_converged
    assert abs(info.rotation_history[-1] - f_relaxed) <= 1e-6 * f_relaxed
    f_central = float(cost(graph, chordal_initialization(graph)))
    assert abs(float(cost(graph, poses)) - f_central) <= 1e-4 * f_central


@pytest.mark.parametrize("rotation", [True, False], ids=["rotation", "translation"])
def test_gamma_is_the_blockwise_majorizer_of_the_laplacian(graph, rotation):
    """Each robot's dense Gamma (Eq. (24)), put on the block diagonal Omega in global pose order,
    agrees with the (rotation connection / translation) Laplacian M within a robot, Omega - M is
    positive semidefinite (Omega >= M) with trace 2 d sum kappa (2 sum tau) over inter-robot edges,
    padding slots hold the identity and anchors are eliminated."""
    from mmpgo_jax._core.pose_graph import data_matrix, host_graph

    g = host_graph(graph)
    d, n = g.dim, g.num_poses
    part = partition(graph, ROBOTS)
    A, n_max = part.pose_mask.shape
    b = d if rotation else 1
    no_anchor = np.zeros((A, n_max), dtype=bool)
    G = dc._gamma_matrices(part, no_anchor, 0.0, d, rotation)
    zero = np.zeros_like(g.kappa)
    only = PoseGraph(g.i, g.j, g.R, g.t, g.kappa if rotation else zero, zero if rotation else g.tau, num_poses=n)
    M = data_matrix(only).toarray()
    cols = (n + d * np.arange(n)[:, None] + np.arange(d)) if rotation else np.arange(n)[:, None]
    M = M[np.ix_(cols.reshape(-1), cols.reshape(-1))]
    robot, slot = np.asarray(part.robot_of_pose), np.asarray(part.slot_of_pose)
    rows = (b * slot[:, None] + np.arange(b)).reshape(-1)  # each pose's rows in its robot's Gamma
    owner = np.repeat(robot, b)
    same = owner[:, None] == owner[None, :]  # both rows of one robot
    Omega = np.where(same, G[owner[:, None], rows[:, None], rows[None, :]], 0.0)
    off_diagonal_block = np.repeat(np.repeat(~np.eye(n, dtype=bool), b, 0), b, 1)
    np.testing.assert_allclose(Omega[same & off_diagonal_block], M[same & off_diagonal_block], atol=1e-12)
    D = Omega - M
    scale = np.abs(M).max()
    assert np.linalg.eigvalsh(D).min() >= -1e-10 * scale
    inter = robot[g.i] != robot[g.j]
    w = g.kappa if rotation else g.tau
    np.testing.assert_allclose(np.trace(D), 2 * b * w[inter].sum(), rtol=1e-10)
    padding = np.repeat(~np.asarray(part.pose_mask), b, axis=1)
    diag = np.diagonal(G, axis1=1, axis2=2)
    assert np.all(diag[padding] == 1.0)
    # anchors: identity rows and columns, the rest unchanged
    anchor = np.zeros((A, n_max), dtype=bool)
    anchor[robot[0], slot[0]] = True
    Ga = dc._gamma_matrices(part, anchor, 0.0, d, rotation)
    fixed = np.repeat(anchor, b, axis=1)[robot[0]]
    np.testing.assert_array_equal(Ga[robot[0]][fixed][:, fixed], np.eye(b))
    assert not Ga[robot[0]][fixed][:, ~fixed].any() and not Ga[robot[0]][~fixed][:, fixed].any()
    np.testing.assert_array_equal(Ga[robot[0]][~fixed][:, ~fixed], G[robot[0]][~fixed][:, ~fixed])


def test_inverses_that_cannot_fit_are_refused_in_one_line(graph, monkeypatch):
    """Dense per-robot inverses are sized before they are built: with too little memory
    ``factorization="dense"`` stops with a ValueError naming the size, the memory available and the
    ways out; ``"auto"`` takes the sparse factors instead and returns the same start."""
    dense, _ = distributed_chordal_initialization(graph, ROBOTS, factorization="dense")
    monkeypatch.setattr(dc, "available_memory_bytes", lambda: 1000)
    with pytest.raises(ValueError, match=r"inverse per robot: 4 robots need about .* GB, more than the 0\.0 GB .*"
                                         r"factorization='sparse' .* more robots .* or init='chordal'"):
        distributed_chordal_initialization(graph, ROBOTS, rotation_iterations=10, factorization="dense")
    auto, info = distributed_chordal_initialization(graph, ROBOTS)
    assert info.factorizations == ("sparse", "sparse")
    np.testing.assert_allclose(np.asarray(auto.R), np.asarray(dense.R), atol=1e-8)
    np.testing.assert_allclose(np.asarray(auto.t), np.asarray(dense.t), atol=1e-7 * np.abs(np.asarray(dense.t)).max())


@pytest.mark.parametrize("dim", [2, 3])
def test_cg_is_monotone_and_terminates_within_the_unknowns(dim):
    """Preconditioned CG on a quadratic with q unknowns per column reaches its minimiser within q
    iterations (up to rounding; the float32 preconditioner's included), and its objective never
    increases on the way: checked on both stages against the centralized sparse solution."""
    graph, _, _ = random_graph(24, dim, 20, seed=200 + dim)
    n, d = graph.num_poses, graph.dim
    Rc = chordal_relaxed_rotations(graph)
    R, hR, kR, _ = distributed_relaxed_rotations(graph, ROBOTS, iterations=d * (n - 1), tol=None)
    assert kR == d * (n - 1)
    assert _rel(relaxed_rotation_cost(graph, R), relaxed_rotation_cost(graph, Rc)) <= 1e-9
    assert np.all(np.diff(hR) <= 1e-12 * hR[0])
    Rp = np.asarray(chordal_initialization(graph).R)
    tc = translations_given_rotations(graph, Rp)
    t, ht, _, _ = distributed_translations(graph, Rp, ROBOTS, iterations=n - 1, tol=None)
    np.testing.assert_allclose(np.asarray(t), tc, atol=1e-6)
    assert np.all(np.diff(ht) <= 1e-12 * ht[0])


def test_cg_preconditioner_in_float32_unless_its_factorization_fails(graph, monkeypatch):
    """CG's Gamma^{-1} is float32 (close to the float64 inverse), and float64 where a float32
    Cholesky factorization fails; AMM-Chordal's majorizer is always in the graph's precision."""
    st = dc._setup(graph, ROBOTS)
    exact = np.asarray(st.gamma_inverse(1e-3, True))
    single = st.gamma_inverse(1e-3, True, single=True)
    assert exact.dtype == np.float64 and single.dtype == np.float32
    np.testing.assert_allclose(np.asarray(single), exact, atol=1e-4 * np.abs(exact).max())
    invert = dc._invert_in_place
    # a float32 factorization reports "not positive definite" (LAPACK info > 0)
    monkeypatch.setattr(dc, "_invert_in_place",
                        lambda G, out=None, max_condition=None: (0, 1) if G.dtype in (np.float32, np.complex64)
                        else invert(G, out, max_condition))
    fallback = st.gamma_inverse(1e-3, True, single=True)
    assert fallback.dtype == np.float64
    np.testing.assert_allclose(np.asarray(fallback), exact, rtol=1e-12, atol=1e-14)


def test_cg_preconditioner_in_float64_where_float32_would_be_inexact(graph, monkeypatch):
    """float32 only where every robot's condition number times float32's roundoff is at most
    SINGLE_PRECISION_ERROR: the rule follows LAPACK's condition estimate (within a factor 10 of the
    exact 1-norm condition number of each robot's Gamma)."""
    st = dc._setup(graph, ROBOTS)
    G = dc._gamma_matrices(st.part, np.asarray(st.anchor), 1e-3, graph.dim, True)
    kappa = max(np.linalg.cond(G[a], 1) for a in range(G.shape[0]))
    u = np.finfo(np.float32).eps
    monkeypatch.setattr(dc, "SINGLE_PRECISION_ERROR", 10 * kappa * u)
    assert st.gamma_inverse(1e-3, True, single=True).dtype == np.float32
    monkeypatch.setattr(dc, "SINGLE_PRECISION_ERROR", 0.1 * kappa * u)
    assert st.gamma_inverse(1e-3, True, single=True).dtype == np.float64


def test_invert_in_place_refuses_an_ill_conditioned_matrix_by_its_condition_estimate():
    """``max_condition``: a matrix whose estimated condition number exceeds it is a failure (info 0)
    and a well-conditioned one is inverted as without it."""
    rng = np.random.default_rng(3)
    Q, _ = np.linalg.qr(rng.normal(size=(40, 40)))
    ill = (Q * np.logspace(0, 8, 40)) @ Q.T
    well = (Q * np.linspace(1, 2, 40)) @ Q.T
    assert dc._invert_in_place(np.stack([well, ill]).astype(np.float32), max_condition=1e6) == (1, 0)
    G = np.stack([well, well]).astype(np.float32)
    assert dc._invert_in_place(G, max_condition=1e6) is None
    np.testing.assert_allclose(G[0], np.linalg.inv(well), rtol=1e-4, atol=1e-5)


def test_scheme_options_are_checked():
    graph, _, _ = random_graph(N, 2, EXTRA, seed=102)
    with pytest.raises(ValueError, match="scheme must be one of 'cg', 'amm'"):
        distributed_chordal_initialization(graph, ROBOTS, scheme="jacobi")
    with pytest.raises(ValueError, match="restart applies to scheme='amm'"):
        distributed_chordal_initialization(graph, ROBOTS, restart=False)
    _, info = distributed_chordal_initialization(graph, ROBOTS, scheme="amm", rotation_iterations=20,
                                                 translation_iterations=20)
    assert info.scheme == "amm" and info.restart


def test_planar_inverse_is_the_real_inverse_as_complex_numbers():
    """For d = 2 every 2 x 2 block of Gamma_R^alpha is a scaled rotation, so the inverse is stored as a
    complex matrix (real and imaginary parts): it equals the dense real inverse's blocks, and applying
    it gives the real inverse's product; a graph with a non-rotation measurement keeps the real one."""
    g, _, _ = random_graph(N, 2, EXTRA, seed=102)
    st = dc._setup(g, ROBOTS)
    anchor = np.asarray(st.anchor)
    planar = dc._gamma_inverses(st.part, anchor, 0.3, 2, True)
    real = np.linalg.inv(dc._gamma_matrices(st.part, anchor, 0.3, 2, True))
    assert planar.shape == (ROBOTS, 2, real.shape[1] // 2, real.shape[1] // 2)
    np.testing.assert_allclose(planar[:, 0], real[:, 0::2, 0::2], atol=1e-12)
    np.testing.assert_allclose(planar[:, 1], real[:, 1::2, 0::2], atol=1e-12)
    G = np.random.default_rng(0).normal(size=(ROBOTS, real.shape[1] // 2, 2, 2))
    np.testing.assert_allclose(np.asarray(dc._apply_inverse_rot(jnp.asarray(planar), jnp.asarray(G))),
                               np.asarray(dc._apply_inverse_rot(jnp.asarray(real), jnp.asarray(G))), atol=1e-12)
    reflected = PoseGraph(g.i, g.j, g.R.at[0].set(jnp.diag(jnp.array([1.0, -1.0]))), g.t, g.kappa, g.tau,
                          num_poses=g.num_poses)
    assert dc._gamma_inverses(dc._setup(reflected, ROBOTS).part, anchor, 0.3, 2, True).ndim == 3


@pytest.mark.parametrize("rotation", [True, False], ids=["rotation", "translation"])
def test_sparse_factors_apply_the_dense_inverse(graph, rotation):
    """The sparse Gamma (all robots block-diagonal, anchors as identity rows) holds each robot's dense
    Gamma on its diagonal block and nothing else, and its factors applied from inside a compiled
    program (the host callback; complex for planar rotations) equal the dense inverse's product."""
    import jax

    st = dc._setup(graph, ROBOTS)
    anchor = np.asarray(st.anchor)
    d = graph.dim
    dense = dc._gamma_matrices(st.part, anchor, 0.3, d, rotation)
    A, N, _ = dense.shape
    planar = rotation and d == 2 and dc._planar(st.part)
    sparse = dc._gamma_sparse(st.part, anchor, 0.3, d, rotation, planar)
    if planar:  # the complex matrix of the 2 x 2 blocks [[a, -b], [b, a]] -> a + i b
        blocks = dense[:, 0::2, 0::2] + 1j * dense[:, 1::2, 0::2]
    else:
        blocks = dense
    from scipy.linalg import block_diag

    # the same entries summed in another order: equal up to rounding
    np.testing.assert_allclose(sparse.toarray(), block_diag(*blocks), rtol=0, atol=1e-13 * np.abs(dense).max())
    handle = dc.SparseFactors.register(sparse)
    try:
        shape = (A, N // d, d, d) if rotation else (A, N, d)
        G = jnp.asarray(np.random.default_rng(1).normal(size=shape))
        got = jax.jit(dc._apply_sparse)(jnp.asarray(handle, jnp.int32), G)
        apply = dc._apply_inverse_rot if rotation else dc._apply_inverse_trans
        want = apply(jnp.asarray(np.linalg.inv(dense)), G)
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=1e-10 * float(np.abs(want).max()))
    finally:
        dc.SparseFactors.release(handle)


@SCHEMES
def test_sparse_and_dense_factorizations_give_the_same_start(graph, scheme):
    """Both stages with the robots' sparse factors: the same iterations and start as with the dense
    inverses (to the float32 preconditioner's rounding for CG; AMM-Chordal's inverse is exact in
    both), and no factor left registered afterwards."""
    dense, di = distributed_chordal_initialization(graph, ROBOTS, scheme=scheme, factorization="dense")
    sparse, si = distributed_chordal_initialization(graph, ROBOTS, scheme=scheme, factorization="sparse")
    assert di.factorizations == ("dense", "dense") and si.factorizations == ("sparse", "sparse")
    assert not dc.SparseFactors._live
    assert abs(si.rotation_iterations - di.rotation_iterations) <= 10
    assert abs(si.translation_iterations - di.translation_iterations) <= 10
    np.testing.assert_allclose(float(cost(graph, sparse)), float(cost(graph, dense)), rtol=1e-8)
    np.testing.assert_allclose(np.asarray(sparse.R), np.asarray(dense.R), atol=1e-6)
    if scheme == "cg":  # the option through initialize(), as the CLI's and solve()'s starts call it
        from mmpgo_jax import initialize

        via = initialize(graph, "distributed-chordal", robots=ROBOTS, factorization="sparse")
        np.testing.assert_array_equal(np.asarray(via.R), np.asarray(sparse.R))


def test_factorization_auto_follows_the_cache_and_is_checked(graph, monkeypatch):
    """``"auto"`` applies dense inverses that fit in the largest CPU cache and sparse factors beyond
    it (each stage on its own size); an unknown value is refused."""
    st = dc._setup(graph, ROBOTS)
    size = dc._dense_inverse_bytes(st, True, True)
    A, n_max = st.part.pose_mask.shape
    planar = graph.dim == 2 and dc._planar(st.part)
    assert size == A * (n_max * (1 if planar else graph.dim)) ** 2 * 4 * (2 if planar else 1)
    monkeypatch.setattr(dc, "last_level_cache_bytes", lambda: size)
    assert not dc._use_sparse(st, True, True, "auto")
    monkeypatch.setattr(dc, "last_level_cache_bytes", lambda: size - 1)
    assert dc._use_sparse(st, True, True, "auto")
    assert not dc._use_sparse(st, True, True, "dense") and dc._use_sparse(st, False, True, "sparse")
    # float32 inverses that fit, refused by the precision rule: their float64 twins do not fit
    solver = dc.CGChordal()
    monkeypatch.setattr(dc, "last_level_cache_bytes", lambda: size)
    with dc._preconditioner(st, 1e-3, True, solver, "auto") as Ginv:
        assert not isinstance(Ginv, int) and Ginv.dtype == np.float32
    monkeypatch.setattr(dc, "SINGLE_PRECISION_ERROR", 0.0)
    with dc._preconditioner(st, 1e-3, True, solver, "auto") as Ginv:
        assert isinstance(Ginv, int)
    assert not dc.SparseFactors._live
    monkeypatch.setattr(dc, "last_level_cache_bytes", lambda: 2 * size)
    with dc._preconditioner(st, 1e-3, True, solver, "auto") as Ginv:
        assert not isinstance(Ginv, int) and Ginv.dtype == np.float64
    with pytest.raises(ValueError, match="factorization must be one of 'auto', 'dense', 'sparse'"):
        distributed_chordal_initialization(graph, ROBOTS, factorization="cholmod")


def test_last_level_cache_is_a_size():
    from mmpgo_jax._core.resources import last_level_cache_bytes

    size = last_level_cache_bytes()
    assert isinstance(size, int) and (1 << 16) <= size <= (1 << 34)


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.complex64, np.complex128])
def test_inverse_of_a_decaying_matrix_is_accurate_and_has_no_subnormals(dtype):
    """A chain with a strong diagonal (as a robot's Gamma with many inter-robot edge ends) has an
    inverse whose entries decay along the chain far below the smallest normal number: the inverse
    (tiny entries flushed between the LAPACK steps) matches the float64 dense inverse normwise to the
    precision's rounding, and holds no subnormal number (they slow every later product)."""
    n, A = 400, 2
    off = -np.ones(n - 1)
    if np.issubdtype(dtype, np.complexfloating):
        off = off * np.exp(0.3j)  # a Hermitian "connection" chain
    M = np.diag(np.full(n, 40.0)) + np.diag(off, -1) + np.diag(off.conj(), 1)  # decay 1/40 per step
    G = np.stack([M, 2.0 * M]).astype(dtype)
    reference = np.linalg.inv(np.stack([M, 2.0 * M]))
    assert abs(reference[0, -1, 0]) < np.finfo(np.float64).tiny  # the decay reaches float64's subnormals
    out = np.empty((A, 2, n, n), np.finfo(dtype).dtype) if np.iscomplexobj(G) else None
    assert dc._invert_in_place(G, out) is None
    inverse = G if out is None else out[:, 0] + 1j * out[:, 1]
    eps = np.finfo(dtype).eps
    for a in range(A):
        assert np.linalg.norm(inverse[a] - reference[a], 2) <= 10 * n * eps * np.linalg.norm(reference[a], 2)
    real_parts = inverse.view(np.finfo(dtype).dtype) if np.iscomplexobj(inverse) else inverse
    assert not np.any((real_parts != 0) & (np.abs(real_parts) < np.finfo(dtype).tiny))


def _ring(n: int, holonomy: float) -> PoseGraph:
    """One cycle of ``n`` unit steps whose measured rotations turn by 2 pi + ``holonomy`` in all: near
    pi the relaxed rotations collapse (the blocks opposite the anchor shrink towards 0), as on long
    noisy chains, and their projection to SO(2) amplifies any error of the rotation stage."""
    i = np.arange(n)
    th = np.full(n, (2 * np.pi + holonomy) / n)
    R = np.stack([np.stack([np.cos(th), -np.sin(th)], -1), np.stack([np.sin(th), np.cos(th)], -1)], -2)
    return PoseGraph.from_arrays(i, (i + 1) % n, R, np.tile([1.0, 0.0], (n, 1)), np.ones(n), np.ones(n),
                                 num_poses=n)


def test_a_collapsed_relaxation_is_solved_until_its_projection_settles():
    """With nearly opposite rotations around the ring the relaxed objective settles (relative change
    under tol) while the blocks it projects are still off; the rotation stage goes on until its
    residual is within sqrt(tol) of the smallest block's singular value, and the start then equals
    the centralized chordal start (the objective's relative-change rule alone stopped at 30
    iterations, 1.1e-6 above it)."""
    g = _ring(300, np.pi - 1e-6)
    X, info = distributed_chordal_initialization(g, 10)
    central = float(cost(g, chordal_initialization(g)))
    assert info.rotation_converged
    assert _rel(float(cost(g, X)), central) < 1e-9
    R, _, _, _ = distributed_relaxed_rotations(g, 10)
    assert np.linalg.svd(np.asarray(R), compute_uv=False)[:, -1].min() < 1e-3  # the collapse the rule is for


def test_the_projection_bound_applies_only_where_the_residual_is_above_it():
    g = np.array([2.0, 1e-9])  # residual norms: the first and the last of a stage
    assert dc._projection_settled(g, 1.0, 1e-10) is None  # 5e-10 <= sqrt(1e-10) * 1
    bound = dc._projection_settled(g, 1e-6, 1e-10)  # 5e-10 > 1e-5 * 1e-6
    assert bound == pytest.approx(2.0 * 1e-5 * 1e-6)
