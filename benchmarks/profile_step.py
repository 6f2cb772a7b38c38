"""Where the time of one outer iteration goes: the compiled pieces timed inside a compiled loop,
the inner solver's work counted, and whole AMM iterations on one and on two CPU devices.

For each file (10 robots, the default config, the centralized chordal start): microseconds per
call of each piece, ``vmap``-ped over the robots and repeated inside one compiled ``fori_loop``
(no Python dispatch in the figure) -- the Gamma^alpha product, the Riemannian Hessian product (Gamma,
the Weingarten term and the tangent projection), the preconditioner's block-Jacobi level and the
whole two-level preconditioner, the retraction, the gradient/share evaluation with its neighbour
gather -- then one whole MM subproblem solve with its trust-region steps and CG iterations (mean /
max over robots: under ``vmap`` every robot waits for the slowest, so the maximum is what the
iteration pays) with the two-level preconditioner and with its block-Jacobi level alone; then ms per
AMM iteration of ``solve`` (one CPU device) and of ``solve_sharded`` over two CPU devices (what
``mmpgo solve`` runs from ``AUTO_THREAD_POSES`` poses on, one device per core), next to the authors' C++ figure.

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

jax.config.update("jax_num_cpu_devices", 2)  # before JAX starts its backend: the two-device runs

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from records import write_record  # noqa: E402  (this folder, on the path as a script's)

import mmpgo_jax as mg  # noqa: E402
from mmpgo_jax._mm.majorization import soa_bmm, soa_T, sym0, tangent_soa, to_soa  # noqa: E402
from mmpgo_jax._mm.outer import start_state  # noqa: E402
from mmpgo_jax._mm.subproblem import _retract_soa, subproblem_steps  # noqa: E402
from mmpgo_jax._mm.weighting import gradients  # noqa: E402
from mmpgo_jax._solve.devices import AUTO_THREAD_POSES  # noqa: E402
from mmpgo_jax.sharding import solve_sharded  # noqa: E402

FILES = ["MITb", "intel", "M3500", "city10000", "sphere2500", "torus3D", "garage"]
AUTHORS_AMM_MS = {"MITb": 0.73, "intel": 1.39, "M3500": 3.53, "city10000": 12.5, "sphere2500": 4.9, "torus3D": 9.4,
                  "garage": 6.0}


def in_loop_us(fn, *args, reps: int = 100) -> float:
    """Microseconds per call of ``fn(*args)`` repeated in one compiled loop (the first argument is
    perturbed by the previous result, so no call can be hoisted), minus the loop's own cost."""
    def body(_, carry):
        out = fn(*carry)
        s = sum(jnp.sum(o) for o in jax.tree.leaves(out))
        return (carry[0] + 1e-30 * s, *carry[1:])

    def empty(_, carry):
        return (carry[0] + 1e-30 * jnp.sum(carry[0]), *carry[1:])

    def best(loop_body):
        f = jax.jit(lambda *a: jax.lax.fori_loop(0, reps, loop_body, a))
        jax.block_until_ready(f(*args))
        times = []
        for _ in range(3):
            t = time.perf_counter()
            jax.block_until_ready(f(*args))
            times.append(time.perf_counter() - t)
        return min(times)

    return 1e6 * max(best(body) - best(empty), 0.0) / reps


def amm_ms(graph, sharded: bool, **kw) -> float:
    run = (lambda: solve_sharded(graph, 10, devices=2, method="amm", iterations=300, **kw)) if sharded else (
        lambda: mg.solve(graph, 10, method="amm", iterations=300, **kw))
    return min(run().ms_per_iteration for _ in range(2))


def profile(name: str) -> dict:
    graph = mg.read_g2o(mg.find_benchmark(name)).graph
    part = mg.partition(graph, 10)
    X0 = part.scatter(mg.initialize(graph, "chordal"))
    config = mg.MMConfig()
    problem = mg.MMProblem.build(part, config.xi, poses=X0)
    state, _ = start_state(problem, X0, config)
    vm = jax.vmap
    Y, egrad = vm(to_soa)(state.X), vm(to_soa)(state.grad)
    W = vm(lambda y, e: sym0(soa_bmm(soa_T(y[:, 1:]), e[:, 1:])))(Y, egrad)
    V = vm(tangent_soa)(Y, jnp.asarray(np.random.default_rng(0).standard_normal(Y.shape)))
    G, P = problem.gamma_soa, problem.newton

    def hess(g, y, w, v):
        return tangent_soa(y, g(v) - jnp.concatenate([jnp.zeros_like(v[:, :1]), soa_bmm(v[:, 1:], w)], axis=1))

    out = {
        "gamma": in_loop_us(lambda v, G: vm(lambda g, x: g(x))(G, v), V, G),
        "hessian": in_loop_us(lambda v, G, Y, W: vm(hess)(G, Y, W, v), V, G, Y, W),
        "block-jacobi": in_loop_us(lambda v, P, Y, W: vm(lambda p, y, w, x: p.without_coarse().at(y, w)(x))(P, Y, W, v),
                                   V, P, Y, W),
        "two-level": in_loop_us(lambda v, P, Y, W: vm(lambda p, y, w, x: p.at(y, w)(x))(P, Y, W, v), V, P, Y, W),
        "retraction": in_loop_us(lambda v, Y: vm(_retract_soa)(Y, 1e-3 * v), V, Y),
        "gradient": in_loop_us(lambda X, problem: gradients(problem, X)[0], state.X, problem, reps=30),
        "aggregate": P.aggregate,
        "poses_per_robot": part.max_poses,
    }
    for kind in ("two-level", "block-jacobi"):
        sub = dataclasses.replace(config.subproblem, preconditioner=kind)
        pre = problem.preconditioner(mg.MMConfig(subproblem=sub))
        solve = vm(lambda G, P, x, g, sub=sub: subproblem_steps(G, P, x, x, g, sub))
        out[f"subproblem {kind}"] = in_loop_us(lambda x, g, G, P, solve=solve: solve(G, P, x, g).Y, state.X, state.grad,
                                              G, pre, reps=10)
        st = jax.jit(solve)(G, pre, state.X, state.grad)
        steps, cg = np.asarray(st.steps), np.asarray(st.cg)
        out[f"steps {kind}"] = f"{steps.mean():.1f} / {steps.max()}"
        out[f"cg {kind}"] = f"{cg.mean():.1f} / {cg.max()}"
        out[f"amm {kind}"] = amm_ms(graph, False, subproblem=sub)
    out["amm 2 devices"] = amm_ms(graph, True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--files", nargs="*", default=FILES)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    mg.enable_float64()
    load = os.getloadavg()[0]
    rows = []
    for name in args.files:
        p = profile(name)
        authors = AUTHORS_AMM_MS.get(name)
        ratio = f"{p['amm 2 devices'] / authors:.2f} / {p['amm two-level'] / authors:.2f}" if authors else "-"
        rows.append(
            f"| {name} | {p['poses_per_robot']} | {p['aggregate']} | {p['gamma']:.0f} | {p['hessian']:.0f} | "
            f"{p['block-jacobi']:.0f} | {p['two-level']:.0f} | {p['retraction']:.0f} | {p['gradient']:.0f} | "
            + " | ".join(f"{p[f'subproblem {k}']:.0f} | {p[f'steps {k}']} | {p[f'cg {k}']} | {p[f'amm {k}']:.2f}"
                         for k in ("two-level", "block-jacobi"))
            + f" | {p['amm 2 devices']:.2f} | {authors if authors else '-'} | {ratio} |\n")
        print(rows[-1], end="", flush=True)
    text = (f"# Profile of one outer iteration (10 robots, default config)\n\n"
            f"Command: `python benchmarks/profile_step.py --out benchmarks/profile_step.md`; {datetime.date.today()}, "
            f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, load average {load:.2f} at the "
            f"start, {os.getloadavg()[0]:.2f} at the end. Pieces: microseconds per call inside a compiled loop, all "
            "robots at once (best of 3), at the chordal start. TR steps / CG iterations: mean / max over robots of "
            "one MM subproblem solve there. AMM ms/it: best of two 300-iteration runs of `solve` (one CPU device) "
            "and of `solve_sharded` over two CPU devices (what `mmpgo solve` runs from "
            f"{AUTO_THREAD_POSES} poses on).\n\n"
            "| file | poses/robot | slots/aggregate | Γ µs | Hessian µs | block-Jacobi µs | two-level µs | "
            "retraction µs | gradient+gather µs | "
            "two-level: MM subproblem µs | TR steps mean/max | CG its mean/max | AMM ms/it | "
            "block-Jacobi: MM subproblem µs | TR steps mean/max | CG its mean/max | AMM ms/it | "
            "AMM ms/it, 2 CPU devices | authors' AMM ms/it | ours / authors' (2 devices / 1) |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n" + "".join(rows))
    if args.out:
        write_record(args.out, text)  # the file's later sections kept
    else:
        print(text)


if __name__ == "__main__":
    main()
