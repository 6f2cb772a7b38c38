"""The Python API on every CPU core: ``mm.solve`` in a fresh process, with and without
``mm.use_cpu_cores()`` (one JAX CPU device per core; ``solve``'s default layout then splits the
robots over them, as ``mmpgo solve`` does).

A 3600-pose Cube graph (Fig. 1's kind), AMM, 300 iterations, robots 5 / 10 / 50, float64. Each
measurement is its own process (the device count is fixed when JAX starts); the two variants run
interleaved, so both see the same machine load; the median of ``--repeats`` runs is reported, as
ms per iteration of the compiled iterations and the whole call's seconds.

    python benchmarks/python_api_cores.py --repeats 3 --out benchmarks/python_api_cores.md
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

from records import write_record

HERE = Path(__file__).resolve().parents[1]

_CHILD = """
import json, sys, time
import mmpgo_jax as mm
if sys.argv[1] == "cores":
    mm.use_cpu_cores()
import jax
jax.config.update("jax_enable_x64", True)
graph = mm.cube_dataset(0, num_poses=3600, grid=12).graph
robots = int(sys.argv[2])
t = time.perf_counter()
r = mm.solve(graph, robots, iterations=300, stop_when_stalled=False)
print(json.dumps(dict(ms=r.ms_per_iteration, seconds=time.perf_counter() - t, devices=r.stats.get("devices") or 1,
                      f=r.f)))
"""


def run(variant: str, robots: int) -> dict:
    env = dict(os.environ, PYTHONPATH=str(HERE))
    out = subprocess.run([sys.executable, "-c", _CHILD, variant, str(robots)], capture_output=True, text=True,
                         env=env, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--robots", type=int, nargs="+", default=[5, 10, 50])
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    load0 = os.getloadavg()[0]
    rows = []
    for a in args.robots:
        runs = {"one": [], "cores": []}
        for _ in range(args.repeats):
            for variant in runs:
                runs[variant].append(run(variant, a))
        one, cores = (statistics.median(r["ms"] for r in runs[v]) for v in ("one", "cores"))
        s_one, s_cores = (statistics.median(r["seconds"] for r in runs[v]) for v in ("one", "cores"))
        rows.append((a, runs["cores"][0]["devices"], one, cores, one / cores, s_one, s_cores, runs["one"][0]["f"],
                     runs["cores"][0]["f"]))
        print(rows[-1], flush=True)
    from mmpgo_jax.cli.bench import cpu_name  # the package only now: this process only starts others

    model = cpu_name()
    lines = [
        "# The Python API on every CPU core",
        "",
        f"Command: `python benchmarks/python_api_cores.py --repeats {args.repeats}`; "
        f"{datetime.date.today().isoformat()}, {model}, {os.cpu_count()} logical CPUs, load average "
        f"{load0:.2f} at the start, {os.getloadavg()[0]:.2f} at the end. A fresh process per run, the two "
        "variants interleaved; medians. 3600-pose Cube (seed 0, grid 12), AMM, 300 iterations, float64.",
        "",
        "| robots | devices with use_cpu_cores() | ms/it, one device | ms/it, use_cpu_cores() | speed-up | "
        "call s, one device | call s, use_cpu_cores() | f (one) | f (cores) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for a, dev, one, cores, ratio, s1, s2, f1, f2 in rows:
        lines.append(f"| {a} | {dev} | {one:.2f} | {cores:.2f} | {ratio:.2f}x | {s1:.1f} | {s2:.1f} | {f1:.6f} | "
                     f"{f2:.6f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        write_record(args.out, text)  # the file's later sections kept


if __name__ == "__main__":
    main()
