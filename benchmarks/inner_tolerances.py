"""The inner solver's two tolerances: time per outer iteration against accuracy.

``SubproblemConfig(gradient_tolerance, cg_tolerance)`` decide how far each robot subproblem is
solved. For each graph and each (cg_tolerance, gradient_tolerance) pair, MM and AMM (10 robots,
contiguous blocks, centralized chordal start, xi = 1e-3, float64) run 1000 iterations; the table
gives ms per outer iteration and f at 100 / 250 / 1000 iterations relative to the runs with
subproblems solved to convergence that ``inner_solver.py`` stored in ``inner_solver_reference.json``.
The pairs run one after another on each graph, so the ms/it of one graph are measured in the same
stretch of time (one CPU device; the two tolerances are traced values: one compilation per graph
and method serves every pair)::

    python benchmarks/inner_tolerances.py --pairs 0.01,0.1 0.03,0.2 --out benchmarks/inner_tolerances.md

``--decrease`` runs each pair with each given ``decrease_tolerance`` (the rule that stops a robot's
solve once the decrease still to gain is below that fraction of its objective share; default: the
current default only), e.g. the study of that rule::

    python benchmarks/inner_tolerances.py --pairs 0.03,0.2 --decrease 0 1e-8 1e-7 --out FILE

kitti_02, kitti_05 and sphere_bignoise_vertex3 are held out: never used to choose the defaults.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import mmpgo_jax as mg  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from inner_solver import HELD_OUT, REFERENCE_FILE, load  # noqa: E402
from records import write_record  # noqa: E402  (this folder, on the path as a script's)

FILES = ["MITb", "CSAIL", "intel", "M3500", "city10000", "manhattan", "kitti_00", "sphere2500", "torus3D",
         "garage", "chain15k"]
CHECKPOINTS = (100, 250, 1000)


def pair(text: str) -> tuple[float, float]:
    cg, grad = (float(x) for x in text.split(","))
    return cg, grad


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pairs", nargs="+", type=pair, default=[(0.01, 0.1), (0.03, 0.2)],
                    help="cg_tolerance,gradient_tolerance pairs (default: the earlier and the current default)")
    ap.add_argument("--decrease", nargs="+", type=float, default=[mg.SubproblemConfig().decrease_tolerance],
                    help="decrease_tolerance values run with every pair (default: the current default)")
    ap.add_argument("--files", nargs="+", default=FILES)
    ap.add_argument("--out", help="Markdown file (rewritten after every graph)")
    args = ap.parse_args()
    reference = json.loads(REFERENCE_FILE.read_text())
    load_start = os.getloadavg()[0]
    header = (f"Command: `python benchmarks/inner_tolerances.py {' '.join(sys.argv[1:])}`; "
              f"{dt.datetime.now(dt.UTC):%Y-%m-%d %H:%M} UTC, {platform.machine()}, {os.cpu_count()} cores, "
              f"load average at start {load_start:.2f}. f columns: (f - f_ref) / f_ref, f_ref with subproblems "
              "solved to convergence (inner_solver_reference.json). ms/it: one CPU device.\n\n"
              "| graph | method | cg_tolerance | gradient_tolerance | decrease_tolerance | ms/it | "
              + " | ".join(f"f@{k}" for k in CHECKPOINTS)
              + " |\n|---|---|---:|---:|---:|---:|" + "---:|" * len(CHECKPOINTS) + "\n")
    rows = []
    for name in args.files:
        graph = load(name)
        for method in ("amm", "mm"):
            ref = reference[f"{name}/{method}/1000"]["f"]
            for (cg, grad), dec in ((p, d) for p in args.pairs for d in args.decrease):
                sub = mg.SubproblemConfig(cg_tolerance=cg, gradient_tolerance=grad, decrease_tolerance=dec)
                r = mg.solve(graph, 10, method=method, iterations=1000, subproblem=sub)
                diffs = [(float(r.history.f[k]) - ref[str(k)]) / ref[str(k)] for k in CHECKPOINTS]
                mark = " (held out)" if name in HELD_OUT else ""
                rows.append(f"| {name}{mark} | {method.upper()} | {cg:g} | {grad:g} | {dec:g} | "
                            f"{r.ms_per_iteration:.2f} | " + " | ".join(f"{d:+.1e}" for d in diffs) + " |\n")
                print(rows[-1], end="", flush=True)
            if args.out:
                write_record(args.out, header + "".join(rows)  # the file's later sections kept
                             + f"\nLoad average at the end: {os.getloadavg()[0]:.2f} ({time.strftime('%H:%M')} UTC).\n")


if __name__ == "__main__":
    main()
