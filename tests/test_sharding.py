"""Sharded solve (robots over devices), communication report, multi-process runs.

Tests that need several CPU devices run in SUBPROCESSES started with
XLA_FLAGS=--xla_force_host_platform_device_count=8, so this process's JAX backend is untouched.

Equality to 1e-10 is tested with a large proximal weight (xi = 1e4) and with the default
xi = 1e-3 at a short inner CG budget (5 iterations): in both the robots' subproblem solves are
well conditioned. With the default budget (20 CG iterations) at xi = 1e-3 the truncated CG
amplifies rounding exponentially in its iteration count while the model Hessian is indefinite:
measured on a single device, perturbing the start by 1e-15 changes f after ONE outer iteration by
4e-16 / 2e-14 / 5e-10 / 4e-5 (relative) with 5 / 10 / 15 / 20 CG iterations. XLA rounds the
robots' reductions differently for different vmap batch sizes (A robots on one device versus
A / D per device), so sharded and single-device runs then agree only to ~1e-5 in f; the same
happens without any sharding between two batch sizes (see benchmarks/scaling.md).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from mmpgo_jax import (
    contiguous_robots,
    cube_dataset,
    partition_stats,
    read_g2o,
    write_g2o,
)
from mmpgo_jax.sharding import (
    communication_report,
    plan_shards,
    run_multiprocess,
    solve_sharded,
)

# Optimization level 0 of XLA's CPU backend: ~30 % less compile time, same arithmetic (no
# fast-math either way); results are compared within one configuration.
FAST_COMPILE = "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"
CHILD_ENV = {
    "XLA_FLAGS": "--xla_force_host_platform_device_count=8 " + FAST_COMPILE,
    "JAX_ENABLE_X64": "1",
    "JAX_PLATFORMS": "cpu",
}

# One child per method; both start at once (module fixture) so that their compilations overlap.
CHILD = textwrap.dedent(
    """
    import json, sys
    import numpy as np
    import jax
    assert len(jax.devices()) == 8, jax.devices()
    from mmpgo_jax import SubproblemConfig, contiguous_robots, cube_dataset, initialize, solve
    from mmpgo_jax.sharding import solve_sharded

    method, ref_path = sys.argv[1], sys.argv[2]
    restart = "paper" if method == "amm" else "adaptive"
    graph = cube_dataset(0, num_poses=400, grid=6).graph
    X0 = initialize(graph, "chordal")

    def compare(ref, res):
        f_ref, f = ref.history.f, res.history.f
        out = {"f_rel": float(np.max(np.abs(f - f_ref) / np.abs(f_ref)))}
        for k in ("R", "t"):
            a, b = np.asarray(getattr(ref.poses, k)), np.asarray(getattr(res.poses, k))
            out[k + "_rel"] = float(np.max(np.abs(a - b)) / np.max(np.abs(a)))
        out["restarts_equal"] = bool(np.array_equal(ref.history.restarts, res.history.restarts))
        out["restarts"] = int(ref.history.restarts.sum())
        out["shape_equal"] = ref.history.restarts.shape == res.history.restarts.shape
        return out

    opts = dict(method=method, restart=restart, iterations=30, chunk_size=20, xi=1e4, init=X0)
    ref = solve(graph, 8, **opts)
    np.savez(ref_path, f=ref.history.f, grad_norm=ref.history.grad_norm, R=np.asarray(ref.poses.R),
             t=np.asarray(ref.poses.t))
    # Each method checks a share of the variants (the two children run at once on a small machine).
    results = {}
    for D in (2, 8) if method == "mm" else (1, 4, 8):
        results[f"D{D}"] = compare(ref, solve_sharded(graph, 8, devices=D, **opts))
    if method == "mm":  # the all_gather exchange (the default is the neighbour-only halo)
        results["all_gather_D4"] = compare(ref, solve_sharded(graph, 8, devices=4, exchange="all_gather", **opts))
    # The default xi with a short CG budget (5 iterations), where the inner solver is well conditioned;
    # block-Jacobi: elementwise, so a robot's arithmetic does not depend on how many share a device.
    opts_xi = dict(opts, xi=1e-3, subproblem=SubproblemConfig(cg_iterations=5, preconditioner="block-jacobi"))
    D = 8 if method == "mm" else 2
    results[f"xi_default_D{D}"] = compare(solve(graph, 8, **opts_xi), solve_sharded(graph, 8, devices=D, **opts_xi))
    if method == "mm":
        # the default two-level preconditioner: its dense coarse product (XLA dot) rounds differently
        # for 4 robots per device than for 8, so sharded and single-device runs agree only to rounding
        opts_two = dict(opts, xi=1e-3, subproblem=SubproblemConfig(cg_iterations=5))
        results["two_level_D2"] = compare(solve(graph, 8, **opts_two),
                                          solve_sharded(graph, 8, devices=2, **opts_two))
    else:
        # The same 8 robots with scrambled labels on 3 devices: padding to 9 and renumbering.
        perm = np.random.default_rng(1).permutation(8)
        rop = perm[contiguous_robots(graph.num_poses, 8)]
        res = solve_sharded(graph, rop, devices=3, reorder=True, **opts)
        r = compare(ref, res)
        r["restarts_equal"] = bool(np.array_equal(ref.history.restarts, res.history.restarts[:, perm]))
        r["padded"] = res.extra["plan"].padded_robots
        results["scrambled8_D3"] = r
    print("RESULT " + json.dumps(results))
    """
)


def _child_env():
    env = dict(os.environ)
    env.update(CHILD_ENV)
    return env


@pytest.fixture(scope="module")
def child_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("sharding")


@pytest.fixture(scope="module")
def sharded_results(child_dir):
    procs = {
        m: subprocess.Popen(
            [sys.executable, "-c", CHILD, m, str(child_dir / f"ref_{m}.npz")],
            env=_child_env(),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for m in ("mm", "amm")
    }
    results = {}
    for m, p in procs.items():
        try:
            out, err = p.communicate(timeout=240)
        except subprocess.TimeoutExpired:
            for q in procs.values():
                if q.poll() is None:
                    q.kill()
            pytest.fail(f"sharded child ({m}) timed out")
        line = [ln for ln in out.splitlines() if ln.startswith("RESULT ")]
        assert p.returncode == 0 and line, f"child {m} failed:\n{out[-3000:]}\n{err[-5000:]}"
        results[m] = json.loads(line[-1][len("RESULT "):])
    return results


SHARDED_CASES = [("mm", "D2"), ("mm", "D8"), ("mm", "all_gather_D4"), ("mm", "xi_default_D8"),
                 ("amm", "D1"), ("amm", "D4"), ("amm", "D8"), ("amm", "xi_default_D2")]


@pytest.mark.parametrize("method, key", SHARDED_CASES)
def test_sharded_equals_single_device(sharded_results, method, key):
    r = sharded_results[method][key]
    assert r["f_rel"] <= 1e-10, r
    assert r["R_rel"] <= 1e-10 and r["t_rel"] <= 1e-10, r
    assert r["shape_equal"] and r["restarts_equal"], r


def test_sharded_two_level_agrees_to_rounding(sharded_results):
    """Measured 2026-12-02: f within 6e-10, poses within 3e-8 (relative)."""
    r = sharded_results["mm"]["two_level_D2"]
    assert r["f_rel"] <= 1e-8 and r["R_rel"] <= 1e-6 and r["t_rel"] <= 1e-6, r
    assert r["shape_equal"], r


def test_amm_case_exercises_restarts(sharded_results):
    # The paper's restart rule falls back to MM steps here, so per-device restart decisions are tested.
    assert sharded_results["amm"]["D8"]["restarts"] > 0


def test_sharded_padding_and_renumbering(sharded_results):
    r = sharded_results["amm"]["scrambled8_D3"]
    assert r["padded"] == 9 and r["restarts"] > 0
    assert r["f_rel"] <= 1e-10 and r["R_rel"] <= 1e-10 and r["t_rel"] <= 1e-10, r
    assert r["shape_equal"] and r["restarts_equal"], r


# ------------------------------------------------------------------------------------------------
# Plans and the communication report (host only, no devices needed)
# ------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cube():
    return cube_dataset(0, num_poses=400, grid=6).graph


def _brute_force_traffic(graph, rop, device_of_robot, D):
    gi, gj = np.asarray(graph.i), np.asarray(graph.j)
    A = int(rop.max()) + 1
    recv = [set() for _ in range(A)]
    sent = [set() for _ in range(A)]
    dev_recv = [set() for _ in range(D)]
    dev_sent = [set() for _ in range(D)]
    for i, j in zip(gi, gj, strict=True):
        a, b = rop[i], rop[j]
        if a == b:
            continue
        recv[a].add(j), recv[b].add(i)
        sent[b].add((a, j)), sent[a].add((b, i))
        da, db = device_of_robot[a], device_of_robot[b]
        if da != db:
            dev_recv[da].add(j), dev_recv[db].add(i)
            dev_sent[db].add((da, j)), dev_sent[da].add((db, i))

    def n(sets):
        return np.array([len(s) for s in sets])

    return n(recv), n(sent), n(dev_recv), n(dev_sent)


@pytest.mark.parametrize("A, D", [(8, 1), (8, 2), (10, 4), (7, 3)])
def test_communication_report_matches_partition_stats(cube, A, D):
    rep = communication_report(cube, A, D)
    rop = contiguous_robots(cube.num_poses, A)
    st = partition_stats(cube, rop)
    np.testing.assert_array_equal(rep.recv_poses, st.received_poses)
    for a in range(A):
        np.testing.assert_array_equal(rep.neighbours[a], st.neighbours[a])
    assert rep.sent_poses.sum() == rep.recv_poses.sum()
    bpp = 8 * (3 + 9)
    assert rep.bytes_per_pose == bpp
    np.testing.assert_array_equal(rep.recv_bytes, bpp * st.received_poses)
    # Contiguous blocks keep the natural order: robot a on device a // ceil(A / D).
    per = -(-A // D)
    np.testing.assert_array_equal(rep.robot_device, np.arange(A) // per)
    recv, sent, dev_recv, dev_sent = _brute_force_traffic(cube, rop, rep.robot_device, D)
    np.testing.assert_array_equal(rep.recv_poses, recv)
    np.testing.assert_array_equal(rep.sent_poses, sent)
    np.testing.assert_array_equal(rep.device_recv_poses, dev_recv)
    np.testing.assert_array_equal(rep.device_sent_poses, dev_sent)
    assert rep.device_recv_poses.sum() == rep.device_sent_poses.sum()
    # What the all_gather actually moves: every other device's padded pose block.
    n_max = int(st.poses.max())
    np.testing.assert_array_equal(rep.allgather_recv_bytes, (per * D - per) * n_max * bpp)
    if D == 1:
        assert rep.device_recv_poses.sum() == 0 and rep.allgather_recv_bytes.sum() == 0
    text = rep.to_text()
    assert "all_gather" in text and f"{bpp} bytes" in text


def test_renumbering_keeps_neighbours_on_one_device():
    # A long walk in a big lattice is nearly a chain: with scrambled robot labels the natural
    # order puts chain neighbours on different devices; the renumbering recovers the chain.
    graph = cube_dataset(0, num_poses=400, grid=20).graph
    A, D = 16, 4
    blocks = contiguous_robots(graph.num_poses, A)
    rop = np.random.default_rng(0).permutation(A)[blocks]
    plan = plan_shards(graph, rop, D)
    assert plan.reordered

    def cross(dev):
        return int(np.count_nonzero(dev[np.asarray(graph.i)] != dev[np.asarray(graph.j)]))

    natural = plan_shards(graph, rop, D, reorder=False)
    contiguous = plan_shards(graph, A, D)
    assert cross(plan.device_of_pose()) < cross(natural.device_of_pose())
    assert cross(plan.device_of_pose()) <= 2 * cross(contiguous.device_of_pose())
    # Renumbering is a permutation and maps back.
    assert sorted(plan.order.tolist()) == list(range(A))
    np.testing.assert_array_equal(plan.order[plan.sharded_robot_of_pose], rop)
    rep = communication_report(graph, rop, D)
    np.testing.assert_array_equal(rep.robot_device, plan.device_of_user_robot)
    assert rep.device_recv_poses.sum() < communication_report(graph, rop, D, reorder=False).device_recv_poses.sum()


@pytest.mark.parametrize("A, D", [(8, 2), (8, 4), (9, 3), (16, 8)])
def test_halo_plan_delivers_exactly_the_cross_device_endpoints(cube, A, D):
    """Each device receives, from each other device, exactly the poses at the far end of their
    cross-device edges, at their global slots; the halo size matches the communication report."""
    from mmpgo_jax import partition
    from mmpgo_jax.sharding import halo_plan

    part = partition(cube, contiguous_robots(cube.num_poses, A), num_robots=-(-A // D) * D)
    send, recv = halo_plan(part, cube, D)
    n_max, B = part.max_poses, part.num_robots // D
    rop, sop = np.asarray(part.robot_of_pose), np.asarray(part.slot_of_pose)
    dev = rop // B
    I, J = np.asarray(cube.i), np.asarray(cube.j)
    for j in range(D):
        need = set()
        for a, b in ((I, J), (J, I)):
            cross = (dev[b] == j) & (dev[a] != j)
            need |= {(int(dev[p]), int(rop[p] * n_max + sop[p])) for p in a[cross]}
        got = set()
        for k in range(D):
            valid = recv[j, k] < part.num_robots * n_max
            # what k sends to j is what j expects from k, slot by slot
            np.testing.assert_array_equal(send[k, j][valid] + k * B * n_max, recv[j, k][valid])
            got |= {(k, int(x)) for x in recv[j, k][valid]}
        assert got == need
    rep = communication_report(cube, contiguous_robots(cube.num_poses, A), D)
    assert rep.halo_size == send.shape[-1]
    assert np.all(rep.halo_recv_bytes == (D - 1) * send.shape[-1] * rep.bytes_per_pose)
    assert rep.halo_recv_bytes.sum() < rep.allgather_recv_bytes.sum()


def test_solve_sharded_argument_errors(cube):
    with pytest.raises(ValueError, match="mesh or devices"):
        from mmpgo_jax.sharding import make_mesh

        solve_sharded(cube, 4, mesh=make_mesh(1), devices=1, iterations=0)
    with pytest.raises(ValueError, match="iterations"):
        solve_sharded(cube, 4, devices=1, iterations=-1)
    with pytest.raises(ValueError, match="devices"):
        solve_sharded(cube, 4, devices=10_000, iterations=0)
    with pytest.raises(ValueError, match="exchange"):
        solve_sharded(cube, 4, devices=1, iterations=0, exchange="ring")


# ------------------------------------------------------------------------------------------------
# Two processes on localhost (jax.distributed, gloo CPU collectives)
# ------------------------------------------------------------------------------------------------


def _read_history(path):
    # Values may be written as repr(np.float64(x)); accept both spellings.
    rows = []
    with open(path) as fh:
        lines = fh.read().splitlines()[1:]
    for line in lines:
        rows.append([float(v) for v in re.sub(r"np\.float64\(([^)]*)\)", r"\1", line).split(",")])
    return np.array(rows)


def test_two_processes_reproduce_single_process(tmp_path, cube, sharded_results, child_dir):
    # The single-process reference: the MM child's solve(graph, 8, ...) (same graph, settings).
    ref = np.load(child_dir / "ref_mm.npz")
    src = tmp_path / "cube.g2o"
    write_g2o(src, cube, None)
    out, hist = tmp_path / "out.g2o", tmp_path / "history.csv"
    args = ["solve", str(src), "--robots", "8", "--method", "mm", "-n", "30", "--chunk", "20", "--xi", "1e4",
            "--no-progress", "--out", str(out), "--history", str(hist)]
    env = dict(os.environ, XLA_FLAGS=FAST_COMPILE)
    run = run_multiprocess(args, processes=2, timeout_s=170, env=env)
    logs = "\n".join(o[-2000:] + e[-3000:] for o, e in run.outputs)
    assert run.ok, f"rc={run.returncodes} timed_out={run.timed_out}\n" + logs
    assert "2 devices, 2 processes" in run.outputs[0][0]
    assert "wrote" not in run.outputs[1][0]  # only process 0 writes

    h = _read_history(hist)
    np.testing.assert_allclose(h[:, 1], ref["f"], rtol=1e-10)
    np.testing.assert_allclose(h[:, 2], ref["grad_norm"], rtol=1e-8)
    est = read_g2o(out).initial
    scale = np.abs(ref["t"]).max()
    assert np.abs(np.asarray(est.t) - ref["t"]).max() <= 1e-10 * scale
    assert np.abs(np.asarray(est.R) - ref["R"]).max() <= 1e-10


def test_multiprocess_failure_stops_all_processes(tmp_path):
    # Every process fails to read the file: all must exit on their own, well before the timeout.
    run = run_multiprocess([str(tmp_path / "missing.g2o"), "--no-progress"], processes=2, timeout_s=120)
    assert not run.ok and not run.timed_out
    assert run.seconds < 100
    assert all(rc != 0 for rc in run.returncodes)
    assert any("error" in e for _, e in run.outputs)
