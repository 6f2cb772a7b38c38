"""End to end: `mmpgo solve FILE` in a fresh process, cold and warm compilation cache.

For each file: one run with an empty cache folder (cold: everything compiles), then one with the
folder the first run filled (warm). Wall time from process start to the result written (`--out`),
and the phases the CLI prints (read, initialize, build, compile, iterations, write). The warm run
neither traces nor compiles: the traced program (``jax.export``) and the compiled one both come
from the cache. Compared with
the authors' C++ code's whole run (AMM, 1000 iterations, 10 robots, same machine; measured
2026-12-01 in the same run as the project's then-current version, see docs/conventions.md §7).

    python benchmarks/end_to_end.py --out benchmarks/end_to_end.md

``--baseline DIR`` (a checkout of another version of the package, e.g. a ``git worktree`` of an
earlier commit) runs that version's cold and warm runs interleaved with ours, each in its own cache
folder, so that both see the same machine load; ``--repeats K`` takes the median of K warm runs.
Every run imports the package from its checkout (``PYTHONPATH``) in a temporary working folder.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from records import write_record  # this folder, on the path as a script's

from mmpgo_jax._solve.devices import AUTO_THREAD_POSES

# The authors' whole run, AMM, 1000 iterations (s): MurpheyLab/DPGO @ da0157f, Release, one thread.
AUTHORS_SECONDS = {"MITb": 1.09, "intel": 2.36, "M3500": 5.56, "city10000": 25.1, "sphere2500": 8.1,
                   "torus3D": 16.2, "garage": 9.1}
PHASES = ("read", "initialize", "build", "compile", "iterations", "write")
HERE = Path(__file__).resolve().parents[1]  # the checkout this script belongs to


def _env(checkout: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(checkout))
    if "MMPGO_DATA" not in env and (checkout.parent / "shared" / "datasets").is_dir():
        env["MMPGO_DATA"] = str(checkout.parent / "shared" / "datasets")
    return env


def run(name: str, cache: Path, out: Path, iterations: int, checkout: Path = HERE) -> tuple[float, dict]:
    cmd = [sys.executable, "-m", "mmpgo_jax.cli", "solve", name, "--iterations", str(iterations), "--no-progress",
           "--compilation-cache", str(cache), "--out", str(out)]
    t = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, check=True, env=_env(checkout), cwd=out.parent)
    wall = time.perf_counter() - t
    line = next(x for x in proc.stdout.splitlines() if x.startswith("time"))
    # a run over several CPU devices reports initialize and build as one figure
    line = re.sub(r"initialize and build ([0-9.]+) s", r"initialize \1 s, build nan s", line)
    phases = {p: float(re.search(rf"{p} ([0-9.na]+) s", line).group(1)) for p in PHASES}
    threads = re.search(r"^threads\s+(\d+)", proc.stdout, re.M)
    phases["threads"] = int(threads.group(1)) if threads else 1
    return wall, phases


def import_seconds(code: str, checkout: Path = HERE) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        subprocess.run([sys.executable, "-c", code], check=True, env=_env(checkout), cwd=tmp)
        return time.perf_counter() - t


def fixed_seconds(wall: float, phases: dict) -> float:
    """The part of a run's wall time outside its phases: interpreter start, imports, argument
    parsing, JAX's set-up, printing and the interpreter's exit."""
    return wall - sum(phases[p] for p in PHASES if phases[p] == phases[p])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--files", nargs="*", default=list(AUTHORS_SECONDS))
    ap.add_argument("--iterations", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=1, help="warm runs per file (the median is reported)")
    ap.add_argument("--baseline", type=Path, default=None,
                    help="a checkout of another version: its runs are interleaved with ours")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    load_start = os.getloadavg()[0]
    solve_path = "import mmpgo_jax.cli, mmpgo_jax.cli.robots, mmpgo_jax._io.g2o, mmpgo_jax._solve.solve"
    imports = {"python": import_seconds("pass"), "jax": import_seconds("import jax"),
               "solve": import_seconds(solve_path)}
    base_imports = import_seconds(solve_path, args.baseline) if args.baseline else None
    checkouts = [("ours", HERE)] + ([("baseline", args.baseline.resolve())] if args.baseline else [])
    rows = []
    for name in args.files:
        with tempfile.TemporaryDirectory() as tmp:
            cold, warm = {}, {}
            for label, checkout in checkouts:  # cold runs, then the warm ones interleaved
                (Path(tmp) / label).mkdir()
                cold[label] = run(name, Path(tmp) / label / "cache", Path(tmp) / label / "out.g2o", args.iterations,
                                  checkout)
            for _ in range(args.repeats):
                for label, checkout in checkouts:
                    warm.setdefault(label, []).append(
                        run(name, Path(tmp) / label / "cache", Path(tmp) / label / "out.g2o", args.iterations,
                            checkout))
        runs = sorted(warm["ours"], key=lambda r: r[0])
        wall, ph = runs[len(runs) // 2]  # the median run (the upper one for an even count)
        authors = AUTHORS_SECONDS.get(name)
        ratio = f"{wall / authors:.2f}" if authors else "-"
        base = ""
        if args.baseline:
            base_runs = sorted(warm["baseline"], key=lambda r: r[0])
            base_wall, base_ph = base_runs[len(base_runs) // 2]
            base = f" | {base_wall:.2f} | {fixed_seconds(base_wall, base_ph):.2f} | {wall / base_wall:.2f}"
        rows.append(f"| {name} | {ph['threads']} | {cold['ours'][0]:.1f} | {cold['ours'][1]['compile']:.2f} | "
                    f"{wall:.2f} | {fixed_seconds(wall, ph):.2f} | {ph['compile']:.2f} | "
                    + " | ".join("—" if ph[p] != ph[p] else f"{ph[p]:.2f}"  # nan: not reported apart
                                 for p in ("read", "initialize", "build", "iterations", "write"))
                    + f" | {authors if authors else '-'} | {ratio}{base} |\n")
        print(rows[-1], end="", flush=True)
    base_head = " baseline warm wall s | baseline fixed s | ours / baseline |" if args.baseline else ""
    base_note = (f" Baseline: `{args.baseline}`, run interleaved with ours (same load); importing its solve path "
                 f"took {base_imports:.2f} s." if args.baseline else "")
    text = (f"# End to end: `mmpgo solve FILE` (AMM, {args.iterations} iterations, 10 robots)\n\n"
            f"Command: `python benchmarks/end_to_end.py"
            f"{' --repeats ' + str(args.repeats) if args.repeats > 1 else ''}"
            f"{' --baseline DIR' if args.baseline else ''}`; {datetime.date.today()}, "
            f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, load average "
            f"{load_start:.2f} at the start, {os.getloadavg()[0]:.2f} at the end. A fresh process per run. In a fresh "
            f"process: the interpreter alone {imports['python']:.2f} s, `import jax` {imports['jax']:.2f} s, the "
            f"modules of `mmpgo solve` ({solve_path.removeprefix('import ')}) {imports['solve']:.2f} s.{base_note} "
            "Cold: empty compilation cache; warm: the cache the cold run wrote"
            f"{f', median of {args.repeats} runs' if args.repeats > 1 else ''}. Phases (s) are the CLI's own `time` "
            "line of that warm run; fixed s is the rest of its wall time (interpreter start, imports, JAX's set-up, "
            "the interpreter's exit).\n\n"
            "Threads: the CPU devices `mmpgo solve` split the robots over (one per core from "
            f"{AUTO_THREAD_POSES} poses on; then initialize and build are one figure, under initialize).\n\n"
            "| file | threads | cold wall s | cold compile s | warm wall s | fixed s | warm compile s | read | "
            "initialize | build | iterations | write | authors' whole run s | warm / authors' |" + base_head + "\n"
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|" + ("---|---|---|" if args.baseline else "")
            + "\n" + "".join(rows))
    if args.out:
        write_record(args.out, text)  # the file's later sections kept
    else:
        print(text)


if __name__ == "__main__":
    main()
