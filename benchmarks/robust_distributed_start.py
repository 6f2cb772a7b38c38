"""The distributed robust start on robot teams with wrong inter-robot loop closures.

    nice python benchmarks/robust_distributed_start.py [--robots 10] [--poses 500] [--intra 5]
        [--inter 30] [--rate 30] [--sigma-R 0.015707963] [--seeds 0 1] [--iterations 1000]
        [--methods start tls dr-tls dr-l2-tls] [--out benchmarks/robust_distributed_start.json]

Each seed builds ``mm.robot_team_dataset`` and adds wrong inter-robot closures as
benchmarks/robust_teams.py does with ``--rate-of inter`` (``--rate`` percent of the inter-robot
closures are outliers). Rows:

* ``start gnc-chordal`` / ``start distributed-robust`` (and ``... tree``, ``... sigma=a,b``): the
  start alone (``initialize``): its ATE, and for the robust starts the inter-robot closures it
  rejects (precision / recall against the planted outliers);
* ``tls``: ``solve(loss="tls")`` from its default start (gnc-chordal), AMM, the team's robots;
* ``dr-tls``: ``solve(loss="tls", start=X0)`` with X0 the distributed robust start (the solver's TLS
  weights start at rho'(s) of X0);
* ``dr-held`` (``drs-held`` from the ``sigma=0.25,3`` start): ``solve(loss="tls", start=X0,
  start_weights=w)`` with the start's weights w held as the first stage (until the weighted objective
  stalls), then TLS's own weights: what ``solve(loss="tls", start="distributed-robust")`` does;
* ``dr-held-gnc``: the same with ``gnc=GNCConfig()`` (GNC-TLS stages after the held stage);
* ``dr-l2-tls``: least squares on the edges the start kept (its weights 1), from X0, then
  ``solve(loss="tls")`` on the whole graph from that result: a stand-in for a solver that would start
  from the start's weights (``solve`` has no argument for initial weights).

ATE: RMSE of positions after rigid alignment, against the ground truth and the outlier-free optimum
(``centralized_optimum``). Precision / recall of the solves: of ``result.inliers`` == False.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import mmpgo_jax as mm  # noqa: E402
from mmpgo_jax._init.robust_distributed import distributed_robust_initialization  # noqa: E402
from mmpgo_jax._init.start import initialize  # noqa: E402


def _poses(p):
    return mm.Poses(np.asarray(p.R), np.asarray(p.t))


def _scores(rejected, outlier, inter):
    s = mm.outlier_scores(~rejected, outlier)
    return dict(precision=s.precision, recall=s.recall, rejected=int(rejected.sum()),
                correct_rejected=int((rejected & ~outlier & inter).sum()))


def run(args) -> list[dict]:
    rows = []
    kw = {} if args.sigma_R is None else dict(sigma_R=args.sigma_R)
    for seed in args.seeds:
        ds = mm.robot_team_dataset(args.robots, args.poses, intra_closures=args.intra, inter_closures=args.inter,
                                   dim=2, seed=seed, **kw)
        rop = ds.robot_of_pose
        opt = mm.centralized_optimum(ds.graph).poses
        n_inter, n_intra = int(ds.inter_robot.sum()), int((ds.edge_kind == 1).sum())
        rate = args.rate / 100
        count = round(rate * n_inter / (1 - rate))
        c = mm.add_outlier_loop_closures(ds.graph, count / (n_inter + n_intra + count), reference=ds.ground_truth,
                                         seed=seed, robot_of_pose=rop, inter_robot_only=True)
        g = c.graph
        inter = rop[np.asarray(g.i)] != rop[np.asarray(g.j)]
        base = dict(seed=seed, poses=ds.num_poses, outliers=c.num_outliers, inter=int(inter.sum()))

        def ate(p, truth=ds.ground_truth, opt=opt):
            p = _poses(p)
            return dict(ate_gt=mm.trajectory_accuracy(p, truth).ate, ate_opt=mm.trajectory_accuracy(p, opt).ate)

        starts = {}
        for name in args.methods:
            if name != "start":
                continue
            t = time.perf_counter()
            X = initialize(g, "gnc-chordal", host=True)
            rows.append({**base, "method": "start gnc-chordal", "seconds": time.perf_counter() - t, **ate(X)})
            print(rows[-1], flush=True)
            for label, opts in [("distributed-robust", {}), ("distributed-robust tree", dict(frames="tree")),
                                ("distributed-robust sigma=0.25,3", dict(map_sigma=(0.25, 3.0)))]:
                t = time.perf_counter()
                st = distributed_robust_initialization(g, rop, **opts)
                sec = time.perf_counter() - t
                starts[label] = st
                rows.append({**base, "method": "start " + label, "seconds": sec, **ate(st.poses),
                             **_scores(inter & ~st.accepted, c.outlier, inter),
                             "unplaced": len(st.unplaced_robots), "unverified": int(st.unverified.sum())})
                print(rows[-1], flush=True)
        for name in args.methods:
            if name == "start":
                continue
            t = time.perf_counter()
            if name.startswith("dr"):
                label = "distributed-robust sigma=0.25,3" if name.startswith("drs") else "distributed-robust"
                st = starts.get(label) or distributed_robust_initialization(
                    g, rop, **(dict(map_sigma=(0.25, 3.0)) if name.startswith("drs") else {}))
                starts[label] = st
                X0 = _poses(st.poses)
            common = dict(iterations=args.iterations, ground_truth=ds.ground_truth)
            if name == "tls":
                res = mm.solve(g, rop, loss="tls", **common)
            elif name in ("dr-tls", "drs-tls"):
                res = mm.solve(g, rop, loss="tls", start=X0, **common)
            elif name == "dr-gnc":
                res = mm.solve(g, rop, loss="tls", start=X0, distributed=True, **common)
            elif name in ("dr-held", "drs-held"):  # the start's weights held as the first stage, then TLS
                res = mm.solve(g, rop, loss="tls", start=X0, start_weights=st.weights, **common)
            elif name == "dr-held-gnc":  # the same, then GNC-TLS stages in the solver
                res = mm.solve(g, rop, loss="tls", start=X0, start_weights=st.weights, gnc=mm.GNCConfig(), **common)
            else:  # dr-l2-tls, drs-l2-tls
                kept = st.weights > 0.5
                first = mm.solve(g.select_edges(kept), rop, start=X0, **common)
                res = mm.solve(g, rop, loss="tls", start=first.poses, **common)
            sec = time.perf_counter() - t
            row = {**base, "method": name, "seconds": sec, "iterations": res.iterations, **ate(res.poses),
                   **_scores(~res.inliers, c.outlier, inter)}
            rows.append(row)
            print(row, flush=True)
    return rows


def markdown(rows) -> str:
    cols = [("seed", "d"), ("method", "s"), ("outliers", "d"), ("rejected", "d"), ("precision", ".3f"),
            ("recall", ".3f"), ("correct_rejected", "d"), ("unplaced", "d"), ("unverified", "d"),
            ("ate_opt", ".4g"), ("ate_gt", ".4g"), ("iterations", "d"), ("seconds", ".1f")]
    heads = ["seed", "method", "outliers", "rejected", "precision", "recall", "correct rejected",
             "robots not placed", "accepted unverified", "ATE vs optimum", "ATE vs truth", "iterations", "s"]
    out = ["| " + " | ".join(heads) + " |", "|" + "---|" * len(heads)]
    for r in rows:
        out.append("| " + " | ".join("—" if r.get(k) is None else (str(r[k]) if f == "s" else format(r[k], f))
                                     for k, f in cols) + " |")
    return "\n".join(out)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robots", type=int, default=10)
    p.add_argument("--poses", type=int, default=500)
    p.add_argument("--intra", type=int, default=5)
    p.add_argument("--inter", type=int, default=30)
    p.add_argument("--rate", type=float, default=30, help="percent of the inter-robot closures that are outliers")
    p.add_argument("--sigma-R", type=float, default=None)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    p.add_argument("--iterations", type=int, default=1000)
    p.add_argument("--methods", nargs="+", default=["start", "tls", "dr-tls", "dr-l2-tls"],
                   choices=["start", "tls", "dr-tls", "dr-l2-tls", "dr-gnc", "drs-tls", "drs-l2-tls", "dr-held",
                            "drs-held", "dr-held-gnc"])
    p.add_argument("--out", default=str(Path(__file__).with_name("robust_distributed_start.json")))
    args = p.parse_args(argv)
    meta = dict(vars(args), started=time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
                load=" ".join(f"{x:.2f}" for x in os.getloadavg()))
    rows = run(args)
    saved = json.loads(Path(args.out).read_text()) if Path(args.out).is_file() else []
    saved.append(dict(meta=meta, rows=rows))
    Path(args.out).write_text(json.dumps(saved, indent=1))
    print(markdown(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
