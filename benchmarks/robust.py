"""Robust losses on outlier-corrupted pose graphs: ATE, outlier classification and cost per kernel.

    python benchmarks/robust.py [--out benchmarks/robust.md] [--rates 0 10 30 50 70] [--iterations 2000]
                                [--robots 10] [--cube-poses 500] [--files NAME ...] [--inter-only-rate 30 50]
                                [--seeds 1 2]

For each graph (a Cube graph of ``--cube-poses`` poses, seed 0, and the benchmark ``--files``),
wrong loop closures are added at each outlier rate (``mmpgo_jax._experiments.outliers.add_outliers``:
uniform random pose pairs not already joined, Haar-random rotation, translation uniform in the map's
extent, the median information of the graph's loop closures, one run per ``--seeds`` value); a rate
is the fraction of outliers among all loop closures. Every kernel is run from its default start (the
GNC-chordal start for every robust kernel) with ``--robots`` contiguous robots, AMM (adaptive
restart), up to ``--iterations`` iterations, grad_tol 1e-6, default scale (chi-square 0.99
quantile). Besides the kernels:

* ``tls+gnc``: GNC-TLS run by the distributed solver (``gnc=GNCConfig()``, from the chordal start);
* ``gnc-start``: the GNC-chordal start alone (centralized GNC, the start of the robust runs);
* ``gtsam-gnc``: GTSAM's GncOptimizer (TLS, odometry known inliers, the same threshold) from the
  chordal start: an independent centralized reference (only when gtsam is installed);
* ``tls-distributed`` (only when named in ``--kernels``): the fully distributed pipeline,
  ``solve(graph, robots, loss="tls", distributed=True)`` (the distributed robust start, its
  classification held as the first stage, then TLS).

Reported per run: ATE and rotation RMSE against the ground truth (Cube) or the outlier-free
optimum (files), precision / recall of the outlier classification (outliers = the edges the run
rejects), f over the true inlier edges against the outlier-free f* (centralized optimum of the
clean graph), iterations and seconds (start + compile + iterations; for the references, their own
solve). Writes the Markdown table, a CSV beside it and a PNG of ATE vs outlier rate per kernel.
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

import mmpgo_jax as mg  # noqa: E402
from mmpgo_jax._experiments.gtsam_lm import gtsam_available, gtsam_gnc  # noqa: E402
from mmpgo_jax._experiments.outliers import add_outliers, outlier_scores  # noqa: E402
from mmpgo_jax._init.robust_start import gnc_chordal_initialization  # noqa: E402
from mmpgo_jax._io.atomic import atomic_write  # noqa: E402
from mmpgo_jax.cli.bench import command_line, machine_info  # noqa: E402

KERNELS = ("l2", "huber", "cauchy", "geman-mcclure", "welsch", "tls")
REFERENCES = ("tls+gnc", "gnc-start", "gtsam-gnc")


def _graphs(args):
    """(name, graph, reference poses, reference is ground truth)."""
    if args.cube_poses:
        ds = mg.cube_dataset(0, grid=args.cube_grid, num_poses=args.cube_poses)
        yield f"cube{args.cube_poses}", ds.graph, ds.ground_truth, True
    for name in args.files:
        graph = mg.read_g2o(mg.find_benchmark(name)).graph
        yield name, graph, None, False


class _Reference:
    """A centralized reference's outcome in SolveResult's terms (poses, inliers, iterations, stats)."""

    def __init__(self, poses, inliers, stages=None):
        self.poses, self.inliers, self.iterations, self.stats = poses, inliers, 0, dict(gnc_stages=stages)


def _run(graph, robots, kernel, iterations):
    """One run of a kernel or of a reference (module docstring)."""
    t = time.perf_counter()
    if kernel == "gnc-start":
        start = gnc_chordal_initialization(graph)
        r = _Reference(start.poses, start.weights > 0.5, start.stages)
    elif kernel == "gtsam-gnc":
        ref = gtsam_gnc(graph, mg.initialize(graph, "chordal"), scale=mg.chi2_scale(graph.dim))
        r = _Reference(ref.poses, ref.weights > 0.5)
    elif kernel == "tls-distributed":
        r = mg.solve(graph, robots, loss="tls", distributed=True, iterations=iterations, grad_tol=1e-6)
    elif kernel == "tls+gnc":
        r = mg.solve(graph, robots, loss="tls", gnc=mg.GNCConfig(), iterations=iterations, grad_tol=1e-6)
    else:
        r = mg.solve(graph, robots, loss=kernel, iterations=iterations, grad_tol=1e-6)
    return r, time.perf_counter() - t


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(Path(__file__).with_name("robust.md")))
    ap.add_argument("--rates", type=float, nargs="*", default=[0, 10, 30, 50, 70])
    ap.add_argument("--kernels", nargs="*", default=[*KERNELS, *REFERENCES])
    ap.add_argument("--iterations", type=int, default=2000)
    ap.add_argument("--seeds", type=int, nargs="*", default=[1])
    ap.add_argument("--robots", type=int, default=10)
    ap.add_argument("--cube-poses", type=int, default=500)
    ap.add_argument("--cube-grid", type=int, default=6)
    ap.add_argument("--files", nargs="*", default=[])
    ap.add_argument("--inter-only-rate", type=float, nargs="*", default=[])
    args = ap.parse_args(argv)
    if not gtsam_available():
        args.kernels = [k for k in args.kernels if k != "gtsam-gnc"]

    rows = []
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    load = Path("/proc/loadavg").read_text().split()[:3]
    for name, graph, reference, is_truth in _graphs(args):
        clean = mg.centralized_optimum(graph)
        fstar = float(clean.f)
        reference = reference if is_truth else clean.poses
        robots = mg.contiguous_robots(graph.num_poses, args.robots)
        runs = [(rate, False, seed) for rate in args.rates for seed in args.seeds]
        runs += [(rate, True, seed) for rate in args.inter_only_rate for seed in args.seeds]
        for rate, inter, seed in runs:
            if rate == 0 and seed != args.seeds[0]:
                continue  # no outliers: every seed gives the same graph
            bad = add_outliers(graph, rate / 100.0, reference=reference, seed=seed, robot_of_pose=robots,
                               inter_robot_only=inter)
            for kernel in args.kernels:
                r, seconds = _run(bad.graph, robots, kernel, args.iterations)
                acc = mg.trajectory_accuracy(r.poses, reference)
                sc = None if r.inliers is None else outlier_scores(r.inliers, bad.outlier)
                f_in = float(mg.cost(graph, r.poses))
                row = dict(graph=name, rate=rate, outliers="inter-robot" if inter else "all", seed=seed, kernel=kernel,
                           added=bad.num_outliers, ate=acc.ate, rot_deg=acc.rotation_deg,
                           precision=None if sc is None else sc.precision, recall=None if sc is None else sc.recall,
                           f_inliers=f_in, fstar=fstar, rel_f=(f_in - fstar) / fstar, iterations=r.iterations,
                           seconds=seconds, stages=r.stats.get("gnc_stages"))
                rows.append(row)
                print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
    _write(args, rows, started, load)
    return 0


def _fmt(v, spec):
    return "—" if v is None else format(v, spec)


def _write(args, rows, started, load):
    out = Path(args.out)
    with atomic_write(out.with_suffix(".csv")) as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    _plot(rows, out.with_suffix(".png"))
    info = machine_info()
    lines = [
        "# Robust losses on outlier-corrupted graphs",
        "",
        f"Command: `{command_line()}`  ",
        f"Run {started}, load average at start {' '.join(load)} (shared 2-core machine), "
        f"{info.get('cpu', '?')}, JAX {info.get('jax', '?')}.",
        "",
        "| graph | outliers | rate % | seed | added | kernel | ATE | rot. deg | precision | recall | "
        "(f_in - f*)/f* | iterations | GNC stages | s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['graph']} | {r['outliers']} | {r['rate']:g} | {r['seed']} | {r['added']} | {r['kernel']} | "
            f"{r['ate']:.4g} | "
            f"{r['rot_deg']:.3g} | {_fmt(r['precision'], '.3f')} | {_fmt(r['recall'], '.3f')} | "
            f"{r['rel_f']:.2e} | {r['iterations']} | {_fmt(r['stages'], 'd')} | {r['seconds']:.1f} |")
    with atomic_write(out) as fh:
        fh.write("\n".join(lines) + "\n")


def _plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    graphs = sorted({r["graph"] for r in rows})
    fig, axes = plt.subplots(1, len(graphs), figsize=(6 * len(graphs), 4.5), squeeze=False)
    for ax, g in zip(axes[0], graphs, strict=True):
        for kernel in dict.fromkeys(r["kernel"] for r in rows):
            by_rate = {}
            for r in rows:
                if r["graph"] == g and r["kernel"] == kernel and r["outliers"] == "all":
                    by_rate.setdefault(r["rate"], []).append(r["ate"])
            pts = sorted((rate, float(np.median(v))) for rate, v in by_rate.items())  # median over seeds
            if pts:
                ax.plot(*zip(*pts, strict=True), "o-", label=kernel)
        ax.set_yscale("log")
        ax.set_xlabel("outlier loop closures [%]")
        ax.set_ylabel("ATE [m] (median over seeds)")
        ax.set_title(g)
        ax.grid(True, lw=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
