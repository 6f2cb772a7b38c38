"""Partition study: contiguous blocks vs METIS vs random balanced parts, MM and AMM.

    nice -n 10 python benchmarks/partitions.py                       # the run recorded in partitions.md
    python benchmarks/partitions.py --files MITb --cube 0 --iterations 100 --out /tmp/p   # a quick look

For each graph (benchmark files found through MMPGO_DATA, and generated Cube graphs) and each
split (``blocks``: the paper's contiguous blocks; ``metis``: METIS k-way through pymetis;
``random``: random balanced parts, seed 0) with 5, 10 and 50 robots, MM-PGO and AMM-PGO
(adaptive restart) run from the centralized chordal start for ``--iterations`` outer iterations.
Reported per configuration: iterations and seconds (compiled iterations, compilation excluded)
to a relative suboptimality (f - f*)/f* <= 1e-3 and 1e-4, inter-robot edges, and poses / bytes
exchanged per iteration (float64 poses, all robots together: each robot's poses needed by each
neighbour). f* is the registry's (``mmpgo_jax.BENCHMARKS``: SE-Sync's certified optimum) for the
files and :func:`~mmpgo_jax.reference_optimum` for the Cube graphs.

Every graph runs in one :func:`~mmpgo_jax.sweep` with the three splits as three named copies of
the graph (``group_by="robots"``: one compilation per (method, robot count), shared by the
splits), one configuration per batch (the CPU's fastest, and AMM keeps its real ``lax.cond``).

Writes ``<out>.md`` (tables, command, date, machine, load; a hand-written "## Conclusions"
section already in the file is kept at its end) and ``<out>.csv`` (one row per configuration).
"""

from __future__ import annotations

import argparse
import csv
import datetime as _dt
import os
import shlex
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import mmpgo_jax as mm  # noqa: E402
from mmpgo_jax._core.partition import partition_stats, split_robots  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from fig1 import machine  # noqa: E402

SPLITS = ("blocks", "metis", "random")
TOLS = (1e-3, 1e-4)
FILES = ("MITb", "intel", "M3500", "sphere", "garage")
CONCLUSIONS = "## Conclusions"


def first_below(rel: np.ndarray, tol: float) -> int | None:
    idx = np.flatnonzero(rel <= tol)
    return int(idx[0]) if idx.size else None


def graphs(args) -> list[tuple[str, object, float]]:
    out = []
    for name in args.files:
        path = mm.find_benchmark(name)
        info = mm.benchmark_info(name)
        out.append((info.name if info else name, mm.read_g2o(path).graph, float(info.fstar)))
    for seed in args.cube:
        ds = mm.cube_dataset(seed=seed, num_poses=args.cube_poses)
        out.append((f"Cube{args.cube_poses}-s{seed}", ds.graph, mm.reference_optimum(ds.graph)))
    return out


def run_graph(name, graph, fstar, args) -> list[dict]:
    named = {f"{name}|{s}": graph for s in SPLITS}
    t = time.perf_counter()
    res = mm.sweep(named, robots=args.robots, methods=("mm", "amm"), iterations=args.iterations,
                   split={f"{name}|{s}": s for s in SPLITS}, group_by="robots", max_batch_configs=1,
                   fstar={k: fstar for k in named},
                   progress=lambda msg: print(f"  [{name}] {msg}", file=sys.stderr, flush=True))
    wall = time.perf_counter() - t
    compile_s = sum(g["compile_seconds"] for g in res.groups)
    rows = []
    for cfg in res.configs:
        gname, split = cfg["graph"].split("|")
        A, method = cfg["robots"], cfg["method"]
        st = partition_stats(graph, split_robots(graph, split, A))
        rel = res.relative_gap(cfg["graph"], A, method)
        sec_per_it = cfg["seconds"] / max(args.iterations, 1)
        row = dict(graph=gname, n=graph.num_poses, m=graph.num_edges, d=graph.dim, split=split, robots=A,
                   method=method, inter_edges=st.total_inter_edges, poses_sent=int(st.sent_poses.sum()),
                   bytes_per_iteration=int(st.sent_bytes(np.float64).sum()),
                   max_poses=int(st.poses.max()), min_poses=int(st.poses.min()),
                   ms_per_iteration=1e3 * sec_per_it, final_rel=float(rel[-1]))
        for tol in TOLS:
            k = first_below(rel, tol)
            row[f"it_{tol:g}"] = k
            row[f"s_{tol:g}"] = None if k is None else k * sec_per_it
        rows.append(row)
    print(f"[{name}] {len(res.configs)} configurations in {wall:.0f} s ({compile_s:.0f} s compiling)",
          file=sys.stderr, flush=True)
    return rows


def fmt(v, kind="int"):
    if v is None:
        return "–"
    if kind == "s":
        return f"{v:.2f}"
    if kind == "ms":
        return f"{v:.1f}"
    if kind == "e":
        return f"{v:.1e}"
    return str(v)


def write_md(path: Path, rows, meta) -> None:
    lines = [
        "# Partition study: contiguous blocks vs METIS vs random balanced parts",
        "",
        f"Command: `{meta['command']}`  ",
        f"Date: {meta['date']}; load average before / after: {meta['load_before']} / {meta['load_after']}  ",
        f"Machine: {meta['machine']}  ",
        f"Total wall time: {meta['seconds']:.0f} s. float64, centralized chordal start, xi = 1e-3, AMM with the "
        f"adaptive restart, {meta['iterations']} iterations; f* from the registry (SE-Sync) for the files, "
        "`reference_optimum` for the Cube graphs.",
        "",
        "Columns: `inter` = inter-robot edges; `sent/it` = poses sent per iteration over all robots (each pose "
        "once per neighbour robot that reads it) and the bytes at float64 (d + d² numbers per pose); `it` / `s` = "
        "iterations / seconds of compiled iterations (compilation excluded, one configuration at a time on the "
        "CPU) to (f − f*)/f* ≤ 1e-3 and 1e-4 (– : not reached); `final` = (f − f*)/f* after the last iteration.",
        "",
    ]
    graphs_ = list(dict.fromkeys(r["graph"] for r in rows))
    for g in graphs_:
        rs = [r for r in rows if r["graph"] == g]
        r0 = rs[0]
        lines += [f"## {g} (n = {r0['n']}, m = {r0['m']}, d = {r0['d']})", "",
                  "| robots | split | poses/robot | inter | sent/it (bytes) | method | ms/it | it → 1e-3 | s → 1e-3 "
                  "| it → 1e-4 | s → 1e-4 | final |",
                  "|---:|---|---|---:|---:|---|---:|---:|---:|---:|---:|---:|"]
        for r in rs:
            lines.append(
                f"| {r['robots']} | {r['split']} | {r['min_poses']}–{r['max_poses']} | {r['inter_edges']} | "
                f"{r['poses_sent']} ({r['bytes_per_iteration']}) | {r['method'].upper()} | "
                f"{fmt(r['ms_per_iteration'], 'ms')} | {fmt(r['it_0.001'])} | {fmt(r['s_0.001'], 's')} | "
                f"{fmt(r['it_0.0001'])} | {fmt(r['s_0.0001'], 's')} | {fmt(r['final_rel'], 'e')} |")
        lines.append("")
    lines += summary(rows)
    # the hand-written conclusions (from the tables above) survive a rerun; check them against new numbers
    old = path.read_text(encoding="utf-8") if path.exists() else ""
    kept = old[old.index(CONCLUSIONS):] if CONCLUSIONS in old else ""
    path.write_text("\n".join(lines) + "\n" + kept, encoding="utf-8")


def summary(rows) -> list[str]:
    """Per (method, robots, tolerance): on how many graphs each split is the fastest to the tolerance
    in iterations, and the median ratio of its iterations to the blocks' iterations."""
    out = ["## Summary (measured above)", "",
           "| method | robots | tol | fewest iterations: blocks / metis / random (graphs) "
           "| median it(metis)/it(blocks) | median it(random)/it(blocks) | median inter-edges metis/blocks "
           "| random/blocks |",
           "|---|---:|---:|---|---:|---:|---:|---:|"]
    methods = list(dict.fromkeys(r["method"] for r in rows))
    robots = sorted({r["robots"] for r in rows})
    graphs_ = list(dict.fromkeys(r["graph"] for r in rows))
    for method in methods:
        for A in robots:
            for tol in TOLS:
                wins = dict.fromkeys(SPLITS, 0)
                ratio = {s: [] for s in SPLITS}
                edges = {s: [] for s in SPLITS}
                for g in graphs_:
                    sel = {r["split"]: r for r in rows
                           if r["graph"] == g and r["method"] == method and r["robots"] == A}
                    if len(sel) < 3:
                        continue
                    its = {s: sel[s][f"it_{tol:g}"] for s in SPLITS}
                    reached = {s: k for s, k in its.items() if k is not None}
                    if reached:
                        best = min(reached.values())
                        for s, k in reached.items():
                            wins[s] += k == best
                    b = its["blocks"]
                    for s in SPLITS:
                        k = its[s]
                        if b is not None and k is not None and b > 0:
                            ratio[s].append(k / b)
                        edges[s].append(sel[s]["inter_edges"] / max(sel["blocks"]["inter_edges"], 1))
                med = {s: (f"{np.median(v):.2f}" if v else "–") for s, v in ratio.items()}
                emed = {s: (f"{np.median(v):.2f}" if v else "–") for s, v in edges.items()}
                out.append(f"| {method.upper()} | {A} | {tol:g} | {wins['blocks']} / {wins['metis']} / "
                           f"{wins['random']} | {med['metis']} | {med['random']} | {emed['metis']} | "
                           f"{emed['random']} |")
    return [*out, ""]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--files", nargs="*", default=list(FILES), help="benchmark names (default: %(default)s)")
    p.add_argument("--cube", nargs="*", type=int, default=[0], help="Cube seeds (default: 0)")
    p.add_argument("--cube-poses", type=int, default=3600)
    p.add_argument("--robots", nargs="*", type=int, default=[5, 10, 50])
    p.add_argument("--iterations", type=int, default=1000)
    p.add_argument("--out", default=str(HERE / "partitions"), help="output prefix (.md, .csv)")
    args = p.parse_args(argv)
    meta = dict(command="python " + " ".join(shlex.quote(a) for a in [os.path.relpath(__file__), *sys.argv[1:]]),
                date=_dt.datetime.now().astimezone().isoformat(timespec="minutes"),
                load_before=" ".join(f"{x:.2f}" for x in os.getloadavg()), machine=machine(),
                iterations=args.iterations)
    t = time.perf_counter()
    rows = []
    for name, graph, fstar in graphs(args):
        rows += run_graph(name, graph, fstar, args)
        out = Path(args.out)
        with open(out.with_suffix(".csv"), "w", newline="", encoding="utf-8") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
        meta.update(seconds=time.perf_counter() - t, load_after=" ".join(f"{x:.2f}" for x in os.getloadavg()))
        write_md(out.with_suffix(".md"), rows, meta)
    print(f"wrote {out.with_suffix('.md')} and {out.with_suffix('.csv')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
