"""``mmpgo sweep``: MM / AMM over several robot counts (and files) in one compiled computation per
shape, with the split of ``--robots-from`` (blocks, metis, random); the command-line face of
:func:`mmpgo_jax.sweep`."""

from __future__ import annotations

import argparse
import time

from . import CLIError, int_in


def add_sweep_parser(sub, *, add_common, robots_type, iterations_type) -> None:
    from .robots import FILE_HELP, add_robots_from

    p = sub.add_parser("sweep", help="MM / AMM over several robot counts in one compiled computation per shape")
    p.add_argument("files", nargs="+", metavar="FILE", help=FILE_HELP + " (one or more, same dimension)")
    p.add_argument("--robots", "-A", type=robots_type, nargs="+", default=[5, 10, 50],
                   help="robot counts, each >= 1 and at most the poses of every file (default 5 10 50)")
    add_robots_from(p, ("blocks", "metis", "random"))
    p.add_argument("--methods", nargs="+", choices=("mm", "amm"), default=["mm", "amm"],
                   help="methods (default mm amm)")
    p.add_argument("--iterations", "-n", type=iterations_type, default=1000, help="outer iterations (default 1000)")
    p.add_argument("--restart", choices=("adaptive", "paper", "average"), default="adaptive",
                   help="AMM restart rule (default adaptive)")
    p.add_argument("--fstar", choices=("registry", "centralized", "none"), default="registry",
                   help="reference optimum of the gaps: the registry's certified f* where the file is a known "
                        "benchmark, else the centralized optimum (registry, default); always the centralized "
                        "optimum (centralized); no gaps (none)")
    p.add_argument("--seed", type=int_in(0), default=0, help="seed of --robots-from random (default 0)")
    p.add_argument("--out", help="write the per-iteration table as CSV (graph, robots, method, iteration, f, gaps)")
    p.add_argument("--configs", help="write the per-configuration table as CSV (time, memory, final f and gap)")
    p.add_argument("--no-progress", action="store_true", help="do not print a line per compiled batch")
    add_common(p)


def run_sweep(args: argparse.Namespace, resolve_file) -> int:
    from .._experiments.sweep import reference_optimum, sweep
    from .._io.atomic import atomic_group
    from .._io.datasets import benchmark_info
    from .robots import read_input

    graphs, fstar = {}, {}
    for name in args.files:
        path = resolve_file(name, args.data)
        graph = read_input(path, args).graph
        key = path.stem if path.stem not in graphs else str(path)
        too_many = [a for a in args.robots if a > graph.num_poses]
        if too_many:
            raise CLIError(f"{path}: --robots {too_many[0]} exceeds its {graph.num_poses} poses")
        graphs[key] = graph
        info = benchmark_info(path.name)
        known = info is not None and info.num_poses == graph.num_poses and info.fstar_reference is not None
        if args.fstar == "registry" and known:
            fstar[key] = info.fstar_reference.value
        elif args.fstar != "none":
            print(f"{key}: computing the centralized optimum f* for the gaps ...", flush=True)
            fstar[key] = reference_optimum(graph)
    say = None if args.no_progress else (lambda line: print(line, flush=True))
    t = time.perf_counter()
    res = sweep(graphs, sorted(set(args.robots)), tuple(args.methods), args.iterations, restart=args.restart,
                fstar=fstar or None, split=args.robots_from or "blocks", seed=args.seed, progress=say)
    print(f"{len(res.configs)} configurations in {time.perf_counter() - t:.1f} s "
          f"({args.robots_from or 'blocks'} split)")
    _print_table(res.configs)
    with atomic_group():  # every output, or none
        if args.out:
            res.to_csv(args.out)
        if args.configs:
            res.configs_to_csv(args.configs)
    return 0


def _print_table(configs) -> None:
    print("| file | method | robots | f final | (f - f*)/f* | ms/iteration |")
    print("|---|---|---|---|---|---|")
    for row in configs:
        gap = "" if row.get("relative_gap") is None else f"{row['relative_gap']:.3e}"
        print(f"| {row['graph']} | {row['method'].upper()} | {row['robots']} | {row['f']:.10g} | {gap} | "
              f"{row['ms_per_iteration']:.2f} |")
