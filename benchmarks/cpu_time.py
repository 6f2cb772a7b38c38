"""Wall and CPU time per AMM iteration against the authors' single-threaded C++ figure.

The authors' code runs on one thread, so its ms per iteration is also its CPU time per iteration.
``mmpgo solve`` splits the robots over both cores from ``AUTO_THREAD_POSES`` poses on, and XLA itself runs large
fused loops on several threads, so a wall-clock ratio alone does not say how much work an
iteration costs. This benchmark measures both, the way ``mmpgo solve`` runs (10 robots, the
centralized chordal start, float64; from ``AUTO_THREAD_POSES`` poses the robots over two CPU devices): in a fresh
process per file, a warm-up call compiles the programs, then ``--short`` and ``--long`` AMM
iterations are run and the difference of their wall time and of the process's CPU time (user +
system, all threads) is divided by the difference of iterations, so that reading, initialization,
set-up and compilation cancel. Best of ``--repeats`` pairs.

    python benchmarks/cpu_time.py --out benchmarks/cpu_time.md
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys

from records import write_record  # this folder, on the path as a script's

from mmpgo_jax._io.datasets import benchmark_info

FILES = ["MITb", "intel", "M3500", "city10000", "sphere2500", "torus3D", "garage"]

CHILD = """
import json, resource, sys, time
import jax
jax.config.update("jax_num_cpu_devices", 2)
import mmpgo_jax as mg
from mmpgo_jax.cli.sharded import AUTO_THREAD_POSES
from mmpgo_jax.sharding import solve_sharded
mg.enable_float64()
name, short, long, repeats = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
graph = mg.read_g2o(mg.find_benchmark(name)).graph
threads = 2 if graph.num_poses >= AUTO_THREAD_POSES else 1  # as mmpgo solve on a 2-core machine
def run(k):
    if threads == 1:
        return mg.solve(graph, 10, method="amm", iterations=k)
    return solve_sharded(graph, 10, devices=2, method="amm", iterations=k)
def clocks():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return time.perf_counter(), r.ru_utime + r.ru_stime
run(short)  # compile
best = None
for _ in range(repeats):
    w0, c0 = clocks(); run(short); w1, c1 = clocks(); run(long); w2, c2 = clocks()
    its = long - short
    wall, cpu = 1e3 * ((w2 - w1) - (w1 - w0)) / its, 1e3 * ((c2 - c1) - (c1 - c0)) / its
    if best is None or wall < best[0]:
        best = (wall, cpu)
print("RESULT", json.dumps({"threads": threads, "wall": best[0], "cpu": best[1]}))
"""


def measure(name: str, short: int, long: int, repeats: int) -> dict:
    out = subprocess.run([sys.executable, "-c", CHILD, name, str(short), str(long), str(repeats)],
                         capture_output=True, text=True, check=True).stdout
    return json.loads(out.split("RESULT", 1)[1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--files", nargs="*", default=FILES)
    ap.add_argument("--short", type=int, default=200)
    ap.add_argument("--long", type=int, default=1200)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    load = os.getloadavg()[0]
    rows = []
    for name in args.files:
        m = measure(name, args.short, args.long, args.repeats)
        authors = benchmark_info(name).code_ms_per_iter_amm  # the registry's same-run figure
        rows.append(f"| {name} | {m['threads']} | {m['wall']:.2f} | {m['cpu']:.2f} | {m['cpu'] / m['wall']:.2f} | "
                    f"{authors} | {m['wall'] / authors:.2f} | {m['cpu'] / authors:.2f} |")
        print(rows[-1], file=sys.stderr, flush=True)
    head = (f"Command: `python benchmarks/cpu_time.py --files {' '.join(args.files)} --short {args.short} --long "
            f"{args.long} --repeats {args.repeats}`; {datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC, "
            f"{platform.machine()}, {os.cpu_count()} cores, load average {load:.2f} at the start, "
            f"{os.getloadavg()[0]:.2f} at the end.\n\n"
            "| file | CPU devices | wall ms/it | CPU ms/it | cores busy | authors' ms/it (one thread) | "
            "wall / authors' | CPU / authors' |\n|---|---|---|---|---|---|---|---|")
    text = head + "\n" + "\n".join(rows) + "\n"
    print(text)
    if args.out:
        write_record(args.out, text)  # the file's later sections kept


if __name__ == "__main__":
    main()
