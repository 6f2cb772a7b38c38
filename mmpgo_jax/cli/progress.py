"""One progress bar for every solve of the CLI (solve, optimum, bench, demo, sharded solve).

:class:`ProgressBar` is the solvers' :class:`~mmpgo_jax._mm.driver.Monitor`: while nothing
iterates it names the phase ("AMM-PGO, reading", "... initializing", "... building",
"... compiling"); when the compiled iterations begin it restarts tqdm's clock, so that the rate
and the ETA count iterations alone, not reading and compilation; after each chunk it advances and
shows f (and ||grad F|| when the run stops at a gradient tolerance). It closes when the iterations
end, so that its rate is theirs alone.

The bar is drawn on stderr when stderr is a terminal (tqdm's ``disable=None``): files and pipes
get no bar. A terminal of unknown size (a pty without one, e.g. under ``script``, reports 0
columns and rows, from which tqdm computes -1 and draws nothing) gets a fixed width. tqdm is
imported lazily so library users who never ask for progress do not pay for it.
"""

from __future__ import annotations

import os
import sys
from contextlib import contextmanager

from .._mm.driver import Monitor

__all__ = ["ProgressBar", "progress_bar", "terminal_size_options", "write_line"]

FALLBACK_COLUMNS = 80  # width of the bar on a terminal that does not know its size
FALLBACK_ROWS = 24


def terminal_size_options(file) -> dict:
    """tqdm's size options for ``file``: follow the terminal's width when it reports one, a fixed
    width when it reports 0 (a pty without a size), tqdm's own defaults when it is no terminal."""
    try:
        columns, rows = os.get_terminal_size(file.fileno())
    except (AttributeError, OSError, ValueError):
        return {}
    if columns > 1 and rows > 1:
        return {"dynamic_ncols": True}
    return {"ncols": columns - 1 if columns > 1 else FALLBACK_COLUMNS, "nrows": rows if rows > 1 else FALLBACK_ROWS}


def write_line(text: str, file=None) -> None:
    """``print(text, file=file)`` that clears a progress bar on the terminal and draws it again
    below the text (instead of writing into the bar's line)."""
    file = sys.stdout if file is None else file
    if "tqdm" in sys.modules:
        from tqdm import tqdm

        tqdm.write(text, file=file)
    else:
        print(text, file=file)
    file.flush()


class ProgressBar(Monitor):
    """A tqdm bar on ``file`` (default stderr) for a solve of ``total`` iterations (None: unknown,
    e.g. a solve to a gradient tolerance). ``show_gradient``: show ||grad F|| beside f."""

    def __init__(self, desc: str, total: int | None, *, leave: bool = True, show_gradient: bool = False,
                 file=None):
        from tqdm.auto import tqdm

        file = sys.stderr if file is None else file
        self.desc = desc
        self.phase_name = ""  # the phase a note() belongs to
        self.show_gradient = show_gradient
        self._new_bar = lambda: tqdm(total=total, desc=desc, unit="it", file=file, leave=leave, disable=None,
                                     **terminal_size_options(file))
        self.bar = self._new_bar()
        self.closed = False

    def phase(self, name: str) -> None:
        if self.closed and name != "finishing":  # a solve from several starts: the next run's bar
            self.bar, self.closed = self._new_bar(), False
        if name == "iterating":
            self.bar.set_description_str(self.desc, refresh=False)
            self.bar.reset(total=self.bar.total)  # the clock of the rate and ETA starts now
        elif name == "finishing":
            self.bar.close()  # the rate stays that of the iterations
            self.closed = True
        else:
            self.phase_name = name
            self.bar.set_description_str(f"{self.desc}, {name}")

    def note(self, text: str) -> None:
        self.bar.set_description_str(f"{self.desc}, {self.phase_name} ({text})")

    def chunk(self, done: int, f, grad_norm) -> None:
        text = f"f={float(f[-1]):.7g}"
        if self.show_gradient:
            text += f", |grad F|={float(grad_norm[-1]):.1e}"
        self.bar.set_postfix_str(text, refresh=False)
        self.bar.update(done - self.bar.n)

    def close(self, *, clear: bool = False) -> None:
        if clear:
            self.bar.leave = False  # an error follows: no half-finished bar above it
        self.bar.close()


def _not_a_terminal(file) -> bool:
    """tqdm's own test for ``disable=None`` (no bar on a file or pipe), made before importing tqdm:
    a run whose stderr is not a terminal does not load it (``import tqdm.auto``: 0.07 s in a fresh
    process, 2026-12-02)."""
    return hasattr(file, "isatty") and not file.isatty()


@contextmanager
def progress_bar(desc: str, total: int | None, *, disable: bool = False, leave: bool = True,
                 show_gradient: bool = False):
    """Yield a :class:`ProgressBar` (a plain, silent :class:`Monitor` when ``disable``, ``total == 0``
    or stderr is not a terminal); it is closed at the end, and cleared when an exception leaves the
    block."""
    if disable or total == 0 or _not_a_terminal(sys.stderr):
        yield Monitor()
        return
    bar = ProgressBar(desc, total, leave=leave, show_gradient=show_gradient)
    try:
        yield bar
    except BaseException:
        bar.close(clear=True)
        raise
    bar.close()
