"""The options of ``mmpgo solve`` about devices, threads, processes and checkpoints, and the CPU
devices a solve uses. Light: the solve command's parser adds these options and an unsharded solve
asks :func:`thread_devices`, so nothing here loads the sharded solver (JAX only inside functions;
tests/test_architecture.py checks what ``mmpgo solve`` loads)."""

from __future__ import annotations

import contextlib

from .._solve.devices import AUTO_THREAD_POSES, cpu_cores, use_cpu_cores
from .options import finite_float, host_port, int_in

# Defaults of the library, not imported at parse time (tests check they agree):
HEARTBEAT_TIMEOUT_S = 30  # = mmpgo_jax._distributed.launcher.HEARTBEAT_TIMEOUT_S
CHECKPOINT_EVERY = 1  # = mmpgo_jax._mm.checkpoint.DEFAULT_EVERY



def add_cli_options(p) -> None:
    """Add the sharding / multi-process options to the ``mmpgo solve`` parser (every number is
    checked when it is parsed: see :func:`mmpgo_jax.cli.options.int_in`)."""
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



def add_threads_option(p) -> None:
    p.add_argument("--threads", type=int_in(1), default=None,
                   help="CPU threads: split the robots over this many CPU devices, >= 1 (default: one per core "
                        f"for graphs of {AUTO_THREAD_POSES} poses or more, else 1; ignored on a GPU)")


def add_checkpoint_options(p) -> None:
    """``--checkpoint FILE``, ``--checkpoint-every N`` and ``--resume FILE`` of ``mmpgo solve``."""
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


def configure_cpu_devices(args) -> None:
    """Give JAX's CPU backend one device per thread the command may use (``--threads``, default one
    per core; at least ``--devices``). It must run before JAX starts its backends: the command line
    does it when it starts; the library never changes this setting."""
    if any(getattr(args, k, None) is not None for k in ("processes", "num_processes", "coordinator")):
        return  # the launcher gives each process its CPU devices
    n = max(getattr(args, "threads", None) or cpu_cores(), getattr(args, "devices", None) or 1)
    if n > 1:
        # RuntimeError: backends already started (e.g. main() called twice in one process)
        with contextlib.suppress(RuntimeError):
            use_cpu_cores(n)


def thread_devices(args, num_poses: int, num_robots: int) -> list | None:
    """The CPU devices an (unsharded) ``solve`` splits its robots over, or None for one device: on
    a CPU backend, ``--threads`` (default: every core from ``AUTO_THREAD_POSES`` poses on), at most
    one device per robot."""
    from .._solve.devices import auto_layout  # the library's rule: what solve() does by default

    return getattr(auto_layout(num_poses, num_robots, threads=args.threads), "devices", None)


def wants_sharding(args) -> bool:
    """True when the parsed ``solve`` arguments ask for a sharded / multi-process run."""
    return any(getattr(args, k, None) is not None for k in ("devices", "processes", "num_processes", "coordinator"))
