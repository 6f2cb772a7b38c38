"""Where the time of one outer iteration goes: the compiled pieces timed alone, and the inner
solver's work counted (trust-region steps and CG iterations per robot subproblem).

For each file (10 robots, the default config, after 50 AMM iterations from the chordal start):
microseconds per call of each piece, ``vmap``-ped over the robots and jitted on its own -- the
Gamma^alpha product, the block-Jacobi and chain preconditioners, the tangent projection, the
retraction (rotation projection), the gradient/share evaluation with its neighbour gather, one
whole MM subproblem solve -- and the mean and maximum over robots of TR steps and CG iterations in
one MM subproblem solve (under ``vmap`` every robot waits for the slowest, so the maximum is what
the iteration pays), with the two-level preconditioner and with block-Jacobi; then ms per AMM
iteration of the whole compiled loop with each.

    python benchmarks/profile_step.py --out benchmarks/profile_step.md
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

import mmpgo_jax as mg
from mmpgo_jax._mm import two_level
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
    X0 = part.scatter(warm.poses)
    problem = mg.MMProblem.build(part, config.xi, poses=X0)
    state, _ = start_state(problem, X0, config)
    X = jax.vmap(to_soa)(state.X)
    V = jax.vmap(to_soa)(jnp.asarray(np.random.default_rng(0).standard_normal(state.X.shape)))
    vm = jax.vmap
    out = {
        "gamma": per_call_us(lambda G, v: vm(lambda g, x: g(x))(G, v), problem.gamma_soa, V),
        "block-jacobi": per_call_us(lambda P, v: vm(lambda p, x: p(x))(P, v), problem.block_jacobi_soa, V),
        "two-level": per_call_us(lambda P, v: vm(lambda p, x: p(x))(P, v), problem.two_level, V),
        "chain": per_call_us(lambda P, v: vm(lambda p, x: preconditioner_to_soa(p)(x))(P, v), problem.chain, V),
        "tangent": per_call_us(lambda y, v: vm(_tangent_soa)(y, v), X, V),
        "retraction": per_call_us(lambda y, v: vm(_retract_soa)(y, 1e-3 * v), X, V),
        "gradient": per_call_us(lambda Y: _gradients(problem, Y)[0], state.X),
        "aggregate": problem.two_level.aggregate,
    }
    for kind, pre in (("two-level", problem.two_level), ("block-jacobi", problem.block_jacobi_soa)):
        sub = dataclasses.replace(config.subproblem, preconditioner=kind)
        solve = vm(lambda G, P, x, g, sub=sub: subproblem_steps(G, P, x, x, g, sub))
        out[f"subproblem {kind}"] = per_call_us(solve, problem.gamma_soa, pre, state.X, state.grad, repeat=50)
        st = jax.jit(solve)(problem.gamma_soa, pre, state.X, state.grad)
        steps, cg = np.asarray(st.steps), np.asarray(st.cg)
        out[f"steps {kind}"] = f"{steps.mean():.1f} / {steps.max()}"
        out[f"cg {kind}"] = f"{cg.mean():.0f} / {cg.max()}"
        res = mg.solve(graph, 10, method="amm", iterations=300, subproblem=sub)
        out[f"amm {kind}"] = res.ms_per_iteration
    # the aggregate size: AMM ms/iteration with 8 and 32 slots per aggregate instead of the default
    for size in (8, 32):
        default, two_level.aggregate_size = two_level.aggregate_size, lambda n, k, size=size: size
        try:
            out[f"amm b={size}"] = mg.solve(graph, 10, method="amm", iterations=300).ms_per_iteration
        finally:
            two_level.aggregate_size = default
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
            f"| {name} | {p['poses_per_robot']} | {p['aggregate']} | {p['gamma']:.0f} | {p['block-jacobi']:.0f} | "
            f"{p['two-level']:.0f} | {p['chain']:.0f} | {p['tangent']:.0f} | {p['retraction']:.0f} | "
            f"{p['gradient']:.0f} | " + " | ".join(
                f"{p[f'subproblem {k}']:.0f} | {p[f'steps {k}']} | {p[f'cg {k}']} | {p[f'amm {k}']:.2f}"
                for k in ("two-level", "block-jacobi")) + f" | {p['amm b=8']:.2f} / {p['amm b=32']:.2f} |\n")
        print(rows[-1], end="", flush=True)
    text = (f"# Profile of one outer iteration (10 robots, default config)\n\n"
            f"Command: `python benchmarks/profile_step.py`; {datetime.date.today()}, "
            f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, load average "
            f"{os.getloadavg()[0]:.2f} at the end. Microseconds per call of each compiled piece, all robots "
            "at once (best of 3). TR steps / CG iterations: mean / max over robots of one MM subproblem "
            "solve after 50 AMM iterations.\n\n"
            "| file | poses/robot | slots/aggregate | Γ µs | block-Jacobi µs | two-level µs | chain µs | "
            "tangent µs | retraction µs | gradient+gather µs | "
            "two-level: MM subproblem µs | TR steps mean/max | CG its mean/max | AMM ms/it | "
            "block-Jacobi: MM subproblem µs | TR steps mean/max | CG its mean/max | AMM ms/it | "
            "two-level AMM ms/it, 8 / 32 slots per aggregate |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n" + "".join(rows))
    if args.out:
        with open(args.out, "w") as fh:
            fh.write(text)
    else:
        print(text)


if __name__ == "__main__":
    main()
