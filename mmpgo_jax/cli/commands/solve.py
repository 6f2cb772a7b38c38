"""``mmpgo solve FILE``: MM-PGO / AMM-PGO (``--method``: any name of the methods registry,
:mod:`mmpgo_jax._solve.methods`) on one device, the CPU cores of this one (``--threads``),
or sharded over devices and processes (``--devices``, ``--processes``, multi-host: handed over to
:mod:`mmpgo_jax.cli.sharded_solve`). The solvers are imported inside :func:`run`, the sharded one
only when asked for (tests/test_architecture.py checks what this command loads)."""

from __future__ import annotations

import argparse
import time

from ..devices import add_checkpoint_options, add_cli_options, add_threads_option, configure_cpu_devices
from ..options import INT_MAX, ITERATIONS, ROBOTS, add_common, add_pcm_options, add_strict, finite_float, int_in
from ..robots import FILE_HELP, add_robots_from


def register(sub) -> None:
    p = sub.add_parser("solve", help="run MM-PGO / AMM-PGO (or a baseline: RBCD, RBCD++, DGS) on a g2o file")
    p.add_argument("file", help=FILE_HELP)
    _add_solver_options(p)
    p.add_argument("--out", "-o", help="write the estimate as g2o (VERTEX lines + the original edges)")
    p.add_argument("--tum", help="write the estimate as a TUM trajectory (index tx ty tz qx qy qz qw)")
    p.add_argument("--tum-dir", metavar="DIR",
                   help="write one TUM trajectory per robot, DIR/<robot>.tum, and the whole one, DIR/all_robots.tum")
    p.add_argument("--out-dir", metavar="DIR",
                   help="write the estimate as one g2o file per robot, DIR/<robot>.g2o (the per-robot folder layout, "
                        "which reads back with --robots-from files)")
    p.add_argument("--history", help="write the per-iteration history as CSV")
    p.add_argument("--plot", help="write convergence and trajectory plots to this PNG")
    p.add_argument(
        "--certify",
        action="store_true",
        help="check global optimality of the result (SE-Sync's dual certificate; meaningful at a critical point)",
    )
    p.add_argument(
        "--ground-truth",
        help="poses to compare with (.g2o VERTEX lines or .npz with R, t): reports ATE and RPE after rigid alignment",
    )
    _add_robust_options(p)
    add_strict(p)
    add_common(p)
    add_checkpoint_options(p)
    add_threads_option(p)
    add_cli_options(p)
    p.set_defaults(run=run, configure=configure_cpu_devices, preload=preload)


def _add_solver_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robots", "-A", type=ROBOTS, default=None,
                   help="number of robots, >= 1 and at most the number of poses (for --robots-from blocks, metis, "
                        "random; default 10)")
    add_robots_from(p)
    from ..._solve.methods import METHOD_NAMES  # names only: no solver is imported here

    p.add_argument("--method", choices=METHOD_NAMES, default="amm", metavar="METHOD",
                   help="amm (AMM-PGO, default), mm (MM-PGO), rbcd / rbcd++ (Riemannian block-coordinate descent, "
                        "greedy block; ++: accelerated), rbcd[++]-uniform, rbcd[++]-round-robin, rbcd[++]-parallel "
                        "(other block selections), dgs (distributed Gauss-Seidel)")
    p.add_argument("--iterations", "-n", type=ITERATIONS, default=1000,
                   help="at most this many outer iterations, >= 0 (default 1000); the run stops earlier when f "
                        "moves only by rounding (see --all-iterations) or at --grad-tol")
    p.add_argument("--all-iterations", action="store_true",
                   help="run every one of --iterations even once f moves only by rounding (fixed-length histories)")
    p.add_argument(
        "--init",
        default=None,
        help="start: chordal (default for least squares), gnc-chordal (GNC-TLS with chordal stages, not bent by "
             "outliers), distributed-chordal, distributed-robust (each robot's own GNC map, placed by robust "
             "averaging of the inter-robot closures), vertices, odometry, or a .g2o/.npz file of poses; several "
             "names joined by commas run from each and keep the lowest objective (the default for a robust --loss: "
             "gnc-chordal,distributed-robust)",
    )
    p.add_argument("--restart", choices=("adaptive", "average", "paper"), default=None,
                   help="AMM restart rule (default adaptive; see README); --method amm only")
    p.add_argument("--xi", type=finite_float(0.0), default=None,
                   help="proximal weight xi of Eq. (13), finite and >= 0 (default 1e-3); --method mm and amm only")
    p.add_argument("--grad-tol", type=finite_float(0.0, strict=True), default=None,
                   help="stop when ||grad F|| falls below this (finite, > 0)")
    p.add_argument("--chunk", type=int_in(1, INT_MAX), default=50,
                   help="iterations per compiled chunk, >= 1 (progress granularity; default 50)")
    p.add_argument("--largest-component", action="store_true", help="solve only the largest connected component")
    p.add_argument("--distributed", action="store_true",
                   help="refuse every centralized step (the chordal, gnc-chordal and odometry starts, --certify, "
                        "--robots-from metis): start from distributed-chordal, or with a robust --loss from "
                        "distributed-robust, whose classification of the edges the solver holds as its first stage")
    p.add_argument("--no-progress", action="store_true", help="do not show a progress bar")


def _add_robust_options(p: argparse.ArgumentParser) -> None:
    from ..._mm.robust import LOSSES

    g = p.add_argument_group("robust losses (outlier loop closures)")
    g.add_argument("--loss", choices=LOSSES, default="l2",
                   help="kernel of the robust objective (default l2, least squares), started from the GNC start "
                        "(--init gnc-chordal); odometry edges (consecutive poses) always keep weight 1")
    g.add_argument("--gnc", action="store_true",
                   help="tls, geman-mcclure: run GNC's stages inside the distributed solver (fully distributed, "
                        "from the chordal start; less reliable than the default GNC start, see README)")
    g.add_argument("--loss-scale", metavar="C", type=finite_float(0.0, strict=True), default=None,
                   help="scale c of the kernel in residual units, > 0 (default: sqrt of the 0.99 chi-square quantile "
                        "with d(d+1)/2 degrees of freedom: 3.37 in 2D, 4.10 in 3D; 4.04 is the 2D quantile for files "
                        "whose angle noise is what their information states, see README)")
    g.add_argument("--edge-weights", metavar="OUT.csv",
                   help="write every edge's final weight and inlier flag as CSV (i, j, weight, inlier; original ids)")
    g.add_argument("--drop-outliers", action="store_true",
                   help="--out / --out-dir keep only the inlier edges (by default every edge is written)")
    add_pcm_options(g, "before the start and the solve; the count and lines are printed")
    g.add_argument("--team-check", action=argparse.BooleanOptionalAction, default=None,
                   help="the distributed robust start (--init distributed-robust, --distributed, or the default's "
                        "second start) checks its accepted inter-robot closures at the team's chordal map, dropping "
                        "closures of largest residual while the TLS objective falls (for long noisy robot chains; "
                        "see README); on by default with --distributed and a robust --loss, off otherwise")
    g.add_argument("--readmit", action="store_true",
                   help="after a robust solve, re-admit rejected loop closures one at a time while the robust "
                        "objective falls (centralized Newton per rejected closure; for robot teams with few "
                        "closures per pair, e.g. with --pcm), then solve again from there")


def preload() -> None:
    """What a solve needs beyond the parser, imported up front by the program (with the garbage
    collector off, see :func:`mmpgo_jax.cli.app.main`); :func:`run` imports it again where used."""
    import mmpgo_jax

    from .. import inputs, outputs, progress  # noqa: F401

    for name in ("solve", "read_g2o"):  # the lazy public names import the solver's and reader's modules
        getattr(mmpgo_jax, name)


def run(args) -> int:
    from ..devices import wants_sharding
    from ..errors import CLIError
    from ..inputs import check_solve_flags

    check_solve_flags(args)  # before anything is read, on every path
    if wants_sharding(args):
        from ..sharded_solve import cli_solve

        if args.ground_truth:
            raise CLIError("--ground-truth is not available with --devices / --processes")
        return cli_solve(args, args.argv)
    return _solve(args)


def _solve(args) -> int:
    """One process: one device, or (``--threads``) this process's CPU devices."""
    import numpy as np

    from ... import solve
    from ..._mm.robust import GNC_LOSSES
    from ..._solve.methods import method_label
    from ..devices import thread_devices
    from ..errors import CLIError
    from ..inputs import load_for_solve, reference_fstar, resolve_file, solve_options
    from ..outputs import check_outputs, finish_solve, print_summary, print_timing
    from ..progress import progress_bar

    args.file = str(resolve_file(args.file, args.data))
    check_outputs(args)
    if args.loss == "l2" and (args.edge_weights or (args.drop_outliers and not args.pcm) or args.loss_scale is not None
                              or args.gnc):
        flag = ("--edge-weights" if args.edge_weights else "--drop-outliers" if args.drop_outliers
                else "--gnc" if args.gnc else "--loss-scale")
        alternative = " or --pcm" if flag == "--drop-outliers" else ""
        raise CLIError(f"{flag} needs a robust --loss (huber, cauchy, geman-mcclure, welsch or tls){alternative}")
    if args.gnc and args.loss not in GNC_LOSSES:
        raise CLIError(f"--gnc applies to --loss {' and '.join(GNC_LOSSES)}, not {args.loss}")
    with progress_bar(method_label(args.method), args.iterations, disable=args.no_progress,
                      show_gradient=args.grad_tol is not None) as progress:
        progress.phase("reading")
        t = time.perf_counter()
        data = load_for_solve(args)
        ground_truth = data.poses_file(args.ground_truth, "--ground-truth file") if args.ground_truth else None
        read = time.perf_counter() - t
        options = solve_options(args, data)
        devices = thread_devices(args, data.graph.num_poses, int(np.max(data.robot_of_pose)) + 1)
        if devices is None:
            result = solve(data.graph, data.robot_of_pose, monitor=progress, ground_truth=ground_truth, **options)
        else:
            from ...sharding import solve_sharded

            result = solve_sharded(data.graph, data.robot_of_pose, devices=devices, monitor=progress,
                                   ground_truth=ground_truth, **options)
    fstar = reference_fstar(data)
    print_summary(result, fstar, data)
    if devices is not None:
        print(f"threads     {len(devices)} (the robots split over {len(devices)} CPU devices)")
    if args.distributed:
        gnc = ", GNC in the solver" if result.loss is not None and bool(result.loss.use_gnc) else ""
        kept = [row for row in result.stats.get("starts", ()) if row["kept"]]
        held = result.stats.get("start_weights_given") or any(row["held"] for row in kept)
        held = ", its edge weights held first" if held else ""
        finished = (", finished from the distributed chordal start of its kept edges"
                    if any(row["finished"] is not None for row in kept) else "")
        start = args.init or ("distributed-chordal" if result.loss is None else "distributed-robust")
        print(f"distributed no centralized step: start {start}{held}{gnc}{finished}")
        print(_exchanged_line(data.graph, result, start, kept[0] if kept else None))
    t = time.perf_counter()
    finish_solve(args, data, result, fstar)
    print_timing(result, read=read, write=time.perf_counter() - t)
    return 0


def _exchanged_line(graph, result, start: str, row: dict | None = None) -> str:
    """The bytes a robot team exchanges for this run: the distributed robust start's messages
    (:class:`~mmpgo_jax._init.robust_distributed.StartTraffic`), the solver's neighbour exchanges
    (every robot's poses at its inter-robot edge ends, d^2 + d float64 numbers each, per iteration),
    the start's team check (each CG iteration of its distributed chordal solves the same boundary
    poses; counted for the first start, not the starts a revisit makes again) and, for a run
    finished from its kept edges (``row``: its line of ``stats["starts"]``), the
    distributed chordal start's (each CG iteration the same boundary poses' rotations, d^2 numbers,
    then translations, d; its scalar all-reductions not counted)."""
    from ..._baselines.rbcd import boundary_poses_sent
    from ..._init.robust_distributed import start_traffic

    d = graph.dim
    boundary = int(boundary_poses_sent(result.partition).sum())
    per_iteration = 8 * (d * d + d) * boundary
    iterations = result.iterations if row is None else row["iterations"]
    parts = []
    if start == "distributed-robust":
        traffic = start_traffic(graph, result.partition)
        parts.append(f"start {traffic.bytes / 1e3:.1f} kB ({traffic.closures} inter-robot closures' far ends, "
                     f"their hypotheses to all {traffic.robots} robots)")
    check = (row or {}).get("team_check") or result.stats.get("team_check")
    if check is not None:
        cg = 8 * boundary * (d * d * check["rotation_iterations"] + d * check["translation_iterations"])
        solves, rounds, dropped = check["solves"], check["rounds"], len(check["removed"])
        parts.append(f"team check {cg / 1e3:.1f} kB ({solves} distributed chordal solve{'s' * (solves != 1)}, "
                     f"{rounds} round{'s' * (rounds != 1)}, {check['rotation_iterations']} + "
                     f"{check['translation_iterations']} CG iterations; {dropped} closure{'s' * (dropped != 1)} "
                     "dropped)")
    parts.append(f"iterations {per_iteration * iterations / 1e3:.1f} kB "
                 f"({per_iteration / 1e3:.2f} kB each, boundary poses)")
    by = None if row is None else row.get("finished_by")
    if by is not None and by.get("by") == "distributed-chordal":
        chordal = 8 * boundary * (d * d * by["rotation_iterations"] + d * by["translation_iterations"])
        parts.append(f"finishing chordal start {chordal / 1e3:.1f} kB ({by['rotation_iterations']} + "
                     f"{by['translation_iterations']} CG iterations)")
    return "exchanged   " + "; ".join(parts)

