"""The ``mmpgo`` command line: ``info``, ``solve``, ``demo`` and ``bench``.

Bad input never ends in a traceback: g2o format problems, missing files and invalid options are
reported as ``mmpgo: error: ...`` (naming file and line where there is one) with exit status 2.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ._progress import progress_bar


class CLIError(Exception):
    """An error to report to the user without a traceback."""


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", help="folder with benchmark g2o files (default: $MMPGO_DATA, else ../shared/datasets)")
    p.add_argument(
        "--precision",
        choices=("float64", "float32"),
        default="float64",
        help="floating-point precision (default float64, as the paper and SE-Sync)",
    )


def _add_solver_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robots", "-A", type=int, default=10, help="number of robots (contiguous blocks; default 10)")
    p.add_argument("--method", choices=("amm", "mm"), default="amm", help="AMM-PGO (default) or MM-PGO")
    p.add_argument("--iterations", "-n", type=int, default=1000, help="outer iterations (default 1000)")
    p.add_argument(
        "--init",
        default="chordal",
        help="start: chordal (default), distributed-chordal, vertices, odometry, or a .g2o/.npz file of poses",
    )
    p.add_argument("--restart", choices=("adaptive", "average", "paper"), default="adaptive",
                   help="AMM restart rule (default adaptive; see README)")
    p.add_argument("--xi", type=float, default=1e-3, help="proximal weight xi of Eq. (13) (default 1e-3)")
    p.add_argument("--grad-tol", type=float, default=None, help="stop when ||grad F|| falls below this")
    p.add_argument("--chunk", type=int, default=50, help="iterations per compiled chunk (progress granularity)")
    p.add_argument("--largest-component", action="store_true", help="solve only the largest connected component")
    p.add_argument("--no-progress", action="store_true", help="do not show a progress bar")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mmpgo", description="Distributed PGO by majorization minimization (JAX)")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("info", help="describe a pose graph and its partition among robots")
    p.add_argument("file", help="g2o file, or a benchmark name (e.g. MITb, city10000)")
    p.add_argument("--robots", "-A", type=int, default=None, help="also describe the split among A robots")
    _add_common(p)

    p = sub.add_parser("solve", help="run MM-PGO / AMM-PGO on a g2o file")
    p.add_argument("file", help="g2o file, or a benchmark name (e.g. MITb, city10000)")
    _add_solver_options(p)
    p.add_argument("--out", "-o", help="write the estimate as g2o (VERTEX lines + the original edges)")
    p.add_argument("--tum", help="write the estimate as a TUM trajectory (index tx ty tz qx qy qz qw)")
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
    _add_common(p)
    from .sharding import add_cli_options

    add_cli_options(p)

    p = sub.add_parser("optimum", help="centralized optimum f* of a g2o file, with its global-optimality certificate")
    p.add_argument("file", help="g2o file, or a benchmark name (e.g. MITb, city10000)")
    p.add_argument("--init", default="chordal", help="start: chordal (default), vertices, odometry, or a .g2o/.npz file")
    p.add_argument("--grad-tol", type=float, default=1e-6, help="stop when ||grad F|| falls below this (default 1e-6)")
    p.add_argument("--max-iterations", type=int, default=5000)
    p.add_argument("--no-certify", action="store_true", help="skip the dual certificate")
    p.add_argument("--out", "-o", help="write the optimum as g2o (VERTEX lines + the original edges)")
    p.add_argument("--tum", help="write the optimum as a TUM trajectory")
    p.add_argument("--largest-component", action="store_true", help="solve only the largest connected component")
    _add_common(p)

    p = sub.add_parser("demo", help="run AMM-PGO on a generated Cube dataset (no download needed)")
    p.add_argument("--out-dir", default="mmpgo-demo", help="folder for the plots and results (default ./mmpgo-demo)")
    p.add_argument("--poses", type=int, default=1000, help="poses of the generated Cube dataset (default 1000)")
    p.add_argument("--robots", "-A", type=int, default=10)
    p.add_argument("--iterations", "-n", type=int, default=300)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-progress", action="store_true")
    _add_common(p)

    p = sub.add_parser("bench", help="reproduce the paper's Tables I/II on the available datasets")
    p.add_argument("--quick", action="store_true", help="a small run for CI: one small dataset, few iterations")
    p.add_argument("--datasets", nargs="*", help="benchmark names (default: all available)")
    p.add_argument("--iterations", "-n", type=int, default=1000)
    p.add_argument("--robots", "-A", type=int, default=10)
    p.add_argument("--out-dir", default="bench-results", help="folder for the Markdown, CSV and JSON tables")
    p.add_argument("--no-progress", action="store_true")
    _add_common(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.precision == "float64":
        from ._precision import enable_float64

        enable_float64()
    from ._datasets import DatasetNotFoundError
    from ._g2o import G2OFormatError

    try:
        if args.command == "info":
            return _cmd_info(args)
        if args.command == "solve":
            from .sharding import cli_solve, wants_sharding

            if wants_sharding(args):
                if args.ground_truth:
                    raise CLIError("--ground-truth is not available with --devices / --processes")
                return cli_solve(args, sys.argv[1:] if argv is None else argv)
            return _cmd_solve(args)
        if args.command == "optimum":
            return _cmd_optimum(args)
        if args.command == "demo":
            from ._demo import run_demo

            return run_demo(args)
        if args.command == "bench":
            from ._bench import run_bench

            return run_bench(args)
    except (G2OFormatError, DatasetNotFoundError, CLIError, ValueError, OSError) as err:
        print(f"mmpgo: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("mmpgo: interrupted", file=sys.stderr)
        return 130
    return 0


def _resolve_file(name: str, data: str | None) -> Path:
    p = Path(name)
    if p.is_file():
        return p
    from ._datasets import find_benchmark

    return find_benchmark(name, data)


def _describe_components(graph, vertex_ids=None) -> tuple[list[np.ndarray], str]:
    from ._pose_graph import connected_components

    comps = connected_components(graph.num_poses, np.asarray(graph.i), np.asarray(graph.j))
    if len(comps) == 1:
        return comps, "connected"
    ids = np.arange(graph.num_poses) if vertex_ids is None else np.asarray(vertex_ids)
    parts = ", ".join(f"{len(c)} poses (vertex ids {ids[c[0]]}..{ids[c[-1]]})" for c in comps[:5])
    more = f", and {len(comps) - 5} more" if len(comps) > 5 else ""
    return comps, f"NOT connected: {len(comps)} components: {parts}{more}"


def _cmd_info(args) -> int:
    from ._g2o import read_g2o
    from ._partition import contiguous_robots, partition_stats

    path = _resolve_file(args.file, args.data)
    g2o = read_g2o(path)
    g = g2o.graph
    kappa, tau = np.asarray(g.kappa), np.asarray(g.tau)
    _, conn = _describe_components(g, g2o.vertex_ids)
    ids = g2o.vertex_ids
    print(f"file        {path}")
    print(f"dimension   d = {g.dim}")
    print(f"poses       n = {g.num_poses}" + ("" if ids[-1] == len(ids) - 1 and ids[0] == 0 else f"  (ids {ids[0]}..{ids[-1]}, remapped)"))
    print(f"edges       m = {g.num_edges}")
    print(f"kappa       {kappa.min():.6g} .. {kappa.max():.6g}")
    print(f"tau         {tau.min():.6g} .. {tau.max():.6g}")
    print(f"graph       {conn}")
    print(f"vertices    {int(g2o.has_vertex.sum())} VERTEX lines, {int(g2o.fixed.sum())} fixed")
    if args.robots:
        rop = contiguous_robots(g.num_poses, args.robots)
        st = partition_stats(g, rop)
        print(f"\npartition   {args.robots} robots (contiguous blocks), {st.total_inter_edges} inter-robot edges")
        print(f"{'robot':>5} {'poses':>7} {'own edges':>10} {'inter edges':>12} {'receives':>9}  neighbours")
        for a in range(args.robots):
            nb = " ".join(map(str, st.neighbours[a].tolist()))
            print(f"{a:>5} {st.poses[a]:>7} {st.own_edges[a]:>10} {st.inter_edges[a]:>12} {st.received_poses[a]:>9}  {nb}")
    return 0


def _largest_component(g2o):
    """Restrict a G2OFile's graph to its largest connected component."""
    from ._pose_graph import PoseGraph, Poses, connected_components

    g = g2o.graph
    comp = connected_components(g.num_poses, np.asarray(g.i), np.asarray(g.j))[0]
    new_index = np.full(g.num_poses, -1)
    new_index[comp] = np.arange(len(comp))
    keep = new_index[np.asarray(g.i)] >= 0
    sub = PoseGraph.from_arrays(
        new_index[np.asarray(g.i)[keep]],
        new_index[np.asarray(g.j)[keep]],
        np.asarray(g.R)[keep],
        np.asarray(g.t)[keep],
        np.asarray(g.kappa)[keep],
        np.asarray(g.tau)[keep],
        len(comp),
        dtype=np.asarray(g.kappa).dtype,
    )
    initial = None
    if g2o.initial is not None:
        initial = Poses(g2o.initial.R[comp], g2o.initial.t[comp])
    return sub, g2o.vertex_ids[comp], g2o.information[keep], initial


def _load_for_solve(args, *, announce: bool = True):
    """(path, graph, vertex_ids, information, initial, components) of ``args.file``; refuses a
    disconnected graph unless ``--largest-component``. ``announce``: print the component note."""
    from ._g2o import read_g2o

    path = _resolve_file(args.file, args.data)
    g2o = read_g2o(path)
    comps, conn = _describe_components(g2o.graph, g2o.vertex_ids)
    if len(comps) > 1:
        if not args.largest_component:
            raise CLIError(
                f"{path}: the pose graph is {conn}. Each component is only determined up to its own "
                "rigid transform, so the problem is ill-posed; pass --largest-component to solve the "
                "largest one (the others are left out of the result)."
            )
        graph, vertex_ids, information, initial = _largest_component(g2o)
        if announce:
            print(f"note: solving the largest component only ({graph.num_poses} of {g2o.graph.num_poses} poses)")
    else:
        graph, vertex_ids, information, initial = g2o.graph, g2o.vertex_ids, g2o.information, g2o.initial
    return path, graph, vertex_ids, information, initial, comps


def _cmd_solve(args) -> int:
    from ._datasets import benchmark_info
    from ._solve import solve

    path, graph, vertex_ids, information, initial, comps = _load_for_solve(args)
    if not 1 <= args.robots <= graph.num_poses:
        raise CLIError(f"--robots must be between 1 and the number of poses ({graph.num_poses}), got {args.robots}")
    ground_truth = None
    if args.ground_truth:
        if len(comps) > 1:
            raise CLIError("--ground-truth cannot be combined with --largest-component (pose indices differ)")
        from ._initialization import load_poses

        ground_truth = load_poses(graph, args.ground_truth, what="ground-truth file")
    init = args.init
    if init not in ("chordal", "distributed-chordal", "vertices", "odometry") and not Path(init).is_file():
        raise CLIError(f"--init {init!r}: not a known method (chordal, distributed-chordal, vertices, odometry) nor a file")

    with progress_bar(f"{args.method.upper()}-PGO", args.iterations, disable=args.no_progress) as progress:
        result = solve(
            graph,
            args.robots,
            method=args.method,
            iterations=args.iterations,
            init=init,
            initial=initial,
            xi=args.xi,
            restart=args.restart,
            chunk_size=args.chunk,
            grad_tol=args.grad_tol,
            callback=progress,
            ground_truth=ground_truth,
        )
    info = benchmark_info(path.name)
    fstar = info.fstar if info is not None else None
    _print_summary(result, fstar)
    finish_solve(args, path, graph, result, fstar, vertex_ids, information)
    return 0


def _print_certificate(graph, poses, *, hint: bool) -> None:
    from ._certificate import certify

    cert = certify(graph, poses)
    print(f"certificate {cert.summary()}")
    if hint and not cert.certified:
        print("            (the certificate decides only at a critical point: run to a tight --grad-tol, e.g. --robots 1)")


def _write_estimate(args, graph, poses, vertex_ids, information) -> None:
    """--out (g2o) and --tum files of an estimate."""
    from ._g2o import write_g2o, write_tum

    if args.out:
        write_g2o(args.out, graph, poses, vertex_ids=vertex_ids, information=information)
        print(f"wrote {args.out}")
    if args.tum:
        write_tum(args.tum, poses, vertex_ids=vertex_ids)
        print(f"wrote {args.tum}")


def finish_solve(args, path, graph, result, fstar, vertex_ids, information) -> None:
    """After a solve (single- or multi-device): --certify, then the --out/--tum/--history/--plot files."""
    if args.certify:
        _print_certificate(graph, result.poses, hint=True)
    _write_estimate(args, graph, result.poses, vertex_ids, information)
    if args.history:
        write_history_csv(args.history, result)
        print(f"wrote {args.history}")
    if args.plot:
        from ._plotting import save_solve_figure

        save_solve_figure(args.plot, graph, result, fstar=fstar, title=path.name)
        print(f"wrote {args.plot}")


def _cmd_optimum(args) -> int:
    from ._datasets import benchmark_info
    from ._solve import centralized_optimum

    path, graph, vertex_ids, information, initial, _ = _load_for_solve(args)
    init = args.init
    if init not in ("chordal", "vertices", "odometry") and not Path(init).is_file():
        raise CLIError(f"--init {init!r}: not a known method (chordal, vertices, odometry) nor a file")
    res = centralized_optimum(graph, init=init, initial=initial, grad_tol=args.grad_tol,
                              max_iterations=args.max_iterations)
    h = res.history
    total = res.init_seconds + res.compile_seconds + res.solve_seconds
    print(f"f* = 2F      {res.f:.10g} ({res.iterations} iterations, {res.stop_reason}, ||grad F|| = {h.grad_norm[-1]:.2e}, "
          f"{total:.1f} s)")
    info = benchmark_info(path.name)
    if info is not None and info.fstar is not None:
        print(f"published   {info.fstar:.6g} ({info.name}); relative difference {(res.f - info.fstar) / info.fstar:+.1e}")
    if not args.no_certify:
        _print_certificate(graph, res.poses, hint=False)
    _write_estimate(args, graph, res.poses, vertex_ids, information)
    return 0


def _print_summary(result, fstar: float | None) -> None:
    h = result.history
    print(f"method      {result.config.method.upper()}-PGO, {result.partition.num_robots} robots, restart={result.config.restart}")
    print(f"iterations  {h.iterations} ({result.stop_reason})")
    print(f"f = 2F      {h.f[0]:.6f} -> {h.f[-1]:.6f}")
    if fstar is not None:
        print(f"f*          {fstar:.6g} (reference), relative gap (f - f*)/f* = {(h.f[-1] - fstar) / fstar:.3e}")
    print(f"|grad F|    {h.grad_norm[-1]:.3e}")
    if result.accuracy is not None:
        a = result.accuracy
        print(f"ATE         {a.ate:.6g} RMSE, {a.ate_max:.6g} max (positions after rigid alignment); "
              f"rotation {a.rotation_deg:.4g} deg RMSE")
        print(f"RPE         {a.rpe_translation:.6g} translation, {a.rpe_rotation_deg:.4g} deg rotation (consecutive poses, RMSE)")
    print(
        f"time        init {result.init_seconds:.2f} s, compile {result.compile_seconds:.2f} s, "
        f"iterations {result.solve_seconds:.2f} s ({result.ms_per_iteration:.2f} ms/iteration)"
    )


def write_history_csv(path, result) -> None:
    from ._atomic import atomic_write

    h = result.history
    with atomic_write(path) as fh:
        fh.write("iteration,f,grad_norm,restarts\n")
        for k in range(len(h.f)):
            fh.write(f"{k},{float(h.f[k])!r},{float(h.grad_norm[k])!r},{int(h.restarts[k].sum())}\n")


if __name__ == "__main__":
    sys.exit(main())
