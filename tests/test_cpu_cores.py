"""Every CPU core from the Python API: use_cpu_cores() before JAX starts, then solve's default layout
splits the robots of large graphs over the CPU devices, as `mmpgo solve` does, and sweep runs one
batch per CPU device at a time."""

import json
import subprocess
import sys
import textwrap

import pytest

_CHILD = textwrap.dedent("""
    import json, sys
    import mmpgo_jax as mm
    n = mm.use_cpu_cores(2)
    import jax
    jax.config.update("jax_enable_x64", True)
    big = mm.cube_dataset(0, num_poses=400, grid=4).graph
    small = mm.cube_dataset(0, num_poses=120, grid=3).graph
    a = mm.solve(big, 4, iterations=6, chunk_size=3)
    b = mm.solve(big, 4, iterations=6, chunk_size=3, layout=mm.OneDevice())
    c = mm.solve(small, 4, iterations=3, chunk_size=3)
    graphs = {f"g{k}": mm.cube_dataset(k, num_poses=120, grid=3).graph for k in range(3)}
    sw = mm.sweep(graphs, [2, 3], "amm", 6, chunk_size=3, max_batch_configs=1)
    same = [float(abs(sw.histories[(g, a, "amm")] - mm.solve(graphs[g], a, iterations=6, chunk_size=3,
                                                             stop_when_stalled=False).history.f).max())
            for g in ("g0",) for a in (2, 3)]  # one graph: a solve per robot count
    try:
        mm.use_cpu_cores(3)  # another count after the backend started
        late = None
    except RuntimeError as err:
        late = str(err)
    print(json.dumps(dict(n=n, devices=a.stats.get("devices"), one=b.stats.get("devices"), small=c.stats.get("devices"),
                          fa=a.history.f.tolist(), fb=b.history.f.tolist(), late=late,
                          sweep_devices=[g["devices"] for g in sw.groups], sweep_batches=[g["batches"] for g in sw.groups],
                          sweep_vs_solve=same)))
""")


@pytest.fixture(scope="module")
def child():
    out = subprocess.run([sys.executable, "-c", _CHILD], capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_default_layout_uses_every_cpu_device_for_large_graphs(child):
    assert child["n"] == 2 and child["devices"] == 2  # 400 poses: split over both CPU devices
    assert child["one"] is None and child["small"] is None  # asked for one device; below AUTO_THREAD_POSES (200)
    assert child["fa"] == pytest.approx(child["fb"], rel=1e-12)  # the same iterates, laid out differently


def test_sweep_runs_its_batches_on_every_cpu_device(child):
    """With two CPU devices a sweep's batches run two at a time, one per device, and each
    configuration of the first graph still equals its solve() (one device, the same iterates)."""
    assert child["sweep_devices"] == [2, 2] and child["sweep_batches"] == [3, 3]
    assert max(child["sweep_vs_solve"]) <= 1e-9 * 1e3, child["sweep_vs_solve"]  # f about 1e3: rounding only


def test_use_cpu_cores_after_jax_started_is_a_one_line_error(child):
    assert child["late"] is not None and "before the first JAX computation" in child["late"]
    assert "\n" not in child["late"]
