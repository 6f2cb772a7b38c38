"""The sharded ``mmpgo solve`` (``--devices``, ``--processes``, multi-host): launching local
processes, joining a multi-process run, and one process's solve with
:func:`~mmpgo_jax.sharding.solve_sharded` (process 0 prints and writes). Imported only when a
solve asks for sharding: it loads JAX's distributed runtime and the sharded solver."""

from __future__ import annotations

import contextlib
import os
import sys
import time
from collections.abc import Sequence

from .devices import HEARTBEAT_TIMEOUT_S


def cli_solve(args, argv: Sequence[str] | None = None) -> int:
    """``mmpgo solve`` with sharding options (see :func:`add_cli_options`).

    ``--processes P`` (P > 1) relaunches this command as P local processes and returns their
    status; ``--coordinator/--num-processes/--process-id`` joins a multi-process run; ``--devices``
    alone shards over this process's devices. ``argv``: the full command line (default sys.argv).
    """
    import jax

    from ..sharding import initialize_distributed, run_multiprocess
    from .errors import CLIError, print_error
    from .inputs import resolve_file
    from .outputs import check_outputs

    if args.process_id in (None, 0):  # the process that writes (or launches the one that does)
        check_outputs(args)
    if args.processes is not None and args.num_processes is None:
        if args.processes < 1:
            raise CLIError(f"--processes must be >= 1, got {args.processes}")
        if args.processes > 1:
            resolve_file(args.file, args.data, announce=False)  # fail before launching; process 0 announces
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

    from .errors import print_error, run_reported

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


def launcher_console():
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
    """Mirror of ``mmpgo solve`` (:mod:`mmpgo_jax.cli.commands.solve`) with :func:`solve_sharded`; process 0 writes."""
    import jax

    from .._solve.methods import method_label
    from ..sharding import solve_sharded
    from .errors import CLIError
    from .inputs import load_for_solve, reference_fstar, resolve_file, solve_options
    from .outputs import finish_solve, print_summary, print_timing
    from .progress import progress_bar

    writer = jax.process_index() == 0
    args.file = str(resolve_file(args.file, args.data, announce=writer))
    quiet = (not writer) or args.no_progress
    with progress_bar(method_label(args.method), args.iterations, disable=quiet,
                      show_gradient=args.grad_tol is not None) as progress:
        progress.phase("reading")
        t = time.perf_counter()
        data = load_for_solve(args, announce=writer)
        read = time.perf_counter() - t
        options = solve_options(args, data)
        local = jax.local_devices()
        if args.devices:
            if args.devices > len(local):
                raise CLIError(f"--devices {args.devices}: this process has only {len(local)} devices")
            local = local[: args.devices]
        # The mesh: this process's devices, or (multi-process) every process's, ordered by process.
        devices = local if jax.process_count() == 1 else sorted(jax.devices(), key=lambda d: (d.process_index, d.id))
        result = solve_sharded(data.graph, data.robot_of_pose, devices=devices, monitor=progress,
                               exchange=args.exchange, **options)
    if not writer:
        return 0
    fstar = reference_fstar(data)
    print_summary(result, fstar, data)
    halo = f", halo of {result.extra['halo_size']} poses per device pair" if result.extra["halo_size"] else ""
    print(f"sharding    {result.extra['devices']} devices, {result.extra['processes']} processes, "
          f"{result.extra['exchange']} exchange{halo}")
    t = time.perf_counter()
    finish_solve(args, data, result, fstar)
    print_timing(result, read=read, write=time.perf_counter() - t)
    return 0
