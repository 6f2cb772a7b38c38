"""Multi-process runs: ``jax.distributed`` set-up and a launcher of local CPU processes."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import jax
import numpy as np

# ------------------------------------------------------------------------------------------------
# Multi-process runs (jax.distributed)
# ------------------------------------------------------------------------------------------------


# How long a multi-process run waits for a process that stopped answering. JAX's coordination
# service declares a process dead when it has sent no heartbeat for HEARTBEAT_TIMEOUT_S seconds
# (heartbeats come from a C++ thread, so long computations, compilations or the Python GIL do not
# delay them) and then aborts every other process. Measured on this project's machine: a process
# killed (SIGKILL) or stopped (SIGSTOP) was declared dead after 17-26 s (docs/scaling.md). JAX's
# own default is 100 s; the former setting here, half of --timeout, was 300 s.
HEARTBEAT_TIMEOUT_S = 30
# How long a process that has finished waits at JAX's shutdown barrier for the others, e.g. for
# process 0 writing the output files of a large graph (JAX's default).
SHUTDOWN_TIMEOUT_S = 300


def initialize_distributed(
    coordinator: str,
    num_processes: int,
    process_id: int,
    *,
    cpu: bool | None = None,
    local_devices: int | None = None,
    timeout_s: int = 120,
    heartbeat_timeout_s: int = HEARTBEAT_TIMEOUT_S,
    shutdown_timeout_s: int = SHUTDOWN_TIMEOUT_S,
) -> None:
    """``jax.distributed.initialize`` with bounded timeouts; call before any other JAX work.

    ``cpu``: force the CPU backend (default: when ``JAX_PLATFORMS`` is ``cpu``), with the gloo
    CPU collectives and ``local_devices`` CPU devices per process. ``timeout_s``: how long to wait
    for every process to join. ``heartbeat_timeout_s``: a process that sends no heartbeat for
    this long is declared dead and the coordination service ends the others (they abort), so a
    lost process or host ends the run instead of leaving it waiting forever (default
    :data:`HEARTBEAT_TIMEOUT_S`). ``shutdown_timeout_s``: how long a finished process waits at the
    shutdown barrier for the others (default :data:`SHUTDOWN_TIMEOUT_S`). JAX's preemption
    service, which would catch SIGTERM, is turned off: SIGTERM ends a process.
    """
    for name, value in (("timeout_s", timeout_s), ("heartbeat_timeout_s", heartbeat_timeout_s),
                        ("shutdown_timeout_s", shutdown_timeout_s)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
    if cpu is None:
        cpu = os.environ.get("JAX_PLATFORMS", "").strip().lower() == "cpu"
    if cpu:
        jax.config.update("jax_platforms", "cpu")
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        if local_devices:
            jax.config.update("jax_num_cpu_devices", int(local_devices))
    jax.config.update("jax_enable_preemption_service", False)
    jax.distributed.initialize(
        coordinator_address=coordinator,
        num_processes=num_processes,
        process_id=process_id,
        initialization_timeout=int(timeout_s),
        heartbeat_timeout_seconds=int(heartbeat_timeout_s),
        shutdown_timeout_seconds=int(shutdown_timeout_s),
    )


def free_port(host: str = "127.0.0.1") -> int:
    """An unused TCP port on ``host`` (for a local coordinator)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


@dataclass
class ProcessRun:
    """The outcome of :func:`run_multiprocess`: per process its exit status (``returncodes``, as
    ``subprocess``: -N for a signal N), captured ``(stdout, stderr)`` and ``pids``; ``failed``:
    the index of the process whose failure ended the run (the first seen to fail; of several seen
    at once, a signal from outside before an exit status before SIGABRT), ``stopped``: the
    processes the launcher then stopped itself."""

    returncodes: list
    outputs: list  # (stdout, stderr) per process
    seconds: float
    timed_out: bool = False
    pids: list = field(default_factory=list)
    failed: int | None = None
    stopped: list = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.timed_out and all(rc == 0 for rc in self.returncodes)

    @property
    def exit_status(self) -> int:
        """0 when every process succeeded; else the failed process's status, 128 + N when it was
        killed by signal N (as a shell reports it), 1 after a timeout."""
        if self.ok:
            return 0
        if self.failed is None:
            return 1
        rc = self.returncodes[self.failed]
        return 128 - rc if rc < 0 else rc

    @property
    def failure(self) -> str | None:
        """One line saying which process ended the run and how (None when the run succeeded or
        timed out), e.g. ``worker process 1 (pid 4242) was killed by signal SIGKILL; the other
        process was stopped; no output written``."""
        if self.failed is None:
            return None
        i = self.failed
        rc = self.returncodes[i]
        pid = f" (pid {self.pids[i]})" if i < len(self.pids) else ""
        what = f"was killed by signal {_signal_name(-rc)}" if rc < 0 else f"exited with status {rc}"
        reason = _last_error(self.outputs[i][1]) if i < len(self.outputs) else None
        text = f"worker process {i}{pid} {what}" + (f": {reason}" if reason else "")
        others = len(self.returncodes) - 1
        failed_too = [j for j, c in enumerate(self.returncodes) if j != i and c != 0 and j not in self.stopped]
        for count, verb in ((len(self.stopped), "was stopped"), (len(failed_too), "failed too")):
            if count:  # e.g. a process whose collective lost its peer fails on its own
                who = "the other process" if others == 1 else f"{count} other process{'es' if count > 1 else ''}"
                text += f"; {who} {verb if count == 1 else verb.replace('was', 'were')}"
        if self.returncodes[0] != 0:
            text += "; no output written"
        return text


def _signal_name(number: int) -> str:
    try:
        return signal.Signals(number).name
    except ValueError:
        return str(number)


# An absl log line of JAX's C++ runtime: "F0102 12:34:56.789012  4242 file.cc:123] message".
_ABSL_FATAL = re.compile(r"^F\d{4} [\d:.]+\s+\d+ [^\]]+\] (.+)$")
_PY_ERROR = re.compile(r"^([A-Za-z_][\w.]*(Error|Exception|Interrupt|Exit))(: .*)?$")


def _last_error(stderr: str) -> str | None:
    """The message a failed process left on its stderr: its ``mmpgo: error:`` line, else the
    last line of a Python traceback, else the last fatal message of JAX's C++ runtime."""
    lines = [x.strip() for x in (stderr or "").splitlines() if x.strip()]
    for line in reversed(lines):
        if line.startswith("mmpgo: error: "):
            return line[len("mmpgo: error: "):]
    for line in reversed(lines):
        if _PY_ERROR.match(line):
            return line
    for line in reversed(lines):
        m = _ABSL_FATAL.match(line)
        if m:
            return m.group(1)
    return None


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
CONSOLE_ENV = "MMPGO_CONSOLE_FD"  # process 0's file descriptor for its progress bar and warnings
LAUNCHER_ENV = "MMPGO_LAUNCHER_PID"  # the launcher's pid, for die_with_launcher
POLL_S = 0.05  # how often the launcher looks at its processes
GRACE_S = 3.0  # SIGTERM, then SIGKILL after this many seconds


def die_with_launcher() -> None:
    """In a launched process (Linux): get SIGKILL when the launcher dies, even by SIGKILL, so that
    no process of a run outlives it (``prctl(PR_SET_PDEATHSIG)``, set by the process itself rather
    than between fork and exec, which a launcher with threads must not run Python in)."""
    launcher = os.environ.pop(LAUNCHER_ENV, None)
    if launcher is None or not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if str(os.getppid()) != launcher:  # the launcher died before prctl
        os._exit(128 + int(signal.SIGKILL))


def _cause(returncode: int) -> int:
    """Rank of an exit seen together with others (lower: likelier the cause of the others): a
    signal from outside (SIGKILL, SIGTERM, ...), then an exit status (a process that failed, or
    whose collective lost its peer), then SIGABRT (JAX's runtime aborting a process whose peer
    is gone)."""
    if returncode == -signal.SIGABRT:
        return 2
    return 0 if returncode < 0 else 1


def _stop(procs, grace_s: float) -> list[int]:
    """SIGTERM every process still running, SIGKILL those left after ``grace_s``; returns their indices."""
    running = [i for i, p in enumerate(procs) if p.poll() is None]
    for i in running:
        with contextlib.suppress(OSError):
            procs[i].terminate()
    end = time.perf_counter() + grace_s
    for i in running:
        try:
            procs[i].wait(timeout=max(0.0, end - time.perf_counter()))
        except subprocess.TimeoutExpired:
            with contextlib.suppress(OSError):
                procs[i].kill()
    for i in running:
        procs[i].wait()
    return running


@contextlib.contextmanager
def _sigterm_exits():
    """In the main thread: SIGTERM raises SystemExit(143), so the launcher stops its processes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise SystemExit(128 + signum)

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def run_multiprocess(
    args_for_solve: Sequence[str],
    processes: int = 2,
    coordinator: str | None = None,
    *,
    local_devices: int = 1,
    timeout_s: float = 600.0,
    env: dict | None = None,
    capture: bool = True,
    console: bool = False,
    grace_s: float = GRACE_S,
) -> ProcessRun:
    """Run ``mmpgo solve <args_for_solve>`` as ``processes`` local CPU processes.

    ``args_for_solve``: the arguments of ``mmpgo solve`` (file and options; a leading ``"solve"``
    is accepted). Every process runs ``python -m mmpgo_jax.sharding`` with ``--coordinator``,
    ``--num-processes`` and ``--process-id`` added, joins the coordinator (default a free port on
    127.0.0.1), owns ``local_devices`` CPU devices, i.e. a contiguous slice of the robots, and
    process 0 prints the summary and writes the output files.

    The launcher watches every process (every :data:`POLL_S` seconds): as soon as one exits with
    a non-zero status or is killed by a signal, the others are stopped (SIGTERM, then SIGKILL
    after ``grace_s`` seconds) instead of waiting in a collective for a peer that is gone;
    ``ProcessRun.failure`` then says in one line which process ended the run and how. The same
    happens after ``timeout_s`` seconds (``timed_out``), when this process is interrupted
    (KeyboardInterrupt, or SIGTERM, which raises SystemExit(143) while it waits in the main
    thread), and on Linux the processes die with the launcher even when it is killed.

    ``capture``: each process's stdout and stderr go to files, returned in ``outputs``.
    ``console`` (with ``capture``; what ``mmpgo solve --processes`` uses): process 0's stdout is
    this process's, and its progress bar and warnings are drawn on this process's stderr, while
    every process's own stderr (where JAX's runtime reports a lost peer, with C++ stack traces) is
    captured. ``capture=False``: everything goes to this process's stdout and stderr.
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
    child_env.pop(CONSOLE_ENV, None)
    child_env[LAUNCHER_ENV] = str(os.getpid())
    if "xla_force_host_platform_device_count" in child_env.get("XLA_FLAGS", ""):
        del child_env["XLA_FLAGS"]  # the device count per process is JAX_NUM_CPU_DEVICES
    console_fd = None
    if capture and console:
        with contextlib.suppress(AttributeError, OSError, ValueError):
            sys.stderr.flush()
            console_fd = os.dup(sys.stderr.fileno())

    procs, logs = [], []
    t0 = time.perf_counter()
    failed, stopped, timed_out = None, [], False
    try:
        with _sigterm_exits():
            for i in range(processes):
                cmd = [
                    sys.executable, "-m", "mmpgo_jax.sharding", "solve", *args,
                    "--coordinator", coordinator,
                    "--num-processes", str(processes),
                    "--process-id", str(i),
                    "--local-devices", str(local_devices),
                ]
                proc_env, pass_fds, out = child_env, (), None
                if capture:  # files, not pipes: a chatty process can never block on a full pipe
                    # kept open while the processes run, closed below once their output is read
                    out, err = tempfile.TemporaryFile("w+"), tempfile.TemporaryFile("w+")  # noqa: SIM115
                    logs.append((out, err))
                    if i == 0 and console:
                        out = None  # process 0's summary goes straight to this process's stdout
                        if console_fd is not None:
                            proc_env = {**child_env, CONSOLE_ENV: str(console_fd)}
                            pass_fds = (console_fd,)
                else:
                    err = None
                procs.append(subprocess.Popen(cmd, env=proc_env, stdout=out, stderr=err, text=True,
                                              pass_fds=pass_fds))
            deadline = t0 + timeout_s
            while True:
                codes = [p.poll() for p in procs]  # every process, every time
                bad = [i for i, rc in enumerate(codes) if rc not in (None, 0)]
                if bad:  # seen in the same look: the likelier cause first (see _cause)
                    failed = min(bad, key=lambda i: (_cause(codes[i]), i))
                    break
                if all(rc is not None for rc in codes):
                    break
                if time.perf_counter() > deadline:
                    timed_out = True
                    break
                time.sleep(POLL_S)
            stopped = _stop(procs, grace_s)
    finally:
        if any(p.poll() is None for p in procs):  # interrupted: no process outlives the launcher
            _stop(procs, grace_s)
        if console_fd is not None:
            os.close(console_fd)
    codes = [p.returncode for p in procs]
    outputs = []
    for out, err in logs:
        out.seek(0), err.seek(0)
        outputs.append((out.read(), err.read()))
        out.close(), err.close()
    if not capture:
        outputs = [("", "")] * processes
    return ProcessRun(codes, outputs, time.perf_counter() - t0, timed_out, [p.pid for p in procs], failed, stopped)
