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
    python benchmarks/scaling.py --one --distributed-start --poses 100000 --robots 100   # the distributed start

Stages (``--stages``, issue "a million poses"): one subprocess per (poses, robots) runs the whole
pipeline from the chordal start with the plain ``solve`` and reports seconds per stage (generate,
partition for each way of splitting, chordal, build, compile, per iteration), peak RSS, and the
padding waste (bytes of padding / bytes used, :meth:`Partition.padding`) of blocks, METIS and
random splits::

    nice -n 5 python benchmarks/scaling.py --stages --poses 100000 --robots 100 1000 --iterations 100

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


def distributed_start(args) -> dict:
    """The distributed chordal start of one configuration against the centralized chordal start, in
    this process: seconds, CG iterations per stage, how each stage applied Gamma (dense / sparse),
    peak memory and the relative gap of f (``--one --distributed-start``)."""
    import jax

    jax.config.update("jax_enable_x64", True)

    from mmpgo_jax import chordal_initialization, cost, cube_dataset, distributed_chordal_initialization

    graph = cube_dataset(args.seed, num_poses=args.poses, grid=args.grid).graph
    t = time.perf_counter()
    poses, info = distributed_chordal_initialization(graph, args.robots)
    start_s = time.perf_counter() - t
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t = time.perf_counter()
    central = chordal_initialization(graph)
    central_s = time.perf_counter() - t
    f, fc = float(cost(graph, poses)), float(cost(graph, central))
    return {"poses": args.poses, "edges": graph.num_edges, "robots": args.robots, "start_s": round(start_s, 1),
            "iterations": [info.rotation_iterations, info.translation_iterations],
            "factorizations": list(info.factorizations), "start_peak_rss_mb": round(rss / 1024, 1),
            "chordal_s": round(central_s, 1), "f": f, "f_chordal": fc, "gap": (f - fc) / fc}


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


def stages(args) -> dict:
    """The pipeline of one (poses, robots) configuration, stage by stage, in this process."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    from mmpgo_jax import chordal_initialization, cube_dataset, solve
    from mmpgo_jax._core.partition import partition

    def rss_mb():
        return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)

    out = {"poses": args.poses, "grid": args.grid, "robots": args.robots, "method": args.method}
    load0 = os.getloadavg()[0]
    t = time.perf_counter()
    graph = cube_dataset(args.seed, num_poses=args.poses, grid=args.grid).graph
    out.update(edges=graph.num_edges, generate_s=round(time.perf_counter() - t, 2), rss_generate_mb=rss_mb())
    if args.read:  # the same graph through a g2o file: what a user's set-up starts with
        import tempfile

        from mmpgo_jax import read_g2o, write_g2o

        with tempfile.TemporaryDirectory() as tmp:
            path = os.path.join(tmp, "cube.g2o")
            write_g2o(path, graph, None)
            t = time.perf_counter()
            graph = read_g2o(path).graph
            out.update(read_s=round(time.perf_counter() - t, 2), file_mb=round(os.path.getsize(path) / 2**20, 1))
    waste = {}
    part = None
    for split in ("blocks", "metis", "random"):
        t = time.perf_counter()
        p = partition(graph, split, args.robots, seed=args.seed)
        pad = p.padding()
        waste[split] = {"partition_s": round(time.perf_counter() - t, 2), "n_max": p.max_poses,
                        "e_max": p.max_edges, "padding_ratio": round(pad.ratio, 4)}
        if split == "blocks":
            part = p
        del p
    out.update(splits=waste, rss_partition_mb=rss_mb())
    t = time.perf_counter()
    X0 = jax.block_until_ready(chordal_initialization(graph))
    out.update(chordal_s=round(time.perf_counter() - t, 2), rss_chordal_mb=rss_mb())
    marks = []

    def mark(done, f_chunk):
        marks.append((done, time.perf_counter(), time.process_time()))

    chunk = max(args.iterations // 2, 1)
    t = time.perf_counter()
    res = solve(graph, part, method=args.method, iterations=2 * chunk, chunk_size=chunk, init=X0, callback=mark)
    total = time.perf_counter() - t
    (k1, w1, c1), (k2, w2, c2) = marks[0], marks[-1]
    per_it = (w2 - w1) / (k2 - k1)
    out.update(
        build_s=round(res.build_seconds, 2), compile_s=round(res.compile_seconds, 2),
        ms_per_iteration=round(1e3 * per_it, 1), cpu_ms_per_iteration=round(1e3 * (c2 - c1) / (k2 - k1), 1),
        iterations=res.iterations, solve_s=round(res.solve_seconds, 2), solve_call_s=round(total, 2),
        f0=float(res.history.f[0]), f=float(res.history.f[-1]), maxrss_mb=rss_mb(),
        loadavg=[round(load0, 2), round(os.getloadavg()[0], 2)], cpu_count=os.cpu_count(), jax=jax.__version__,
        finite=bool(np.isfinite(res.history.f).all()),
    )
    # end to end (chordal start + the iterations run): what a user waits for after generating the graph
    out["end_to_end_s"] = round(waste["blocks"]["partition_s"] + out["chordal_s"] + total, 1)
    return out


def stages_table(rows) -> str:
    head = ("| poses | edges | robots | generate s | read g2o s | partition s (blocks / METIS / random) "
            "| chordal s | build s | compile s | s / iteration | iterations | end to end s "
            "| padding waste blocks / METIS / random | peak RSS MB | load |\n"
            "|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---|---:|---|")
    out = [head]
    for r in rows:
        if "error" in r:
            out.append(f"| {r['poses']} | | {r['robots']} | error: {r['error'][-80:]} |" + " |" * 10)
            continue
        sp_ = r["splits"]
        parts = " / ".join(f"{sp_[k]['partition_s']}" for k in ("blocks", "metis", "random"))
        waste = " / ".join(f"{100 * sp_[k]['padding_ratio']:.1f} %" for k in ("blocks", "metis", "random"))
        read = f"{r['read_s']} ({r['file_mb']} MB)" if "read_s" in r else "not run"
        out.append(f"| {r['poses']} | {r['edges']} | {r['robots']} | {r['generate_s']} | {read} | {parts} | "
                   f"{r['chordal_s']} | {r['build_s']} | {r['compile_s']} | {r['ms_per_iteration'] / 1e3:.2f} | "
                   f"{r['iterations']} | "
                   f"{r['end_to_end_s']} | {waste} | {r['maxrss_mb']} | {r['loadavg'][0]:.1f}-{r['loadavg'][1]:.1f} |")
    return "\n".join(out)


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
    ] + (["--stages"] if args.stages else []) + (["--read"] if args.read else [])
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
    ap.add_argument("--read", action="store_true", help="--stages: also write the graph to g2o and time reading it")
    ap.add_argument("--distributed-start", action="store_true",
                    help="with --one: the distributed chordal start against the centralized chordal start")
    ap.add_argument("--stages", action="store_true",
                    help="seconds per stage from the chordal start, peak memory, padding waste per split")
    args = ap.parse_args(argv)

    if args.one:
        args.poses, args.robots, args.devices = args.poses[0], args.robots[0], args.devices[0]
        args.grid = args.grid or default_grid(args.poses)
        run = distributed_start if args.distributed_start else stages if args.stages else one
        print(json.dumps(run(args)), flush=True)
        return 0

    print(f"machine: {platform.platform()}, {os.cpu_count()} logical CPUs, python {platform.python_version()}",
          file=sys.stderr)
    rows = []
    if args.stages:
        configs = [(n, a, 0) for n in args.poses for a in args.robots]
    elif args.memory:
        configs = [(n, args.robots[0], 1) for n in args.memory]
    else:
        configs = [(n, a, d) for n in args.poses for a in args.robots for d in args.devices]
    for n, a, d in configs:
        r = run_config(n, a, d, args)
        print(json.dumps(r), file=sys.stderr, flush=True)
        rows.append(r)
    print(stages_table(rows) if args.stages else table(rows))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
