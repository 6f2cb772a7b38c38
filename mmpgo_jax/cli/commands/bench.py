"""``mmpgo bench``: the parser of the command; the benchmark itself is :mod:`mmpgo_jax.cli.bench`,
imported when the command runs."""

from __future__ import annotations

from ..devices import add_threads_option, configure_cpu_devices
from ..options import INT_MAX, ROBOTS, add_common, int_in
from ..robots import add_robots_from


def register(sub) -> None:
    p = sub.add_parser("bench", help="reproduce the paper's Tables I/II on the available datasets")
    p.add_argument("--quick", action="store_true", help="a small run for CI: one small dataset, few iterations")
    p.add_argument("--datasets", nargs="*", help="benchmark names (default: all available)")
    p.add_argument("--iterations", "-n", type=int_in(1, INT_MAX), default=1000,
                   help="outer iterations, >= 1 (default 1000)")
    p.add_argument("--robots", "-A", type=ROBOTS, default=10, help="robots, >= 1 (default 10)")
    add_robots_from(p, ("blocks", "metis", "random"))
    from ..._solve.methods import METHOD_NAMES  # names only: no solver is imported here

    extra = [m for m in METHOD_NAMES if m not in ("mm", "amm", "dgs")]  # those three are the paper's rows already
    p.add_argument("--extra-methods", nargs="+", choices=extra, metavar="METHOD", default=None,
                   help=f"more rows beside the paper's MM / AMM / DGS runs, from the same start: {', '.join(extra)} "
                        "(no paper or code columns)")
    add_threads_option(p)
    p.add_argument("--out-dir", default="bench-results", help="folder for the Markdown, CSV and JSON tables")
    p.add_argument("--no-progress", action="store_true")
    add_common(p)
    p.set_defaults(run=run, configure=configure_cpu_devices)


def run(args) -> int:
    from ..bench import run_bench

    return run_bench(args)
