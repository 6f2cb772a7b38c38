"""``mmpgo sweep``: MM / AMM (``--methods``: any names of the methods registry,
:mod:`mmpgo_jax._solve.methods`, e.g. rbcd, rbcd++, dgs) over several robot counts (and files) in one
compiled computation per method and shape, with the split of ``--robots-from`` (blocks, metis,
random); the command-line face of :func:`mmpgo_jax.sweep`. ``--losses`` adds robust kernels as an
axis and ``--outlier-rates`` runs each file again with seeded wrong loop closures added
(:func:`mmpgo_jax._experiments.outliers.add_outliers`), scored by precision and recall."""

from __future__ import annotations

import argparse
import math
import time

from ..options import INT_MAX, ROBOTS, add_common, add_pcm_options, int_in, pcm_prefilter
from ..robots import FILE_HELP, add_robots_from


def percent(text: str) -> float:
    """argparse ``type``: an outlier rate in percent, 0 <= value < 100."""
    try:
        value = float(text)
    except (TypeError, ValueError):
        value = math.nan
    if not math.isfinite(value) or not 0.0 <= value < 100.0:
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0 and < 100, got {text!r}")
    return value


percent.__name__ = "number"


def register(sub) -> None:
    p = sub.add_parser("sweep", help="MM / AMM (or baselines: RBCD, RBCD++, DGS) over several robot counts in one "
                                     "compiled computation per method and shape")
    p.add_argument("files", nargs="+", metavar="FILE", help=FILE_HELP + " (one or more, same dimension)")
    p.add_argument("--robots", "-A", type=ROBOTS, nargs="+", default=[5, 10, 50],
                   help="robot counts, each >= 1 and at most the poses of every file (default 5 10 50)")
    add_robots_from(p, ("blocks", "metis", "random"))
    from ..._solve.methods import METHOD_NAMES  # names only: no solver is imported here

    p.add_argument("--methods", nargs="+", choices=METHOD_NAMES, metavar="METHOD", default=["mm", "amm"],
                   help="methods (default mm amm): mm, amm, rbcd, rbcd++, rbcd[++]-uniform, rbcd[++]-round-robin, "
                        "rbcd[++]-parallel, dgs (as mmpgo solve --method)")
    p.add_argument("--iterations", "-n", type=int_in(1, INT_MAX), default=1000, help="outer iterations (default 1000)")
    p.add_argument("--restart", choices=("adaptive", "paper", "average"), default=None,
                   help="AMM restart rule (default adaptive); needs amm among --methods")
    p.add_argument("--fstar", choices=("registry", "centralized", "none"), default="registry",
                   help="reference optimum of the gaps: the registry's certified f* where the file is a known "
                        "benchmark, else the centralized optimum (registry, default); always the centralized "
                        "optimum (centralized); no gaps (none)")
    p.add_argument("--seed", type=int_in(0), default=0, help="seed of --robots-from random (default 0)")
    from ..._mm.robust import LOSSES

    p.add_argument("--losses", nargs="+", choices=LOSSES, metavar="KERNEL", default=None,
                   help=f"robust kernels to sweep ({', '.join(LOSSES)}; default: least squares only), all in the "
                        "same compilation, each from the GNC start (gnc-chordal); odometry edges keep weight 1")
    p.add_argument("--outlier-rates", nargs="+", type=percent, metavar="PCT", default=None,
                   help="run each file at these outlier rates: wrong loop closures added (uniform random pose pairs, "
                        "random rotation, translation within the map's extent), PCT %% of all loop closures "
                        "after the addition; 0 keeps the file as it is. Reports precision and recall of the "
                        "rejected edges; gaps to f* are then left out")
    p.add_argument("--outlier-seed", type=int_in(0), default=1, help="seed of the added outliers (default 1)")
    add_pcm_options(p, "before the start and the solve, per file and robot count (as mmpgo solve --pcm); the "
                       "table counts them; gaps to f* are then left out")
    p.add_argument("--out", help="write the per-iteration table as CSV (graph, robots, method, iteration, f, gaps)")
    p.add_argument("--configs", help="write the per-configuration table as CSV (time, memory, final f and gap)")
    p.add_argument("--no-progress", action="store_true", help="do not print a line per compiled batch")
    add_common(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from ... import reference_optimum, sweep
    from ..._io.atomic import atomic_group
    from ..._io.datasets import benchmark_info
    from ..errors import CLIError
    from ..inputs import resolve_file
    from ..robots import read_input

    methods = tuple(dict.fromkeys(args.methods))
    _check_methods(args, methods)
    rates = None if args.outlier_rates is None else list(dict.fromkeys(args.outlier_rates))
    robust = args.losses is not None and any(k != "l2" for k in args.losses)
    gaps = args.fstar != "none" and not robust and not any(rates or []) and not args.pcm
    if args.fstar != "none" and not gaps:
        print("robust losses / outliers / PCM: f is 2 F_rho or of another edge set, no gaps to the least-squares f*")
    graphs, fstar = {}, {}
    for name in args.files:
        path = resolve_file(name, args.data)
        graph = read_input(path, args).graph
        key = path.stem if path.stem not in graphs else str(path)
        too_many = [a for a in args.robots if a > graph.num_poses]
        if too_many:
            raise CLIError(f"{path}: --robots {too_many[0]} exceeds its {graph.num_poses} poses")
        if rates is not None:
            graphs.update(_with_outliers(key, graph, rates, args.outlier_seed))
            continue
        graphs[key] = graph
        info = benchmark_info(path.name)
        known = info is not None and info.num_poses == graph.num_poses and info.fstar_reference is not None
        if args.fstar == "registry" and known and gaps:
            fstar[key] = info.fstar_reference.value
        elif gaps:
            print(f"{key}: computing the centralized optimum f* for the gaps ...", flush=True)
            fstar[key] = reference_optimum(graph)
    say = None if args.no_progress else (lambda line: print(line, flush=True))
    t = time.perf_counter()
    res = sweep(graphs, sorted(set(args.robots)), methods, args.iterations, restart=args.restart,
                fstar=fstar or None, split=args.robots_from or "blocks", seed=args.seed, progress=say,
                loss=list(dict.fromkeys(args.losses)) if args.losses else None, prefilter=pcm_prefilter(args))
    print(f"{len(res.configs)} configurations in {time.perf_counter() - t:.1f} s "
          f"({args.robots_from or 'blocks'} split)")
    _print_table(res.configs, robust=args.losses is not None or rates is not None or args.pcm, pcm=args.pcm)
    with atomic_group():  # every output, or none
        if args.out:
            res.to_csv(args.out)
        if args.configs:
            res.configs_to_csv(args.configs)
    return 0


def _check_methods(args, methods: tuple) -> None:
    """Before any file is read: ``--restart`` without amm, robust ``--losses`` with a least-squares
    method and a method that cannot run (dgs before it is a solver) refused in one line."""
    from ..._solve.methods import MAJORIZATION, solver_for
    from ..errors import CLIError

    pcm_prefilter(args)  # --pcm-confidence without --pcm: one line
    if args.restart is not None and "amm" not in methods:
        raise CLIError(f"--restart applies to amm, which is not among --methods {' '.join(methods)}")
    robust = [k for k in args.losses or () if k != "l2"]
    others = [m for m in methods if m not in MAJORIZATION]
    if robust and others:
        raise CLIError(f"--losses {robust[0]}: {others[0]} minimises the least-squares F only (robust losses run "
                       "with mm or amm)")
    for m in others:
        solver_for(m)  # ValueError (one line) where the method is not available


def _with_outliers(key: str, graph, rates, seed: int) -> dict:
    """name -> CorruptedGraph of ``graph`` at each rate (percent); the map's extent is read from the
    chordal initialization of the clean graph (no ground truth in a g2o file)."""
    from ..._experiments.outliers import add_outliers
    from ..._init.start import initialize

    reference = initialize(graph, "chordal")
    return {f"{key}@{rate:g}%": add_outliers(graph, rate / 100.0, reference=reference, seed=seed) for rate in rates}


def _print_table(configs, *, robust: bool = False, pcm: bool = False) -> None:
    """One row per configuration. A batch's configurations run together (one vmapped program), so its
    time is the batch's: "batch ms/it" is the wall time of one iteration of the whole batch of
    "in batch" configurations, and "ms/it share" that time divided among them (what one
    configuration costs inside the batch, not what it costs run alone with ``mmpgo solve``)."""
    timing = ("in batch", "batch ms/it", "ms/it share")
    head = ["file", "method", "robots", *(("loss", "outlier rate %") if robust else ()), "f final", "(f - f*)/f*",
            *(("precision", "recall") if robust else ()), *(("PCM rejected",) if pcm else ()), *timing]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for row in configs:
        gap = "" if row.get("relative_gap") is None else f"{row['relative_gap']:.3e}"
        cells = [row["graph"], row["method"].upper(), row["robots"]]
        if robust:
            rate = "" if row.get("outlier_rate") is None else f"{100 * row['outlier_rate']:g}"
            cells += [row.get("loss", "l2"), rate]
        cells += [f"{row['f']:.10g}", gap]
        if robust:
            cells += ["" if row.get(k) is None else f"{row[k]:.3f}" for k in ("precision", "recall")]
        if pcm:
            cells.append(row.get("pcm_rejected", ""))
        cells += [row["batch_size"], f"{row['batch_ms_per_iteration']:.2f}", f"{row['ms_per_iteration']:.2f}"]
        print("| " + " | ".join(str(c) for c in cells) + " |")
