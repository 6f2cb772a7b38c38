"""One GPU run: ms/iteration, compile seconds, peak device memory and the gap reached, in one command.

    python benchmarks/gpu.py                      # the full run, about 5 minutes on one GPU -> benchmarks/gpu.md
    python benchmarks/gpu.py --quick --out /tmp/gpu_quick.md    # a tiny version of every part (a minute on a CPU)

This script is what a session lent a GPU runs, so that the figures come back in a single call and can
be committed with the date and the GPU (benchmarks/gpu.md: an H200, 2026-12-04). Three parts:

(a) files: every benchmark file of the data folder, ``solve(graph, 10, method="amm", iterations=N,
    stop_when_stalled=False)``, in float64 and in float32, against the registry's f*;
(b) sweep: Fig. 1's kind of study, 20 Cube graphs (3600 poses, grid 12) x {5, 10, 50} robots, AMM,
    through ``sweep(...)`` (one compiled executable per robot count, all graphs in one vmap batch on
    an accelerator);
(c) scale: Cube graphs of 10^5 and 10^6 poses (benchmarks/scaling.py's density), 100 robots, from the
    chordal start, a few iterations;
(d) paths: the other solver paths on a few files -- MM, TLS with 30 % wrong inter-robot loop closures
    (the default centralized GNC start, and ``distributed=True``), and the distributed chordal start.

Each part runs in a subprocess of its own: the precision is a process-wide JAX setting (float64 is
switched on explicitly in the float64 parts only), a part that overruns can be killed without
losing the others, and the parent never touches the GPU (JAX would reserve most of its memory).
A child prints one ``@gpu {json}`` line per record; the parent collects them and writes the report
atomically. Time is shared out by ``--budget-s`` (default 270 s): each part gets a share of what is
left, skips the cases it has no time for (the report lists them) and is killed at the end of the
budget; what it finished is kept.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import importlib.util
import json
import os
import platform
import resource
import shlex
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
if importlib.util.find_spec("mmpgo_jax") is None:  # a bare checkout (a device machine): the package beside us
    sys.path.insert(0, str(HERE.parent))
TAG = "@gpu "
PRECISIONS = {"files-float64": "float64", "files-float32": "float32", "sweep": "float64", "scale": "float64",
              "paths": "float64"}
SHARES = {"files-float64": 0.2, "files-float32": 0.15, "sweep": 0.17, "scale": 0.33, "paths": 0.15}  # of the time left
SLACK_S = 20.0  # a part may overrun its share by this much before it is killed (the last part: never)

FULL = dict(files=None, file_iterations=250, robots=10,
            sweep_graphs=20, sweep_robots=(5, 10, 50), sweep_poses=3600, sweep_grid=12, sweep_iterations=200,
            scale_poses=(100_000, 1_000_000), scale_iterations=(20, 10), scale_robots=100, scale_min_left_s=60.0,
            paths_mm=("MITb", "M3500", "sphere2500"), paths_robust=("M3500",), paths_start=("city10000", "sphere2500"),
            paths_iterations=250)
QUICK = dict(files=("MITb", "smallGrid3D"), file_iterations=20, robots=10,
             sweep_graphs=3, sweep_robots=(5, 10), sweep_poses=200, sweep_grid=4, sweep_iterations=20,
             scale_poses=(10_000,), scale_iterations=(5,), scale_robots=10, scale_min_left_s=0.0,
             paths_mm=("MITb",), paths_robust=("MITb",), paths_start=("MITb",), paths_iterations=20)


# ----------------------------------------------------------------------------------------------- child


def emit(kind: str, **fields) -> None:
    """One record for the parent (a line it recognises; everything else it only echoes)."""
    print(TAG + json.dumps({"kind": kind, **fields}), flush=True)


def say(msg: str) -> None:
    print(f"[gpu] {msg}", flush=True)


def setup_precision(precision: str) -> None:
    """float64 is switched on here, explicitly, in the float64 children only (never by the library)."""
    import jax

    if precision == "float64":
        jax.config.update("jax_enable_x64", True)


def peak_mib() -> float | None:
    """The device allocator's peak since the process began (None where the backend keeps no stats, a CPU)."""
    import jax

    stats = jax.devices()[0].memory_stats() or {}
    peak = stats.get("peak_bytes_in_use")
    return None if peak is None else peak / 2**20


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def environment() -> dict:
    """What the report says about the device and the software (read in a child: the parent never starts JAX)."""
    import jax
    import jaxlib

    from mmpgo_jax import data_dir
    from mmpgo_jax._core.sparse import pardiso_available

    dev = jax.devices()
    stats = dev[0].memory_stats() or {}
    return dict(devices=str(dev), device_kind=dev[0].device_kind, platform=dev[0].platform,
                jax=jax.__version__, jaxlib=jaxlib.__version__, x64=bool(jax.config.jax_enable_x64),
                bytes_limit=stats.get("bytes_limit"), pardiso=pardiso_available(),
                pymetis=importlib.util.find_spec("pymetis") is not None, data=str(data_dir()))


def out_of_time(deadline: float, case: str, part: str, need_s: float = 0.0) -> bool:
    """Whether ``case`` must be skipped: the part's share is spent (or less than ``need_s`` is left)."""
    left = deadline - time.time()
    if left > need_s:
        return False
    reason = "the part's time share was spent" if left <= 0 else f"only {left:.0f} s left, {need_s:.0f} s needed"
    emit("skip", part=part, case=case, reason=reason)
    say(f"skipped {case}: {reason}")
    return True


def file_names(settings: dict) -> tuple[list[str], list[str]]:
    """The files of part (a): the given names, or every registered file present (registry order: the paper's
    first); and the given names that are not there."""
    import mmpgo_jax

    present = [info.name for info in mmpgo_jax.available_benchmarks()]
    if settings["files"] is None:
        return present, []
    named = {n: mmpgo_jax.benchmark_info(n) for n in settings["files"]}  # "MIT", "mit.g2o" name MITb too
    names = [info.name for info in named.values() if info is not None and info.name in present]
    return list(dict.fromkeys(names)), [n for n, info in named.items() if info is None or info.name not in present]


def run_file(name: str, settings: dict, precision: str) -> dict:
    """One benchmark file: AMM with the paper's robot count, a fixed number of iterations."""
    import mmpgo_jax

    info = mmpgo_jax.BENCHMARKS[name]
    graph = mmpgo_jax.read_g2o(mmpgo_jax.find_benchmark(name)).graph
    robots = min(settings["robots"], graph.num_poses)  # tinyGrid3D has 9 poses
    res = mmpgo_jax.solve(graph, robots, method="amm", iterations=settings["file_iterations"],
                          stop_when_stalled=False)
    ref = info.fstar_reference
    return dict(name=name, precision=precision, robots=robots, dim=graph.dim, poses=graph.num_poses,
                edges=graph.num_edges, dtype=str(graph.R.dtype), iterations=res.iterations,
                start_s=res.initialize_seconds, build_s=res.build_seconds, compile_s=res.compile_seconds,
                solve_s=res.solve_seconds, ms_per_iteration=res.ms_per_iteration, f=res.f,
                gap=None if ref is None else float(ref.gap(res.f)), fstar_source=None if ref is None else ref.label,
                peak_mib=peak_mib())


def part_files(settings: dict, precision: str, deadline: float) -> None:
    part = f"files-{precision}"
    names, missing = file_names(settings)
    for name in missing:
        emit("skip", part=part, case=name, reason="not a registered benchmark present in the data folder")
    if not names:
        import mmpgo_jax

        emit("skip", part=part, case="every file", reason=f"no benchmark file in the data folder "
             f"({mmpgo_jax.data_dir()}; set --data or $MMPGO_DATA)")
    for name in names:
        if out_of_time(deadline, name, part):
            continue
        emit("stage", part=part, case=name, stage="solve")
        try:
            row = run_file(name, settings, precision)
        except Exception as exc:  # one file's failure (e.g. float32 overflow) must not lose the others
            emit("error", part=part, case=name, error=f"{type(exc).__name__}: {exc}"[:300])
            say(f"{name} ({precision}): {type(exc).__name__}: {exc}")
            continue
        emit("file", **row)
        say(f"{name} ({precision}): {row['ms_per_iteration']:.2f} ms/iteration, compile {row['compile_s']:.1f} s, "
            f"gap {fmt_gap(row['gap'])}")


def part_sweep(settings: dict, deadline: float) -> None:
    """Fig. 1's kind of sweep: graphs x robot counts, one compiled executable per robot count."""
    import jax

    import mmpgo_jax

    case = f"{settings['sweep_graphs']} graphs x {list(settings['sweep_robots'])} robots"
    if out_of_time(deadline, case, "sweep"):
        return
    emit("stage", part="sweep", case=case, stage="generate")
    t0 = time.perf_counter()
    graphs = {f"cube{s:02d}": mmpgo_jax.cube_dataset(s, num_poses=settings["sweep_poses"], grid=settings["sweep_grid"])
              for s in range(settings["sweep_graphs"])}
    generate_s = time.perf_counter() - t0
    emit("stage", part="sweep", case=case, stage="sweep")
    batch = 1 if jax.default_backend() == "cpu" else None  # a CPU runs small batches faster (benchmarks/fig1.py)
    t0 = time.perf_counter()
    res = mmpgo_jax.sweep(graphs, list(settings["sweep_robots"]), ("amm",), settings["sweep_iterations"],
                          group_by="robots", max_batch_configs=batch, progress=say)
    total_s = time.perf_counter() - t0
    configs = [{k: r[k] for k in ("graph", "robots", "ms_per_iteration", "batch_ms_per_iteration", "batch_size")}
               | {"f": float(r["f"])} for r in res.configs]
    groups = [{k: g[k] for k in ("robots", "configs", "batches", "compile_seconds", "run_seconds", "setup_seconds")}
              for g in res.groups]
    emit("sweep", case=case, graphs=settings["sweep_graphs"], poses=settings["sweep_poses"],
         grid=settings["sweep_grid"], iterations=settings["sweep_iterations"], generate_s=generate_s,
         total_s=total_s, batch_configs=batch, configs=configs, groups=groups, peak_mib=peak_mib())
    say(f"sweep: {total_s:.1f} s, compile {sum(g['compile_seconds'] for g in groups):.1f} s")


def run_scale(poses: int, iterations: int, settings: dict) -> dict:
    """One large Cube graph from the chordal start (the odometry start when only SuperLU could factor it)."""
    sys.path.insert(0, str(HERE))
    from scaling import default_grid  # the density benchmarks/scaling.py uses

    import mmpgo_jax
    from mmpgo_jax._core.sparse import pardiso_available

    case, grid = f"{poses} poses", default_grid(poses)
    t0 = time.perf_counter()
    graph = mmpgo_jax.cube_dataset(0, num_poses=poses, grid=grid).graph
    generate_s = time.perf_counter() - t0
    # SuperLU did not finish the chordal start of 10^6 poses in 19 minutes (benchmarks/scaling.md)
    start = "chordal" if poses <= 300_000 or pardiso_available() else "odometry"
    emit("stage", part="scale", case=case, stage=f"{start} start")
    t0 = time.perf_counter()
    X0 = mmpgo_jax.initialize(graph, start)
    start_s = time.perf_counter() - t0
    emit("stage", part="scale", case=case, stage="build, compile and iterations")
    res = mmpgo_jax.solve(graph, settings["scale_robots"], method="amm", init=X0, iterations=iterations,
                          chunk_size=iterations, stop_when_stalled=False)
    return dict(case=case, poses=poses, edges=graph.num_edges, grid=grid, robots=settings["scale_robots"],
                start=start, generate_s=generate_s, start_s=start_s, build_s=res.build_seconds,
                compile_s=res.compile_seconds, iterations=res.iterations, ms_per_iteration=res.ms_per_iteration,
                f0=float(res.history.f[0]), f=res.f, peak_mib=peak_mib(), rss_mb=rss_mb())


def part_scale(settings: dict, deadline: float) -> None:
    for poses, iterations in zip(settings["scale_poses"], settings["scale_iterations"], strict=True):
        need = settings["scale_min_left_s"] if poses >= 1_000_000 else 0.0
        if out_of_time(deadline, f"{poses} poses", "scale", need):
            continue
        emit("stage", part="scale", case=f"{poses} poses", stage="generate")
        row = run_scale(poses, iterations, settings)
        emit("scale", **row)
        say(f"{poses} poses: start {row['start_s']:.1f} s, {row['ms_per_iteration']:.1f} ms/iteration")


def path_row(case: str, kind: str, name: str, res, **extra) -> dict:
    return dict(case=case, kind_of=kind, name=name, robots=10, iterations=res.iterations,
                start_s=res.initialize_seconds, compile_s=res.compile_seconds,
                ms_per_iteration=res.ms_per_iteration, f=res.f, peak_mib=peak_mib(), **extra)


def part_paths(settings: dict, deadline: float) -> None:
    """MM, robust (centralized and distributed) and the distributed start: what parts (a)-(c) do not run."""
    import numpy as np

    import mmpgo_jax

    present = {info.name for info in mmpgo_jax.available_benchmarks()}
    its = settings["paths_iterations"]

    def registered(name):  # "sphere2500" is the registry's "sphere"
        info = mmpgo_jax.benchmark_info(name)
        return None if info is None else info.name

    def graph_of(name):
        return mmpgo_jax.read_g2o(mmpgo_jax.find_benchmark(name)).graph

    # the centralized GNC start last: on the first GPU machine it had not finished M3500 in 140 s
    cases = [(f"mm {n}", "mm", n) for n in settings["paths_mm"]]
    cases += [(f"start {n}", "start", n) for n in settings["paths_start"]]
    cases += [(f"{how} {n}", how, n) for how in ("tls-distributed", "tls") for n in settings["paths_robust"]]
    for case, how, name in cases:
        name = registered(name) or name
        if name not in present:
            emit("skip", part="paths", case=case, reason="file not in the data folder")
            continue
        if out_of_time(deadline, case, "paths"):
            continue
        emit("stage", part="paths", case=case, stage=how)
        try:
            graph = graph_of(name)
            if how == "mm":
                res = mmpgo_jax.solve(graph, 10, method="mm", iterations=its, stop_when_stalled=False)
                row = path_row(case, how, name, res)
            elif how.startswith("tls"):
                rop = mmpgo_jax.contiguous_robots(graph.num_poses, 10)
                inter = rop[np.asarray(graph.i)] != rop[np.asarray(graph.j)]
                loops = int((np.abs(np.asarray(graph.i) - np.asarray(graph.j)) != 1).sum())
                count = round(0.3 * int(inter.sum()) / 0.7)  # 30 % of the inter-robot closures wrong
                c = mmpgo_jax.add_outlier_loop_closures(graph, count / (loops + count), seed=1, robot_of_pose=rop,
                                                        inter_robot_only=True,
                                                        reference=mmpgo_jax.initialize(graph, "chordal"))
                res = mmpgo_jax.solve(c.graph, rop, loss="tls", iterations=its, stop_when_stalled=False,
                                      distributed=how == "tls-distributed")
                s = mmpgo_jax.outlier_scores(res.inliers, c.outlier)
                row = path_row(case, how, name, res, outliers=int(c.outlier.sum()), precision=s.precision,
                               recall=s.recall)
            else:
                t0 = time.perf_counter()
                mmpgo_jax.initialize(graph, "distributed-chordal", robots=10)
                first = time.perf_counter() - t0
                t0 = time.perf_counter()
                X = mmpgo_jax.initialize(graph, "distributed-chordal", robots=10)
                again = time.perf_counter() - t0
                row = dict(case=case, kind_of=how, name=name, robots=10, first_s=first, again_s=again,
                           f=2.0 * float(mmpgo_jax.objective(graph, X)), peak_mib=peak_mib())  # f = 2F
        except Exception as exc:
            emit("error", part="paths", case=case, error=f"{type(exc).__name__}: {exc}"[:300])
            say(f"{case}: {type(exc).__name__}: {exc}")
            continue
        emit("path", **row)
        say(f"{case}: done")


def child(args) -> int:
    """One part, in this process (its precision set before any array exists)."""
    setup_precision(PRECISIONS[args.part])
    emit("env", **environment())
    settings = dict(QUICK if args.quick else FULL)
    if args.files:
        settings["files"] = tuple(args.files)
    if args.part.startswith("files-"):
        part_files(settings, PRECISIONS[args.part], args.deadline)
    elif args.part == "sweep":
        part_sweep(settings, args.deadline)
    elif args.part == "paths":
        part_paths(settings, args.deadline)
    else:
        part_scale(settings, args.deadline)
    emit("done")  # a kill after this line loses nothing (the process was only exiting)
    return 0


# ---------------------------------------------------------------------------------------------- parent


def run_part(part: str, args, soft_s: float, hard_s: float, records: list) -> None:
    """Run one part in a subprocess: echo its lines, keep its records, kill it (its process group) at ``hard_s``."""
    cmd = [sys.executable, "-u", str(Path(__file__).resolve()), "--part", part,
           "--deadline", f"{time.time() + soft_s:.3f}"] + (["--quick"] if args.quick else []) \
        + (["--files", *args.files] if args.files else [])
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True, start_new_session=True)
    killed = threading.Event()

    def kill() -> None:
        killed.set()
        with contextlib.suppress(ProcessLookupError):  # it ended on its own meanwhile
            os.killpg(proc.pid, signal.SIGKILL)

    timer = threading.Timer(max(hard_s, 1.0), kill)
    timer.start()
    t0 = time.perf_counter()
    try:
        for line in proc.stdout:
            if line.startswith(TAG):
                records.append({"part": part, **json.loads(line[len(TAG):])})
            else:
                print(line, end="", flush=True)
        rc = proc.wait()
    finally:
        timer.cancel()
    if killed.is_set():
        records.append({"kind": "killed", "part": part, "after_s": time.perf_counter() - t0})
        print(f"[gpu] {part}: killed at the end of its time ({hard_s:.0f} s)", flush=True)
    elif rc != 0:
        records.append({"kind": "failed", "part": part, "rc": rc})


def parent(args, parts: list[str]) -> int:
    """Share the budget among the parts, run them one after another, write and print the report."""
    t_start = time.time()
    end = t_start + args.budget_s
    records: list[dict] = []
    for i, part in enumerate(parts):
        left = end - time.time()
        if left <= 1:
            records.append({"kind": "skip", "part": part, "case": "the whole part", "reason": "the budget was spent"})
            print(f"[gpu] skipped {part}: the budget was spent", flush=True)
            continue
        soft = left * SHARES[part] / sum(SHARES[p] for p in parts[i:])
        hard = left if i == len(parts) - 1 else min(left, soft + SLACK_S)
        print(f"[gpu] {part}: {soft:.0f} s share (killed after {hard:.0f} s)", flush=True)
        run_part(part, args, soft, hard, records)
    text = report(args, parts, records, time.time() - t_start, t_start)
    from mmpgo_jax._io.atomic import atomic_write

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(out) as fh:
        fh.write(text)
    print(text)
    print(f"[gpu] wrote {out}", flush=True)
    return 0


# ---------------------------------------------------------------------------------------------- report


def fmt_mib(x) -> str:
    return "n/a" if x is None else f"{x:.0f}"


def fmt_gap(x) -> str:
    return "n/a" if x is None else f"{x:.2e}"


def command_line(argv) -> str:
    return "python benchmarks/gpu.py" + "".join(" " + shlex.quote(a) for a in argv)


def header(args, env: dict | None, wall: float, t_start: float) -> list[str]:
    """Date, device, versions, command: what makes the figures comparable with another run."""
    date = datetime.datetime.fromtimestamp(t_start, datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    lines = [f"# GPU run{' (--quick)' if args.quick else ''}\n", f"Date: {date}. Wall time {wall:.0f} s "
             f"(budget {args.budget_s:.0f} s).\n", f"Command: `{command_line(args.argv)}`\n"]
    if env is None:
        return [*lines, "**No part started: no device information.**\n"]
    import mmpgo_jax

    lines.append(f"Device: {env['device_kind']} (`jax.devices()` = `{env['devices']}`, platform {env['platform']}"
                 + (f", {env['bytes_limit'] / 2**30:.0f} GiB for JAX" if env.get("bytes_limit") else "") + ").\n")
    lines.append(f"Software: jax {env['jax']}, jaxlib {env['jaxlib']}, mmpgo-jax {mmpgo_jax.__version__}, "
                 f"Python {platform.python_version()}; pymetis {'installed' if env['pymetis'] else 'ABSENT'}, "
                 f"MKL PARDISO {'installed' if env['pardiso'] else 'absent'}. "
                 f"Host: {os.cpu_count()} logical CPUs. Data folder: {env['data']}.\n")
    if env["platform"] == "cpu":
        lines.append("**This ran on a CPU: these are not GPU figures.**\n")
    lines.append("Timings: ms / iteration = the compiled iterations alone (`SolveResult.solve_seconds` / "
                 "iterations; the sweep: each configuration's share of its batch); compile = cold compilation "
                 "(no persistent cache); start = partition and chordal start on the host. Peak device memory: "
                 "`jax.devices()[0].memory_stats()['peak_bytes_in_use']` of the part's process when the row "
                 "ended (JAX cannot reset it: a row's figure is the largest of it and the rows before it in the "
                 "same part), n/a on a CPU.\n")
    return lines


def files_section(records: list[dict], settings: dict) -> list[str]:
    rows = [r for r in records if r["kind"] == "file"]
    fewer = sorted({f"{r['name']}: {r['robots']}" for r in rows if r["robots"] != settings["robots"]})
    lines = [f"## (a) Benchmark files: AMM, {settings['robots']} robots"
             + (f" ({', '.join(fewer)})" if fewer else "") + f", {settings['file_iterations']} iterations\n",
             "`solve(graph, 10, method=\"amm\", iterations=N, stop_when_stalled=False)`, chordal start; gap = "
             "(f − f*)/|f*| against the registry's reference f* (`BENCHMARKS[name].fstar_reference`).\n",
             "| file | d | n | m | precision | start s | build s | compile s | ms / iteration | f | (f − f*)/f* "
             "| f* | peak device MiB |", "|---|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---|---:|"]
    order = list(dict.fromkeys(r["name"] for r in rows))  # the run's order (the registry's), both precisions
    for r in sorted(rows, key=lambda r: (order.index(r["name"]), r["precision"] != "float64")):
        lines.append(f"| {r['name']} | {r['dim']} | {r['poses']} | {r['edges']} | {r['precision']} | "
                     f"{r['start_s']:.2f} | {r['build_s']:.2f} | {r['compile_s']:.1f} | {r['ms_per_iteration']:.2f} | "
                     f"{r['f']:.8g} | {fmt_gap(r['gap'])} | {r['fstar_source']} | {fmt_mib(r['peak_mib'])} |")
    return [*lines, ""]


def sweep_section(records: list[dict]) -> list[str]:
    rows = [r for r in records if r["kind"] == "sweep"]
    if not rows:
        return ["## (b) Sweep\n", "Not run (see Skipped).\n"]
    s = rows[0]
    lines = [f"## (b) Sweep: {s['graphs']} Cube graphs ({s['poses']} poses, grid {s['grid']}) × robots, AMM, "
             f"{s['iterations']} iterations\n",
             f"`sweep(graphs, robots, (\"amm\",), {s['iterations']}, group_by=\"robots\", "
             f"max_batch_configs={s['batch_configs']})`: {s['total_s']:.1f} s in all (compile "
             f"{sum(g['compile_seconds'] for g in s['groups']):.1f} s), graphs generated in {s['generate_s']:.1f} s; "
             f"peak device MiB {fmt_mib(s['peak_mib'])}.\n",
             "| robots | configs | batches | batch size | set-up s | compile s | run s | ms / iteration / config "
             "(median, min–max) | batch ms / iteration (median) |", "|---:|---:|---:|---:|---:|---:|---:|---|---:|"]
    for g in s["groups"]:
        robots = g["robots"][0] if isinstance(g["robots"], list) else g["robots"]
        cs = [c for c in s["configs"] if c["robots"] == robots]
        ms = sorted(c["ms_per_iteration"] for c in cs)
        batch_ms = sorted(c["batch_ms_per_iteration"] for c in cs)
        lines.append(f"| {robots} | {g['configs']} | {g['batches']} | {max(c['batch_size'] for c in cs)} | "
                     f"{g['setup_seconds']:.1f} | {g['compile_seconds']:.1f} | {g['run_seconds']:.2f} | "
                     f"{ms[len(ms) // 2]:.2f} ({ms[0]:.2f}–{ms[-1]:.2f}) | {batch_ms[len(batch_ms) // 2]:.2f} |")
    return [*lines, ""]


def scale_section(records: list[dict]) -> list[str]:
    rows = [r for r in records if r["kind"] == "scale"]
    lines = ["## (c) Large Cube graphs: AMM from the chordal start\n",
             "benchmarks/scaling.py's density (`default_grid`), contiguous robots, float64; start = "
             "`initialize(graph, method)` on the host (SciPy / PARDISO).\n",
             "| poses | edges | robots | generate s | start | start s | build s | compile s | iterations "
             "| ms / iteration | f0 → f | peak device MiB | peak RSS MB |",
             "|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|---|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['poses']} | {r['edges']} | {r['robots']} | {r['generate_s']:.1f} | {r['start']} | "
                     f"{r['start_s']:.1f} | {r['build_s']:.1f} | {r['compile_s']:.1f} | {r['iterations']} | "
                     f"{r['ms_per_iteration']:.1f} | {r['f0']:.4g} → {r['f']:.4g} | {fmt_mib(r['peak_mib'])} | "
                     f"{r['rss_mb']:.0f} |")
    return [*lines, ""]


def paths_section(records: list[dict], settings: dict) -> list[str]:
    rows = [r for r in records if r["kind"] == "path"]
    lines = [f"## (d) Other paths: MM, TLS, the distributed start (10 robots, {settings['paths_iterations']} "
             "iterations, float64)\n",
             "MM: `solve(graph, 10, method=\"mm\")`; TLS: 30 % of the inter-robot loop closures wrong "
             "(`add_outlier_loop_closures(..., inter_robot_only=True, seed=1)`), `solve(..., loss=\"tls\")` from "
             "the default GNC-chordal start (host) and with `distributed=True`; start: "
             "`initialize(graph, \"distributed-chordal\", robots=10)`, a first call (compilation included) and "
             "a second.\n",
             "| case | start s | compile s | ms / iteration | f | precision / recall | distributed start: first s "
             "/ again s | peak device MiB |", "|---|---:|---:|---:|---:|---|---|---:|"]
    for r in rows:
        if r["kind_of"] == "start":
            lines.append(f"| {r['case']} | | | | {r['f']:.8g} | | {r['first_s']:.2f} / {r['again_s']:.2f} | "
                         f"{fmt_mib(r['peak_mib'])} |")
            continue
        pr = f"{r['precision']:.3f} / {r['recall']:.3f}" if "precision" in r else ""
        lines.append(f"| {r['case']} | {r['start_s']:.2f} | {r['compile_s']:.1f} | {r['ms_per_iteration']:.2f} | "
                     f"{r['f']:.8g} | {pr} | | {fmt_mib(r['peak_mib'])} |")
    return [*lines, ""]


def unfinished(records: list[dict]) -> list[str]:
    """Skipped cases, errors, and the case a killed part was in (its last stage), so nothing is lost silently."""
    finished = ("file", "sweep", "scale", "path")
    done = {(r["part"], r.get("case", r.get("name"))) for r in records if r["kind"] in finished}
    lines = []
    for r in records:
        if r["kind"] == "skip":
            lines.append(f"- {r['part']}: {r['case']} skipped ({r['reason']}).")
        elif r["kind"] == "error":
            lines.append(f"- {r['part']}: {r['case']} failed: {r['error']}")
        elif r["kind"] == "failed":
            lines.append(f"- {r['part']}: the process exited with status {r['rc']}.")
        elif r["kind"] == "killed" and any(d["kind"] == "done" and d["part"] == r["part"] for d in records):
            lines.append(f"- {r['part']}: killed while exiting, after {r['after_s']:.0f} s (all its results were in).")
        elif r["kind"] == "killed":
            stages = [s for s in records if s["kind"] == "stage" and s["part"] == r["part"]
                      and (s["part"], s["case"]) not in done]
            where = f" during {stages[-1]['case']} ({stages[-1]['stage']})" if stages else ""
            lines.append(f"- {r['part']}: killed at the end of its time, after {r['after_s']:.0f} s{where}.")
    return ["## Skipped, failed or cut short\n", *(lines or ["Nothing."]), ""]


def report(args, parts: list[str], records: list[dict], wall: float, t_start: float) -> str:
    settings = QUICK if args.quick else FULL
    envs = [r for r in records if r["kind"] == "env"]
    lines = header(args, envs[0] if envs else None, wall, t_start)
    lines.append(f"Parts run: {', '.join(parts)}.\n")
    if any(p.startswith("files-") for p in parts):
        lines += files_section(records, settings)
    if "sweep" in parts:
        lines += sweep_section(records)
    if "scale" in parts:
        lines += scale_section(records)
    if "paths" in parts:
        lines += paths_section(records, settings)
    lines += unfinished(records)
    return "\n".join(lines)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="a tiny version of every part (checks the script on a CPU)")
    ap.add_argument("--out", default=str(HERE / "gpu.md"), help="the report (default benchmarks/gpu.md)")
    ap.add_argument("--budget-s", type=float, default=270.0,
                    help="wall seconds for all parts together; what does not fit is skipped (default 270)")
    ap.add_argument("--data", help="the folder of the benchmark files (default: $MMPGO_DATA, else ../shared/datasets)")
    ap.add_argument("--files", nargs="+", help="benchmark names for part (a) (default: every file present; "
                    "--quick: MITb smallGrid3D), e.g. to finish the files a first run skipped")
    ap.add_argument("--parts", nargs="+", default=list(SHARES), choices=list(SHARES), help="which parts (default all)")
    ap.add_argument("--part", choices=list(SHARES), help=argparse.SUPPRESS)  # a child: run this part here
    ap.add_argument("--deadline", type=float, default=float("inf"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    args.argv = argv
    if args.part:
        return child(args)
    if args.data:  # the children find the files through the library's own look-up
        os.environ["MMPGO_DATA"] = str(Path(args.data).resolve())
    return parent(args, list(dict.fromkeys(args.parts)))


if __name__ == "__main__":
    sys.exit(main())
