"""DGS as a solver of the one solve path (``mm.solve(graph, robots, solver=mm.DGS())``): its history is
``dgs()``'s, its stopping rule stops the driver, the colour-class schedule is a Gauss–Seidel order of its
own and converges to a dense solve of the Gauss–Newton system (tests/test_dgs.py's NumPy reference), and a
run sharded over two devices equals the one-device run."""

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from test_dgs import _dense_gauss_newton, _weights

import mmpgo_jax as mm
from mmpgo_jax._baselines.dgs import dgs
from mmpgo_jax._baselines.dgs_solver import colour_classes

ROBOTS = 3


@pytest.fixture(scope="module")
def graphs():
    return {
        3: mm.cube_dataset(seed=0, grid=3, num_poses=60).graph,
        2: mm.grid_2d_dataset(seed=1, grid=4, num_poses=45).graph,
    }


def _solve(graph, solver, iterations, robots=ROBOTS, chunk_size=25):  # dgs()'s chunk: one compilation
    return mm.solve(graph, robots, solver=solver, iterations=iterations, chunk_size=chunk_size,
                    stop_when_stalled=False)


@pytest.mark.parametrize(("d", "weights"), [(3, "information"), (2, "unit")])
def test_history_is_dgs_functions(graphs, d, weights):
    """Budget runs (the change rule does not hold within 40 sweeps): f per sweep and the poses."""
    g = graphs[d]
    r = _solve(g, mm.DGS(weights=weights), 40)
    ref = dgs(g, ROBOTS, iterations=40, weights=weights)
    assert r.result is mm.RESULTS.iterations and ref.stop_reason == "max_iterations"
    np.testing.assert_allclose(r.history.f, ref.history, rtol=1e-10, atol=0)
    np.testing.assert_allclose(np.asarray(r.poses.t), np.asarray(ref.poses.t), atol=1e-9)
    assert r.f == pytest.approx(float(mm.cost(g, r.poses)), rel=1e-12)


def test_stopping_rule_stops_the_driver(graphs):
    """Their rule (every robot's change <= pose_tol after a sweep, not the first) stops the run inside a
    chunk: the history ends at that sweep, as dgs()'s does, and the state after it is that sweep's."""
    g = graphs[2]
    solver = mm.DGS(weights="unit", pose_tol=1e-5)
    r = _solve(g, solver, 3000, chunk_size=7)
    ref = dgs(g, ROBOTS, iterations=3000, weights="unit", pose_tol=1e-5)
    K = r.history.iterations
    assert r.result is mm.RESULTS.converged and ref.stop_reason == "converged"
    assert 1 < K < 3000 and K % 7 != 0 and K == ref.iterations
    np.testing.assert_allclose(r.history.f, ref.history, rtol=1e-10, atol=0)
    budget = _solve(g, mm.DGS(weights="unit", pose_tol=0.0), K, chunk_size=7)  # the rule off: K sweeps
    assert budget.result is mm.RESULTS.iterations
    np.testing.assert_allclose(np.asarray(r.poses.t), np.asarray(budget.poses.t), rtol=0, atol=1e-12)


def test_colour_classes_are_a_gauss_seidel_order(graphs):
    """A colour class updates at once; its robots share no edge, so the sweep equals the sequential one
    in the order sorted by class."""
    g = graphs[2]
    robots = 6
    part = mm.partition(g, robots)
    colour = colour_classes(part, np.arange(robots))
    assert colour.max() + 1 < robots  # classes of several robots
    order = np.argsort(colour, kind="stable")
    colours = _solve(g, mm.DGS(order="natural", schedule="colours"), 12, robots=robots)
    sequential = _solve(g, mm.DGS(order=order), 12, robots=robots)
    np.testing.assert_allclose(colours.history.f, sequential.history.f, rtol=1e-10, atol=0)
    np.testing.assert_allclose(np.asarray(colours.poses.t), np.asarray(sequential.poses.t), atol=1e-10)


@pytest.mark.parametrize("d", [2, 3])
def test_colours_converge_to_the_dense_gauss_newton_step(graphs, d):
    """Unit weights (their contraction per sweep is fast), flagged first sweep by class."""
    g = graphs[d]
    r = _solve(g, mm.DGS(weights="unit", schedule="colours", pose_tol=1e-11), 3000, robots=6)
    assert r.result is mm.RESULTS.converged
    R, t = _dense_gauss_newton(g, mm.initialize(g, "chordal"), _weights(g, "unit"))
    np.testing.assert_allclose(np.asarray(r.poses.R), np.asarray(R), atol=1e-8)
    np.testing.assert_allclose(np.asarray(r.poses.t), np.asarray(t), atol=1e-8)


def test_settings_are_checked(graphs):
    with pytest.raises(ValueError, match="weights"):
        mm.DGS(weights="covariance")
    with pytest.raises(ValueError, match="schedule"):
        mm.DGS(schedule="random")
    with pytest.raises(ValueError, match="relaxation"):
        mm.DGS(relaxation=0.0)
    with pytest.raises(ValueError, match="pose_tol"):
        mm.DGS(pose_tol=-1.0)
    with pytest.raises(ValueError, match="order"):
        mm.DGS(order=[0, 0, 1])
    with pytest.raises(ValueError, match="jacobi"):
        mm.DGS(jacobi=True, schedule="colours")
    with pytest.raises(ValueError, match=r"rotation stage.*start='code'"):
        mm.DGS(rotations=True)
    with pytest.raises(ValueError, match="permutation of the 3 robots"):
        mm.solve(graphs[2], ROBOTS, solver=mm.DGS(order=[1, 0]), iterations=2)
    with pytest.raises(ValueError, match="least-squares"):
        mm.solve(graphs[2], ROBOTS, solver=mm.DGS(), iterations=2, loss="huber")


# one device and two virtual CPU devices in a child process (the device count is fixed when JAX starts)
_CHILD = textwrap.dedent("""
    import json
    import jax
    jax.config.update("jax_enable_x64", True)
    import mmpgo_jax as mm
    from mmpgo_jax.sharding import Sharded

    graph = mm.grid_2d_dataset(seed=1, grid=4, num_poses=45).graph
    out = {}
    for schedule in ("sequential", "colours"):
        for name, layout in (("one", mm.OneDevice()), ("two", Sharded(devices=2))):
            r = mm.solve(graph, 3, solver=mm.DGS(weights="unit", schedule=schedule, pose_tol=1e-4), layout=layout,
                         iterations=500, chunk_size=10, stop_when_stalled=False)
            out[schedule + name] = dict(f=r.history.f.tolist(), t=r.poses.t.tolist(), result=r.result.value,
                                        devices=r.stats.get("devices", 1))
    print(json.dumps(out))
""")


@pytest.mark.slow  # ~60 s: a child process with two devices, four compilations
def test_sharded_equals_one_device():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    proc = subprocess.run([sys.executable, "-c", _CHILD], capture_output=True, text=True, env=env, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    for schedule in ("sequential", "colours"):
        one, two = out[schedule + "one"], out[schedule + "two"]
        assert two["devices"] == 2 and one["result"] == two["result"] == "converged"
        np.testing.assert_allclose(two["f"], one["f"], rtol=1e-12, atol=0, err_msg=schedule)
        np.testing.assert_allclose(two["t"], one["t"], rtol=0, atol=1e-10, err_msg=schedule)
