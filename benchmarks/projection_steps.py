"""The AMM momentum point's projection onto SO(3): Newton steps taken and time, stopping on
convergence against a fixed six steps.

For each 3D file (10 robots, AMM from the chordal start, float64): the momentum point's rotations
Y = R_k + 0.9 (R_k - R_{k-1}) at outer iterations k (the iterates of two runs of ``solve``, k - 1
and k iterations), then

* the steps the scaled Newton polar iteration takes before no entry changes by more than
  sqrt(eps) (``nearest_rotations(..., method="fast")``, the solver's projection),
* its distance to the SVD projection, and that of six fixed steps,
* microseconds per projection of all robots' rotations, both ways, inside one compiled loop.

    python benchmarks/projection_steps.py [--files sphere2500 torus3D garage] [--at 2 10 50 200 800]
"""

from __future__ import annotations

import argparse
import datetime
import os
import time

import jax
import jax.numpy as jnp

import mmpgo_jax as mg
from mmpgo_jax._core.geometry import _newton_polar_3d, project_to_so


def in_loop_us(fn, M, reps: int = 100) -> float:
    """Microseconds per call of ``fn(M)`` repeated in one compiled loop (best of three)."""
    loop = jax.jit(lambda M: jax.lax.fori_loop(0, reps, lambda _, X: X + 1e-30 * jnp.sum(fn(X)), M))
    jax.block_until_ready(loop(M))
    best = float("inf")
    for _ in range(3):
        t = time.perf_counter()
        jax.block_until_ready(loop(M))
        best = min(best, time.perf_counter() - t)
    return 1e6 * best / reps


def steps_taken(M) -> int:
    """Newton steps before convergence (the same test as ``_newton_polar_3d``)."""
    settled, X = jnp.sqrt(jnp.finfo(M.dtype).eps), M
    for k in range(1, 7):
        X_next = _newton_polar_3d(X, max_iterations=1, settled=0.0)
        if float(jnp.max(jnp.abs(X_next - X))) <= settled:
            return k
        X = X_next
    return 6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--files", nargs="*", default=["sphere2500", "torus3D", "garage"])
    ap.add_argument("--at", nargs="*", type=int, default=[2, 10, 50, 200, 800])
    args = ap.parse_args()
    mg.enable_float64()
    print(f"# {datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC, load average {os.getloadavg()[0]:.2f}\n")
    print("| file | k | max |R_k - R_k-1| | steps | adaptive − SVD | six steps − SVD | adaptive µs | six steps µs |")
    print("|---|---|---|---|---|---|---|---|")
    fixed = jax.jit(lambda M: _newton_polar_3d(M, settled=0.0))
    adaptive = jax.jit(_newton_polar_3d)
    for name in args.files:
        graph = mg.read_g2o(mg.find_benchmark(name)).graph
        for k in args.at:
            before = mg.solve(graph, 10, method="amm", iterations=k - 1).poses.R
            now = mg.solve(graph, 10, method="amm", iterations=k).poses.R
            Y = jnp.moveaxis(now + 0.9 * (now - before), (-2, -1), (0, 1))  # entries first, as the solver
            svd = jnp.moveaxis(project_to_so(jnp.moveaxis(Y, (0, 1), (-2, -1))), (-2, -1), (0, 1))
            print(f"| {name} | {k} | {float(jnp.max(jnp.abs(now - before))):.1e} | {steps_taken(Y)} | "
                  f"{float(jnp.max(jnp.abs(adaptive(Y) - svd))):.1e} | {float(jnp.max(jnp.abs(fixed(Y) - svd))):.1e} | "
                  f"{in_loop_us(adaptive, Y):.0f} | {in_loop_us(fixed, Y):.0f} |", flush=True)


if __name__ == "__main__":
    main()
