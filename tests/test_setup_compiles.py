"""The host set-up of a run compiles nothing: partitioning, the chordal start, building Gamma and
the preconditioner, and unpacking a result move host arrays to the device by transfers, never by
a JAX operation (op by op, every new shape would compile a small program: 1-16 ms each, a dozen
per run before these were removed; benchmarks/end_to_end.md). Checked with JAX's own compile log
on shapes no other test uses."""

import logging

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mmpgo_jax import cube_dataset, grid_2d_dataset, initialize
from mmpgo_jax._core.partition import partition
from mmpgo_jax._core.pose_graph import Poses
from mmpgo_jax._core.precision import to_device
from mmpgo_jax._mm.majorization import stack, unstack
from mmpgo_jax._mm.outer import MMConfig, MMProblem
from mmpgo_jax._mm.subproblem import SubproblemConfig


def _compiled(caplog, fn):
    """fn's result and the programs JAX compiled while it ran (their log lines)."""
    caplog.clear()
    with jax.log_compiles(True), caplog.at_level(logging.DEBUG):
        out = fn()
    return out, [r.getMessage() for r in caplog.records if r.getMessage().startswith("Compiling")]


@pytest.mark.parametrize("dim, poses, robots", [(2, 53, 3), (3, 41, 4)])
def test_build_and_unpacking_compile_nothing(caplog, dim, poses, robots):
    make = grid_2d_dataset if dim == 2 else cube_dataset
    graph = make(7, num_poses=poses, grid=4).graph
    part, compiled = _compiled(caplog, lambda: partition(graph, robots))
    assert not compiled
    X0, _ = _compiled(caplog, lambda: initialize(graph, "chordal"))
    padded = part.scatter(X0)
    for kind in ("two-level", "block-jacobi"):
        config = MMConfig(subproblem=SubproblemConfig(preconditioner=kind))
        problem, compiled = _compiled(caplog, lambda config=config: MMProblem.build(part, config=config, poses=padded))
        assert not compiled, compiled
        assert problem.xi.dtype == problem.gamma_soa.diag.dtype
    # a result's unpacking (solve's last step) on the host
    Y = np.asarray(stack(jax.tree.map(np.asarray, padded)))
    poses_back, compiled = _compiled(caplog, lambda: part.gather(unstack(Y)))
    assert not compiled, compiled
    np.testing.assert_array_equal(np.asarray(poses_back.t), np.asarray(X0.t))


def test_to_device_gives_the_dtype_jnp_asarray_gives():
    for x, dt in [(np.arange(5), np.int32), (np.ones((2, 3)), None), (np.ones(3, np.float32), np.float64),
                  (np.array([True, False]), None), (0.5, np.float64)]:
        ours, theirs = to_device(x, dt), jnp.asarray(x, dt)
        assert isinstance(ours, jax.Array) and ours.dtype == theirs.dtype and ours.shape == theirs.shape
        np.testing.assert_array_equal(np.asarray(ours), np.asarray(theirs))


def test_stack_keeps_host_arrays_on_the_host():
    R = np.broadcast_to(np.eye(2), (4, 2, 2)).copy()
    t = np.arange(8.0).reshape(4, 2)
    Y = stack(Poses(R, t))
    assert isinstance(Y, np.ndarray) and Y.shape == (4, 2, 3)
    np.testing.assert_array_equal(Y[..., 0], t)
    assert isinstance(stack(Poses(jax.device_put(R), jax.device_put(t))), jax.Array)


@pytest.mark.parametrize("dim, poses", [(2, 47), (3, 39)])
def test_a_robust_solves_host_decisions_compile_nothing(caplog, dim, poses):
    """Edge selection, edge costs and GNC's weights between runs (the robust starts, re-admissions,
    removals) run in NumPy: op by op they compiled about 140 small programs in a cold TLS run on MIT
    (3.5 s of its 9.5 s). Their values are those of the jitted functions."""
    from mmpgo_jax._core.pose_graph import edge_costs, host_edge_costs, host_graph
    from mmpgo_jax._mm.robust import TLS, gnc_initial_mu, gnc_rho, gnc_weight

    make = grid_2d_dataset if dim == 2 else cube_dataset
    graph = make(5, num_poses=poses, grid=4).graph  # device arrays
    X = initialize(graph, "odometry")  # device poses, away from the optimum
    keep = np.arange(graph.num_edges) % 3 != 1
    sub, compiled = _compiled(caplog, lambda: graph.select_edges(keep))
    assert not compiled, compiled
    for ours, theirs in zip(jax.tree.leaves(sub), jax.tree.leaves(graph), strict=True):
        assert isinstance(ours, jax.Array) and ours.dtype == theirs.dtype and ours.sharding == theirs.sharding
        np.testing.assert_array_equal(np.asarray(ours), np.asarray(theirs)[keep])
    reference = np.asarray(jax.jit(edge_costs)(graph, X))
    for g in (graph, host_graph(graph)):
        s, compiled = _compiled(caplog, lambda g=g: host_edge_costs(g, X))
        assert not compiled, compiled
        assert isinstance(s, np.ndarray)
        np.testing.assert_allclose(s, reference, rtol=1e-10, atol=1e-12 * reference.max())
    s_np = np.concatenate([s, [0.0, 9.0, 1e12]])
    c2 = 2.5 * float(np.median(s_np))
    for mu in (0.3, 7.0, np.inf):
        (w, r), compiled = _compiled(caplog, lambda mu=mu: (gnc_weight(TLS, s_np, c2, mu), gnc_rho(TLS, s_np, c2, mu)))
        assert not compiled, compiled
        assert isinstance(w, np.ndarray) and np.all(np.isfinite(w)) and np.all(np.isfinite(r))
        w_jit, r_jit = jax.jit(lambda s, mu: (gnc_weight(TLS, s, c2, mu), gnc_rho(TLS, s, c2, mu)))(s_np, mu)
        np.testing.assert_allclose(w, np.asarray(w_jit), rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(r, np.asarray(r_jit), rtol=1e-12, atol=1e-12 * c2)
    mu0, compiled = _compiled(caplog, lambda: gnc_initial_mu(TLS, np.max(s_np), c2))
    assert not compiled and np.isclose(mu0, c2 / (2.0 * 1e12 - c2), rtol=1e-12)
