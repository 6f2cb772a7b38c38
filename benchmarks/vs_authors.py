"""Against the authors' C++ code, in the same run on this machine: ``mmpgo solve`` and the authors'
MM-PGO / AMM-PGO (MurpheyLab/DPGO @ da0157f, built by ``../shared/anchors/build_dpgo.sh`` with
``-O3 -march=native``, one thread, robots one after another: ``run_dpgo.sh FILE 10 1000 amm``).

Both run AMM with their own adaptive restart, 10 robots (contiguous blocks), the centralized chordal
start, 1000 iterations; ours with its defaults (float64, every iteration: ``--all-iterations``), a
warm compilation cache and Python's bytecode cache (one untimed run first; ``PYTHONDONTWRITEBYTECODE``
is dropped from our processes' environment, since an installed package's modules are compiled once,
not at every start). Interleaved run by run (authors', ours, authors',
...), so that both see the same machine load; medians of ``--repeats``. Reported: ms per iteration
(theirs: their driver's nanosecond clock around iterate()+update(); ours: the compiled iterations),
the whole process's wall seconds, its processor seconds (user + sys of the child), and f at 1000
(both f = 2F of the same objective). ``--start`` adds the distributed initializations: the
authors' ``dist_pgo --dist_init true --iters 1`` against ``mmpgo solve --init distributed-chordal
--iterations 0`` (whole process; f at the start, and our centralized chordal start's f beside it);
``--start-only`` runs only those; ``--baseline DIR`` runs another checkout's start beside ours
(interleaved; e.g. ``git archive`` of the commit before a change, unpacked in DIR). Besides the
benchmark files, ``chain15k``: the long-chain graph of ``benchmarks/inner_solver.py`` (15 000 planar
poses, mostly odometry chains, 10 robots of 1 500),
written to a temporary g2o file that both programs read.

    DPGO_MIRROR=... bash ../shared/anchors/build_dpgo.sh      # once per machine
    python benchmarks/vs_authors.py --repeats 3 --start --out benchmarks/vs_authors.md
"""

from __future__ import annotations

import argparse
import datetime
import os
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from records import write_record  # this folder, on the path as a script's

HERE = Path(__file__).resolve().parents[1]
ANCHORS = HERE.parent / "shared" / "anchors"
FILES = {"MITb": "MIT.g2o", "intel": "intel.g2o", "M3500": "M3500.g2o", "city10000": "city10000.g2o",
         "sphere2500": "sphere2500.g2o", "torus3D": "torus3D.g2o", "garage": "parking-garage.g2o",
         "chain15k": None}  # None: generated (module docstring)


def dataset_file(name: str, data: Path, tmp: Path) -> str:
    """The g2o path of ``name``: a benchmark file in ``data``, or the generated ``chain15k`` in ``tmp``."""
    if FILES[name] is not None:
        return str(data / FILES[name])
    from inner_solver import chain15k  # the graph's one definition (this folder is on the path as a script)

    import mmpgo_jax as mm  # only to write the graph; this process runs no solve

    ds = chain15k()
    path = tmp / f"{name}.g2o"
    mm.write_g2o(path, ds.graph, ds.ground_truth)
    return str(path)


def timed_process(cmd: list[str], env: dict | None = None, cwd: Path | None = None) -> tuple[str, float, float]:
    """(stdout, wall seconds, processor seconds of the child) of one process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=cwd, check=True).stdout
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return out, wall, cpu


def authors(file: str) -> dict:
    out, wall, cpu = timed_process(["bash", str(ANCHORS / "run_dpgo.sh"), file, "10", "1000", "amm"])
    last = out.strip().splitlines()[-1]
    ms = float(re.search(r"ms_per_iter=([0-9.eE+-]+)", last).group(1))
    f1000 = float(re.search(r"f1000=([0-9.eE+-]+)", last).group(1))
    return dict(ms=ms, wall=wall, cpu=cpu, f=f1000)


def ours_env(root: Path) -> dict:
    """Our processes' environment: the checkout ``root`` first on the path, and Python's bytecode
    cache on (a shell's ``PYTHONDONTWRITEBYTECODE`` would recompile every module at every start, about
    0.1 s that an installed package does not pay). The processes also run in ``root``: ``python -m``
    puts the working directory before ``PYTHONPATH``, so a run started from another checkout would
    import that one (until 2026-12-07 15:10 UTC, ``--baseline`` started from this repository ran
    this repository's code in both columns)."""
    env = dict(os.environ, PYTHONPATH=str(root))
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    return env


def ours(file: str) -> dict:
    out, wall, cpu = timed_process([sys.executable, "-m", "mmpgo_jax.cli", "solve", file, "--robots", "10",
                             "--iterations", "1000", "--all-iterations"], ours_env(HERE), cwd=HERE)
    ms = float(re.search(r"\(([0-9.]+) ms/iteration\)", out).group(1))
    f = float(re.search(r"f = 2F\s+\S+ -> (\S+)", out).group(1))
    return dict(ms=ms, wall=wall, cpu=cpu, f=f)


def authors_start(file: str) -> dict:
    root = Path(os.environ.get("DPGO_ROOT", Path.home() / ".cache" / "dpgo-build"))
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    out, wall, cpu = timed_process([str(root / "build" / "bin" / "dist_pgo"), "--dataset", file, "--num_nodes", "10",
                             "--iters", "1", "--dist_init", "true", "--save", "false"], env)
    # after "Distributed PGO": "0: f |grad|" is the objective at the start (its 2F convention)
    f = re.findall(r"^0: ([0-9.eE+-]+) [0-9.eE+-]+$", out, re.M)
    return dict(wall=wall, cpu=cpu, f=float(f[-1]) if f else float("nan"))


def ours_start(file: str, init: str = "distributed-chordal", root: Path = HERE) -> dict:
    out, wall, cpu = timed_process([sys.executable, "-m", "mmpgo_jax.cli", "solve", file, "--robots", "10",
                             "--init", init, "--iterations", "0"], ours_env(root), cwd=root)
    f = float(re.search(r"f = 2F\s+(\S+)", out).group(1))
    inside = float(re.search(r"initialize ([0-9.]+) s", out).group(1))  # the start itself, in the process
    return dict(wall=wall, cpu=cpu, f=f, inside=inside)


def _median(rows: list[dict], key: str) -> float:
    return statistics.median(r[key] for r in rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--files", nargs="+", default=list(FILES))
    ap.add_argument("--start", action="store_true", help="also the distributed initializations")
    ap.add_argument("--start-only", action="store_true",
                    help="only the distributed initializations (their table, without the solves')")
    ap.add_argument("--baseline", type=Path,
                    help="another checkout (e.g. a `git archive` of an earlier commit) whose distributed start "
                         "runs beside ours, interleaved, in the start table (an A/B of a change)")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    data = Path(os.environ.get("MMPGO_DATA", HERE.parent / "shared" / "datasets"))
    load0 = os.getloadavg()
    lines = []
    solve_rows, start_rows = [], []
    tmp_dir = tempfile.TemporaryDirectory(prefix="vs_authors_")  # removed when the script ends
    tmp = Path(tmp_dir.name)
    for name in args.files:
        file = dataset_file(name, data, tmp)
        if not args.start_only:
            ours(file)  # warm the compilation cache (untimed)
            a, o = [], []
            for _ in range(args.repeats):
                a.append(authors(file))
                o.append(ours(file))
            row = (name, *(_median(a, k) for k in ("ms", "wall", "cpu")),
                   *(_median(o, k) for k in ("ms", "wall", "cpu")), a[0]["f"], o[0]["f"])
            solve_rows.append(row)
            print(row, flush=True)
        if args.start or args.start_only:
            ours_start(file)  # warm
            if args.baseline:
                ours_start(file, root=args.baseline)
            sa, so, sb = [], [], []
            for _ in range(args.repeats):
                sa.append(authors_start(file))
                so.append(ours_start(file))
                if args.baseline:
                    sb.append(ours_start(file, root=args.baseline))
            before = (_median(sb, "wall"), _median(sb, "inside")) if sb else ()
            start_rows.append((name, _median(sa, "wall"), _median(so, "wall"), _median(so, "inside"),
                               _median(sa, "cpu"), _median(so, "cpu"), sa[0]["f"], so[0]["f"],
                               ours_start(file, "chordal")["f"], *before))
            print(start_rows[-1], flush=True)
    from mmpgo_jax.cli.bench import cpu_name  # the package only now: this process only starts others

    model = cpu_name()
    flag = " --start-only" if args.start_only else (" --start" if args.start else "")
    flag += f" --baseline {args.baseline}" if args.baseline else ""
    run = (f"Command: `python benchmarks/vs_authors.py --repeats {args.repeats}{flag}`; "
           f"{datetime.date.today().isoformat()}, {model}, {os.cpu_count()} logical CPUs, load average "
           f"{load0[0]:.2f} at the start, {os.getloadavg()[0]:.2f} at the end. Authors: MurpheyLab/DPGO @ da0157f, "
           "Release `-O3 -march=native`, one thread. Interleaved run by run; medians.")
    lines += ["# Against the authors' C++ code (same run, same machine)", "", run]
    if solve_rows:
        lines += [
            "",
            "Solves: authors' `run_dpgo.sh FILE 10 1000 amm`; ours: `mmpgo solve FILE --robots 10 --iterations 1000 "
            "--all-iterations` (defaults, float64, warm compilation and bytecode caches).",
            "",
            "| file | authors' ms/it | ours ms/it | ratio (ours / theirs) | whole run s, authors' / ours | "
            "processor s (user+sys), authors' / ours | f at 1000, authors' / ours |",
            "|---|---|---|---|---|---|---|",
        ]
    for name, ams, awall, acpu, oms, owall, ocpu, af, of in solve_rows:
        lines.append(f"| {name} | {ams:.2f} | {oms:.2f} | {oms / ams:.2f} | {awall:.2f} / {owall:.2f} | "
                     f"{acpu:.2f} / {ocpu:.2f} ({ocpu / acpu:.2f}x) | {af:.6f} / {of:.6f} |")
    if start_rows:
        lines += ["", "Distributed initialization, 10 robots, whole process (authors: `dist_pgo --dist_init true "
                  "--iters 1`; ours: `mmpgo solve FILE --init distributed-chordal --iterations 0`):", "",
                  "| file | authors' s | ours s | ratio | ours: the start in the process s "
                  "| processor s, authors' / ours | f at the start, authors' / ours | centralized chordal f "
                  "| ours against it |"
                  + (" baseline s | baseline: the start in the process s |" if args.baseline else ""),
                  "|---|---|---|---|---|---|---|---|---|" + ("---|---|" if args.baseline else "")]
        for name, aw, ow, oi, ac, oc, af, of, fc, *before in start_rows:
            lines.append(f"| {name} | {aw:.2f} | {ow:.2f} | {ow / aw:.2f} | {oi:.2f} | {ac:.2f} / {oc:.2f} "
                         f"| {af:.4f} / {of:.4f} | {fc:.4f} | {(of - fc) / fc:+.1e} |"
                         + "".join(f" {x:.2f} |" for x in before))
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:  # all or nothing: a stopped run leaves the old file; the file's later sections kept
        write_record(args.out, text)


if __name__ == "__main__":
    main()
