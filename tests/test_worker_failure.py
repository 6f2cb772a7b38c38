"""A process of a multi-process run that dies ends the run at once, in one line.

``mmpgo solve --processes 2``: one worker is killed with SIGKILL while the run iterates (once
process 0 has written its first checkpoint). The launcher must notice within seconds, stop the
other worker, print ONE line naming the process, its pid and the signal (none of JAX's C++ stack
traces, no Python traceback), exit with a non-zero status and leave no output file (nor any
temporary file). Plus the one-line messages themselves and the heartbeat setting.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import mmpgo_jax as mm
from mmpgo_jax._distributed.launcher import HEARTBEAT_TIMEOUT_S, ProcessRun, _last_error
from mmpgo_jax._mm.checkpoint import load

FAST_COMPILE = "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"
NOISE = ("Traceback", "Check failure", "stack trace", "@     0x", "coordination_service")
ABSL_LINE = re.compile(r"^[FEWI]\d{4} \d\d:\d\d:\d\d", re.MULTILINE)  # a log line of JAX's C++ runtime


def _children(pid: int) -> dict[int, int]:
    """{--process-id: pid} of the worker processes whose parent is ``pid`` (Linux /proc)."""
    out = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmd = (entry / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        if ppid == pid and b"--process-id" in cmd:
            out[int(cmd[cmd.index(b"--process-id") + 1])] = int(entry.name)
    return out


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="finds the workers through /proc")
@pytest.mark.parametrize("victim", [0, 1])
def test_killed_worker_ends_the_run_in_one_line(tmp_path, victim):
    src = tmp_path / "cube.g2o"
    mm.write_g2o(src, mm.cube_dataset(0, num_poses=200, grid=5).graph, None)
    out, ck = tmp_path / "out.g2o", tmp_path / "ck.npz"
    env = dict(os.environ, XLA_FLAGS=FAST_COMPILE, MMPGO_COMPILATION_CACHE="off")
    cmd = [sys.executable, "-m", "mmpgo_jax.cli", "solve", str(src), "--robots", "8", "--processes", "2",
           "--iterations", "1000000", "--chunk", "10", "--out", str(out), "--checkpoint", str(ck),
           "--checkpoint-every", "1", "--timeout", "400"]
    launcher = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                                cwd=tmp_path)
    try:
        deadline = time.monotonic() + 300  # start-up and compilation of two processes on a busy machine
        while not ck.exists():  # process 0 wrote its first checkpoint: both processes iterate
            assert launcher.poll() is None, launcher.communicate()
            assert time.monotonic() < deadline, "the run did not start iterating"
            time.sleep(0.1)
        workers = _children(launcher.pid)
        assert sorted(workers) == [0, 1], workers
        pid = workers[victim]
        os.kill(pid, signal.SIGKILL)
        killed = time.monotonic()
        stdout, stderr = launcher.communicate(timeout=60)
        elapsed = time.monotonic() - killed
    finally:
        if launcher.poll() is None:
            launcher.kill()
            launcher.communicate()
    assert elapsed < 30, f"the run ended {elapsed:.1f} s after the kill"
    lines = [x for x in stderr.splitlines() if x.strip()]
    # the other process is stopped by the launcher, or has already failed on its own (its
    # collective lost its peer): either way it is gone, and its own report stays out of sight
    assert len(lines) == 1 and re.fullmatch(
        rf"mmpgo: error: worker process {victim} \(pid {pid}\) was killed by signal SIGKILL; "
        r"the other process (was stopped|failed too); no output written", lines[0]), stderr
    assert not any(word in stdout + stderr for word in NOISE), stdout + stderr
    assert not ABSL_LINE.search(stdout + stderr), stdout + stderr
    assert launcher.returncode == 128 + signal.SIGKILL
    assert not out.exists()
    assert not any(_alive(p) for p in workers.values())  # no process outlives the run
    assert load(ck).iterations % 10 == 0 and load(ck).iterations >= 10  # the checkpoint is whole
    names = sorted(p.name for p in tmp_path.iterdir())
    if victim == 0:  # SIGKILL during a checkpoint's write leaves its temporary file (nothing can remove it)
        names = [x for x in names if not re.fullmatch(r"\.ck\.npz\..+\.tmp", x)]
    assert names == ["ck.npz", "cube.g2o"]  # no output, no temporary file


def test_failure_lines():
    run = ProcessRun([0, -9], [("", ""), ("", "")], 1.0, pids=[11, 12], failed=1, stopped=[0])
    assert run.failure == "worker process 1 (pid 12) was killed by signal SIGKILL; the other process was stopped"
    assert run.exit_status == 137 and not run.ok
    run = ProcessRun([2, -15, -15], [("", "mmpgo: warning: x\nmmpgo: error: bad.g2o: line 3: no\n"), ("", ""),
                                     ("", "")], 1.0, pids=[1, 2, 3], failed=0, stopped=[1, 2])
    assert run.failure == ("worker process 0 (pid 1) exited with status 2: bad.g2o: line 3: no; 2 other processes "
                           "were stopped; no output written")
    assert run.exit_status == 2
    run = ProcessRun([1, -9, -15], [("", "")] * 3, 1.0, pids=[1, 2, 3], failed=1, stopped=[2])
    assert run.failure == ("worker process 1 (pid 2) was killed by signal SIGKILL; 1 other process was stopped; "
                           "1 other process failed too; no output written")
    run = ProcessRun([1, -9], [("", "")] * 2, 1.0, pids=[1, 2], failed=1)
    assert run.failure == "worker process 1 (pid 2) was killed by signal SIGKILL; the other process failed too; " \
                          "no output written"
    ok = ProcessRun([0, 0], [("", ""), ("", "")], 1.0, pids=[1, 2])
    assert ok.ok and ok.failure is None and ok.exit_status == 0


def test_last_error_of_a_worker():
    traceback = ('Traceback (most recent call last):\n  File "x.py", line 1, in <module>\n'
                 "jax.errors.JaxRuntimeError: INTERNAL: Gloo: connection closed by peer\n")
    assert _last_error(traceback) == "jax.errors.JaxRuntimeError: INTERNAL: Gloo: connection closed by peer"
    absl = ("E1203 16:30:17.014115   18864 coordination_service.cc:1549] propagate\n"
            "F1203 16:30:17.014747   18864 coordination_service_agent.cc:332] Terminating process because the "
            "JAX distributed service detected fatal errors.\n*** Check failure stack trace: ***\n"
            "    @     0x7f9224240634  absl::log_internal::LogMessage::SendToLog()\n")
    assert _last_error(absl).startswith("Terminating process because the JAX distributed service")
    assert _last_error("") is None and _last_error("[Gloo] Rank 0 is connected\n") is None


def test_cli_defaults_are_the_library_defaults():
    from mmpgo_jax._mm.checkpoint import DEFAULT_EVERY
    from mmpgo_jax.cli import sharded
    from mmpgo_jax.cli.app import build_parser

    assert sharded.HEARTBEAT_TIMEOUT_S == HEARTBEAT_TIMEOUT_S == 30
    assert sharded.CHECKPOINT_EVERY == DEFAULT_EVERY
    args = build_parser().parse_args(["solve", "x.g2o", "--processes", "2"])
    assert args.heartbeat_timeout == HEARTBEAT_TIMEOUT_S and args.checkpoint_every == DEFAULT_EVERY
