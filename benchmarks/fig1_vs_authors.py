"""The Fig. 1 study's time against the authors' code, on a same-run sample, extrapolated.

    nice python benchmarks/fig1_vs_authors.py [--datasets 2] [--iterations 1000] [--robots 5 10 50]
        [--repeats 1] [--out benchmarks/fig1_vs_authors.md]

The study (``benchmarks/fig1.py``): 20 Cube graphs (3600 poses, grid 12) x {5, 10, 50} robots x
{MM, AMM} x 1000 iterations. Here a sample of it runs on this machine, interleaved per repeat:

* the authors' code (``../shared/anchors/run_dpgo.sh FILE A ITERS mm|amm``, one thread, robots one
  after another; built by ``build_dpgo.sh``) on each sampled graph (written as g2o) and robot count:
  its per-iteration time (``ms_per_iter``: iterate + update of all robots) and its whole process;
* ``mm.sweep`` of the same configurations in a fresh process, as ``fig1.py`` runs it (one
  configuration per batch, grouped by robot count), once on JAX's single default CPU device and once
  after ``mm.use_cpu_cores()`` (one CPU device per core: the sweep then runs one batch per device at a
  time), each twice in its process: the first sweep's wall time (compilation included) and the
  second's (everything compiled: set-up and iterations alone).

Extrapolation to the whole study (20 graphs, 1000 iterations): the authors' configurations run one
after another, so their time is sum over the sampled configurations of ms_per_iter x 1000, times
20 / (sampled graphs) (the iterations alone; their processes add reading and the chordal start);
ours is the second sweep's wall x (1000 / iterations) x 20 / (sampled graphs) plus what the first
cost more (compilation, which does not grow with the graphs or the iterations; the set-up of each
configuration, its start and partition, is in the wall time, so with fewer than 1000 iterations it
is over-counted: run the default 1000). An even number of sampled graphs pairs the batches of a
group on two devices as the 20 graphs of the study do. Same graphs, same robot counts, same methods.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from records import write_record

HERE = Path(__file__).parent
ANCHORS = HERE.parent.parent / "shared" / "anchors"

_CHILD = """
import json, sys, time
import mmpgo_jax as mm
cores = {cores}
if cores:
    mm.use_cpu_cores()
import jax
jax.config.update("jax_enable_x64", True)
graphs = {{f"cube{{s:02d}}": mm.cube_dataset(s, num_poses={poses}, grid={grid}).graph for s in range({datasets})}}
walls = []
for _ in range(2):  # the second sweep compiles nothing: its wall is set-up and iterations alone
    t = time.perf_counter()
    res = mm.sweep(graphs, {robots}, ("mm", "amm"), {iterations}, group_by="robots", max_batch_configs=1)
    walls.append(time.perf_counter() - t)
print(json.dumps(dict(wall=walls[0], compiled_wall=walls[1],
                      devices=max(g.get("devices", 1) for g in res.groups), cpu_devices=len(jax.devices("cpu")),
                      f={{"|".join(map(str, k)): float(v[-1]) for k, v in res.histories.items()}})))
"""


def _ours(args, cores: bool) -> dict:
    code = _CHILD.format(cores=cores, poses=args.poses, grid=args.grid, datasets=args.datasets,
                         robots=list(args.robots), iterations=args.iterations)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def _authors(path: Path, robots: int, iterations: int, method: str) -> dict:
    out = subprocess.run(["bash", str(ANCHORS / "run_dpgo.sh"), str(path), str(robots), str(iterations), method],
                         capture_output=True, text=True, check=True).stdout
    last = out.strip().splitlines()[-1]
    ms = float(re.search(r"ms_per_iter=([0-9.eE+-]+)", last).group(1))
    total = float(re.search(r"total_s=([0-9.eE+-]+)", last).group(1))
    return dict(ms_per_iter=ms, total_s=total)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", type=int, default=2)
    ap.add_argument("--iterations", type=int, default=1000)
    ap.add_argument("--robots", type=int, nargs="+", default=[5, 10, 50])
    ap.add_argument("--poses", type=int, default=3600)
    ap.add_argument("--grid", type=int, default=12)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--out", default=str(HERE / "fig1_vs_authors.md"))
    args = ap.parse_args(argv)

    import mmpgo_jax as mm  # the graphs and the g2o writer; this process runs no solve
    from mmpgo_jax._io.atomic import atomic_write
    from mmpgo_jax.cli.bench import machine_info

    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    load = os.getloadavg()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        files = []
        for s in range(args.datasets):
            ds = mm.cube_dataset(s, num_poses=args.poses, grid=args.grid)
            files.append(Path(tmp) / f"cube{s:02d}.g2o")
            mm.write_g2o(files[-1], ds.graph, ds.ground_truth)
        for rep in range(args.repeats):
            theirs = {f"{f.stem}|{a}|{m}": _authors(f, a, args.iterations, m)
                      for f in files for a in args.robots for m in ("mm", "amm")}
            one, cores = _ours(args, False), _ours(args, True)
            rows.append(dict(repeat=rep, theirs=theirs, one=one, cores=cores))
            print(f"repeat {rep}: authors' iterations {sum(v['ms_per_iter'] for v in theirs.values()):.1f} ms per "
                  f"study iteration; ours {one['wall']:.1f} s (one device), {cores['wall']:.1f} s "
                  f"({cores['cpu_devices']} devices)", flush=True)
    scale = 20 / args.datasets
    lines = [
        "# The Fig. 1 study against the authors' code (same-run sample, extrapolated)",
        "",
        f"Command: `{' '.join(['python', 'benchmarks/fig1_vs_authors.py', *sys.argv[1:]])}`; {started}, "
        f"{machine_info().get('cpu')}, {os.cpu_count()} logical CPUs, load average {load[0]:.2f} at the start, "
        f"{os.getloadavg()[0]:.2f} at the end. Method: the script's docstring. Sample: {args.datasets} Cube graphs "
        f"({args.poses} poses) x robots {args.robots} x {{MM, AMM}} x {args.iterations} iterations.",
        "",
        "| repeat | authors: sum of ms/it over the sample | authors: whole study, s (extrapolated) | "
        "ours, one CPU device: sample wall s, first / compiled | whole study s | ratio to authors | "
        "ours, use_cpu_cores(): sample wall s, first / compiled | whole study s | ratio to authors |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        ms = sum(v["ms_per_iter"] for v in r["theirs"].values())
        theirs = ms * 1000 / 1000 * scale  # ms per iteration x 1000 iterations, in s, for 20 graphs
        cells = [str(r["repeat"]), f"{ms:.1f}", f"{theirs:.0f}"]
        for side in ("one", "cores"):
            o = r[side]
            study = o["compiled_wall"] * (1000 / args.iterations) * scale + (o["wall"] - o["compiled_wall"])
            cells += [f"{o['wall']:.1f} / {o['compiled_wall']:.1f}", f"{study:.0f}", f"{study / theirs:.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    drift = max(abs(r["one"]["f"][k] - r["cores"]["f"][k]) / abs(r["one"]["f"][k]) for r in rows for k in r["one"]["f"])
    lines += ["", f"f at the last iteration, one device against use_cpu_cores(): largest relative difference "
              f"{drift:.1e} (the same iterates on another device).", ""]
    write_record(args.out, "\n".join(lines))  # the file's later sections kept
    with atomic_write(Path(args.out).with_suffix(".json")) as fh:
        fh.write(json.dumps(dict(args=vars(args), rows=rows), indent=1))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
