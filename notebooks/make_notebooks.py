"""Generate the example notebooks so that they are reproducible:

    python notebooks/make_notebooks.py             # sources only (no outputs)
    python notebooks/make_notebooks.py --execute   # and run them, keeping the outputs (as committed)

Writes ``01_quickstart.ipynb``, ``02_reproduce_tables.ipynb``, ``03_robot_sweeps.ipynb`` and
``04_outliers.ipynb`` next to this file. Every notebook reads the data folder from ``MMPGO_DATA`` (through
``mmpgo_jax.find_benchmark`` / ``available_benchmarks``) and its iteration budget from
``MMPGO_NOTEBOOK_ITERATIONS`` (small by default, so that each runs in well under two minutes on a
2-core machine; ``tests/test_notebooks.py`` runs them with an even smaller value).

The notebooks are committed executed, so that a reader on a code host sees the tables and figures.
``--execute`` runs each in a fresh Jupyter kernel (nbclient) with the settings of
:data:`EXECUTE_SETTINGS` (small: all four take a few minutes on 2 cores) and the benchmark files of
``MMPGO_DATA``, keeps the outputs (figures as PNG) and drops what changes from run to run without
meaning (cell timings, the kernel's version strings), so that regenerating rewrites only the outputs.
Only the notebook code uses public names of the package (``tests/test_notebooks.py`` checks it).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import nbformat
from nbformat.v4 import new_code_cell, new_markdown_cell, new_notebook

HERE = Path(__file__).resolve().parent
REPO = HERE.parent

# The settings the committed outputs were made with (``--execute``), per notebook: environment
# variables the notebooks read, on top of their defaults. Small, so that executing all four takes a
# few minutes on 2 cores, yet large enough to show what each notebook teaches.
EXECUTE_SETTINGS: dict[str, dict[str, str]] = {
    "01_quickstart.ipynb": {},
    "02_reproduce_tables.ipynb": {"MMPGO_NOTEBOOK_DATASETS": "intel,MITb,garage"},  # one row of plots
    "03_robot_sweeps.ipynb": {"MMPGO_NOTEBOOK_ITERATIONS": "100"},
    "04_outliers.ipynb": {"MMPGO_NOTEBOOK_ITERATIONS": "300"},
}


def outputs_note(name: str) -> str:
    """The sentence on the committed outputs, at the end of a notebook's first cell."""
    settings = " ".join(f"`{k}={v}`" for k, v in EXECUTE_SETTINGS[name].items())
    return ("\n\nThe outputs shown were made by `python notebooks/make_notebooks.py --execute` "
            + (f"with {settings} (else the defaults)." if settings else "with the defaults."))

# The first code cell of every notebook: its imports (stdlib, third party, this package, as ruff's
# isort rules want them), then the common set-up.
SETUP = '''\
{stdlib}

import jax
import matplotlib.pyplot as plt
{numpy}{third_party}
import mmpgo_jax as mm
{first_party}
mm.enable_float64()  # explicit: the paper's numbers are float64
ITERATIONS = int(os.environ.get("MMPGO_NOTEBOOK_ITERATIONS", "{default}"))
print("iterations:", ITERATIONS, "| data folder:", mm.data_dir(), "| jax", jax.__version__, jax.default_backend())'''


def setup_cell(default: int, *, stdlib=("os",), third_party: str = "", first_party: str = "", after: str = "",
               numpy: bool = True):
    """The set-up cell: ``import`` lines for ``stdlib``, numpy (unless ``numpy=False``), extra third-party /
    first-party import lines, the common set-up with iteration budget ``default``, then ``after``
    (notebook constants)."""
    src = SETUP.format(
        stdlib="\n".join(f"import {m}" for m in stdlib),
        numpy="import numpy as np\n" if numpy else "",
        third_party=third_party + "\n" if third_party else "",
        first_party=first_party + "\n" if first_party else "",
        default=default,
    )
    return new_code_cell(src + ("\n\n" + after if after else ""))


def quickstart() -> nbformat.NotebookNode:
    cells = [
        new_markdown_cell(
            "# Quick start: distributed pose graph optimization with AMM-PGO\n\n"
            "Load a pose graph (the MIT benchmark from the data folder `MMPGO_DATA` when it is there, "
            "otherwise a generated Cube dataset), split it among 10 robots, run the accelerated "
            "majorization-minimization method (AMM-PGO, Algorithm 2 of Fan & Murphey) from the chordal "
            "initialization, and plot the trajectory and the convergence.\n\n"
            "The iteration budget comes from `MMPGO_NOTEBOOK_ITERATIONS` (default 300)."),
        setup_cell(300),
        new_markdown_cell("## 1. Data\n`find_benchmark` looks in `MMPGO_DATA` (or `../shared/datasets`); "
                          "objective values are f = 2F, the convention of the paper's tables."),
        new_code_cell(
            'ground_truth = None\n'
            'try:\n'
            '    path = mm.find_benchmark("MITb")\n'
            '    g2o = mm.read_g2o(path)\n'
            '    graph, name = g2o.graph, "MITb"\n'
            '    reference = mm.BENCHMARKS["MITb"].fstar_reference  # the certified f* where the registry has one\n'
            '    fstar, fstar_label = reference.value, reference.label\n'
            'except mm.DatasetNotFoundError as err:\n'
            '    print("MIT not found, using a generated Cube dataset instead:", str(err).split(".")[0])\n'
            '    data = mm.cube_dataset(0, num_poses=1000, grid=8)\n'
            '    graph, name, ground_truth = data.graph, data.name, data.ground_truth\n'
            '    fstar = mm.centralized_optimum(graph, grad_tol=1e-5, max_iterations=500).f\n'
            '    fstar_label = "f* (centralized solve)"\n'
            'print(f"{name}: d={graph.dim}, n={graph.num_poses} poses, m={graph.num_edges} measurements, "\n'
            '      f"{fstar_label} = {fstar:.10g}")'),
        new_markdown_cell("## 2. Partition among robots\nContiguous blocks of poses (as in the paper); "
                          "inter-robot edges are the ones whose majorization couples robots."),
        new_code_cell(
            'ROBOTS = 10\n'
            'part = mm.partition(graph, ROBOTS)\n'
            'stats = mm.partition_stats(graph, np.asarray(part.robot_of_pose))\n'
            'print("poses per robot:      ", stats.poses)\n'
            'print("inter-robot edges:    ", stats.total_inter_edges)\n'
            'print("poses received / iter:", stats.received_poses)'),
        new_markdown_cell("## 3. Solve with AMM-PGO\nThe whole outer loop is one jitted `lax.scan` chunk; "
                          "all robots' subproblems run in one `vmap`."),
        new_code_cell(
            'result = mm.solve(graph, part, method="amm", iterations=ITERATIONS, init="chordal")\n'
            'f = result.history.f\n'
            'print(f"f: {f[0]:.6g} (chordal start) -> {f[-1]:.6g} after {result.iterations} iterations; "\n'
            '      f"relative gap to the {fstar_label}: {(f[-1] - fstar) / fstar:.2e}")\n'
            'print(f"compile {result.compile_seconds:.1f} s, {result.ms_per_iteration:.2f} ms per iteration")'),
        new_markdown_cell("## 4. Trajectory and convergence"),
        new_code_cell(
            'from mmpgo_jax.plotting import plot_trajectory\n\n'
            'fig = plt.figure(figsize=(13, 5))\n'
            'ax_t = fig.add_subplot(1, 2, 1, projection="3d" if graph.dim == 3 else None)\n'
            'plot_trajectory(ax_t, graph, result.poses, np.asarray(part.robot_of_pose), legend=False)\n'
            'ax_t.set_title(f"{name}: AMM-PGO estimate, {ROBOTS} robots")\n'
            'ax_c = fig.add_subplot(1, 2, 2)\n'
            'ax_c.semilogy(np.maximum((f - fstar) / fstar, 1e-14), label="AMM-PGO")\n'
            'mm_run = mm.solve(graph, part, method="mm", iterations=ITERATIONS)\n'
            'ax_c.semilogy(np.maximum((mm_run.history.f - fstar) / fstar, 1e-14), "--", label="MM-PGO")\n'
            'ax_c.set_xlabel("iteration")\n'
            'ax_c.set_ylabel(f"(f - f*) / f*, f* = {fstar_label}")\n'
            'ax_c.grid(alpha=0.4)\n'
            'ax_c.legend()\n'
            'ax_c.set_title("relative suboptimality")\n'
            'plt.show()'),
        new_code_cell(
            'if ground_truth is not None:  # generated data: accuracy against the ground truth\n'
            '    print(f"ATE {mm.absolute_trajectory_error(result.poses, ground_truth):.4f} m, "\n'
            '          f"RPE {mm.relative_pose_error(result.poses, ground_truth)}")'),
        new_markdown_cell("## 5. Is it the global optimum?\n`centralized_optimum` (one robot, near-exact Newton "
                          "steps) finds a critical point; `certify` checks SE-Sync's dual certificate "
                          "S = M - Λ(X) ≽ 0 there, which proves global optimality."),
        new_code_cell(
            'ref = mm.centralized_optimum(graph)\n'
            'cert = mm.certify(graph, ref.poses)\n'
            'print(f"centralized: {ref.iterations} iterations, f = {ref.f:.10g}")\n'
            'print(cert.summary())'),
    ]
    return _notebook(cells, "01_quickstart.ipynb")


def reproduce_tables() -> nbformat.NotebookNode:
    cells = [
        new_markdown_cell(
            "# Tables I/II: MM-PGO and AMM-PGO with 10 robots on the benchmark files\n\n"
            "Runs both methods on the paper's benchmark files found in the data folder (`MMPGO_DATA`; "
            "selection: `MMPGO_NOTEBOOK_DATASETS`) and shows "
            "f = 2F after the iteration checkpoints next to the paper's numbers (registry "
            "`mmpgo_jax.BENCHMARKS`). The default budget (`MMPGO_NOTEBOOK_ITERATIONS`, 100) "
            "fills the 100-iteration column; set it to 1000 for all three columns."),
        setup_cell(100, stdlib=("os", "time"), third_party="from IPython.display import Markdown, display",
                   after="ROBOTS = 10\nCHECKPOINTS = (100, 250, 1000)", numpy=False),
        new_code_cell(
            '# MMPGO_NOTEBOOK_DATASETS: comma-separated names ("MITb,garage"), "all", or empty (default:\n'
            '# the paper\'s benchmarks found in the data folder with at most 3500 poses, which keeps this\n'
            '# notebook under two minutes; "all" adds city10000 and torus3D, about a minute more).\n'
            'SELECT = os.environ.get("MMPGO_NOTEBOOK_DATASETS", "").strip()\n'
            'paper = [info for info in mm.available_benchmarks() if info.in_paper]\n'
            'if SELECT.lower() == "all":\n'
            '    chosen = paper\n'
            'elif SELECT:\n'
            '    wanted = {mm.benchmark_info(s) for s in SELECT.split(",")}\n'
            '    chosen = [info for info in paper if info in wanted]\n'
            'else:\n'
            '    chosen = [info for info in paper if info.num_poses <= 3500]\n'
            'print("paper benchmarks found:", [info.name for info in paper] or "none")\n'
            'print("running:", [info.name for info in chosen] or "none")\n'
            'if not paper:\n'
            '    print("Set MMPGO_DATA to a folder holding the .g2o files (see datasets/README.md).")'),
        new_code_cell(
            'runs = {}\n'
            'for info in chosen:\n'
            '    graph = mm.read_g2o(info.path()).graph\n'
            '    for method in ("mm", "amm"):\n'
            '        t = time.perf_counter()\n'
            '        r = mm.solve(graph, ROBOTS, method=method, iterations=ITERATIONS)\n'
            '        runs[(info.name, method)] = r\n'
            '        print(f"{info.name:>10} {method.upper():>3}: f = {r.f:.6g} after {r.iterations} iterations "\n'
            '              f"({time.perf_counter() - t:.1f} s, {r.ms_per_iteration:.2f} ms/iteration)")'),
        new_markdown_cell("## Ours beside the paper\n`paper` = Table I/II; `f*` = the registry's reference "
                          "optimum (`BenchmarkInfo.fstar_reference`: this project's certified f* where it has "
                          "one, else the published, rounded value; sources: `docs/conventions.md`). Columns "
                          "appear for checkpoints within the budget."),
        new_code_cell(
            'cps = [k for k in CHECKPOINTS if k <= ITERATIONS]\n'
            'if not cps:\n'
            '    print(f"budget {ITERATIONS} < 100: showing f after {ITERATIONS} iterations "\n'
            '          "beside the paper\'s 100-iteration column")\n'
            'cols = cps or [ITERATIONS]\n'
            'pairs = " | ".join(f"ours @{k} | paper @{k if cps else 100}" for k in cols)\n'
            'head = "| dataset | method | f* | " + pairs + " |"\n'
            'lines = [head, "|" + "---|" * (3 + 2 * len(cols))]\n'
            'for (name, method), r in runs.items():\n'
            '    info = mm.BENCHMARKS[name]\n'
            '    paper = info.paper_mm if method == "mm" else info.paper_amm\n'
            '    cells = []\n'
            '    for k in cols:\n'
            '        ref = paper.get(k if cps else 100) if paper else None\n'
            '        f = r.history.f[min(k, len(r.history.f) - 1)]  # stopped early (f stalled): its last f\n'
            '        cells += [f"{f:.6g}", "–" if ref is None else f"{ref:.6g}"]\n'
            '    ref = info.fstar_reference\n'
            '    fs = "–" if ref is None else f"{ref.value:.10g} ({ref.label})"\n'
            '    lines.append(f"| {name} | {method.upper()}-PGO | {fs} | " + " | ".join(cells) + " |")\n'
            'display(Markdown("\\n".join(lines) if runs else "_no benchmark files available_"))'),
        new_markdown_cell("## Convergence\nRelative suboptimality against the registry's reference f* (each "
                          "title says which: the certified f* where there is one). Every value Tables I/II print "
                          "within the run is a marker, its bar the range its 4 digits stand for; a print at or "
                          "below f* sits at the floor of the axis. The axis ends with the run: "
                          "`MMPGO_NOTEBOOK_ITERATIONS=1000` shows all three checkpoints."),
        new_code_cell(
            'from mmpgo_jax.plotting import plot_convergence\n\n'
            'names = list(dict.fromkeys(name for name, _ in runs))\n'
            'if names:\n'
            '    ncols = min(3, len(names))\n'
            '    nrows = -(-len(names) // ncols)\n'
            '    fig, axes = plt.subplots(nrows, ncols, figsize=(5.5 * ncols, 4 * nrows), squeeze=False)\n'
            '    for ax in axes.flat[len(names):]:\n'
            '        ax.set_visible(False)\n'
            '    for ax, name in zip(axes.flat, names, strict=False):  # the spare axes are hidden\n'
            '        info = mm.BENCHMARKS[name]\n'
            '        ref = info.fstar_reference\n'
            '        if ref is None:\n'
            '            ax.set_title(f"{name}: no reference f*")\n'
            '            continue\n'
            '        curves = {f"{m.upper()}-PGO": runs[(name, m)].history for m in ("mm", "amm")}\n'
            '        paper = {"MM-PGO (paper)": dict(info.paper_mm or {}),\n'
            '                 "AMM-PGO (paper)": dict(info.paper_amm or {})}\n'
            '        plot_convergence(ax, curves, ref.value, references=paper, printed_digits=4)\n'
            '        ax.set_title(f"{name}: gap to the {ref.label} {ref.value:.10g}", fontsize=9)\n'
            '    fig.tight_layout()\n'
            '    plt.show()'),
    ]
    return _notebook(cells, "02_reproduce_tables.ipynb")


def robot_sweeps() -> nbformat.NotebookNode:
    cells = [
        new_markdown_cell(
            "# Robot-count sweeps (Fig. 1 style) with the sweep API\n\n"
            "`mmpgo_jax.sweep(graphs, robots, methods, iterations, ...)` pads every (graph, robot "
            "count) configuration of a method to one shape, stacks them along a new leading axis and "
            "runs them with ONE compiled `jit(vmap(run))` chunk. Here: small Cube datasets, 5/10/20 "
            "robots, MM vs AMM, and the two panels of the paper's Fig. 1 (f − f* and (f − f*)/f*, "
            "median and 10–90 % band over datasets). The full study is `benchmarks/fig1.py`.\n\n"
            "Budget: `MMPGO_NOTEBOOK_ITERATIONS` (default 150); robot counts `MMPGO_NOTEBOOK_ROBOTS` "
            "(default `5,10,20`) and number of Cube datasets `MMPGO_NOTEBOOK_CUBES` (default 3)."),
        setup_cell(150, stdlib=("os", "tempfile", "time"),
                   third_party="from IPython.display import Markdown, display",
                   first_party="from mmpgo_jax import reference_optimum, sweep",
                   after='ROBOTS = [int(a) for a in os.environ.get("MMPGO_NOTEBOOK_ROBOTS", "5,10,20").split(",")]\n'
                         'NUM_DATASETS = int(os.environ.get("MMPGO_NOTEBOOK_CUBES", "3"))'),
        new_code_cell(
            'datasets = {f"cube{s}": mm.cube_dataset(s, num_poses=600, grid=6) for s in range(NUM_DATASETS)}\n'
            'fstar = {name: reference_optimum(ds.graph) for name, ds in datasets.items()}  # centralized optimum\n'
            'for name, ds in datasets.items():\n'
            '    print(f"{name}: n={ds.num_poses}, m={ds.num_edges}, f*={fstar[name]:.8g}")'),
        new_markdown_cell(
            "## One compilation per method\nWith the default `group_by=\"method\"` all robot counts of a "
            "method share one padded shape (robot axis padded to the largest count; padded robots own "
            "nothing), so the sweep compiles the run chunk once per method. A sweep result's `groups` has one "
            "row per compiled group; its `traces` counts how often JAX traced the batched chunk (1: one "
            "compilation; 0: JAX had it already)."),
        new_code_cell(
            'one = sweep({"cube0": datasets["cube0"]}, ROBOTS, ("mm", "amm"), min(ITERATIONS, 20),\n'
            '            fstar={"cube0": fstar["cube0"]}, chunk_size=10)\n'
            'groups = {m: sum(g["method"] == m for g in one.groups) for m in one.methods}\n'
            'print("compiled groups per method:", groups)\n'
            'for g in one.groups:\n'
            '    print(f"{g[\'method\']}: {g[\'configs\']} configs padded to A={g[\'A\']} x n_max={g[\'n_max\']} "\n'
            '          f"(x{g[\'padding_factor\']:.1f} slots), {g[\'bytes_per_config\'] / 2**20:.1f} MiB/config, "\n'
            '          f"traced {g[\'traces\']}x, compile {g[\'compile_seconds\']:.1f} s, "\n'
            '          f"run {g[\'run_seconds\']:.1f} s")'),
        new_markdown_cell(
            "## The Fig. 1 study at small settings\nPadding 5 robots to 20 multiplies the work; "
            "`group_by=\"robots\"` stacks only configurations with the same robot count (one "
            "compilation per method and robot count, much less padding). Results are the same."),
        new_code_cell(
            't = time.perf_counter()\n'
            'res = sweep(datasets, ROBOTS, ("mm", "amm"), ITERATIONS, fstar=fstar, group_by="robots")\n'
            'print(f"{len(res.configs)} configurations in {time.perf_counter() - t:.1f} s")\n'
            'lines = ["| method | robots | median (f - f*)/f* at the end | ms/iteration/config | median ATE [m] |",\n'
            '         "|---|---|---|---|---|"]\n'
            'for method in res.methods:\n'
            '    for a in res.robots:\n'
            '        rows = [r for r in res.configs if r["method"] == method and r["robots"] == a]\n'
            '        gap, ms, ate = (np.median([r[k] for r in rows]) for k in ("relative_gap", "ms_per_iteration",\n'
            '                                                                  "ate"))\n'
            '        lines.append(f"| {method.upper()} | {a} | {gap:.2e} | {ms:.1f} | {ate:.4f} |")\n'
            'display(Markdown("\\n".join(lines)))'),
        new_code_cell(
            'colors = {5: "tab:blue", 10: "tab:orange", 20: "tab:purple", 50: "tab:green"}\n'
            'fig, axes = plt.subplots(1, 2, figsize=(13, 4.8))\n'
            'fs = np.array([fstar[g] for g in res.graphs])[:, None]\n'
            'for method, style in (("mm", "--"), ("amm", "-")):\n'
            '    for a in res.robots:\n'
            '        f = res.stack(method, a, relative=False)\n'
            '        for ax, gap in zip(axes, (f - fs, (f - fs) / fs), strict=True):\n'
            '            gap = np.maximum(gap, 1e-14)\n'
            '            x = np.arange(gap.shape[1])\n'
            '            label = f"{method.upper()}-PGO, {a} robots"\n'
            '            ax.plot(x, np.median(gap, 0), style, color=colors.get(a), label=label)\n'
            '            lo, hi = np.quantile(gap, 0.1, 0), np.quantile(gap, 0.9, 0)\n'
            '            ax.fill_between(x, lo, hi, color=colors.get(a), alpha=0.1)\n'
            'for ax, label in zip(axes, ("f - f*", "(f - f*) / f*"), strict=True):\n'
            '    ax.set_yscale("log")\n'
            '    ax.set_xlabel("iteration")\n'
            '    ax.set_ylabel(label)\n'
            '    ax.grid(alpha=0.4)\n'
            'axes[1].legend(ncol=2, fontsize=8)\n'
            'fig.suptitle(f"{len(res.graphs)} Cube datasets (600 poses): median and 10-90 % band")\n'
            'plt.tight_layout()\n'
            'plt.show()'),
        new_markdown_cell("## Tidy results\n`res.rows` (one dict per graph × robots × method × iteration), "
                          "`res.to_csv(path)`, `res.configs` (memory, time, ATE/RPE per configuration)."),
        new_code_cell(
            'path = os.path.join(tempfile.mkdtemp(), "sweep.csv")\n'
            'res.to_csv(path)\n'
            'with open(path) as fh:\n'
            '    print(fh.read().splitlines()[:4])\n'
            'keys = ("graph", "robots", "method", "f", "relative_gap", "bytes", "seconds", "ate", "rpe_translation",\n'
            '        "rpe_rotation_deg")\n'
            'print({k: res.configs[0][k] for k in keys})'),
    ]
    return _notebook(cells, "03_robot_sweeps.ipynb")


def outliers() -> nbformat.NotebookNode:
    cells = [
        new_markdown_cell(
            "# Outlier loop closures and robust losses\n\n"
            "Wrong loop closures (perceptual aliasing) bend a least-squares estimate. Here: a Cube "
            "dataset with seeded outlier loop closures (`mm.add_outlier_loop_closures`), "
            "the least-squares solve bent by them, the robust kernels huber, cauchy and tls (truncated "
            "least squares through graduated non-convexity, GNC) with `mm.solve(..., loss=...)`, the "
            "trajectories with the rejected edges in red, and ATE against the outlier rate from one "
            "`mm.sweep` over rates × kernels (one compilation per method).\n\n"
            "Budget: `MMPGO_NOTEBOOK_ITERATIONS` (default 1500); Cube size `MMPGO_NOTEBOOK_OUTLIER_POSES` "
            "(default 200); outlier rates in percent `MMPGO_NOTEBOOK_OUTLIER_RATES` (default `0,20,40,60`)."),
        setup_cell(1500,
                   third_party="from IPython.display import Markdown, display",
                   first_party="from mmpgo_jax.plotting import plot_trajectory",
                   after='POSES = int(os.environ.get("MMPGO_NOTEBOOK_OUTLIER_POSES", "200"))\n'
                         'RATES = [float(p) for p in os.environ.get("MMPGO_NOTEBOOK_OUTLIER_RATES", "0,20,40,60")'
                         '.split(",")]\n'
                         'ROBOTS = 4\n'
                         'KERNELS = ["huber", "cauchy", "tls"]'),
        new_markdown_cell(
            "## Kernels and their scale\n"
            "Per edge the squared residual is s = κ‖R_i R̃_ij − R_j‖² + τ‖R_i t̃_ij + t_i − t_j‖² (one term of "
            "f = 2F) and the robust objective is F_ρ = ½ Σ ρ_c(s); reported objectives are f = 2F_ρ. Every "
            "kernel is normalised to ρ(s) ≈ s for s ≪ c², so an edge well within the scale costs what it costs "
            "in least squares. The scale c is in residual units (r = √s): an edge starts to be discounted "
            "around r = c. Its default is √χ²_{d(d+1)/2}(0.99), the residual a correct edge exceeds with "
            "probability 1 % under SE-Sync's noise model (`mm.chi2_scale`); a 2D file whose angle noise is "
            "what its I33 states exceeds the 2D default with probability 4.2 %, and "
            "`mm.chi2_scale(2, noise=\"information\")` = 4.04 is its 0.99 quantile (measured as the default "
            "and not kept: `docs/conventions.md` §10). Each kernel is concave in s, so "
            "the paper's majorizer with every edge's κ, τ multiplied by the weight w = ρ'(s) at the current "
            "iterate majorizes F_ρ: MM keeps F_ρ non-increasing. Least squares (and so the chordal "
            "start) is bent by the outliers, so every robust kernel runs by default from two robust starts "
            "and keeps the run of lower F_ρ: `\"gnc-chordal\"`, graduated non-convexity with TLS (Yang et "
            "al., RA-L 2020), a sequence of surrogate kernels from least squares to TLS with the weights set "
            "in closed form after each stage, every stage solved from scratch (chordal relaxation of the "
            "weighted graph, then Newton), and `\"distributed-robust\"`, each robot's own GNC map placed by "
            "the frames its inter-robot closures agree on (`res.stats[\"starts\"]` reports both; `mm.sweep` "
            "runs from `\"gnc-chordal\"` alone). "
            "Odometry edges (consecutive poses) keep weight 1. Details: `docs/conventions.md` §10. "
            "The kernels are `mm.loss_rho` and `mm.loss_weight` (ρ and ρ' of a kernel by name, "
            "at scale c; `mm.LOSSES` lists the names)."),
        new_code_cell(
            'c = mm.chi2_scale(3)\n'
            'print(f"default scale: c = {mm.chi2_scale(2):.3f} (2D), {c:.3f} (3D)")\n'
            'r = np.linspace(0.0, 4.0 * c, 400)\n'
            'fig, axes = plt.subplots(1, 2, figsize=(12, 4))\n'
            'for name in mm.LOSSES:\n'
            '    axes[0].plot(r / c, np.asarray(mm.loss_rho(name, r**2, c)) / c**2, label=name)\n'
            '    axes[1].plot(r / c, np.asarray(mm.loss_weight(name, r**2, c)), label=name)\n'
            'axes[0].set_ylim(0, 4)\n'
            'axes[0].set_ylabel("ρ(s) / c²")\n'
            'axes[1].set_ylabel("weight ρ\'(s)")\n'
            'for ax in axes:\n'
            '    ax.set_xlabel("residual r / c")\n'
            '    ax.grid(alpha=0.4)\n'
            'axes[1].legend()\n'
            'plt.tight_layout()\n'
            'plt.show()'),
        new_markdown_cell(
            "## A graph with outliers\n"
            "`mm.add_outlier_loop_closures(graph, rate, reference=..., seed=...)` appends wrong loop "
            "closures: uniform "
            "random pose pairs not already joined, a Haar-random rotation, a translation uniform within the "
            "map's extent, the median information of the graph's loop closures. The rate is the fraction "
            "of outliers among all loop closures after the addition; the result is a `CorruptedGraph` "
            "whose `outlier` marks them."),
        new_code_cell(
            'data = mm.cube_dataset(0, grid=4, num_poses=POSES)\n'
            'truth = data.ground_truth\n'
            'bad = mm.add_outlier_loop_closures(data.graph, 0.3, reference=truth, seed=1)\n'
            'robots = mm.contiguous_robots(data.num_poses, ROBOTS)\n'
            'print(f"{data.name}: n={data.num_poses}, m={data.num_edges} -> {bad.graph.num_edges} edges "\n'
            '      f"({bad.num_outliers} outlier loop closures, 30 % of the loop closures)")'),
        new_markdown_cell(
            "## Least squares and robust kernels\n`loss=` picks the kernel (default scale; `loss_scale=` sets "
            "c, `gnc=` a `GNCConfig`). The result holds the final edge `weights` and the `inliers` (final "
            "residual within the scale); precision / recall score the rejected edges against the true "
            "outliers (`mm.outlier_scores`), ATE is against the ground truth after rigid alignment. Least "
            "squares runs here as "
            "`RobustLoss(\"l2\")`: the same objective through the weighted program (every weight 1), so that "
            "the four runs share one compilation; its \"rejected\" edges are those whose final residual "
            "lies beyond the scale (it starts from the chordal start, the robust kernels from their two "
            "robust starts). The clean graph's ATE is the 0 % row of the sweep below. `gnc=mm.GNCConfig()` would "
            "run GNC's stages inside the distributed solver instead (fully distributed, from the chordal "
            "start; less reliable, see `benchmarks/robust.md`)."),
        new_code_cell(
            'runs = {}\n'
            'for kernel in ["l2", *KERNELS]:\n'
            '    loss = mm.RobustLoss("l2") if kernel == "l2" else kernel\n'
            '    runs[kernel] = mm.solve(bad.graph, robots, iterations=ITERATIONS, loss=loss, ground_truth=truth)\n'
            'lines = ["| kernel | ATE [m] | rejected | precision | recall | GNC stages |",\n'
            '         "|---|---|---|---|---|---|"]\n'
            'for kernel, r in runs.items():\n'
            '    sc = mm.outlier_scores(r.inliers, bad.outlier)\n'
            '    lines.append(f"| {kernel} | {r.accuracy.ate:.4f} | {sc.rejected} | {sc.precision:.3f} | "\n'
            '                 f"{sc.recall:.3f} | {r.stats.get(\'gnc_stages\', 0)} |")\n'
            'display(Markdown("\\n".join(lines)))'),
        new_markdown_cell(
            "## Trajectories\nTop view, one colour per robot; in red the edges each run rejected. Least "
            "squares is bent by the outliers; the robust runs keep the cube's shape."),
        new_code_cell(
            'fig, axes = plt.subplots(1, len(runs), figsize=(4.5 * len(runs), 4.5))\n'
            'for ax, (kernel, r) in zip(axes, runs.items(), strict=True):\n'
            '    plot_trajectory(ax, bad.graph, r.poses, robots, inter_robot_edges=False, legend=False,\n'
            '                    outliers=r.outliers)\n'
            '    ax.set_title(f"{kernel}: ATE {r.accuracy.ate:.3f} m", fontsize=10)\n'
            '    ax.set_aspect("equal")\n'
            'plt.tight_layout()\n'
            'plt.show()'),
        new_markdown_cell(
            "## ATE against the outlier rate, one sweep\n`mm.sweep(graphs, ..., loss=[...])`: the kernel "
            "is a traced number of the problem and graphs with different edge counts (the rates) are padded "
            "to one shape, so every (rate, kernel) configuration of a method runs in one compiled "
            "`jit(vmap(run))` chunk. A `CorruptedGraph` brings its outlier mask: the configurations report "
            "precision and recall. From the command line: `mmpgo sweep FILE --losses huber cauchy tls "
            "--outlier-rates 0 20 40`."),
        new_code_cell(
            'graphs = {f"{p:g}%": mm.add_outlier_loop_closures(data.graph, p / 100.0, reference=truth, seed=1)\n'
            '          for p in RATES}\n'
            'res = mm.sweep(graphs, [ROBOTS], "amm", ITERATIONS, loss=["l2", *KERNELS],\n'
            '               ground_truth={name: truth for name in graphs})\n'
            'print(f"{len(res.configs)} configurations in {len(res.groups)} compiled group(s), "\n'
            '      f"traces of the batched chunk: {[g[\'traces\'] for g in res.groups]}")\n'
            'ate = {(row["graph"], row["loss"]): row for row in res.configs}\n'
            'lines = ["| outlier rate | " + " | ".join(res.losses) + " |", "|---" * (len(res.losses) + 1) + "|"]\n'
            'for name in graphs:\n'
            '    cells = []\n'
            '    for loss in res.losses:\n'
            '        row = ate[(name, loss)]\n'
            '        cells.append(f"{row[\'ate\']:.4f} (P {row[\'precision\']:.2f}, R {row[\'recall\']:.2f})")\n'
            '    lines.append(f"| {name} | " + " | ".join(cells) + " |")\n'
            'display(Markdown("ATE [m] (precision, recall of the rejected edges)\\n\\n" + "\\n".join(lines)))'),
        new_code_cell(
            'fig, ax = plt.subplots(figsize=(6, 4))\n'
            'for loss in res.losses:\n'
            '    ax.plot(RATES, [ate[(name, loss)]["ate"] for name in graphs], "o-", label=loss)\n'
            'ax.set_yscale("log")\n'
            'ax.set_xlabel("outlier loop closures [%]")\n'
            'ax.set_ylabel("ATE [m]")\n'
            'ax.grid(alpha=0.4)\n'
            'ax.legend()\n'
            'plt.tight_layout()\n'
            'plt.show()'),
        new_markdown_cell(
            "The full study (more rates, all kernels, benchmark files, GNC from other starts) is "
            "`benchmarks/robust.py` (results in `benchmarks/robust.md`)."),
    ]
    return _notebook(cells, "04_outliers.ipynb")


def _notebook(cells, name: str) -> nbformat.NotebookNode:
    cells[0].source += outputs_note(name)
    nb = new_notebook(cells=cells)
    nb.metadata["kernelspec"] = {"display_name": "Python 3", "language": "python", "name": "python3"}
    nb.metadata["language_info"] = {"name": "python"}
    nbformat.validate(nb)
    return nb


NOTEBOOKS = {
    "01_quickstart.ipynb": quickstart,
    "02_reproduce_tables.ipynb": reproduce_tables,
    "03_robot_sweeps.ipynb": robot_sweeps,
    "04_outliers.ipynb": outliers,
}


def build(name: str) -> nbformat.NotebookNode:
    """Notebook ``name`` as generated (no outputs), with stable cell ids, so that regenerating gives
    byte-identical files."""
    nb = NOTEBOOKS[name]()
    for k, cell in enumerate(nb.cells):
        cell["id"] = f"cell-{k:02d}"
    return nb


def execute(nb: nbformat.NotebookNode, env: dict[str, str] | None = None, timeout: int = 900) -> nbformat.NotebookNode:
    """Run ``nb`` in place in a fresh ``python3`` kernel started in this folder, with environment ``env``
    (default: this process's), this checkout first on ``PYTHONPATH``; raises ``CellExecutionError``
    on the first failing cell. Drops what changes from run to run without meaning: the cells'
    timing metadata and the kernel's ``language_info`` (Python version); a cell's consecutive prints
    are one output (as Jupyter shows them)."""
    import nbclient  # here: writing the sources needs only nbformat

    env = dict(os.environ if env is None else env)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    client = nbclient.NotebookClient(nb, timeout=timeout, kernel_name="python3", record_timing=False,
                                     coalesce_streams=True, resources={"metadata": {"path": str(HERE)}})
    client.execute(env=env)
    nb.metadata["language_info"] = {"name": "python"}
    for cell in nb.cells:
        cell.metadata.pop("execution", None)
    nbformat.validate(nb)
    return nb


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Write the example notebooks (and optionally run them).")
    parser.add_argument("names", nargs="*", metavar="NAME",
                        help=f"notebooks to write (default: all): {', '.join(NOTEBOOKS)}")
    parser.add_argument("--execute", action="store_true",
                        help="run each notebook (EXECUTE_SETTINGS, MMPGO_DATA) and keep its outputs")
    args = parser.parse_args(argv)
    unknown = [name for name in args.names if name not in NOTEBOOKS]
    if unknown:
        parser.error(f"unknown notebook {unknown[0]!r}: choose from {', '.join(NOTEBOOKS)}")
    for name in args.names or NOTEBOOKS:
        nb = build(name)
        if args.execute:
            t = time.perf_counter()
            execute(nb, {**os.environ, **EXECUTE_SETTINGS[name]})
            print(f"executed {name} in {time.perf_counter() - t:.0f} s", file=sys.stderr)
        nbformat.write(nb, HERE / name)
        print("wrote", HERE / name)


if __name__ == "__main__":
    main()
