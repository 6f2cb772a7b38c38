"""The sharded ``mmpgo solve`` (``--devices``, ``--processes``, multi-host) and ``python -m mmpgo_jax.sharding``."""

from __future__ import annotations

import contextlib
import os
import sys
import time
from collections.abc import Sequence

# JAX and the sharded solver are imported where they are used: ``mmpgo solve`` adds this module's
# options to its parser and asks thread_devices, but an unsharded solve never loads
# mmpgo_jax._distributed (tests/test_architecture.py checks its import set).

# ------------------------------------------------------------------------------------------------
# Command line: options for `mmpgo solve` and the sharded solve command
# ------------------------------------------------------------------------------------------------


def add_cli_options(p) -> None:
    """Add the sharding / multi-process options to the ``mmpgo solve`` parser (every number is
    checked when it is parsed: see :func:`mmpgo_jax.cli.int_in`)."""
    from . import finite_float, host_port, int_in

    g = p.add_argument_group("sharding over devices and processes")
    g.add_argument("--devices", type=int_in(0), default=None,
                   help="shard the robots over this many devices of this process, >= 0 (0: all)")
    g.add_argument("--processes", type=int_in(1), default=None,
                   help="run as P >= 1 local CPU processes (jax.distributed on 127.0.0.1)")
    g.add_argument("--coordinator", type=host_port, default=None,
                   help="HOST:PORT of process 0, PORT 1..65535 (multi-host runs; with --num-processes, --process-id)")
    g.add_argument("--num-processes", type=int_in(1), default=None,
                   help="number of processes of a multi-host run, >= 1")
    g.add_argument("--process-id", type=int_in(0), default=None,
                   help="this process's index 0..P-1 (process 0 writes the outputs)")
    g.add_argument("--local-devices", type=int_in(1), default=None,
                   help="CPU devices per process, >= 1 (with JAX_PLATFORMS=cpu)")
    g.add_argument("--timeout", type=finite_float(0.0, strict=True), default=600.0,
                   help="seconds before launched processes are killed, > 0 (default 600)")
    g.add_argument("--exchange", choices=("halo", "all_gather"), default="halo",
                   help="per-iteration pose exchange between devices: neighbour poses only (default) or all poses")


# A solve splits its robots over the CPU cores (one JAX CPU device each) from this many poses on:
# measured on this project's 2-core machine (benchmarks/profile_step.md), MIT (808 poses) ran at the
# same speed on 1 and 2 devices, intel (1728 poses) 1.7x faster on 2.
AUTO_THREAD_POSES = 1000


def add_threads_option(p) -> None:
    from . import int_in

    p.add_argument("--threads", type=int_in(1), default=None,
                   help="CPU threads: split the robots over this many CPU devices, >= 1 (default: one per core "
                        f"for graphs of {AUTO_THREAD_POSES} poses or more, else 1; ignored on a GPU)")


def cpu_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def configure_cpu_devices(args) -> None:
    """Give JAX's CPU backend one device per thread the command may use (``--threads``, default one
    per core; at least ``--devices``). It must run before JAX starts its backends: the command line
    does it when it starts; the library never changes this setting."""
    if any(getattr(args, k, None) is not None for k in ("processes", "num_processes", "coordinator")):
        return  # the launcher gives each process its CPU devices
    n = max(getattr(args, "threads", None) or cpu_cores(), getattr(args, "devices", None) or 1)
    if n > 1:
        import jax

        # RuntimeError: backends already started (e.g. main() called twice in one process)
        with contextlib.suppress(RuntimeError):
            jax.config.update("jax_num_cpu_devices", n)


def thread_devices(args, num_poses: int, num_robots: int) -> list | None:
    """The CPU devices an (unsharded) ``solve`` splits its robots over, or None for one device: on
    a CPU backend, ``--threads`` (default: every core from ``AUTO_THREAD_POSES`` poses on), at most
    one device per robot."""
    import jax

    if jax.default_backend() != "cpu":
        return None
    n = args.threads or (cpu_cores() if num_poses >= AUTO_THREAD_POSES else 1)
    devices = jax.devices("cpu")
    n = min(n, num_robots, len(devices))
    return devices[:n] if n > 1 else None


def wants_sharding(args) -> bool:
    """True when the parsed ``solve`` arguments ask for a sharded / multi-process run."""
    return any(getattr(args, k, None) is not None for k in ("devices", "processes", "num_processes", "coordinator"))


def cli_solve(args, argv: Sequence[str] | None = None) -> int:
    """``mmpgo solve`` with sharding options (see :func:`add_cli_options`).

    ``--processes P`` (P > 1) relaunches this command as P local processes and returns their
    status; ``--coordinator/--num-processes/--process-id`` joins a multi-process run; ``--devices``
    alone shards over this process's devices. ``argv``: the full command line (default sys.argv).
    """
    import jax

    from .._distributed.launcher import initialize_distributed, run_multiprocess
    from . import CLIError, _resolve_file, check_outputs

    if args.process_id in (None, 0):  # the process that writes (or launches the one that does)
        check_outputs(args)
    if args.processes is not None and args.num_processes is None:
        if args.processes < 1:
            raise CLIError(f"--processes must be >= 1, got {args.processes}")
        if args.processes > 1:
            _resolve_file(args.file, args.data, announce=False)  # fail before launching; process 0 announces
            argv = list(sys.argv[1:] if argv is None else argv)
            run = run_multiprocess(argv, args.processes, local_devices=args.local_devices or 1, timeout_s=args.timeout,
                                   capture=False)
            if run.timed_out:
                raise CLIError(
                    f"the {args.processes} processes did not finish within {args.timeout:g} s and were stopped"
                )
            return max((abs(rc) for rc in run.returncodes), default=0)
    if args.num_processes is not None or args.coordinator is not None:
        if args.num_processes is None or args.process_id is None or args.coordinator is None:
            raise CLIError("a multi-process run needs --coordinator HOST:PORT, --num-processes P and --process-id I")
        if not 0 <= args.process_id < args.num_processes:
            raise CLIError(f"--process-id must be between 0 and {args.num_processes - 1}, got {args.process_id}")
        initialize_distributed(args.coordinator, args.num_processes, args.process_id, local_devices=args.local_devices,
                               timeout_s=max(1, int(min(args.timeout, 600))))
        try:
            return _cli_solve_sharded(args)
        finally:
            jax.distributed.shutdown()
    return _cli_solve_sharded(args)


def _cli_solve_sharded(args) -> int:
    """Mirror of ``mmpgo solve`` (cli._cmd_solve) with :func:`solve_sharded`; process 0 writes."""
    import jax

    from .. import cli
    from .._distributed.solve import solve_sharded
    from .progress import progress_bar

    writer = jax.process_index() == 0
    args.file = str(cli._resolve_file(args.file, args.data, announce=writer))
    quiet = (not writer) or args.no_progress
    with progress_bar(f"{args.method.upper()}-PGO", args.iterations, disable=quiet,
                      show_gradient=args.grad_tol is not None) as progress:
        progress.phase("reading")
        t = time.perf_counter()
        data = cli._load_for_solve(args, announce=writer)
        read = time.perf_counter() - t
        options = cli.solve_options(args, data)
        local = jax.local_devices()
        if args.devices:
            if args.devices > len(local):
                raise cli.CLIError(f"--devices {args.devices}: this process has only {len(local)} devices")
            local = local[: args.devices]
        # The mesh: this process's devices, or (multi-process) every process's, ordered by process.
        devices = local if jax.process_count() == 1 else sorted(jax.devices(), key=lambda d: (d.process_index, d.id))
        result = solve_sharded(data.graph, data.robot_of_pose, devices=devices, monitor=progress,
                               exchange=args.exchange, **options)
    if not writer:
        return 0
    fstar = cli.reference_fstar(data)
    cli._print_summary(result, fstar, data)
    halo = f", halo of {result.extra['halo_size']} poses per device pair" if result.extra["halo_size"] else ""
    print(f"sharding    {result.extra['devices']} devices, {result.extra['processes']} processes, "
          f"{result.extra['exchange']} exchange{halo}")
    t = time.perf_counter()
    cli.finish_solve(args, data, result, fstar)
    cli.print_timing(result, read=read, write=time.perf_counter() - t)
    return 0


def build_parser():
    """``mmpgo``'s parser with the sharding options on ``solve`` (used by ``python -m``)."""
    from . import build_parser as base

    parser = base()
    solve_parser = next(a for a in parser._subparsers._group_actions if hasattr(a, "choices")).choices["solve"]
    if not any(o in solve_parser._option_string_actions for o in ("--processes", "--coordinator")):
        add_cli_options(solve_parser)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m mmpgo_jax.sharding solve FILE [options]``: one process of a sharded solve."""
    from . import _exit_status, cli_warnings, run_reported

    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] != "solve":
        argv = ["solve", *argv]
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # --help, or a bad option (reported in one line)
        return _exit_status(exc)
    if args.precision == "float64":
        import jax

        jax.config.update("jax_enable_x64", True)
    with cli_warnings():
        return run_reported(lambda: cli_solve(args, argv))


if __name__ == "__main__":
    sys.exit(main())
