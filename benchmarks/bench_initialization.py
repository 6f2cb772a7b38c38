"""Benchmark of the initializations: centralized chordal vs distributed chordal (10 robots), by
preconditioned conjugate gradients (the default) and by AMM-Chordal (the paper's Algorithm 3).

Prints the markdown tables of ``benchmarks/initialization.md``:

    python benchmarks/bench_initialization.py [--data DIR] [--robots 10] [--budget 3000] [NAME ...]

Per dataset (float64 throughout):

* centralized chordal initialization (``chordal_initialization``): f = 2F at the start, the reference
  value of docs/conventions.md §5, and the wall time (best of 3, after one warm-up call);
* the distributed relaxed rotations, run for ``--budget`` iterations without a stopping rule, by
  CG (``scheme="cg"``, the default: float32 Gamma_R^alpha inverses as preconditioner) and by
  AMM-Chordal with the per-robot momentum restart and without it (Algorithm 3 verbatim): the first
  iteration after which the relaxed rotation objective stays within a relative 1e-6 of the
  centralized optimum; ms per iteration of the jitted loop (all robots, compiled, measured as the
  time difference of two budgets on the same compiled loop); the one-off set-up (dense Cholesky
  inverses of Gamma_R^alpha) and the resulting time to 1e-6;
* the distributed initialization with all defaults (``distributed_chordal_initialization(graph,
  robots)``: CG, default budgets (20000 + 20000), tol 1e-10): iterations used by each stage, the
  translation stage's first iteration within 1e-6 of the centralized translation optimum for the
  same rotations, f = 2F of the result and its relative difference from the centralized start,
  and the wall time of the whole call (set-up and compilation included).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

# Host-side LAPACK (the one-off dense Cholesky inverses of Gamma^alpha) single-threaded: on this
# shared 2-core machine a multi-threaded OpenBLAS competing with other processes was measured
# 5x slower (torus3D set-up 11-13 s vs 2.1-2.3 s). Must be set before numpy is imported.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import mmpgo_jax._init.distributed_chordal as dc  # noqa: E402
from mmpgo_jax import cost  # noqa: E402
from mmpgo_jax._init.chordal import (  # noqa: E402
    chordal_initialization,
    chordal_relaxed_rotations,
    relaxed_rotation_cost,
    relaxed_translation_cost,
    translations_given_rotations,
)
from mmpgo_jax._io.g2o import read_g2o  # noqa: E402

# paper name -> (file, reference f = 2F at the centralized chordal start, docs/conventions.md §5)
DATASETS = {
    "MITb": ("MIT.g2o", 88.132),
    "CSAIL": ("CSAIL.g2o", 31.718),
    "intel": ("intel.g2o", 53.395),
    "M3500": ("M3500.g2o", 222.62),
    "city10000": ("city10000.g2o", 715.65),
    "sphere2500": ("sphere2500.g2o", 1971.2),
    "torus3D": ("torus3D.g2o", 24669.0),
    "parking-garage": ("parking-garage.g2o", 1.4153),
}
THRESHOLD = 1e-6


def first_within(history: np.ndarray, target: float, thr: float = THRESHOLD):
    """First k such that |h[k'] - target| / target <= thr for every k' >= k (None if never)."""
    rel = np.abs(history - target) / abs(target)
    bad = np.flatnonzero(rel > thr)
    if len(bad) == 0:
        return 0
    k = int(bad[-1]) + 1
    return k if k < len(history) else None


def sig4_match(f: float, ref: float) -> bool:
    unit = 10.0 ** (np.floor(np.log10(abs(ref))) - 3)
    return abs(f - ref) <= 0.5 * unit


def timed(fn, *args, **kw):
    t = time.perf_counter()
    out = fn(*args, **kw)
    jax.block_until_ready(out)
    return out, time.perf_counter() - t


def bench(name: str, path: Path, ref: float, robots: int, budget: int) -> dict:
    g = read_g2o(path).graph
    row = {"name": name, "n": g.num_poses, "m": g.num_edges, "d": g.dim, "ref": ref}

    # --- centralized -------------------------------------------------------------------------
    chordal_initialization(g)  # warm-up (JAX projection kernel)
    times = []
    for _ in range(3):
        p, t = timed(chordal_initialization, g)
        times.append(t)
    row["f_c"] = float(cost(g, p))
    row["t_c"] = min(times)
    fR = relaxed_rotation_cost(g, chordal_relaxed_rotations(g))

    # --- distributed rotations: iterations to 1e-6, ms / iteration ---------------------------
    st = dc._setup(g, robots)
    R0 = dc._initial_rotations(st, None, g.num_poses)
    schemes = {"cg": dc.CGChordal(), "restart": dc.AMMChordal(restart=True), "plain": dc.AMMChordal(restart=False)}
    inverses = {}
    for key, solver in schemes.items():
        single = isinstance(solver, dc.CGChordal)
        if single not in inverses:
            inverses[single], row[f"setup_{key}"] = timed(st.gamma_inverse, dc.DEFAULT_XI, True, single)
        GinvR = inverses[single]
        _, hist, _, _ = dc._run_rotations(st, GinvR, R0, budget, None, solver)
        row[f"k_{key}"] = first_within(hist, fR)
        row[f"gap_{key}"] = abs(hist[-1] - fR) / fR
        if key == "plain":
            continue
        # one compiled chunk for both budgets (that of the run above; budgets are traced)
        _, t_short = timed(lambda G=GinvR, s=solver: dc._run_rotations(st, G, R0, 10, None, s)[0])
        _, t_long = timed(lambda G=GinvR, s=solver: dc._run_rotations(st, G, R0, 210, None, s)[0])
        row[f"ms_{key}"] = (t_long - t_short) / 200 * 1e3
        k = row[f"k_{key}"]
        row[f"t6_{key}"] = None if k is None else row[f"setup_{key}"] + k * row[f"ms_{key}"] / 1e3

    # --- distributed, all defaults ----------------------------------------------------------
    (pd, info), row["t_d"] = timed(dc.distributed_chordal_initialization, g, robots)
    row["k_R"] = info.rotation_iterations
    row["k_t"] = info.translation_iterations
    row["conv"] = (info.rotation_converged, info.translation_converged)
    Rd = np.asarray(pd.R)
    ft_opt = relaxed_translation_cost(g, Rd, translations_given_rotations(g, Rd))
    row["k_t6"] = first_within(info.translation_history, ft_opt)
    row["gapR_d"] = abs(info.rotation_history[-1] - fR) / fR
    row["f_d"] = float(cost(g, pd))
    row["rel_d"] = (row["f_d"] - row["f_c"]) / row["f_c"]
    return row


def fmt_k(k, budget, gap):
    return f"{k}" if k is not None else f"> {budget} ({gap:.0e})"


def tables(rows: list[dict], budget: int, robots: int) -> str:
    out = []
    out.append("### Centralized chordal initialization\n")
    out.append("| dataset | n | m | d | f = 2F (ours) | f (reference) | 4 sig. digits | time [s] |")
    out.append("|---|---:|---:|---:|---:|---:|:---:|---:|")
    for r in rows:
        out.append(
            f"| {r['name']} | {r['n']} | {r['m']} | {r['d']} | {r['f_c']:.6g} | {r['ref']:.5g} | "
            f"{'yes' if sig4_match(r['f_c'], r['ref']) else 'NO'} | {r['t_c']:.3f} |"
        )
    out.append("")
    out.append(f"### Distributed relaxed rotations ({robots} robots, budget {budget}, no stopping rule)\n")
    out.append(
        "Iterations until the relaxed rotation objective stays within a relative 1e-6 of the centralized "
        "optimum (in parentheses: the relative gap at the end of the budget when not reached); ms / iter, "
        "set-up and time to 1e-6 for CG (float32 preconditioner) / AMM-Chordal with restart (float64 majorizer).\n"
    )
    out.append("| dataset | iters, CG (default) | iters, AMM restart | iters, Alg. 3 verbatim | ms / iter, CG / AMM "
               "| set-up [s], CG / AMM | time to 1e-6 [s], CG / AMM |")
    out.append("|---|---:|---:|---:|---:|---:|---:|")

    def t6(r, key):
        return f"{r[f't6_{key}']:.2f}" if r[f"t6_{key}"] is not None else "—"

    for r in rows:
        out.append(
            f"| {r['name']} | {fmt_k(r['k_cg'], budget, r['gap_cg'])} | "
            f"{fmt_k(r['k_restart'], budget, r['gap_restart'])} | {fmt_k(r['k_plain'], budget, r['gap_plain'])} | "
            f"{r['ms_cg']:.2f} / {r['ms_restart']:.2f} | {r['setup_cg']:.2f} / {r['setup_restart']:.2f} | "
            f"{t6(r, 'cg')} / {t6(r, 'restart')} |"
        )
    out.append("")
    out.append(f"### Distributed chordal initialization with the defaults ({robots} robots)\n")
    out.append(
        f"`distributed_chordal_initialization(graph, 10)`: budgets {dc.DEFAULT_ROTATION_ITERATIONS} + "
        f"{dc.DEFAULT_TRANSLATION_ITERATIONS}, tol 1e-10, scheme {dc.DEFAULT_SCHEME!r}, xi 1e-3. "
        "Rotation gap: relative gap of the relaxed rotation objective at the stop; translation iterations to "
        "1e-6: against the centralized translation optimum for the same (distributed) rotations; f: "
        "2F of the result vs the centralized chordal start; time: the whole call (set-up and compilation included).\n"
    )
    out.append(
        "| dataset | rot. iters | rot. gap | trans. iters | trans. iters to 1e-6 | f = 2F | f (centralized) "
        "| rel. diff | time [s] |"
    )
    out.append("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        kt6 = r["k_t6"] if r["k_t6"] is not None else "not reached"
        out.append(
            f"| {r['name']} | {r['k_R']} | {r['gapR_d']:.1e} | {r['k_t']} | {kt6} | {r['f_d']:.6g} | "
            f"{r['f_c']:.6g} | {r['rel_d']:+.1e} | {r['t_d']:.1f} |"
        )
    return "\n".join(out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default_data = os.environ.get("MMPGO_DATA") or str(Path(__file__).resolve().parents[2] / "shared" / "datasets")
    ap.add_argument("--data", default=default_data,
                    help="folder with the g2o files (default: $MMPGO_DATA or ../shared/datasets)")
    ap.add_argument("--robots", type=int, default=10)
    ap.add_argument("--budget", type=int, default=3000, help="iterations of the no-stopping-rule rotation runs")
    ap.add_argument("names", nargs="*", help=f"subset of {', '.join(DATASETS)}")
    args = ap.parse_args(argv)
    names = args.names or list(DATASETS)
    rows = []
    for name in names:
        fname, ref = DATASETS[name]
        path = Path(args.data) / fname
        if not path.is_file():
            print(f"skipping {name}: {path} not found", file=sys.stderr)
            continue
        t = time.perf_counter()
        rows.append(bench(name, path, ref, args.robots, args.budget))
        print(f"[{name} done in {time.perf_counter() - t:.0f} s]", file=sys.stderr, flush=True)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"<!-- python {platform.python_version()}, jax {jax.__version__}, {jax.devices()[0].platform}, "
          f"{os.cpu_count()} cpus, float64, OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}, "
          f"load average at the end {load:.1f} -->")
    print(tables(rows, args.budget, args.robots))


if __name__ == "__main__":
    main()
