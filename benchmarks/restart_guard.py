"""AMM's momentum guard (``MMConfig.rise_limit``) on randomised graphs unlike the benchmark files.

    python benchmarks/restart_guard.py [--seeds 6 156] [--min-poses 40] [--iterations 300]
        [--out benchmarks/restart_guard.md]

Each seed writes a random pose graph as a g2o file and reads it back (the user's path, SE-Sync's
kappa / tau from the information matrices): 2D or 3D, 2-90 poses on a random walk, odometry and
random loop closures (some stored j -> i, sometimes a duplicated edge, sometimes one gross
outlier), measurement noise 0-0.5 rad, and information matrices of one kind per graph: isotropic,
anisotropic diagonals or full random SPD matrices whose entries span up to nine orders of
magnitude, or rotation-heavy ones; 1-10 contiguous robots. The start poses of the file are the
truth perturbed. On every graph of at least ``--min-poses`` poses, least squares from the default
start, ``--iterations`` iterations without early stop: AMM with the adaptive restart and no guard
(``rise_limit=inf``, the default before the guard), the default (the guard on), and Algorithm 2's
monotone test (``restart="paper"``). Reported: each run's f at the end, the largest f of its
history against its start, and the guard's resets; rows where the guard changed f by more than
1e-6 (relative), and counts.
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
from scipy.spatial.transform import Rotation  # noqa: E402

import mmpgo_jax as mm  # noqa: E402
from mmpgo_jax._io.atomic import atomic_write  # noqa: E402
from mmpgo_jax.cli.bench import command_line, machine_info  # noqa: E402

KINDS = ("iso", "aniso", "full", "rot-heavy")


def _rotation(d, rng, scale):
    if d == 2:
        a = rng.normal() * scale
        return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return Rotation.from_rotvec(rng.normal(size=3) * scale).as_matrix()


def random_walk(d, n, rng) -> list:
    """n poses (R, t) from the identity, each step a random turn (0.3 rad per axis) and a unit step."""
    truth = [(np.eye(d), np.zeros(d))]
    for _ in range(n - 1):
        R0, t0 = truth[-1]
        truth.append((R0 @ _rotation(d, rng, 0.3), t0 + R0 @ rng.normal(size=d)))
    return truth


def _information(d, rng, kind):
    k = 3 if d == 2 else 6
    if kind == "iso":
        return np.eye(k) * 10 ** rng.uniform(-3, 6)
    if kind == "aniso":
        return np.diag(10 ** rng.uniform(-3, 6, size=k))
    if kind == "full":
        M = rng.normal(size=(k, k))
        return (M @ M.T + 1e-3 * np.eye(k)) * 10 ** rng.uniform(-2, 4)
    v = np.ones(k)
    v[2 if d == 2 else slice(3, None)] = 1e6  # rotation-heavy
    return np.diag(v)


def _write_g2o(path, d, poses, edges):
    def pose(R, t):
        if d == 2:
            return f"{t[0]:.17g} {t[1]:.17g} {np.arctan2(R[1, 0], R[0, 0]):.17g}"
        return " ".join(f"{x:.17g}" for x in [*t, *Rotation.from_matrix(R).as_quat()])

    lines = [f"{'VERTEX_SE2' if d == 2 else 'VERTEX_SE3:QUAT'} {i} {pose(R, t)}" for i, (R, t) in enumerate(poses)]
    for i, j, R, t, info in edges:
        upper = " ".join(f"{info[a, b]:.17g}" for a in range(len(info)) for b in range(a, len(info)))
        lines.append(f"{'EDGE_SE2' if d == 2 else 'EDGE_SE3:QUAT'} {i} {j} {pose(R, t)} {upper}")
    Path(path).write_text("\n".join(lines) + "\n")


def random_graph(seed: int, path) -> dict:
    """Write seed's graph to ``path`` (g2o); returns its description."""
    rng = np.random.default_rng(seed)
    d = int(rng.choice([2, 3]))
    n = int(rng.choice([2, 3, 5, 12, 40, 90]))
    kind = str(rng.choice(KINDS))
    noise = float(rng.choice([0.0, 0.01, 0.1, 0.5]))
    truth = random_walk(d, n, rng)

    def measured(i, j):
        (Ri, ti), (Rj, tj) = truth[i], truth[j]
        return Ri.T @ Rj @ _rotation(d, rng, noise), Ri.T @ (tj - ti) + noise * rng.normal(size=d)

    edges = [(i, i + 1, *measured(i, i + 1), _information(d, rng, kind)) for i in range(n - 1)]
    for _ in range(int(rng.integers(0, n + 1))):
        i, j = (int(v) for v in rng.choice(n, 2, replace=False))
        if rng.random() < 0.3:  # stored the other way round
            i, j = max(i, j), min(i, j)
        edges.append((i, j, *measured(i, j), _information(d, rng, kind)))
    if rng.random() < 0.3 and edges:  # a duplicated measurement
        edges.append(edges[int(rng.integers(len(edges)))])
    if rng.random() < 0.2:  # one gross outlier
        i, j = (int(v) for v in rng.choice(n, 2, replace=False))
        edges.append((i, j, _rotation(d, rng, 3.0), 20 * rng.normal(size=d), _information(d, rng, kind)))
    start = [(R @ _rotation(d, rng, 0.2), t + rng.normal(size=d)) for R, t in truth]
    _write_g2o(path, d, start, edges)
    robots = int(np.random.default_rng(10_000 + seed).choice([1, 2, 3, 5, 10]))
    return dict(seed=seed, d=d, poses=n, edges=len(edges), information=kind, noise=noise, robots=min(robots, n))


RUNS = {"no guard": dict(solver=mm.AMM(rise_limit=float("inf"))), "guard (default)": {},
        "paper": dict(restart="paper")}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", nargs=2, type=int, default=[6, 156], metavar=("FIRST", "STOP"))
    p.add_argument("--min-poses", type=int, default=40)
    p.add_argument("--iterations", type=int, default=300)
    p.add_argument("--out", default=str(Path(__file__).with_name("restart_guard.md")))
    args = p.parse_args(argv)
    info = machine_info()
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for seed in range(*args.seeds):
            path = Path(folder) / f"graph{seed}.g2o"
            row = random_graph(seed, path)
            if row["poses"] < args.min_poses:
                continue
            graph = mm.read_g2o(path).graph
            for name, options in RUNS.items():
                r = mm.solve(graph, row["robots"], iterations=args.iterations, stop_when_stalled=False, **options)
                f = np.asarray(r.history.f)
                row[name] = dict(f=float(f[-1]), rise=float(f.max() / f[0]), resets=r.stats.get("momentum_resets"))
            rows.append(row)
            print(json.dumps(row), flush=True)
    lines = ["# AMM's momentum guard on randomised graphs", "",
             f"Command: `{command_line()}`; {started}, {info['cpu']}, {info['usable_cores']} cores, JAX "
             f"{info['jax']}. Definitions: the script's docstring.", "",
             "| seed | dim | poses | information | noise | robots | f, no guard | f, guard | f, paper | "
             "largest f / start: no guard, guard | guard resets |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    changed = 0
    for row in rows:
        a, g, q = (row[k]["f"] for k in RUNS)
        if abs(g - a) > 1e-6 * abs(a):
            changed += 1
            lines.append(f"| {row['seed']} | {row['d']} | {row['poses']} | {row['information']} | {row['noise']} | "
                         f"{row['robots']} | {a:.6g} | {g:.6g} | {q:.6g} | {row['no guard']['rise']:.2f}, "
                         f"{row['guard (default)']['rise']:.2f} | {row['guard (default)']['resets']} |")
    above = [sum(row[k]["rise"] > 1 + 1e-9 for row in rows) for k in RUNS]
    lines += ["", f"{len(rows)} graphs; the guard changed f on {changed} (rows above). Runs whose f rose above "
              f"its start: {above[0]} without the guard, {above[1]} with it, {above[2]} with Algorithm 2's test."]
    with atomic_write(args.out) as fh:
        fh.write("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
