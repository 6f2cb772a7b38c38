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
    g.add_argument("--heartbeat-timeout", metavar="S", type=int_in(1, 3600), default=HEARTBEAT_TIMEOUT_S,
                   help="multi-process runs: a process silent for S seconds is declared dead and the run ends, "
                        f"1..3600 (default {HEARTBEAT_TIMEOUT_S}; --processes also notices a dead process at once)")
    g.add_argument("--exchange", choices=("halo", "all_gather"), default="halo",
                   help="per-iteration pose exchange between devices: neighbour poses only (default) or all poses")


# Defaults of the library, not imported at parse time (see above; tests check they agree):
HEARTBEAT_TIMEOUT_S = 30  # = mmpgo_jax._distributed.launcher.HEARTBEAT_TIMEOUT_S
CHECKPOINT_EVERY = 1  # = mmpgo_jax._mm.checkpoint.DEFAULT_EVERY

# A solve splits its robots over the CPU cores (one JAX CPU device each) from this many poses on:
# measured on this project's 2-core machine (benchmarks/profile_step.md), MIT (808 poses) ran at the
# same speed on 1 and 2 devices, intel (1728 poses) 1.7x faster on 2.
AUTO_THREAD_POSES = 1000


def add_threads_option(p) -> None:
    from . import int_in

    p.add_argument("--threads", type=int_in(1), default=None,
                   help="CPU threads: split the robots over this many CPU devices, >= 1 (default: one per core "
                        f"for graphs of {AUTO_THREAD_POSES} poses or more, else 1; ignored on a GPU)")


def add_checkpoint_options(p) -> None:
    """``--checkpoint FILE``, ``--checkpoint-every N`` and ``--resume FILE`` of ``mmpgo solve``."""
    from . import int_in

    g = p.add_argument_group("checkpoints (long runs)")
    g.add_argument("--checkpoint", metavar="FILE",
                   help="write the run's state to FILE (.npz, replaced atomically) every --checkpoint-every chunks")
    g.add_argument("--checkpoint-every", metavar="N", type=int_in(1), default=CHECKPOINT_EVERY,
                   help=f"chunks (of --chunk iterations) between checkpoints, >= 1 (default {CHECKPOINT_EVERY})")
    g.add_argument("--resume", metavar="FILE",
                   help="continue the run saved in FILE (same input and options; --iterations may be larger); "
                        "may be the --checkpoint file")


def checkpoint_options(args) -> dict:
    """``solve`` / ``solve_sharded`` keyword arguments of the checkpoint options (none when unset)."""
    if getattr(args, "checkpoint", None) is None and getattr(args, "resume", None) is None:
        return {}
    return dict(checkpoint=args.checkpoint, checkpoint_every=args.checkpoint_every, resume=args.resume)


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
    from . import CLIError, _resolve_file, check_outputs, print_error

    if args.process_id in (None, 0):  # the process that writes (or launches the one that does)
        check_outputs(args)
    if args.processes is not None and args.num_processes is None:
        if args.processes < 1:
            raise CLIError(f"--processes must be >= 1, got {args.processes}")
        if args.processes > 1:
            _resolve_file(args.file, args.data, announce=False)  # fail before launching; process 0 announces
            if args.resume is not None and not os.path.isfile(args.resume):
                raise CLIError(f"checkpoint {args.resume}: no such file")
            argv = list(sys.argv[1:] if argv is None else argv)
            # every process's stderr is captured (a lost peer makes JAX's runtime abort the others
            # with C++ stack traces): a failure is reported here in one line
            run = run_multiprocess(argv, args.processes, local_devices=args.local_devices or 1, timeout_s=args.timeout,
                                   console=True)
            if run.timed_out:
                raise CLIError(
                    f"the {args.processes} processes did not finish within {args.timeout:g} s and were stopped"
                )
            if run.failure is not None:
                if sys.stderr.isatty():  # the line of process 0's progress bar, left as it was drawn
                    sys.stderr.write("\r\x1b[K")
                print_error(run.failure)
            return run.exit_status
    if args.num_processes is not None or args.coordinator is not None:
        if args.num_processes is None or args.process_id is None or args.coordinator is None:
            raise CLIError("a multi-process run needs --coordinator HOST:PORT, --num-processes P and --process-id I")
        if not 0 <= args.process_id < args.num_processes:
            raise CLIError(f"--process-id must be between 0 and {args.num_processes - 1}, got {args.process_id}")
        initialize_distributed(args.coordinator, args.num_processes, args.process_id, local_devices=args.local_devices,
                               timeout_s=max(1, int(min(args.timeout, 600))),
                               heartbeat_timeout_s=getattr(args, "heartbeat_timeout", HEARTBEAT_TIMEOUT_S))
        _sigterm_exits()  # a stopped process still removes its half-written files (atomic_write)
        try:
            status = _cli_solve_sharded(args)
        except BaseException as exc:  # every way out of a failed process is the same
            _leave_run(exc)
        jax.distributed.shutdown()  # waits for the others (process 0 may still be writing)
        return status
    return _cli_solve_sharded(args)


def _leave_run(exc: BaseException):
    """End this process of a multi-process run after ``exc``: report it as the command line does
    (one line, or a traceback for an unexpected error) on this process's own stderr, then exit at
    once. Not through JAX's shutdown barrier, where it would wait (up to the shutdown timeout) for
    processes that may be waiting in a collective for this one: they notice this one gone instead
    (the launcher at once, else the heartbeat)."""
    import traceback

    import jax

    from . import print_error, run_reported

    def again():
        raise exc

    status = 1
    with contextlib.redirect_stderr(sys.__stderr__ or sys.stderr):
        try:
            if isinstance(exc, SystemExit):
                status = exc.code if isinstance(exc.code, int) else 1
            elif isinstance(exc, jax.errors.JaxRuntimeError):  # e.g. a collective whose peer is gone
                first = next((x for x in str(exc).splitlines() if x.strip()), type(exc).__name__)
                print_error(f"process {jax.process_index()} of {jax.process_count()}: {first}")
            else:
                status = run_reported(again)
        except BaseException:  # not one of the command line's errors: a traceback
            traceback.print_exception(exc)
    for stream in (sys.stdout, sys.stderr, sys.__stderr__):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(status)


def _sigterm_exits() -> None:
    """SIGTERM raises SystemExit(143) in this process (the launcher stops its processes so)."""
    import signal

    def handler(signum, frame):
        raise SystemExit(128 + signum)

    with contextlib.suppress(ValueError):  # not the main thread
        signal.signal(signal.SIGTERM, handler)


def _console():
    """The stream a launched process 0 draws its progress bar and warnings on (its own stderr is
    captured by the launcher), or None."""
    from .._distributed.launcher import CONSOLE_ENV

    fd = os.environ.pop(CONSOLE_ENV, None)
    if fd is None:
        return None
    try:
        return os.fdopen(int(fd), "w", buffering=1)
    except (OSError, ValueError):
        return None


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
    from .._distributed.launcher import die_with_launcher

    die_with_launcher()
    console = _console()

    def command():
        if console is None:
            return cli_solve(args, argv)
        # the progress bar and warnings on the launcher's terminal; errors (reported after this
        # block) and the runtime's messages stay in the stderr the launcher captures
        with contextlib.redirect_stderr(console):
            return cli_solve(args, argv)

    with cli_warnings():
        return run_reported(command)


if __name__ == "__main__":
    sys.exit(main())
