"""Scaling of the sharded solver: time per iteration vs robots and devices, compile time, memory.

Every configuration runs in its own subprocess (the CPU device count is fixed when JAX starts:
``XLA_FLAGS=--xla_force_host_platform_device_count=D``) with a wall-clock limit, and reports one
JSON line; the driver collects them into a Markdown table.

Graph: ``cube_dataset(seed, num_poses=N, grid=G)`` -- the paper's Cube model (random walk on a
lattice, loop closures with probability 0.1 between poses at most one cell apart, sigma_t = 0.02 m,
sigma_R = 0.02 pi) at a larger size; the default G = 38 keeps the paper's density of ~1.7 poses
per lattice vertex (3600 poses on 13^3 vertices there, 100k on 39^3 here).

Examples::

    python benchmarks/scaling.py                       # the default grid, table on stdout
    python benchmarks/scaling.py --robots 10 100 1000 --devices 1 2 4 8 --json out.json
    python benchmarks/scaling.py --memory 25000 50000 100000 200000   # memory vs poses
    python benchmarks/scaling.py --one --poses 100000 --robots 100 --devices 2   # one run

On CPU the D "devices" are virtual: they share the machine's physical cores, so D > cores only
shows the overhead of sharding, not a speed-up.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time


def one(args) -> dict:
    """One configuration, in this process (its device count is already set)."""
    import jax

    jax.config.update("jax_enable_x64", True)

    from mmpgo_jax import cube_dataset, initialize, solve
    from mmpgo_jax.sharding import solve_sharded

    t0 = time.perf_counter()
    ds = cube_dataset(args.seed, num_poses=args.poses, grid=args.grid)
    graph = ds.graph
    gen_s = time.perf_counter() - t0
    X0 = ds.ground_truth if args.init == "ground-truth" else initialize(graph, args.init)
    rss_graph = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    # Two chunks; the second one is timed (wall and this process's CPU time, all threads) from
    # the callback, which runs right after each chunk's results reached the host.
    marks = []

    def mark(done, f_chunk):
        marks.append((done, time.perf_counter(), time.process_time()))

    half = max(args.iterations // 2, 1)
    opts = dict(method=args.method, iterations=2 * half, chunk_size=half, init=X0, callback=mark)
    load0 = os.getloadavg()[0]
    if args.devices == 0:
        res = solve(graph, args.robots, **opts)
        devices = 1
    else:
        res = solve_sharded(graph, args.robots, devices=args.devices, exchange=args.exchange, **opts)
        devices = res.extra["devices"]
    load1 = os.getloadavg()[0]
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    (k1, w1, c1), (k2, w2, c2) = marks[0], marks[-1]
    part = res.partition
    return {
        "poses": graph.num_poses,
        "grid": args.grid,
        "edges": graph.num_edges,
        "robots": args.robots,
        "devices": devices,
        "sharded": args.devices != 0,
        "exchange": args.exchange if args.devices != 0 else None,
        "method": args.method,
        "init": args.init,
        "iterations": res.iterations,
        "n_max": part.max_poses,
        "e_max": part.max_edges,
        "generate_s": round(gen_s, 2),
        "setup_s": round(res.init_seconds, 2),
        "compile_s": round(res.compile_seconds, 2),
        "ms_per_iteration": round(1e3 * (w2 - w1) / (k2 - k1), 1),
        "cpu_ms_per_iteration": round(1e3 * (c2 - c1) / (k2 - k1), 1),
        "loadavg": [round(load0, 2), round(load1, 2)],
        "f0": float(res.history.f[0]),
        "f": float(res.history.f[-1]),
        "maxrss_mb": round(rss / 1024, 1),
        "maxrss_graph_mb": round(rss_graph / 1024, 1),
        "cpu_count": os.cpu_count(),
        "jax": jax.__version__,
    }


def default_grid(poses: int) -> int:
    """Cells per axis keeping the paper's Cube density (3600 poses on 13^3 lattice vertices)."""
    return max(2, round((poses * 13**3 / 3600) ** (1 / 3)) - 1)


def run_config(poses, robots, devices, args) -> dict:
    grid = args.grid or default_grid(poses)
    cmd = [
        sys.executable, os.path.abspath(__file__), "--one",
        "--poses", str(poses), "--grid", str(grid), "--robots", str(robots), "--devices", str(devices),
        "--iterations", str(args.iterations), "--method", args.method, "--init", args.init, "--seed", str(args.seed),
        "--exchange", args.exchange,
    ]
    env = dict(os.environ)
    env["JAX_PLATFORMS"] = env.get("JAX_PLATFORMS", "cpu")
    if env["JAX_PLATFORMS"] == "cpu":
        env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={max(devices, 1)}"
    t = time.perf_counter()
    try:
        p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=args.timeout)
    except subprocess.TimeoutExpired:
        return {"poses": poses, "robots": robots, "devices": devices, "error": f"timeout after {args.timeout} s"}
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("{")]
    if p.returncode != 0 or not lines:
        return {"poses": poses, "robots": robots, "devices": devices, "error": p.stderr[-500:]}
    out = json.loads(lines[-1])
    out["wall_s"] = round(time.perf_counter() - t, 1)
    return out


def table(rows) -> str:
    head = ("| poses | robots | devices | sharded | n_max | setup s | compile s | ms / iteration (wall) "
            "| CPU ms / iteration | load avg | f0 -> f | peak RSS MB |\n"
            "|---:|---:|---:|:-:|---:|---:|---:|---:|---:|---|---|---:|")
    out = [head]
    for r in rows:
        if "error" in r:
            out.append(f"| {r['poses']} | {r['robots']} | {r['devices']} | | | | | error: {r['error'][:60]} | | | | |")
            continue
        out.append(
            f"| {r['poses']} | {r['robots']} | {r['devices']} | {'yes' if r['sharded'] else 'no (solve)'} | "
            f"{r['n_max']} | "
            f"{r['setup_s']} | {r['compile_s']} | {r['ms_per_iteration']} | {r['cpu_ms_per_iteration']} | "
            f"{r['loadavg'][0]:.1f}-{r['loadavg'][1]:.1f} | {r['f0']:.4g} -> {r['f']:.4g} | {r['maxrss_mb']} |"
        )
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--one", action="store_true", help="run one configuration in this process and print JSON")
    ap.add_argument("--poses", type=int, nargs="*", default=[100_000])
    ap.add_argument("--grid", type=int, default=None,
                    help="lattice cells per axis (default: the paper's ~1.7 poses per vertex, 38 for 100k poses)")
    ap.add_argument("--robots", type=int, nargs="*", default=[10, 100, 1000])
    ap.add_argument("--devices", type=int, nargs="*", default=[1, 2, 4, 8],
                    help="device counts (0: plain single-device solve, no shard_map)")
    ap.add_argument("--memory", type=int, nargs="*", default=None,
                    help="pose counts for the memory-vs-size runs (robots = first --robots, 1 device)")
    ap.add_argument("--iterations", type=int, default=10)
    ap.add_argument("--method", default="amm", choices=("amm", "mm"))
    ap.add_argument("--init", default="ground-truth", help="ground-truth (default), odometry, chordal")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--exchange", default="halo", choices=("halo", "all_gather"),
                    help="solve_sharded's pose exchange between devices (default halo)")
    ap.add_argument("--timeout", type=float, default=540.0, help="seconds per configuration (default 540)")
    ap.add_argument("--json", help="also write the rows as JSON")
    args = ap.parse_args(argv)

    if args.one:
        args.poses, args.robots, args.devices = args.poses[0], args.robots[0], args.devices[0]
        args.grid = args.grid or default_grid(args.poses)
        print(json.dumps(one(args)), flush=True)
        return 0

    print(f"machine: {platform.platform()}, {os.cpu_count()} logical CPUs, python {platform.python_version()}",
          file=sys.stderr)
    rows = []
    if args.memory:
        configs = [(n, args.robots[0], 1) for n in args.memory]
    else:
        configs = [(n, a, d) for n in args.poses for a in args.robots for d in args.devices]
    for n, a, d in configs:
        r = run_config(n, a, d, args)
        print(json.dumps(r), file=sys.stderr, flush=True)
        rows.append(r)
    print(table(rows))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
