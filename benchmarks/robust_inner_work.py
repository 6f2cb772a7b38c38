"""How hard the robots' inner solver works per outer iteration, least squares against robust kernels.

    nice python benchmarks/robust_inner_work.py [--file city10000] [--iterations 300] [--every 25]
        [--losses l2 tls huber cauchy huber-fixed] [--out benchmarks/robust_inner_work.md]

Same graph as ``robust_cost.py``: 10 contiguous robots, 30 % wrong inter-robot loop closures (seed 1),
the distributed robust start's poses (its weights are not held here: every kernel starts from
rho'(s) at X^0, so that the kernels differ only in their weights). AMM, default settings. The outer
iterations run one compiled ``step`` at a time from Python (this is a measurement, not the solver's
loop); every ``--every`` iterations the robots' first-pass subproblem of that iteration (from AMM's
momentum point, as ``_amm_update`` solves it) is solved again by ``subproblem_steps`` to read its
trust-region steps and CG iterations. Reported per kernel: the mean over the sampled iterations of
the largest count over robots (under ``vmap`` every robot waits for the slowest) and of the mean
count. ``huber-fixed``: Huber with its weights set once at X^0 (``update_every`` larger than the run).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import equinox as eqx
import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from robust_cost import corrupted  # noqa: E402

import mmpgo_jax as mm  # noqa: E402
from mmpgo_jax._init.start import initialize_with_weights  # noqa: E402
from mmpgo_jax._io.atomic import atomic_write  # noqa: E402
from mmpgo_jax._mm.outer import MMConfig, MMProblem, momentum_point, start_state, step  # noqa: E402
from mmpgo_jax._mm.subproblem import subproblem_steps  # noqa: E402
from mmpgo_jax.cli.bench import machine_info  # noqa: E402

LOSSES = ("l2", "tls", "huber", "cauchy", "huber-fixed")


def kernel(name: str, iterations: int):
    if name == "l2":
        return None
    if name == "huber-fixed":
        return mm.RobustLoss("huber", update_every=iterations + 1)
    return mm.RobustLoss(name)


def first_pass_work(problem: MMProblem, config: MMConfig, st):
    """(steps, cg) per robot of the subproblem AMM's first pass solves in the next iteration."""
    gamma, pre, _ = problem.weighting.operators(problem, config, st.weighting)
    _, Y, gY, start = momentum_point(problem, st)
    free_axis = None if problem.free is None else 0
    # with the robot's share as scale, as the outer loop solves it (the decrease rule included)
    out = jax.vmap(lambda G, P, x0, c, g, free, share: subproblem_steps(G, P, x0, c, g, config.subproblem, free,
                                                                          share),
                   in_axes=(0, 0, 0, 0, 0, free_axis, 0))(gamma, pre, start, Y, gY, problem.free, st.share)
    return out.steps, out.cg


def measure(graph, rop, X0, name: str, iterations: int, every: int) -> dict:
    part = mm.partition(graph, rop)
    Xs = part.scatter(X0)
    config = MMConfig()
    problem = MMProblem.build(part, config=config, poses=Xs, loss=kernel(name, iterations))
    st, _ = start_state(problem, Xs, config)
    advance = eqx.filter_jit(lambda p, s: step(p, config, s)[0])
    work = eqx.filter_jit(lambda p, s: first_pass_work(p, config, s))
    steps_max, steps_mean, cg_max, cg_mean = [], [], [], []
    t0 = time.perf_counter()
    for k in range(1, iterations + 1):
        st = advance(problem, st)
        if k % every == 0:
            steps, cg = (np.asarray(x) for x in work(problem, st))
            steps_max.append(steps.max())
            steps_mean.append(steps.mean())
            cg_max.append(cg.max())
            cg_mean.append(cg.mean())
    f = 2.0 * float(jnp.sum(st.share))
    return dict(loss=name, steps_max=np.mean(steps_max), steps_mean=np.mean(steps_mean), cg_max=np.mean(cg_max),
                cg_mean=np.mean(cg_mean), samples=len(cg_max), f=f, seconds=time.perf_counter() - t0)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--file", default="city10000")
    p.add_argument("--iterations", type=int, default=300)
    p.add_argument("--every", type=int, default=25)
    p.add_argument("--losses", nargs="+", choices=LOSSES, default=list(LOSSES))
    p.add_argument("--out", default=str(Path(__file__).with_name("robust_inner_work.md")))
    args = p.parse_args(argv)
    info = machine_info()
    graph, rop, count = corrupted(args.file)
    X0, _ = initialize_with_weights(graph, "distributed-robust", robots=rop)
    lines = ["# Inner-solver work per outer iteration: least squares against robust kernels", "",
             f"Command: `nice python benchmarks/robust_inner_work.py --file {args.file} --iterations "
             f"{args.iterations} --every {args.every} --losses {' '.join(args.losses)}`  ",
             f"Run {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, load average "
             f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}, {info['cpu']}, JAX {info['jax']}; "
             f"{graph.num_edges} edges ({count} wrong inter-robot closures added). Definitions: the script's "
             "docstring.",
             "", "| loss | trust-region steps: max over robots / mean | CG iterations: max over robots / mean "
             "| samples | f at the end |", "|---|---|---|---|---|"]
    for name in args.losses:
        r = measure(graph, rop, X0, name, args.iterations, args.every)
        lines.append(f"| {name} | {r['steps_max']:.2f} / {r['steps_mean']:.2f} | {r['cg_max']:.1f} / "
                     f"{r['cg_mean']:.1f} | {r['samples']} | {r['f']:.10g} |")
        print(lines[-1], flush=True)
    with atomic_write(args.out) as fh:
        fh.write("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
