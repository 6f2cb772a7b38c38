"""Robust solves of robot teams with long odometry chains and wrong inter-robot loop closures.

    python benchmarks/robust_teams.py [--out benchmarks/robust_teams.md] [--robots 10] [--poses 500]
        [--intra 5] [--inter 30] [--dim 2] [--rate 30] [--seeds 0 1] [--iterations 1000]
        [--methods tls pcm pcm+tls] [--render]

Each seed builds ``mm.robot_team_dataset`` (``--robots`` robots of ``--poses`` poses each, a random
walk on the lattice, ``--intra`` intra-robot loop closures per robot and ``--inter`` inter-robot
ones for the team), computes the outlier-free optimum (``centralized_optimum``), and adds wrong
inter-robot loop closures with ``add_outlier_loop_closures(..., inter_robot_only=True)`` at
``--rate`` percent (its definition: the outliers' share of all loop closures after the addition).
Methods (AMM, the team's robots, ``--iterations`` at most, default stopping rules):

* ``tls``: ``loss="tls"`` from its default start (the centralized GNC-chordal start until 2026-12-05,
  the rows of the tables before then; since, a run from it and from the distributed robust start, the
  lower objective kept);
* ``pcm``: ``prefilter="pcm"`` then least squares (chordal start);
* ``pcm+tls``: ``prefilter="pcm"`` then ``loss="tls"`` (its default start on the filtered graph);
* ``l2``: least squares on the corrupted graph (no defence);
* ``dist-tls``, ``dist-pcm+tls``: ``distributed=True`` (since 2026-12-04 the distributed robust start,
  its classification held, then TLS, finished and revisited as ``solve`` does; the tables of
  2026-12-03 ran the distributed chordal start with GNC in the solver);
* ``dist-pcmties+tls``: ``dist-pcm+tls`` with ``PCM(ties="keep")`` (every closure of a maximum clique
  kept where cliques of the largest size disagree);
* ``dist-tls-checked``: ``dist-tls`` with the start's accepted inter-robot closures checked at the
  team's distributed chordal map (``NamedStart("distributed-robust", {"team_check": True})``), what
  ``dist-tls`` runs by default since 2026-12-08; ``dist-tls-unchecked``: without the check
  (``start="distributed-robust"``), what ``dist-tls`` ran until 2026-12-07;
* ``tls+readmit``, ``pcm+tls+readmit``: ``tls`` and ``pcm+tls`` with ``readmit=True`` (rejected loop
  closures, PCM's removals included, re-admitted one at a time while the TLS objective falls, then a run
  from there);
* ``pcm-filter``: ``pcm_filter`` alone (no solve), with the robot pairs holding one or two closures;
* ``gtsam``: a reference outside this package, GTSAM's ``GncOptimizer`` (TLS, Levenberg-Marquardt
  stages) from the centralized chordal start, odometry known inliers, the same scale c
  (:func:`~mmpgo_jax._experiments.gtsam_lm.gtsam_gnc`; needs ``pip install gtsam``); its inliers are the
  edges of weight >= 0.5, its iterations not kept.

Reported: precision / recall of the rejected edges (``result.inliers``, the PCM-removed edges
included) against the planted outliers, the correct edges rejected, PCM's rejections, ATE (RMSE of
positions after rigid alignment) against the outlier-free optimum and against the ground truth,
and the seconds of the whole ``solve`` call (PCM, start, compilation, iterations). Raw rows go to
the ``.json`` beside ``--out``; ``--render`` rewrites the Markdown from it without solving.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

from records import write_record  # noqa: E402  (this folder, on the path as a script's)

import mmpgo_jax as mm  # noqa: E402
from mmpgo_jax._io.atomic import atomic_write  # noqa: E402

METHODS = {
    "l2": dict(),
    "tls": dict(loss="tls"),
    "pcm": dict(prefilter="pcm"),
    "pcm+tls": dict(prefilter="pcm", loss="tls"),
    "dist-tls": dict(loss="tls", distributed=True),
    "dist-pcm+tls": dict(prefilter="pcm", loss="tls", distributed=True),
    "dist-pcmties+tls": dict(prefilter=mm.PCM(ties="keep"), loss="tls", distributed=True),
    "dist-tls-checked": dict(loss="tls", distributed=True,
                             start=mm.NamedStart("distributed-robust", {"team_check": True})),
    "dist-tls-unchecked": dict(loss="tls", distributed=True, start="distributed-robust"),
    "tls+readmit": dict(loss="tls", readmit=True),
    "pcm+tls+readmit": dict(prefilter="pcm", loss="tls", readmit=True),
    "pcm-filter": None,  # pcm_filter alone, no solve: its precision / recall and seconds
    "gtsam": "gtsam",  # GTSAM's GncOptimizer (TLS), a reference outside this package: _gtsam
}

# What the table shows (written from the run recorded in robust_teams.md; numbers are in the table).
FINDINGS = [
    "## Findings",
    "",
    "* **PCM does not fix the wrong basin on these teams.** With 30 inter-robot closures among 10 robots,",
    "  24-27 of the 27-35 robot pairs that share closures hold at most two. PCM works pair by pair, so its",
    "  maximum clique has no majority to find: a pair with one correct closure and one outlier is a tie (it",
    "  keeps one of the two), a pair with only outliers keeps one of them. Alone it removed 0-47 % of the",
    "  outliers and dropped 2-8 correct closures per graph (`pcm-filter` rows), and PCM + TLS ends as far",
    "  from the outlier-free optimum as TLS alone (ATE 5.7-19.5 against 5.9-20.0, maps about 20 cells across).",
    "* **TLS from the GNC start lands in a wrong basin** on every graph with outliers and 30 inter-robot",
    "  closures, even at 13 outliers (30 % of the inter-robot closures): ATE 5.9-20 against the outlier-free",
    "  optimum, 14-34 correct closures rejected (low noise). It is a basin, not the objective: a separate",
    "  check on the graphs of the first and third tables (same generator and outlier calls, seeds 0 and 1)",
    "  evaluated the TLS objective at the outlier-free optimum and at the solve's result: 634 vs 910 and",
    "  570 vs 833 (low noise), 607 vs 1078 (Cube noise, seed 0); the right answer is far cheaper. Without",
    "  outliers TLS returns the optimum (last two tables: ATE 1e-11 and below against it) and PCM drops no",
    "  closure. The distributed variants",
    "  (`dist-tls`, `dist-pcm+tls`: distributed chordal start, GNC in the solver) fail the same way.",
    "* **Where PCM works, TLS already did.** With 200 inter-robot closures (4-5 per robot pair) and low noise,",
    "  PCM is nearly exact (precision 0.97-0.98, recall 0.94-0.97, 2-3 correct closures dropped, under a",
    "  second), but the 3-6 outliers it keeps bend least squares (ATE 0.84-1.0 against the optimum), while TLS",
    "  alone and PCM + TLS both reach the optimum (ATE 0.017-0.046 against it). PCM + TLS was faster there",
    "  (12.5 and 5.8 s against 30.4 and 15.0 s: the GNC start has fewer outliers to sort out; timings on a",
    "  shared machine under varying load).",
    "* **Long noisy chains weaken PCM's test itself.** With the Cube's noise (0.02 pi rad per step, chains of",
    "  hundreds of steps drift by radians) the first-order chain covariance passes outliers: at 13 outliers",
    "  PCM removed none on seed 0 (3 correct closures dropped instead) and 2 of 13 on seed 1.",
    "* **What is left open**: a robust start that gets the relative placement of robots right from one or two",
    "  closures per robot pair (e.g. consistency over cycles through three or more robots, or keeping",
    "  several hypotheses per pair), which neither pairwise PCM nor GNC-TLS provides here.",
    "* **Not run**: 1500 poses per robot and 3D teams (each 5000-pose configuration took 2-25 minutes on this",
    "  shared 2-core machine); every table above is 10 robots x 500 poses in 2D, two seeds.",
]


def _cpu() -> str:
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return "unknown CPU"
    info = dict(line.split(":", 1) for line in out.splitlines() if ":" in line)
    get = lambda k: info.get(k, "?").strip()  # noqa: E731
    return f"{get('Model name')}, {get('CPU(s)')} CPUs (lscpu)"


def run(args) -> list[dict]:
    rows = []
    for seed in args.seeds:
        ds = mm.robot_team_dataset(args.robots, args.poses, intra_closures=args.intra, inter_closures=args.inter,
                                   dim=args.dim, seed=seed, **_noise(args))
        rop = ds.robot_of_pose
        t = time.perf_counter()
        opt = mm.centralized_optimum(ds.graph)
        base = dict(seed=seed, poses=ds.num_poses, edges=ds.num_edges, inter=int(ds.inter_robot.sum()),
                    intra=int((ds.edge_kind == 1).sum()))
        rows.append({**base, "method": "optimum (no outliers)", "seconds": time.perf_counter() - t,
                     "ate_gt": mm.trajectory_accuracy(opt.poses, ds.ground_truth).ate, "ate_opt": 0.0})
        rate = args.rate / 100
        if args.rate_of == "inter":  # outliers / (inter-robot closures + outliers) = rate, in add_outliers' terms
            count = round(rate * base["inter"] / (1 - rate))
            rate = count / (base["inter"] + base["intra"] + count)
        c = mm.add_outlier_loop_closures(ds.graph, rate, reference=ds.ground_truth, seed=seed,
                                         robot_of_pose=rop, inter_robot_only=True)
        print(f"seed {seed}: {ds.num_poses} poses, {ds.num_edges} edges, {c.num_outliers} outliers", flush=True)
        for name in args.methods:
            t = time.perf_counter()
            if METHODS[name] is None:
                pcm = mm.pcm_filter(c.graph, rop)
                s = mm.outlier_scores(pcm.keep, c.outlier)
                rows.append({**base, "method": name, "outliers": c.num_outliers, "seconds": time.perf_counter() - t,
                             "precision": s.precision, "recall": s.recall, "rejected": s.rejected,
                             "correct_rejected": int((~pcm.keep & ~c.outlier).sum()), "pcm_rejected": pcm.num_rejected,
                             "pcm_correct": int((~pcm.keep & ~c.outlier).sum()), "pairs": len(pcm.pairs),
                             "pairs_le2": int((pcm.closures <= 2).sum())})
                print(f"  {name}: {rows[-1]}", flush=True)
                continue
            try:
                res = _gtsam(c.graph, ds.ground_truth) if name == "gtsam" else mm.solve(
                    c.graph, rop, iterations=args.iterations, ground_truth=ds.ground_truth, **METHODS[name])
            except Exception as exc:  # a failed method is a result, not the end of the run
                error = f"{type(exc).__name__}: {exc}"
                rows.append({**base, "method": name, "outliers": c.num_outliers, "error": error})
                print(f"  {name}: {exc}", flush=True)
                continue
            seconds = time.perf_counter() - t
            row = {**base, "method": name, "outliers": c.num_outliers, "seconds": seconds,
                   "iterations": res.iterations, "ate_gt": res.accuracy.ate,
                   "ate_opt": mm.trajectory_accuracy(res.poses, opt.poses).ate}
            if res.inliers is not None:
                s = mm.outlier_scores(res.inliers, c.outlier)
                row.update(precision=s.precision, recall=s.recall, rejected=s.rejected,
                           correct_rejected=int((~res.inliers & ~c.outlier).sum()))
            if res.prefiltered is not None:
                row.update(pcm_rejected=int(res.prefiltered.sum()),
                           pcm_correct=int((res.prefiltered & ~c.outlier).sum()),
                           pcm_seconds=res.stats["pcm_seconds"], components=res.stats["pcm_components"])
            rows.append(row)
            print(f"  {name}: {json.dumps({k: v for k, v in row.items() if k not in base})}", flush=True)
    return rows


def _gtsam(graph, ground_truth):
    """GTSAM's GNC from the chordal start, as a ``SolveResult``-like record of what ``run`` reads."""
    from types import SimpleNamespace

    from mmpgo_jax._experiments.gtsam_lm import gtsam_gnc

    ref = gtsam_gnc(graph, mm.initialize(graph, "chordal"), scale=mm.chi2_scale(graph.dim))
    poses = mm.Poses(R=ref.poses.R, t=ref.poses.t)
    return SimpleNamespace(poses=poses, inliers=ref.weights >= 0.5, iterations=None, prefiltered=None,
                           accuracy=mm.trajectory_accuracy(poses, ground_truth))


def _noise(args) -> dict:
    """The generator's noise keywords that differ from its defaults (the Cube's)."""
    out = {}
    if getattr(args, "sigma_t", None) is not None:
        out["sigma_t"] = args.sigma_t
    if getattr(args, "sigma_R", None) is not None:
        out["sigma_R"] = args.sigma_R
    return out


def _fmt(v, spec):
    return "—" if v is None else format(v, spec)


def _section(rows, meta) -> list[str]:
    cols = [("seed", "d"), ("method", "s"), ("outliers", "d"), ("pcm_rejected", "d"), ("pcm_correct", "d"),
            ("components", "d"), ("rejected", "d"), ("precision", ".3f"), ("recall", ".3f"),
            ("correct_rejected", "d"), ("pairs", "d"), ("pairs_le2", "d"), ("ate_opt", ".4g"), ("ate_gt", ".4g"),
            ("iterations", "d"), ("seconds", ".1f")]
    heads = ["seed", "method", "outliers", "PCM rejected", "of which correct", "components after PCM",
             "rejected (all)", "precision", "recall", "correct rejected", "robot pairs with closures",
             "of which with <= 2", "ATE vs optimum", "ATE vs truth",
             "iterations", "s"]
    noise = meta.get("noise") or {}
    noise_text = ", ".join(f"{k}={v:g}" for k, v in noise.items())
    lines = [
        f"## {meta['robots']} robots x {meta['poses']} poses, {meta['dim']}D, {meta['inter']} inter-robot closures, "
        + (noise_text if noise_text else "Cube noise")
        + f", {meta['rate']:g} % outliers "
        + ("(of the inter-robot closures)" if meta.get("rate_of") == "inter" else "(of all loop closures)"),
        "",
        f"Command: `{meta['command']}`  ",
        f"Run {meta['started']}, load average at start {meta['load']} (shared 2-core machine), {meta['cpu']}, "
        f"JAX {jax.__version__}.",
        "",
        f"Graph: `mm.robot_team_dataset({meta['robots']}, {meta['poses']}, intra_closures={meta['intra']}, "
        f"inter_closures={meta['inter']}, dim={meta['dim']}, seed=s"
        + "".join(f", {k}={v:g}" for k, v in noise.items()) + ")` (default noise: the Cube's, sigma_t 0.02, "
        "sigma_R 0.02 pi rad per 1-cell step); outliers: "
        + (f"`add_outlier_loop_closures(graph, rate, inter_robot_only=True, seed=s)` with the rate that makes "
           f"{meta['rate']:g} % of the inter-robot loop closures outliers. "
           if meta.get("rate_of") == "inter" else
           f"`add_outlier_loop_closures(graph, {meta['rate'] / 100}, inter_robot_only=True, seed=s)` "
           f"({meta['rate']:g} % of all loop closures, intra-robot ones included, are outliers). ")
        + "Method definitions: the module docstring of benchmarks/robust_teams.py. Precision / recall: of "
        "the edges marked rejected in `result.inliers` (PCM's removals included) against the planted "
        "outliers. ATE: RMSE of the positions after rigid alignment.",
        "",
        "Graphs: " + "; ".join(f"seed {r['seed']}: {r['poses']} poses, {r['edges']} edges ({r['intra']} intra-robot "
                               f"and {r['inter']} inter-robot loop closures)"
                               for r in rows if r["method"].startswith("optimum")) + ".",
        "",
        "| " + " | ".join(heads) + " |",
        "|" + "---|" * len(heads),
    ]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['seed']} | {r['method']} | {r.get('outliers', '—')} | failed: {r['error']} |"
                         + " |" * (len(heads) - 4))
            continue
        cells = [_fmt(r.get(k), f) if f != "s" else str(r.get(k)) for k, f in cols]
        lines.append("| " + " | ".join(cells) + " |")
    return [*lines, ""]


def write(args, runs) -> None:
    lines = ["# Robust solves of robot teams (long odometry chains, wrong inter-robot loop closures)", ""]
    for run_ in runs:
        lines += _section(run_["rows"], run_["meta"])
    lines += [*FINDINGS, ""]
    # the sections other scripts append (benchmarks/robust_distributed_start.py) are kept as they are
    write_record(args.out, "\n".join(lines))


def _load(raw: Path) -> list[dict]:
    if not raw.is_file():
        return []
    saved = json.loads(raw.read_text())
    return saved.get("runs", [saved])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default=str(Path(__file__).with_name("robust_teams.md")))
    p.add_argument("--robots", type=int, default=10)
    p.add_argument("--poses", type=int, default=500)
    p.add_argument("--intra", type=int, default=5)
    p.add_argument("--inter", type=int, default=30)
    p.add_argument("--dim", type=int, default=2)
    p.add_argument("--rate", type=float, default=30)
    p.add_argument("--rate-of", choices=("all", "inter"), default="all",
                   help="--rate is the outliers' share of all loop closures (add_outliers' definition, default) or "
                        "of the inter-robot ones")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    p.add_argument("--iterations", type=int, default=1000)
    p.add_argument("--sigma-t", type=float, default=None, help="odometry and closure noise (default the Cube's)")
    p.add_argument("--sigma-R", type=float, default=None, help="rotation noise in rad (default 0.02 pi)")
    p.add_argument("--methods", nargs="+", choices=list(METHODS), default=["tls", "pcm", "pcm+tls"])
    p.add_argument("--render", action="store_true", help="rewrite the Markdown from the saved rows")
    args = p.parse_args(argv)
    raw = Path(args.out).with_suffix(".json")
    runs = _load(raw)
    if not args.render:
        given = sys.argv[1:] if argv is None else argv
        meta = dict(command="python " + " ".join(["benchmarks/robust_teams.py", *given]),
                    started=time.strftime("%Y-%m-%d %H:%M"), load=" ".join(f"{x:.2f}" for x in os.getloadavg()),
                    cpu=_cpu(), robots=args.robots, poses=args.poses, intra=args.intra, inter=args.inter,
                    dim=args.dim, rate=args.rate, noise=_noise(args), rate_of=args.rate_of)
        rows = run(args)
        # a rerun replaces the run of its configuration
        same = ("robots", "poses", "intra", "inter", "dim", "rate", "noise", "rate_of")
        runs = [r for r in runs if any(r["meta"].get(k) != meta[k] for k in same)] + [dict(meta=meta, rows=rows)]
        with atomic_write(raw) as fh:
            json.dump(dict(runs=runs), fh, indent=1)
    write(args, runs)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
