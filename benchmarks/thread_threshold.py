"""From how many poses two CPU devices beat one: ``mmpgo solve FILE --robots 10 --threads 1`` against
``--threads 2`` (the robots split over two CPU devices, one per core), the sizes around
``AUTO_THREAD_POSES`` (``mmpgo_jax/_solve/devices.py``: the default splits from that many poses on).

Graphs: Cube graphs (Fig. 1's kind, ``cube_dataset(0, num_poses=n, grid=6)``, written to a temporary
folder) of ``--sizes`` poses and the small benchmark files ``--files``. AMM, 1000 iterations without
early stop, float64, a warm compilation cache (one untimed run of each first; ``--cold``: an empty
cache for every run, the compile phase then compiles). Every run is a fresh
process; the two thread counts run interleaved, so both see the same machine load; medians of
``--repeats``. Reported: ms per iteration (the CLI's compiled iterations), the whole process's wall
seconds and its processor seconds (user + sys), the CLI's compile phase, and f at the end (the same
iterates either way, up to rounding).

    python benchmarks/thread_threshold.py --repeats 3 --out benchmarks/thread_threshold.md
"""

from __future__ import annotations

import argparse
import datetime
import os
import re
import statistics
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(HERE))

from records import write_record  # noqa: E402  (this folder, on the path as a script's)
from vs_authors import timed_process  # noqa: E402  (this folder is on sys.path when run as a script)

from mmpgo_jax.cli.bench import machine_info  # noqa: E402

_TIME = re.compile(r"iterations [0-9.]+ s \(([0-9.]+) ms/iteration\)")
_COMPILE = re.compile(r"compile ([0-9.]+) s")
_F = re.compile(r"f = 2F\s+\S+ -> (\S+)")
_THREADS = re.compile(r"threads\s+(\d+)")


def one_run(path: str, threads: int, cold: bool = False) -> dict:
    cmd = [sys.executable, "-m", "mmpgo_jax.cli", "solve", path, "--robots", "10", "--iterations", "1000",
           "--all-iterations", "--threads", str(threads)]
    with tempfile.TemporaryDirectory() as cache:  # cold: an empty compilation cache of its own
        cmd += ["--compilation-cache", cache] if cold else []
        out, wall, cpu = timed_process(cmd, env=dict(os.environ, PYTHONPATH=str(HERE)))
    return dict(ms=float(_TIME.search(out).group(1)), wall=wall, cpu=cpu, f=float(_F.search(out).group(1)),
                compile=float(_COMPILE.search(out).group(1)),
                devices=int(m.group(1)) if (m := _THREADS.search(out)) else 1)


def _row(label, n, med, f1, f2, devices) -> str:
    one, two = med[1], med[2]
    pairs = " | ".join(f"{one[k]:.2f} / {two[k]:.2f}" for k in ("wall", "cpu", "compile"))
    return (f"| {label} | {n} | 1 / {devices} | {one['ms']:.2f} | {two['ms']:.2f} | {two['ms'] / one['ms']:.2f} | "
            f"{pairs} | {f1:.6f} | {f2:.6f} |")


def graphs(sizes, files, folder: Path) -> list[tuple[str, str, int]]:
    """(label, path or benchmark name, poses)."""
    import mmpgo_jax as mm

    out = []
    for n in sizes:
        g = mm.cube_dataset(0, num_poses=n, grid=6).graph
        path = folder / f"cube{n}.g2o"
        mm.write_g2o(path, g, None)
        out.append((f"Cube {n}", str(path), n))
    for name in files:
        out.append((name, name, mm.read_g2o(mm.find_benchmark(name)).graph.num_poses))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", nargs="+", type=int, default=[100, 200, 400, 800])
    ap.add_argument("--files", nargs="+", default=["smallGrid3D", "MIT", "CSAIL"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--cold", action="store_true", help="every run with an empty compilation cache")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    info = machine_info()
    start = f"{datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC"
    load0 = os.getloadavg()[0]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for label, path, n in sorted(graphs(args.sizes, args.files, Path(tmp)), key=lambda r: r[2]):
            for threads in (1, 2):
                if not args.cold:
                    one_run(path, threads)  # fills the compilation cache
            runs = {1: [], 2: []}
            for _ in range(args.repeats):
                for threads in (1, 2):
                    runs[threads].append(one_run(path, threads, args.cold))
            keys = ("ms", "wall", "cpu", "compile")
            med = {t: {k: statistics.median(r[k] for r in rs) for k in keys} for t, rs in runs.items()}
            rows.append((label, n, med, runs[1][-1]["f"], runs[2][-1]["f"], runs[2][-1]["devices"]))
            m1, m2 = med[1], med[2]
            print(label, n, m1, m2, flush=True)
    lines = ["# Two CPU devices against one, by graph size", "",
             f"Command: `python benchmarks/thread_threshold.py --repeats {args.repeats}{' --cold' * args.cold}`; "
             f"started {start}, "
             f"{info['cpu']}, {info['usable_cores']} logical CPUs, load average {load0:.2f} at the start, "
             f"{os.getloadavg()[0]:.2f} at the end. `mmpgo solve FILE --robots 10 --iterations 1000 --all-iterations "
             "--threads 1` against `--threads 2`, fresh process per run, "
             f"{'an empty' if args.cold else 'a warm'} compilation cache, interleaved; "
             "medians.", "",
             "| graph | poses | devices used | ms/it, 1 device | ms/it, 2 devices | 2 / 1 | wall s, 1 / 2 "
             "| processor s, 1 / 2 | compile s, 1 / 2 | f, 1 device | f, 2 devices |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    lines += [_row(*row) for row in rows]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        write_record(args.out, text)  # the file's later sections kept
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
