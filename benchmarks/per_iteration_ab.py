"""AMM (or MM) ms per outer iteration of two checkouts, measured interleaved in one run.

Each measurement is a fresh process that imports ``mmpgo_jax`` from the given checkout (through
``PYTHONPATH``) and runs ``solve_sharded`` over two CPU devices (``--devices 2``, the default; what
``mmpgo solve`` runs from 1000 poses on) or ``solve`` on one (``--devices 1``): 10 robots,
``--iterations`` outer iterations from the chordal start in float64 (as ``mmpgo bench``; ``--precision
float32``: JAX's default precision, the graph read in float32), twice; its
figure is the faster of the two. The processes of both checkouts alternate file by file and round
by round, so both see the same load; the table reports the fastest round of each and their ratio.
Use it to decide whether a change is faster: on a shared machine figures from different runs are
not comparable, ratios from one run are.

    python benchmarks/per_iteration_ab.py --baseline ../old-checkout --files MITb intel --rounds 3
"""

from __future__ import annotations

import argparse
import datetime
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
FILES = ["MITb", "intel", "M3500", "city10000", "sphere2500", "torus3D", "garage"]
CHILD = """
import sys, jax
jax.config.update("jax_num_cpu_devices", 2)
import mmpgo_jax as mg
from mmpgo_jax.sharding import solve_sharded
if sys.argv[5] == "float64":
    mg.enable_float64()
graph = mg.read_g2o(mg.find_benchmark(sys.argv[1])).graph
kw = dict(method=sys.argv[2], iterations=int(sys.argv[3]))
one = (lambda: mg.solve(graph, 10, **kw)) if sys.argv[4] == "1" else (lambda: solve_sharded(graph, 10, devices=2, **kw))
runs = [one() for _ in range(2)]
print("RESULT", min(r.ms_per_iteration for r in runs), repr(float(runs[-1].history.f[-1])), mg.__file__)
"""


def measure(tree: Path, name: str, method: str, iterations: int, devices: int,
            precision: str = "float64") -> tuple[float, float]:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    # run in the checkout: `python -c` puts the working directory first on sys.path, so from another
    # checkout's root the child would import that one (as it did before 2026-12-04: both sides then
    # ran the same code)
    out = subprocess.run([sys.executable, "-c", CHILD, name, method, str(iterations), str(devices), precision],
                         env=env, cwd=tree, capture_output=True, text=True, check=True).stdout
    ms, f, module = out.split("RESULT", 1)[1].split()
    if not Path(module).resolve().is_relative_to(tree.resolve()):
        raise RuntimeError(f"the child imported {module}, not the checkout {tree}")
    return float(ms), float(f)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--baseline", required=True, type=Path, help="the other checkout (its repository root)")
    ap.add_argument("--files", nargs="*", default=FILES)
    ap.add_argument("--method", default="amm", choices=["amm", "mm"])
    ap.add_argument("--iterations", type=int, default=1000)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--devices", type=int, default=2, choices=[1, 2])
    ap.add_argument("--precision", default="float64", choices=["float64", "float32"])
    args = ap.parse_args()
    trees = {"baseline": args.baseline.resolve(), "ours": REPO}
    load = os.getloadavg()[0]
    best: dict[tuple[str, str], float] = {}
    final: dict[tuple[str, str], float] = {}
    for _ in range(args.rounds):
        for name in args.files:
            for who, tree in trees.items():
                ms, f = measure(tree, name, args.method, args.iterations, args.devices, args.precision)
                best[name, who] = min(ms, best.get((name, who), ms))
                final[name, who] = f
                print(f"{name} {who}: {ms:.3f} ms/it, f {f:.10g}", file=sys.stderr, flush=True)
    print(f"Command: `python benchmarks/per_iteration_ab.py --baseline {args.baseline} --files {' '.join(args.files)} "
          f"--method {args.method} --iterations {args.iterations} --rounds {args.rounds} --devices {args.devices} "
          f"--precision {args.precision}`; "
          f"{datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC, {os.cpu_count()} cores, load average "
          f"{load:.2f} at the start, {os.getloadavg()[0]:.2f} at the end.\n")
    print("| file | baseline ms/it | ours ms/it | ours / baseline | f baseline | f ours |\n|---|---|---|---|---|---|")
    for name in args.files:
        b, o = best[name, "baseline"], best[name, "ours"]
        fb, fo = final[name, "baseline"], final[name, "ours"]
        print(f"| {name} | {b:.3f} | {o:.3f} | {o / b:.3f} | {fb:.10g} | {fo:.10g} |")


if __name__ == "__main__":
    main()
