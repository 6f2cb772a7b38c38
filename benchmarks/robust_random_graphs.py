"""Robust solves of randomised graphs whose noise is what their information matrices state.

    python benchmarks/robust_random_graphs.py [--seeds 0 60] [--noise se-sync|information] [--json OUT.json]
        [--out OUT.md]

Each seed writes a random pose graph as a g2o file and reads it back (the user's path, SE-Sync's kappa
/ tau from the information matrices): 2D or 3D, 30-250 poses on a random walk, odometry and loop
closures (mostly between poses less than 3 units apart), every measurement's noise drawn from the
covariance its information matrix states (the g2o meaning: translation and rotation-angle errors with
covariance I^-1; rms per axis sigma_t 0.01-0.2, sigma_R 0.002-0.03 rad, isotropic or, for 30 % of the
graphs, each axis scaled by up to 10^0.5 either way); 1, 2, 3 or 5 contiguous robots; then 0, 10, 30
or 50 % of the loop closures replaced by wrong ones (``add_outlier_loop_closures``, between robots
when there are several). Two pipelines with ``loss="tls"``: the default and ``distributed=True``.
Reported per run: precision and recall of the rejected edges against the planted outliers, correct
closures rejected, ATE against the outlier-free least-squares optimum in % of its extent, and the TLS
objective sum min(s, c^2) at the result and at that optimum (the result's lower than the optimum's
means the objective itself prefers the result's classification). ``--noise information``: the scale
``chi2_scale(d, noise="information")`` (the quantile for noise that is what the information states;
in 2D 4.04 instead of the default 3.37) passed as ``loss_scale``.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from records import write_record  # noqa: E402  (this folder, on the path as a script's)
from restart_guard import _write_g2o, random_walk  # noqa: E402  (the same g2o writer and rotation noise)
from scipy.spatial.transform import Rotation  # noqa: E402

import mmpgo_jax as mm  # noqa: E402
from mmpgo_jax._io.atomic import atomic_write  # noqa: E402
from mmpgo_jax.cli.bench import command_line, machine_info  # noqa: E402

PIPELINES = {"default": {}, "distributed": dict(distributed=True)}


def random_graph(seed: int, path) -> dict:
    """Write seed's graph to ``path`` (g2o, vertices at the truth); returns its description."""
    rng = np.random.default_rng(seed)
    d = int(rng.choice([2, 3]))
    n = int(rng.choice([30, 60, 120, 250]))
    sig_t = float(rng.choice([0.01, 0.05, 0.2]))
    sig_R = float(rng.choice([0.002, 0.01, 0.03]))
    aniso = bool(rng.random() < 0.3)
    rot_axes = 1 if d == 2 else 3

    def noise_model():
        st = np.full(d, sig_t) * (10 ** rng.uniform(-0.5, 0.5, d) if aniso else 1)
        sr = np.full(rot_axes, sig_R) * (10 ** rng.uniform(-0.5, 0.5, rot_axes) if aniso else 1)
        return np.diag(np.r_[1 / st**2, 1 / sr**2]), st, sr

    truth = random_walk(d, n, rng)

    def measured(i, j):
        (Ri, ti), (Rj, tj) = truth[i], truth[j]
        info, st, sr = noise_model()
        if d == 2:
            a = rng.normal() * sr[0]
            noise = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        else:
            noise = Rotation.from_rotvec(rng.normal(size=3) * sr).as_matrix()
        return (i, j, Ri.T @ Rj @ noise, Ri.T @ (tj - ti) + st * rng.normal(size=d), info)

    edges = [measured(i, i + 1) for i in range(n - 1)]
    pos = np.array([t for _, t in truth])
    for _ in range(int(rng.integers(n // 10, n // 3 + 2))):
        i = int(rng.integers(n))
        near = np.flatnonzero((np.linalg.norm(pos - pos[i], axis=1) < 3.0) & (np.abs(np.arange(n) - i) > 2))
        j = int(rng.choice(near)) if len(near) and rng.random() < 0.7 else int(rng.integers(n))
        if abs(i - j) > 1:
            edges.append(measured(min(i, j), max(i, j)))
    _write_g2o(path, d, truth, edges)
    return dict(seed=seed, d=d, poses=n, sigma_t=sig_t, sigma_R=sig_R, anisotropic=aniso,
                loop_closures=len(edges) - (n - 1), robots=int(rng.choice([1, 2, 3, 5])),
                rate=float(rng.choice([0.0, 0.1, 0.3, 0.5])))


def run_seed(seed: int, folder: Path, noise: str = "se-sync") -> dict:
    path = folder / f"graph{seed}.g2o"
    row = random_graph(seed, path)
    graph = mm.read_g2o(path).graph
    opt = mm.centralized_optimum(graph).poses
    rop = mm.contiguous_robots(graph.num_poses, row["robots"])
    several = row["robots"] > 1
    c = mm.add_outlier_loop_closures(graph, row["rate"], reference=opt, seed=seed,
                                     robot_of_pose=rop if several else None, inter_robot_only=several)
    pts = np.asarray(opt.t)
    extent = float((pts.max(0) - pts.min(0)).max())
    row["outliers"] = int(c.outlier.sum())
    outlier = np.asarray(c.outlier, bool)
    scale = {} if noise == "se-sync" else dict(loss_scale=mm.chi2_scale(graph.dim, noise=noise))
    for name, options in PIPELINES.items():
        t = time.perf_counter()
        r = mm.solve(c.graph, rop, loss="tls", **scale, **options)
        seconds = time.perf_counter() - t
        c2 = float(r.loss.scale) ** 2
        scores = mm.outlier_scores(r.inliers, c.outlier)
        rejected = ~np.asarray(r.inliers, bool)
        row[name] = dict(
            precision=float(scores.precision), recall=float(scores.recall),
            correct_rejected=int((rejected & ~outlier).sum()),
            ate_percent=float(100 * mm.trajectory_accuracy(r.poses, opt).ate / extent),
            f_tls=float(np.minimum(np.asarray(mm.edge_costs(c.graph, r.poses)), c2).sum()),
            f_tls_at_optimum=float(np.minimum(np.asarray(mm.edge_costs(c.graph, opt)), c2).sum()),
            scale=float(r.loss.scale), seconds=seconds)
    print(json.dumps(row), flush=True)
    return row


def _meets(x) -> bool:
    return x["precision"] >= 0.95 and x["recall"] >= 0.99 and x["ate_percent"] <= 1.0


def report(rows, header: str) -> str:
    lines = [header, "", "| seed | dim | poses | robots | rate | outliers | pipeline | precision | recall | "
             "correct rejected | ATE % of extent | TLS objective: result / optimum |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        for name in PIPELINES:
            x = row[name]
            lines.append(f"| {row['seed']} | {row['d']} | {row['poses']} | {row['robots']} | {row['rate']:g} | "
                         f"{row['outliers']} | {name} | {x['precision']:.3f} | {x['recall']:.3f} | "
                         f"{x['correct_rejected']} | {x['ate_percent']:.2g} | {x['f_tls']:.1f} / "
                         f"{x['f_tls_at_optimum']:.1f} |")
    lines.append("")
    for name in PIPELINES:
        for d in (2, 3):
            sub = [row[name] for row in rows if row["d"] == d]
            lines.append(f"{name}, {d}D: {sum(_meets(x) for x in sub)} of {len(sub)} graphs with precision >= 0.95, "
                         f"recall >= 0.99 and ATE <= 1 % of the extent; {sum(x['correct_rejected'] for x in sub)} "
                         f"correct closures rejected, {sum(x['recall'] < 1 for x in sub)} graphs with an outlier "
                         "accepted.")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", nargs=2, type=int, default=[0, 60], metavar=("FIRST", "STOP"))
    p.add_argument("--noise", choices=("se-sync", "information"), default="se-sync",
                   help="the noise model of the TLS scale (chi2_scale's noise; default: the library's default)")
    p.add_argument("--json", help="write the rows as JSON too")
    p.add_argument("--out", default=None, help="markdown report (default: print it)")
    args = p.parse_args(argv)
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    with tempfile.TemporaryDirectory() as folder:
        rows = [run_seed(seed, Path(folder), args.noise) for seed in range(*args.seeds)]
    info = machine_info()
    header = (f"Command: `{command_line()}`; {started}, {info['cpu']}, {info['usable_cores']} cores, JAX "
              f"{info['jax']}. Definitions: the script's docstring.")
    text = report(rows, header)
    if args.json:
        with atomic_write(args.json) as fh:
            fh.write(json.dumps(rows, indent=1))
    if args.out:
        write_record(args.out, text)  # the file's later sections kept
    else:
        print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
