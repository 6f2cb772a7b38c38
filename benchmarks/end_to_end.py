"""End to end: `mmpgo solve FILE` in a fresh process, cold and warm compilation cache.

For each file: one run with an empty cache folder (cold: everything compiles), then one with the
folder the first run filled (warm). Wall time from process start to the result written (`--out`),
and the phases the CLI prints (read, initialize, build, compile, iterations, write). The warm run
neither traces nor compiles: the traced program (``jax.export``) and the compiled one both come
from the cache. Compared with
the authors' C++ code's whole run (AMM, 1000 iterations, 10 robots, same machine; measured
2026-12-01 in the same run as the project's then-current version, see docs/conventions.md §7).

    python benchmarks/end_to_end.py --out benchmarks/end_to_end.md
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

# The authors' whole run, AMM, 1000 iterations (s): MurpheyLab/DPGO @ da0157f, Release, one thread.
AUTHORS_SECONDS = {"MITb": 1.09, "intel": 2.36, "M3500": 5.56, "city10000": 25.1, "sphere2500": 8.1,
                   "torus3D": 16.2, "garage": 9.1}
PHASES = ("read", "initialize", "build", "compile", "iterations", "write")


def run(name: str, cache: Path, out: Path, iterations: int) -> tuple[float, dict]:
    cmd = [sys.executable, "-m", "mmpgo_jax.cli", "solve", name, "--iterations", str(iterations), "--no-progress",
           "--compilation-cache", str(cache), "--out", str(out)]
    t = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, check=True)
    wall = time.perf_counter() - t
    line = next(x for x in proc.stdout.splitlines() if x.startswith("time"))
    # a run over several CPU devices reports initialize and build as one figure
    line = re.sub(r"initialize and build ([0-9.]+) s", r"initialize \1 s, build nan s", line)
    phases = {p: float(re.search(rf"{p} ([0-9.na]+) s", line).group(1)) for p in PHASES}
    threads = re.search(r"^threads\s+(\d+)", proc.stdout, re.M)
    phases["threads"] = int(threads.group(1)) if threads else 1
    return wall, phases


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--files", nargs="*", default=list(AUTHORS_SECONDS))
    ap.add_argument("--iterations", type=int, default=1000)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    t = time.perf_counter()
    subprocess.run([sys.executable, "-c", "import mmpgo_jax.cli"], check=True)
    import_seconds = time.perf_counter() - t
    rows = []
    for name in args.files:
        with tempfile.TemporaryDirectory() as tmp:
            cache, out = Path(tmp) / "cache", Path(tmp) / "out.g2o"
            cold = run(name, cache, out, args.iterations)
            warm = run(name, cache, out, args.iterations)
        authors = AUTHORS_SECONDS.get(name)
        ratio = f"{warm[0] / authors:.2f}" if authors else "-"
        ph = warm[1]
        rows.append(f"| {name} | {ph['threads']} | {cold[0]:.1f} | {cold[1]['compile']:.2f} | {warm[0]:.1f} | "
                    f"{ph['compile']:.2f} | "
                    + " | ".join("—" if ph[p] != ph[p] else f"{ph[p]:.2f}"  # nan: not reported apart
                                 for p in ("read", "initialize", "build", "iterations", "write"))
                    + f" | {authors if authors else '-'} | {ratio} |\n")
        print(rows[-1], end="", flush=True)
    text = (f"# End to end: `mmpgo solve FILE` (AMM, {args.iterations} iterations, 10 robots)\n\n"
            f"Command: `python benchmarks/end_to_end.py`; {datetime.date.today()}, "
            f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, load average "
            f"{os.getloadavg()[0]:.2f} at the end. A fresh process per run; `import mmpgo_jax.cli` alone takes "
            f"{import_seconds:.1f} s in a fresh process (included in every wall time). Cold: empty compilation "
            "cache; warm: the cache the cold run wrote. Phases (s) are the CLI's own `time` line of the warm run.\n\n"
            "Threads: the CPU devices `mmpgo solve` split the robots over (one per core from 1000 poses on; "
            "then initialize and build are one figure, under initialize).\n\n"
            "| file | threads | cold wall s | cold compile s | warm wall s | warm compile s | read | initialize | "
            "build | iterations | write | authors' whole run s | warm / authors' |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|\n" + "".join(rows))
    if args.out:
        Path(args.out).write_text(text)
    else:
        print(text)


if __name__ == "__main__":
    main()
