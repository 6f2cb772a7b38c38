"""Progress of solves: the phases a solve reports (library :class:`Monitor`), and the CLI's tqdm bar
(phase in words while nothing iterates, the rate counted from the first iteration, drawn on a
terminal that does not know its size, nothing drawn on a pipe). In-process, small graphs."""

from __future__ import annotations

import contextlib
import os
import pty
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import mmpgo_jax as mm
from mmpgo_jax.cli import main
from mmpgo_jax.cli.progress import FALLBACK_COLUMNS, ProgressBar, terminal_size_options

TINY = Path(__file__).resolve().parent / "data" / "tiny2d.g2o"  # 4 poses


class Recorder(mm.Monitor):
    def __init__(self):
        self.events = []

    def phase(self, name):
        self.events.append(name)

    def chunk(self, done, f, grad_norm):
        self.events.append((done, np.array(f), np.array(grad_norm)))

    @property
    def phases(self):
        return [e for e in self.events if isinstance(e, str)]

    @property
    def chunks(self):
        return [e for e in self.events if not isinstance(e, str)]


@contextlib.contextmanager
def unsized_terminal():
    """A pseudo-terminal without a size (0 columns, 0 rows, as under ``script``): yields its
    writable end and an object whose ``text`` is everything written, once the block ends."""
    master, slave = pty.openpty()
    chunks: list[bytes] = []

    def pump():  # read as it is written: a full pty buffer would block the writer
        while True:
            try:
                data = os.read(master, 4096)
            except OSError:  # EIO once the writing end is closed
                break
            if not data:
                break
            chunks.append(data)

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    out = SimpleNamespace(text="")
    term = open(slave, "w", encoding="utf-8")  # noqa: SIM115 (closed below, before reading the rest)
    try:
        yield term, out
    finally:
        term.close()
        reader.join(10)
        os.close(master)
        out.text = b"".join(chunks).decode("utf-8", "replace")


def _graph():
    return mm.read_g2o(TINY).graph


def test_solve_reports_phases_then_chunks():
    rec = Recorder()
    res = mm.solve(_graph(), 2, iterations=6, chunk_size=3, monitor=rec)
    assert rec.phases == ["initializing", "building", "compiling", "building", "compiling", "iterating", "finishing"]
    # the chunks come between "iterating" and "finishing", with the history's f and ||grad F||
    assert rec.events.index("iterating") < rec.events.index(rec.chunks[0]) < rec.events.index("finishing")
    assert [c[0] for c in rec.chunks] == [3, 6]
    np.testing.assert_array_equal(np.concatenate([c[1] for c in rec.chunks]), res.history.f[1:])
    np.testing.assert_array_equal(np.concatenate([c[2] for c in rec.chunks]), res.history.grad_norm[1:])


def test_optimum_reports_gradient_after_every_step():
    rec = Recorder()
    res = mm.centralized_optimum(_graph(), grad_tol=1e-9, chunk_size=1, monitor=rec)
    grads = [float(c[2][-1]) for c in rec.chunks]
    assert [c[0] for c in rec.chunks] == list(range(1, res.iterations + 1))
    # chunks of one: it stops at the first iterate below the tolerance
    assert grads[-1] <= 1e-9 and all(g > 1e-9 for g in grads[:-1])
    assert res.stop_reason == "grad_tol"


def test_bar_draws_on_a_terminal_without_size():
    with unsized_terminal() as (term, out):
        assert tuple(os.get_terminal_size(term.fileno())) == (0, 0)
        assert terminal_size_options(term) == {"ncols": FALLBACK_COLUMNS, "nrows": 24}
        bar = ProgressBar("AMM-PGO", 100, file=term)
        for name in ("reading", "initializing", "building", "compiling", "iterating"):
            bar.phase(name)
        bar.chunk(50, np.array([3.5]), np.array([1e-3]))
        bar.chunk(100, np.array([2.25]), np.array([1e-4]))
        bar.phase("finishing")
        bar.close()
    for words in ("AMM-PGO, reading", "AMM-PGO, initializing", "AMM-PGO, building", "AMM-PGO, compiling",
                  "100/100", "f=2.25"):
        assert words in out.text, out.text
    assert all(len(line) <= FALLBACK_COLUMNS for line in out.text.replace("\r", "\n").splitlines())


def test_rate_counts_iterations_only():
    with unsized_terminal() as (term, _):
        bar = ProgressBar("MM-PGO", 10, file=term)
        bar.phase("compiling")
        time.sleep(0.2)  # a slow compilation
        before = time.time()
        bar.phase("iterating")
        assert bar.bar.start_t >= before  # the clock of the rate and ETA starts with the iterations
        bar.chunk(5, np.array([1.0]), np.array([1.0]))
        assert bar.bar.format_dict["elapsed"] < 0.2
        bar.close()


def test_cli_bar_on_terminal_and_not_on_pipe(monkeypatch, capsys):
    argv = ["solve", str(TINY), "-A", "2", "-n", "4", "--chunk", "2"]
    assert main(argv) == 0
    assert capsys.readouterr().err == ""  # stderr is no terminal here: no bar
    with unsized_terminal() as (term, out):
        monkeypatch.setattr("sys.stderr", term)
        assert main(argv) == 0
        assert main(["optimum", str(TINY), "--no-certify"]) == 0
        monkeypatch.undo()
    for words in ("AMM-PGO, reading", "AMM-PGO, compiling", "4/4", "optimum, reading", "optimum, compiling",
                  "|grad F|="):
        assert words in out.text, out.text


@pytest.mark.parametrize("command", ["solve", "optimum"])
def test_cli_error_clears_the_bar(command, monkeypatch, tmp_path):
    bad = tmp_path / "bad.g2o"
    bad.write_text("EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 0 1 oops\n")
    with unsized_terminal() as (term, out):
        monkeypatch.setattr("sys.stderr", term)
        assert main([command, str(bad)]) == 2
        monkeypatch.undo()
    last = out.text.replace("\r", "\n").strip().splitlines()[-1]
    assert last.startswith("mmpgo: error: ") and "bad.g2o:2:" in last, out.text


def test_bar_of_a_solve_from_two_starts():
    """A solve from several starts reports each run's phases with its start's label, and the bar,
    closed when the first run's iterations end, opens again for the next run."""
    from test_robust import _outlier_problem

    graph, _, _ = _outlier_problem(seed=5, n=20, loops=8, outliers=5)
    rec = Recorder()
    mm.solve(graph, 2, loss="tls", start=("odometry", "gnc-chordal"), iterations=4, chunk_size=2, monitor=rec)
    phases = rec.phases
    assert "initializing, start 1 of 2, odometry" in phases and "initializing, start 2 of 2, gnc-chordal" in phases
    assert phases.count("iterating") >= 2 and phases.count("finishing") >= 2
    with unsized_terminal() as (term, out):
        bar = ProgressBar("AMM-PGO", 4, file=term)
        for name in phases:
            bar.phase(name)
            if name == "iterating":
                bar.chunk(4, np.array([1.5]), np.array([1e-3]))
        bar.close()
    assert out.text.count("4/4") >= 2 and "start 2 of 2, gnc-chordal" in out.text, out.text
