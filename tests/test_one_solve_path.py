"""One solve path: solvers as objects, the layout as an argument, one builder for every entry point."""

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import mmpgo_jax as mm
from mmpgo_jax._mm.driver import Termination

TIMINGS = ("initialize_seconds", "build_seconds", "init_seconds", "compile_seconds", "solve_seconds")

# solve, solve_sharded on two virtual CPU devices and a sweep of one configuration, in a child process
# (the device count is fixed when JAX starts); float64 so that 1e-12 is a meaningful tolerance.
_CHILD = textwrap.dedent("""
    import dataclasses, json
    import jax
    jax.config.update("jax_enable_x64", True)
    import mmpgo_jax as mm
    from mmpgo_jax.sharding import solve_sharded

    graph = mm.cube_dataset(3, num_poses=150, grid=4).graph
    common = dict(iterations=40, chunk_size=10, stop_when_stalled=False)
    results = {
        "solve": mm.solve(graph, 4, **common),
        "solve_sharded": solve_sharded(graph, 4, devices=2, **common),
        "sweep": mm.sweep({"cube": graph}, robots=4, methods="amm", iterations=40,
                          chunk_size=10).results[("cube", 4, "amm")],
    }
    out = {}
    for name, r in results.items():
        out[name] = dict(f=r.history.f.tolist(), fields=[f.name for f in dataclasses.fields(r)],
                         stats={k: r.stats.get(k) for k in TIMINGS}, solver=repr(r.solver), config=repr(r.config),
                         result=r.result.value, poses_R=r.poses.R.tolist(), start_t=r.start.t.tolist(),
                         devices=r.stats.get("devices"))
    print(json.dumps(out))
""").replace("TIMINGS", repr(TIMINGS))


@pytest.fixture(scope="module")
def three_entry_points():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    proc = subprocess.run([sys.executable, "-c", _CHILD], capture_output=True, text=True, env=env, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_entry_points_share_one_builder(three_entry_points):
    r = three_entry_points
    f = np.asarray(r["solve"]["f"])
    assert len(f) == 41
    for name in ("solve_sharded", "sweep"):
        np.testing.assert_allclose(r[name]["f"], f, rtol=1e-12, atol=0, err_msg=name)
        np.testing.assert_allclose(r[name]["poses_R"], r["solve"]["poses_R"], rtol=0, atol=1e-9, err_msg=name)
        np.testing.assert_array_equal(r[name]["start_t"], r["solve"]["start_t"], err_msg=name)
    assert r["solve_sharded"]["devices"] == 2
    fields = {tuple(v["fields"]) for v in r.values()}
    assert len(fields) == 1, fields  # the same result fields whatever the layout
    assert {v["solver"] for v in r.values()} == {r["solve"]["solver"]}
    assert {v["result"] for v in r.values()} == {"iterations"}
    for name, v in r.items():
        for key in TIMINGS:  # every timing measured, none 0.0 by omission
            assert v["stats"][key] is not None and v["stats"][key] > 0, (name, key, v["stats"])


@pytest.fixture(scope="module")
def cube():
    return mm.cube_dataset(1, num_poses=100, grid=4).graph


def test_solver_objects_equal_the_shortcuts(cube):
    a = mm.solve(cube, 3, method="mm", xi=2e-3, iterations=15, chunk_size=5)
    b = mm.solve(cube, 3, solver=mm.MM(xi=2e-3), termination=Termination(15, 5))
    np.testing.assert_array_equal(a.history.f, b.history.f)
    assert a.solver == b.solver and a.config == b.solver.config and a.config.xi == 2e-3
    c = mm.solve(cube, 3, solver=mm.AMM(restart="paper"), iterations=15, chunk_size=5)
    d = mm.solve(cube, 3, method="amm", restart="paper", iterations=15, chunk_size=5)
    np.testing.assert_array_equal(c.history.f, d.history.f)


def test_each_number_has_one_owner(cube):
    with pytest.raises(ValueError, match="inside the solver"):
        mm.solve(cube, 3, solver=mm.AMM(), xi=1e-2)
    with pytest.raises(ValueError, match="inside the Termination"):
        mm.solve(cube, 3, termination=Termination(10), iterations=5)
    with pytest.raises(TypeError, match="solver must be a Solver"):
        mm.solve(cube, 3, solver="amm")
    with pytest.raises(ValueError, match=r"start= .* not both"):
        mm.solve(cube, 3, start="chordal", init="odometry")


def test_mmconfig_still_names_a_solver(cube):
    config = mm.MMConfig(method="amm", restart="average", xi=5e-3)
    r = mm.solve(cube, 3, solver=config, iterations=10, chunk_size=5)
    assert isinstance(r.solver, mm.AMM) and r.solver.config == config


def test_solver_is_traced_numbers_static_structure(cube):
    """Two solvers that differ only in xi run one compiled chunk (xi is a traced leaf)."""
    from mmpgo_jax._mm import driver

    mm.solve(cube, 3, solver=mm.AMM(xi=1e-3), iterations=10, chunk_size=5)
    before = set(driver._COMPILED)  # keys, not the size: the cache is bounded
    mm.solve(cube, 3, solver=mm.AMM(xi=4e-3), iterations=10, chunk_size=5)
    assert set(driver._COMPILED) <= before
