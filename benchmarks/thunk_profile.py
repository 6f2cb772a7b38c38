"""Where an AMM iteration's time goes, kernel by kernel: a JAX profiler trace of the compiled chunk.

For each file (10 robots, the default config, the centralized chordal start, float64, one CPU
device): a warm-up ``solve`` compiles the program, then ``--iterations`` AMM iterations run under
``jax.profiler`` with XLA:CPU's per-kernel trace events on (``--xla_cpu_enable_xprof_traceme``, set
in the child process's ``XLA_FLAGS``). It reports, per outer iteration, the kernel time in the
kernels that run more than once per outer iteration (those of the truncated-CG loop: once per CG
iteration) against all kernels, and lists the kernels that take the most time with how often each
runs.

Kernel times are summed over XLA's threads (independent kernels and the halves of a large loop
can run at once), so they add up to more than the wall time on the larger files. Tracing adds a
fixed cost to every kernel, and library-call kernels (XLA's YNNPACK reductions) lose the most:
4.7 us under the trace against about 1 us without, measured on a lone inner product. Read the
shares, not the absolute figures.

    python benchmarks/thunk_profile.py --files MITb torus3D --out benchmarks/thunk_profile.md
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys

from records import write_record

CHILD = """
import collections, glob, gzip, json, sys, tempfile
import jax
import mmpgo_jax as mg
mg.enable_float64()
name, iterations, top = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
graph = mg.read_g2o(mg.find_benchmark(name)).graph
mg.solve(graph, 10, method="amm", iterations=100)  # compile
folder = tempfile.mkdtemp()
jax.profiler.start_trace(folder, create_perfetto_trace=True)
result = mg.solve(graph, 10, method="amm", iterations=iterations)
jax.profiler.stop_trace()
events = json.load(gzip.open(glob.glob(folder + "/**/*.trace.json.gz", recursive=True)[-1]))["traceEvents"]
total, calls = collections.Counter(), collections.Counter()
for e in events:
    name_ = e.get("name", "")
    if e.get("ph") == "X" and not name_.startswith("$") and "(" not in name_ and "Thunk" not in name_ \\
            and not name_.startswith("end:"):
        total[name_] += e.get("dur", 0)
        calls[name_] += 1
kernels = [k for k, _ in total.most_common() if not k.startswith(("while.", "cond.")) and "::" not in k
           and k not in ("shard_args", "DevicePut", "DevicePutWithSharding", "ParseArguments")]
repeated = [k for k in kernels if calls[k] > 1.5 * iterations]  # once per CG iteration
print("RESULT", json.dumps({
    "ms_per_iteration": result.ms_per_iteration, "poses_per_robot": result.partition.max_poses,
    "all_us": sum(total[k] for k in kernels) / iterations, "cg_us": sum(total[k] for k in repeated) / iterations,
    "cg_runs": calls[repeated[0]] / iterations if repeated else 0.0,  # of the CG loop's costliest kernel
    "kernels": [(k, total[k] / iterations, calls[k] / iterations) for k in kernels[:top]]}))
"""


def profile(name: str, iterations: int, top: int) -> dict:
    flags = os.environ.get("XLA_FLAGS", "") + " --xla_cpu_enable_xprof_traceme=true"
    env = {**os.environ, "XLA_FLAGS": flags.strip()}
    out = subprocess.run([sys.executable, "-c", CHILD, name, str(iterations), str(top)], env=env, capture_output=True,
                         text=True, check=True).stdout
    return json.loads(out.split("RESULT", 1)[1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--files", nargs="*", default=["MITb", "torus3D"])
    ap.add_argument("--iterations", type=int, default=200)
    ap.add_argument("--top", type=int, default=15, help="kernels listed per file")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    load = os.getloadavg()[0]
    parts = []
    for name in args.files:
        p = profile(name, args.iterations, args.top)
        lines = [f"### {name} ({p['poses_per_robot']} poses per robot; {p['ms_per_iteration']:.2f} ms per "
                 "iteration traced)", "",
                 f"Kernel time per outer iteration {p['all_us']:.0f} µs, of which the CG loop's kernels "
                 f"({p['cg_runs']:.2f} CG iterations per outer iteration) {p['cg_us']:.0f} µs "
                 f"({100 * p['cg_us'] / p['all_us']:.0f} %).", "",
                 "| kernel | µs per outer iteration | runs per outer iteration | µs per run |", "|---|---|---|---|"]
        for k, us, n in p["kernels"]:
            lines.append(f"| `{k}` | {us:.0f} | {n:.2f} | {us / n:.1f} |")
        parts.append("\n".join(lines))
        print(parts[-1], file=sys.stderr, flush=True)
    text = (f"Command: `python benchmarks/thunk_profile.py --files {' '.join(args.files)} --iterations "
            f"{args.iterations} --top {args.top}`; {datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC, "
            f"{os.cpu_count()} cores, load average {load:.2f} at the start, {os.getloadavg()[0]:.2f} at the end.\n\n"
            + "\n\n".join(parts) + "\n")
    if not args.out:
        print(text)
        return
    write_record(args.out, text)  # the tables went to stderr as they came; the file's later sections kept


if __name__ == "__main__":
    main()
