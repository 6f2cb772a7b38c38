"""Cold compile against iteration speed: ``mmpgo solve`` compiled the fast way and the optimized way.

For each file (10 robots, AMM, 1000 iterations, the CLI's defaults otherwise) and each compile mode
(``MMPGO_COMPILE_MODE=fast``: XLA:CPU's older LLVM IR emitters; ``optimized``: XLA's MLIR fusion
emitters, its default), a fresh process with an empty compilation cache reports the CLI's own
``time`` line: the compile phase (every program of the run: the start's and the outer loop's,
traced and compiled) and ms per iteration. A robust run (``--loss tls``) on the first file is
measured the same way. The modes run interleaved, repeat by repeat, so both see the same load;
medians of ``--repeats`` are reported, with f after the run (both modes must agree to rounding).

    python benchmarks/compile_mode.py --repeats 3 --out benchmarks/compile_mode.md
"""

from __future__ import annotations

import argparse
import datetime
import os
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from records import write_record  # this folder, on the path as a script's

from mmpgo_jax.cli.bench import machine_info

HERE = Path(__file__).resolve().parents[1]
FILES = ["MITb", "intel", "M3500", "city10000", "sphere2500", "torus3D", "garage"]
MODES = ("fast", "optimized")


def run(name: str, mode: str, extra: list[str]) -> dict:
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, MMPGO_COMPILE_MODE=mode, PYTHONPATH=str(HERE))
        cmd = [sys.executable, "-m", "mmpgo_jax.cli", "solve", name, "--robots", "10", "--no-progress",
               "--compilation-cache", cache, *extra]
        out = subprocess.run(cmd, capture_output=True, text=True, env=env, check=True).stdout
    compile_s = float(re.search(r"compile ([0-9.]+) s", out).group(1))
    ms = float(re.search(r"\(([0-9.]+) ms/iteration", out).group(1))
    f = float(re.search(r"f = 2F\s+\S+ -> (\S+)", out).group(1))
    return dict(compile=compile_s, ms=ms, f=f)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--files", nargs="+", default=FILES)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    load0 = os.getloadavg()[0]
    started = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    cases = [(name, name, []) for name in args.files] + [(f"{args.files[0]} --loss tls", args.files[0],
                                                          ["--loss", "tls"])]
    rows = []
    for label, name, extra in cases:
        runs = {m: [] for m in MODES}
        for _ in range(args.repeats):
            for mode in MODES:
                runs[mode].append(run(name, mode, extra))
        med = {m: {k: statistics.median(r[k] for r in runs[m]) for k in ("compile", "ms")} for m in MODES}
        rows.append((label, med, runs["fast"][0]["f"], runs["optimized"][0]["f"]))
        print(label, med, flush=True)
    info = machine_info()
    lines = [
        "# Compile mode: cold compile against iteration speed",
        "",
        f"Command: `python benchmarks/compile_mode.py --repeats {args.repeats}`; started {started}, "
        f"{info.get('cpu')}, {os.cpu_count()} logical CPUs, load average {load0:.2f} at the start, "
        f"{os.getloadavg()[0]:.2f} at the end. `mmpgo solve FILE --robots 10` (AMM, 1000 iterations), a fresh "
        "process and an empty compilation cache per run, the modes interleaved; medians. Compile: the CLI's "
        "compile phase (the start's and the outer loop's programs, traced and compiled).",
        "",
        "| run | compile s, fast | compile s, optimized | saved s | ms/it, fast | ms/it, optimized | "
        "ms/it fast / optimized | f, fast | f, optimized |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for label, med, f_fast, f_opt in rows:
        fa, op = med["fast"], med["optimized"]
        lines.append(f"| {label} | {fa['compile']:.2f} | {op['compile']:.2f} | {op['compile'] - fa['compile']:.2f} | "
                     f"{fa['ms']:.3f} | {op['ms']:.3f} | {fa['ms'] / op['ms']:.2f} | {f_fast:.6f} | {f_opt:.6f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        write_record(args.out, text)  # the file's later sections kept


if __name__ == "__main__":
    main()
