"""``mmpgo optimum FILE``: the centralized optimum f* of a graph, with its global-optimality
certificate and the registry's f* beside it."""

from __future__ import annotations

from ..options import INT_MAX, add_common, add_strict, finite_float, int_in
from ..robots import FILE_HELP


def register(sub) -> None:
    p = sub.add_parser("optimum", help="centralized optimum f* of a g2o file, with its global-optimality certificate")
    p.add_argument("file", help=FILE_HELP)  # read as solve reads it (TORO, per-robot folders too)
    p.add_argument("--init", default="chordal",
                   help="start: chordal (default), vertices, odometry, or a .g2o/.npz file")
    p.add_argument("--grad-tol", type=finite_float(0.0, strict=True), default=1e-6,
                   help="stop when ||grad F|| falls below this (finite, > 0; default 1e-6)")
    p.add_argument("--max-iterations", type=int_in(1, INT_MAX), default=5000,
                   help="at most this many iterations, >= 1 (default 5000)")
    p.add_argument("--no-certify", action="store_true", help="skip the dual certificate")
    p.add_argument("--out", "-o", help="write the optimum as g2o (VERTEX lines + the original edges)")
    p.add_argument("--tum", help="write the optimum as a TUM trajectory")
    p.add_argument("--largest-component", action="store_true", help="solve only the largest connected component")
    p.add_argument("--no-progress", action="store_true", help="do not show a progress bar")
    add_strict(p)
    add_common(p)
    p.set_defaults(run=run)


def run(args) -> int:
    from ... import centralized_optimum
    from ..._io.atomic import atomic_group
    from ..._io.datasets import benchmark_info
    from ..inputs import OPTIMUM_STARTS, load_for_solve, reference_fstar, resolve_file
    from ..outputs import check_outputs, print_certificate, write_estimate
    from ..progress import progress_bar

    args.file = str(resolve_file(args.file, args.data))
    check_outputs(args)
    # float64: the gradient is checked after every Newton step (the bar moves with each, and the solve
    # stops at the first ||grad F|| <= tol); float32's stall rule compares f over chunks of 25
    chunk = 1 if args.precision == "float64" else 25
    with progress_bar("optimum", None, disable=args.no_progress, show_gradient=True) as progress:
        progress.phase("reading")
        data = load_for_solve(args)
        init = data.start(args.init, OPTIMUM_STARTS)
        res = centralized_optimum(data.graph, init=init, initial=data.initial, grad_tol=args.grad_tol,
                                  max_iterations=args.max_iterations, fixed=data.fixed, frame=data.frame,
                                  monitor=progress, chunk_size=chunk)
    h = res.history
    total = res.init_seconds + res.compile_seconds + res.solve_seconds
    print(f"f* = 2F      {res.f:.12g} ({res.iterations} iterations, {res.stop_description}, "
          f"||grad F|| = {h.grad_norm[-1]:.2e}, {total:.1f} s)")
    info = benchmark_info(data.path.name) if reference_fstar(data) is not None else None
    for ref in () if info is None else info.fstar_references:
        print(f"registry    {ref.value:.12g}, {ref.label} of {info.name}: relative difference {ref.gap(res.f):+.1e}")
    if not args.no_certify:
        print_certificate(data, res.poses, hint=False)
    with atomic_group():
        written = write_estimate(args, data, res.poses)
    for path in written:
        print(f"wrote {path}")
    return 0
