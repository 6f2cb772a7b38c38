"""Bytes held by MMProblem (sum of its leaves' nbytes), before and after dropping unused copies.

Before: the code of git revision ``--before`` (default cee380d, the last commit whose MMProblem
carried stacked-layout copies of Gamma, the chain and the block-Jacobi preconditioner next to the
solver's structure-of-arrays ones), extracted with ``git archive`` into a temporary folder and run
in a subprocess. After: this checkout, for the default config (``MMProblem.build(partition,
config=MMConfig())``: Gamma and block-Jacobi, structure-of-arrays only), for the chain
preconditioner's config, and without a config (both preconditioners, so that any config can run).

    python benchmarks/problem_memory.py [--robots 10] [--before REV] [--out benchmarks/problem_memory.md]

Datasets (MIT, 2-D; sphere2500, 3-D) from ``MMPGO_DATA`` (default /work/shared/datasets); float64.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DATASETS = ("MIT.g2o", "sphere2500.g2o")

# Runs in a subprocess against either version of the package (public API only).
MEASURE = r"""
import dataclasses, json, sys
import jax
jax.config.update("jax_enable_x64", True)
import mmpgo_jax as mm

path, robots, variant = sys.argv[1], int(sys.argv[2]), sys.argv[3]
graph = mm.read_g2o(path).graph
part = mm.partition(graph, robots)
if variant == "old":
    problem = mm.MMProblem.build(part, 1e-3)
elif variant == "none":
    problem = mm.MMProblem.build(part, 1e-3)
else:
    sub = mm.SubproblemConfig(preconditioner=variant)
    problem = mm.MMProblem.build(part, config=mm.MMConfig(subproblem=sub))
nbytes = lambda tree: int(sum(getattr(x, "nbytes", 0) for x in jax.tree.leaves(tree)))  # old xi: a static float
fields = {f.name: nbytes(getattr(problem, f.name)) for f in dataclasses.fields(problem)}
print(json.dumps(dict(total=nbytes(problem), fields=fields, poses=graph.num_poses, dim=graph.dim,
                      A=part.num_robots, n_max=part.max_poses, e_max=part.max_edges)))
"""


def _measure(pythonpath: Path, path: Path, robots: int, variant: str) -> dict:
    env = dict(os.environ, PYTHONPATH=str(pythonpath), JAX_PLATFORMS="cpu")
    out = subprocess.run([sys.executable, "-c", MEASURE, str(path), str(robots), variant], env=env,
                         capture_output=True, text=True, check=True, cwd=tempfile.gettempdir())
    return json.loads(out.stdout.strip().splitlines()[-1])


def _mib(b: int) -> str:
    return f"{b / 2**20:.2f}"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=10)
    ap.add_argument("--before", default="cee380d", help="git revision of the 'before' code")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "problem_memory.md")
    args = ap.parse_args(argv)
    data = Path(os.environ.get("MMPGO_DATA", "/work/shared/datasets"))
    load = " ".join(Path("/proc/loadavg").read_text().split()[:3]) if Path("/proc/loadavg").exists() else "?"
    uptime = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()

    results = {}
    with tempfile.TemporaryDirectory() as old:
        archive = subprocess.run(["git", "-C", str(REPO), "archive", args.before, "mmpgo_jax"], capture_output=True,
                                 check=True).stdout
        subprocess.run(["tar", "-x", "-C", old], input=archive, check=True)
        for name in DATASETS:
            path = data / name
            results[name] = {
                "before": _measure(Path(old), path, args.robots, "old"),
                "after (default config, block-jacobi)": _measure(REPO, path, args.robots, "block-jacobi"),
                "after (chain config)": _measure(REPO, path, args.robots, "chain"),
                "after (no config: both preconditioners)": _measure(REPO, path, args.robots, "none"),
            }

    lines = [
        "# MMProblem memory: before / after dropping the unused copies",
        "",
        f"Command: `python benchmarks/problem_memory.py --robots {args.robots} --before {args.before}`  ",
        f"Date: {datetime.datetime.now().isoformat(timespec='seconds')}; machine: {platform.machine()}, "
        f"{os.cpu_count()} cores, load average {load} (`uptime`: {uptime})  ",
        "Bytes = sum of the leaves' nbytes of `MMProblem.build(partition(graph, robots), ...)`, float64, "
        f"{args.robots} robots (contiguous blocks). 'before' is the code of {args.before}, "
        "`MMProblem.build(part, 1e-3)`.",
        "",
    ]
    for name, rows in results.items():
        before = rows["before"]
        lines += [f"## {name} (n = {before['poses']}, d = {before['dim']}, A = {before['A']}, "
                  f"n_max = {before['n_max']}, e_max = {before['e_max']})", "",
                  "| variant | bytes | MiB | vs before | fields (MiB) |", "|---|---:|---:|---:|---|"]
        for variant, r in rows.items():
            fields = ", ".join(f"{k} {_mib(v)}" for k, v in r["fields"].items() if v)
            ratio = r["total"] / before["total"]
            lines.append(f"| {variant} | {r['total']:,} | {_mib(r['total'])} | {ratio:.1%} | {fields} |")
        lines.append("")
    text = "\n".join(lines)
    print(text)
    args.out.write_text(text)


if __name__ == "__main__":
    main()
