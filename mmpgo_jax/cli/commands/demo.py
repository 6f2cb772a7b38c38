"""``mmpgo demo``: the parser of the command; the demo itself is :mod:`mmpgo_jax.cli.demo`,
imported when the command runs."""

from __future__ import annotations

from ..options import INT_MAX, ITERATIONS, ROBOTS, add_common, int_in


def register(sub) -> None:
    p = sub.add_parser("demo", help="run AMM-PGO on a generated Cube dataset (no download needed)")
    p.add_argument("--out-dir", default="mmpgo-demo", help="folder for the plots and results (default ./mmpgo-demo)")
    p.add_argument("--poses", type=int_in(2, INT_MAX), default=1000,
                   help="poses of the generated Cube dataset, >= 2 (default 1000)")
    p.add_argument("--robots", "-A", type=ROBOTS, default=10, help="robots, 1 .. --poses (default 10)")
    p.add_argument("--iterations", "-n", type=ITERATIONS, default=300, help="outer iterations, >= 0 (default 300)")
    p.add_argument("--seed", type=int_in(0), default=0, help="seed of the generated dataset, >= 0 (default 0)")
    p.add_argument("--no-progress", action="store_true")
    add_common(p)
    p.set_defaults(run=run)


def run(args) -> int:
    from ..demo import run_demo

    return run_demo(args)
