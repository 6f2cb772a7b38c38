"""Accuracy of the default inner solver against inner solves run to convergence.

For each graph, MM and AMM (10 robots, contiguous blocks, centralized chordal start, xi = 1e-3)
run twice: with the default ``SubproblemConfig()`` and with a reference config that solves every
robot subproblem to a tight criterion (trust region, up to 30 steps and 300 CG iterations per step,
||grad G|| <= 1e-4 of its start, CG residual 1e-3). Prints f at the checkpoints, the relative
difference default vs reference, and ms/iteration of both; writes a Markdown table. Reference runs
are stored in ``inner_solver_reference.json`` with the preconditioner they used (the earlier ones
block-Jacobi, new ones the two-level default: solved this tightly, the result does not depend on it).

    python benchmarks/inner_solver.py --iterations 250 --out benchmarks/inner_solver.md

The synthetic ``chain15k`` graph is 15 000 planar poses that are mostly odometry chains (10 robots of
1 500 poses, loop-closure probability 0.05 on a 300 x 300 lattice): the case the old budgeted
default got wrong. kitti_02, kitti_05 and sphere_bignoise_vertex3 were not used to choose the default.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
from records import write_record  # this folder, on the path as a script's

import mmpgo_jax as mg

FILES = ["MITb", "intel", "CSAIL", "M3500", "sphere2500", "garage", "torus3D", "city10000", "kitti_00", "manhattan",
         "kitti_02", "kitti_05", "sphere_bignoise_vertex3", "chain15k"]
HELD_OUT = {"kitti_02", "kitti_05", "sphere_bignoise_vertex3"}
REFERENCE_FILE = Path(__file__).with_name("inner_solver_reference.json")
REFERENCE = mg.SubproblemConfig(max_steps=30, cg_iterations=300, cg_tolerance=1e-3, gradient_tolerance=1e-4,
                             decrease_tolerance=0.0)


def chain15k():
    """The synthetic long-chain graph (module docstring) as a dataset (graph and ground truth)."""
    return mg.grid_2d_dataset(0, grid=300, num_poses=15000, loop_closure_prob=0.05)


def load(name: str):
    if name == "chain15k":
        return chain15k().graph
    return mg.read_g2o(mg.find_benchmark(name)).graph


def checkpoints(iterations: int) -> list[int]:
    return [k for k in (100, 250, 1000) if k <= iterations]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--iterations", type=int, default=250)
    ap.add_argument("--files", nargs="*", default=FILES)
    ap.add_argument("--out", default=None, help="Markdown file (rewritten after every graph)")
    ap.add_argument("--rerun-reference", action="store_true", help="ignore the stored reference runs")
    args = ap.parse_args()
    mg.enable_float64()
    ks = checkpoints(args.iterations)
    header = (f"# Inner solver: default vs subproblems solved to convergence\n\n"
              f"Command: `python benchmarks/inner_solver.py --iterations {args.iterations}`; "
              f"{datetime.date.today()}, {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
              f"load average at start {os.getloadavg()[0]:.2f}. 10 robots, centralized chordal start, xi = 1e-3, "
              f"float64. Reference: `{REFERENCE}`.\n\n"
              "| graph | method | " + " | ".join(f"f@{k} default / reference (rel. diff)" for k in ks)
              + " | ms/it default / reference (its preconditioner) |\n|---|---|" + "---|" * len(ks) + "---|\n")
    reference = json.loads(REFERENCE_FILE.read_text()) if REFERENCE_FILE.exists() else {}
    rows = []
    for name in args.files:
        try:
            graph = load(name)
        except mg.DatasetNotFoundError as err:
            print(f"skip {name}: {err}")
            continue
        for method in ("mm", "amm"):
            out = {}
            key = f"{name}/{method}/{args.iterations}"
            stored = None if args.rerun_reference else reference.get(key)
            used = (stored or {}).get("preconditioner", REFERENCE.preconditioner)
            for label, sub in (("default", mg.SubproblemConfig()), ("reference", REFERENCE)):
                if label == "reference" and stored is not None:
                    out[label] = stored
                    continue
                t = time.perf_counter()
                r = mg.solve(graph, 10, method=method, iterations=args.iterations, subproblem=sub)
                out[label] = {"f": {str(k): float(r.history.f[k]) for k in ks}, "ms_per_iteration": r.ms_per_iteration,
                              "preconditioner": sub.preconditioner}
                print(f"{name} {method} {label}: f {[round(float(r.history.f[k]), 6) for k in ks]} "
                      f"{r.ms_per_iteration:.2f} ms/it ({time.perf_counter() - t:.0f} s)", flush=True)
            if stored is None:
                reference[key] = out["reference"]
                REFERENCE_FILE.write_text(json.dumps(reference, indent=1, sort_keys=True) + "\n")
            cells = []
            for k in ks:
                fd, fr = out["default"]["f"][str(k)], out["reference"]["f"][str(k)]
                cells.append(f"{fd:.6g} / {fr:.6g} ({(fd - fr) / fr:+.2e})")
            mark = " (held out)" if name in HELD_OUT else ""
            ms = out["default"]["ms_per_iteration"], out["reference"]["ms_per_iteration"]
            rows.append(f"| {name}{mark} | {method.upper()} | " + " | ".join(cells)
                        + f" | {ms[0]:.2f} / {ms[1]:.1f} ({used}) |\n")
            if args.out:
                write_record(args.out, header + "".join(rows))  # the file's later sections kept
    worst = max((abs(float(x)) for row in rows for x in _diffs(row)), default=np.nan)
    print(f"largest relative difference: {worst:.2e}")


def _diffs(row: str):
    import re

    return re.findall(r"\(([+-][0-9.e+-]+)\)", row)


if __name__ == "__main__":
    main()
