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
