"""Multi-process runs: ``jax.distributed`` set-up and a launcher of local CPU processes."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass

import jax
import numpy as np

# ------------------------------------------------------------------------------------------------
# Multi-process runs (jax.distributed)
# ------------------------------------------------------------------------------------------------


def initialize_distributed(
    coordinator: str,
    num_processes: int,
    process_id: int,
    *,
    cpu: bool | None = None,
    local_devices: int | None = None,
    timeout_s: int = 120,
) -> None:
    """``jax.distributed.initialize`` with bounded timeouts; call before any other JAX work.

    ``cpu``: force the CPU backend (default: when ``JAX_PLATFORMS`` is ``cpu``), with the gloo
    CPU collectives and ``local_devices`` CPU devices per process.
    """
    if cpu is None:
        cpu = os.environ.get("JAX_PLATFORMS", "").strip().lower() == "cpu"
    if cpu:
        jax.config.update("jax_platforms", "cpu")
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        if local_devices:
            jax.config.update("jax_num_cpu_devices", int(local_devices))
    jax.distributed.initialize(
        coordinator_address=coordinator,
        num_processes=num_processes,
        process_id=process_id,
        initialization_timeout=timeout_s,
        heartbeat_timeout_seconds=max(10, timeout_s // 2),
        shutdown_timeout_seconds=max(10, timeout_s // 2),
    )


def free_port(host: str = "127.0.0.1") -> int:
    """An unused TCP port on ``host`` (for a local coordinator)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


@dataclass
class ProcessRun:
    returncodes: list
    outputs: list  # (stdout, stderr) per process
    seconds: float
    timed_out: bool = False

    @property
    def ok(self) -> bool:
        return not self.timed_out and all(rc == 0 for rc in self.returncodes)


def _strip_options(argv: Sequence[str], names: Sequence[str]) -> list[str]:
    """argv without the options ``names`` (each taking one value, as ``--x v`` or ``--x=v``)."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
            continue
        if a in names:
            skip = True
            continue
        if any(a.startswith(n + "=") for n in names):
            continue
        out.append(a)
    return out


_LAUNCH_OPTIONS = ("--processes", "--coordinator", "--num-processes", "--process-id")


def run_multiprocess(
    args_for_solve: Sequence[str],
    processes: int = 2,
    coordinator: str | None = None,
    *,
    local_devices: int = 1,
    timeout_s: float = 600.0,
    env: dict | None = None,
    capture: bool = True,
) -> ProcessRun:
    """Run ``mmpgo solve <args_for_solve>`` as ``processes`` local CPU processes.

    ``args_for_solve``: the arguments of ``mmpgo solve`` (file and options; a leading ``"solve"``
    is accepted). Every process runs ``python -m mmpgo_jax.sharding`` with ``--coordinator``,
    ``--num-processes`` and ``--process-id`` added, joins the coordinator (default a free port on
    127.0.0.1), owns ``local_devices`` CPU devices, i.e. a contiguous slice of the robots, and
    process 0 prints the summary and writes the output files. The processes are killed if they
    have not all exited after ``timeout_s`` seconds.
    """
    args = list(args_for_solve)
    if args and args[0] == "solve":
        args = args[1:]
    args = _strip_options(args, _LAUNCH_OPTIONS)
    if isinstance(processes, bool) or not isinstance(processes, (int, np.integer)) or processes < 1:
        raise ValueError(f"processes must be an integer >= 1, got {processes!r}")
    if isinstance(local_devices, bool) or not isinstance(local_devices, (int, np.integer)) or local_devices < 1:
        raise ValueError(f"local_devices must be an integer >= 1, got {local_devices!r}")
    if not (isinstance(timeout_s, (int, float, np.number)) and np.isfinite(timeout_s) and timeout_s > 0):
        raise ValueError(f"timeout_s must be a finite number > 0, got {timeout_s!r}")
    coordinator = coordinator or f"127.0.0.1:{free_port()}"
    child_env = dict(os.environ if env is None else env)
    child_env["JAX_PLATFORMS"] = "cpu"
    child_env["JAX_NUM_CPU_DEVICES"] = str(local_devices)
    if "xla_force_host_platform_device_count" in child_env.get("XLA_FLAGS", ""):
        del child_env["XLA_FLAGS"]  # the device count per process is JAX_NUM_CPU_DEVICES
    import tempfile

    procs, logs = [], []
    t0 = time.perf_counter()
    for i in range(processes):
        cmd = [
            sys.executable,
            "-m",
            "mmpgo_jax.sharding",
            "solve",
            *args,
            "--coordinator",
            coordinator,
            "--num-processes",
            str(processes),
            "--process-id",
            str(i),
            "--local-devices",
            str(local_devices),
        ]
        if capture:  # files, not pipes: a chatty process can never block on a full pipe
            # kept open while the processes run, closed below once their output is read
            out, err = tempfile.TemporaryFile("w+"), tempfile.TemporaryFile("w+")  # noqa: SIM115
            logs.append((out, err))
        else:
            out = err = None
        procs.append(subprocess.Popen(cmd, env=child_env, stdout=out, stderr=err, text=True))
    # Wait for all; if one fails (or time runs out) stop the others at once instead of letting
    # them wait in a collective for a peer that is gone.
    deadline = t0 + timeout_s
    timed_out = False
    while any(p.poll() is None for p in procs):
        failed = any(p.returncode not in (None, 0) for p in procs)
        if failed or time.perf_counter() > deadline:
            timed_out = not failed
            for p in procs:
                if p.poll() is None:
                    p.kill()
            for p in procs:
                p.wait()
            break
        time.sleep(0.1)
    codes = [p.returncode for p in procs]
    outputs = []
    for out, err in logs:
        out.seek(0), err.seek(0)
        outputs.append((out.read(), err.read()))
        out.close(), err.close()
    if not capture:
        outputs = [("", "")] * processes
    return ProcessRun(codes, outputs, time.perf_counter() - t0, timed_out)
