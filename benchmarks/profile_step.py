"""Where the time of one outer iteration goes: the compiled pieces timed alone, and the inner
solver's work counted (trust-region steps and CG iterations per robot subproblem).

For each file (10 robots, the default config, after 50 AMM iterations from the chordal start):
microseconds per call of each piece, ``vmap``-ped over the robots and jitted on its own -- the
Gamma^alpha product, the block-Jacobi and chain preconditioners, the tangent projection, the
retraction (rotation projection), the gradient/share evaluation with its neighbour gather, one
whole MM subproblem solve -- and the mean and maximum over robots of TR steps and CG iterations in
one MM subproblem solve (under ``vmap`` every robot waits for the slowest, so the maximum is what
the iteration pays). Then ms per AMM iteration of the whole compiled loop.

    python benchmarks/profile_step.py --out benchmarks/profile_step.md
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

import mmpgo_jax as mg
from mmpgo_jax._mm.majorization import preconditioner_to_soa, to_soa
from mmpgo_jax._mm.outer import _gradients, start_state
from mmpgo_jax._mm.subproblem import _retract_soa, _tangent_soa, subproblem_steps

FILES = ["MITb", "intel", "M3500", "city10000", "sphere2500", "torus3D", "garage"]


def per_call_us(fn, *args, repeat: int = 200) -> float:
    fn = jax.jit(fn)
    jax.block_until_ready(fn(*args))
    best = np.inf
    for _ in range(3):
        t = time.perf_counter()
        for _ in range(repeat):
            out = fn(*args)
        jax.block_until_ready(out)
        best = min(best, (time.perf_counter() - t) / repeat)
    return 1e6 * best


def profile(name: str) -> dict:
    graph = mg.read_g2o(mg.find_benchmark(name)).graph
    warm = mg.solve(graph, 10, method="amm", iterations=50)
    part = warm.partition
    config = warm.config
    problem = mg.MMProblem.build(part, config.xi)
    state, _ = start_state(problem, part.scatter(warm.poses), config)
    X = jax.vmap(to_soa)(state.X)
    V = jax.vmap(to_soa)(jnp.asarray(np.random.default_rng(0).standard_normal(state.X.shape)))
    vm = jax.vmap
    out = {
        "gamma": per_call_us(lambda G, v: vm(lambda g, x: g(x))(G, v), problem.gamma_soa, V),
        "block-jacobi": per_call_us(lambda P, v: vm(lambda p, x: p(x))(P, v), problem.block_jacobi_soa, V),
        "chain": per_call_us(lambda P, v: vm(lambda p, x: preconditioner_to_soa(p)(x))(P, v), problem.chain, V),
        "tangent": per_call_us(lambda y, v: vm(_tangent_soa)(y, v), X, V),
        "retraction": per_call_us(lambda y, v: vm(_retract_soa)(y, 1e-3 * v), X, V),
        "gradient": per_call_us(lambda Y: _gradients(problem, Y)[0], state.X),
    }
    sub = config.subproblem
    solve = vm(lambda G, P, x, g: subproblem_steps(G, P, x, x, g, sub))
    out["subproblem"] = per_call_us(solve, problem.gamma_soa, problem.block_jacobi_soa, state.X, state.grad, repeat=50)
    st = jax.jit(solve)(problem.gamma_soa, problem.block_jacobi_soa, state.X, state.grad)
    steps, cg = np.asarray(st.steps), np.asarray(st.cg)
    out.update(steps_mean=steps.mean(), steps_max=steps.max(), cg_mean=cg.mean(), cg_max=cg.max())
    res = mg.solve(graph, 10, method="amm", iterations=300)
    out["amm_ms"] = res.ms_per_iteration
    out["poses_per_robot"] = part.max_poses
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--files", nargs="*", default=FILES)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    mg.enable_float64()
    rows = []
    for name in args.files:
        p = profile(name)
        rows.append(
            f"| {name} | {p['poses_per_robot']} | {p['gamma']:.0f} | {p['block-jacobi']:.0f} | {p['chain']:.0f} | "
            f"{p['tangent']:.0f} | {p['retraction']:.0f} | {p['gradient']:.0f} | {p['subproblem']:.0f} | "
            f"{p['steps_mean']:.1f} / {p['steps_max']} | {p['cg_mean']:.0f} / {p['cg_max']} | {p['amm_ms']:.2f} |\n")
        print(rows[-1], end="", flush=True)
    text = (f"# Profile of one outer iteration (10 robots, default config)\n\n"
            f"Command: `python benchmarks/profile_step.py`; {datetime.date.today()}, "
            f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, load average "
            f"{os.getloadavg()[0]:.2f} at the end. Microseconds per call of each compiled piece, all robots "
            "at once (best of 3). TR steps / CG iterations: mean / max over robots of one MM subproblem "
            "solve after 50 AMM iterations.\n\n"
            "| file | poses/robot | Γ µs | block-Jacobi µs | chain µs | tangent µs | retraction µs | "
            "gradient+gather µs | MM subproblem µs | TR steps mean/max | CG its mean/max | AMM ms/it |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|---|\n" + "".join(rows))
    if args.out:
        with open(args.out, "w") as fh:
            fh.write(text)
    else:
        print(text)


if __name__ == "__main__":
    main()
