"""The ``mmpgo`` program: its parser (built from each command module's ``register``), ``main``
and the set-up every command shares (CPU devices, precision, compilation cache, warnings).

Bad input never ends in a traceback: g2o format problems, missing files and invalid options are
reported as ONE line ``mmpgo: error: ...`` (naming file and line where there is one; at most about
300 characters, long tokens shortened in the middle with "…") with exit status 2. Input rules:

* FILE: a path, or a bare benchmark name looked up in the data folder (:mod:`.inputs`).
* Every numeric option is checked when it is parsed (range in the message, exit status 2;
  :mod:`.options`).
* The output files (--out, --tum, --history, --plot) are checked before anything is read or
  solved, and written all-or-none (:mod:`.outputs`).
* Warnings of the reader (``G2OWarning``) and other ``UserWarning``s of mmpgo_jax are shown as one
  line ``mmpgo: warning: ...`` on stderr (:mod:`.errors`).

This module is the top of the command line: it imports the commands, none of them imports it
(except :mod:`.sharded`, the program ``python -m mmpgo_jax.sharding``, which reuses its parser).
"""

from __future__ import annotations

import argparse
import gc
import re
import sys

import numpy as np

from .commands import bench, demo, info, optimum, solve, sweep
from .errors import cli_warnings, exit_status, one_line, print_error, run_reported

COMMANDS = (info, solve, optimum, demo, bench, sweep)  # in the order of ``mmpgo --help``


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (``mmpgo: error: argument --chunk: ...``, exit status 2).

    Values such as ``-1e-3`` or ``-inf`` are taken as (negative) numbers, not as options, so that
    the option's own check reports them with its range.
    """

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(
            r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$|^-(inf|infinity|nan)$", re.IGNORECASE)

    def error(self, message):
        print_error(f"{message} (see '{self.prog} --help')")
        self.exit(2)

    def parse_args(self, args=None, namespace=None):
        """As argparse's, but an unknown option is reported by the command it was given to, with
        the closest option that command has (``--iters``: did you mean ``--iterations``?)."""
        parsed, extra = self.parse_known_args(args, namespace)
        if extra:
            command = self._command_parser(getattr(parsed, "command", None))
            print_error(f"unrecognized argument{'s' if len(extra) > 1 else ''} {' '.join(extra)}"
                        f"{_suggestion(extra, command)} (see '{command.prog} --help')")
            self.exit(2)
        return parsed

    def _command_parser(self, command: str | None) -> argparse.ArgumentParser:
        for action in self._actions:
            if isinstance(action, argparse._SubParsersAction) and command in action.choices:
                return action.choices[command]
        return self


def _suggestion(extra: list[str], parser: argparse.ArgumentParser) -> str:
    """" (did you mean --x?)" for the first unknown option that is close to one of ``parser``'s."""
    import difflib

    options = [o for o in parser._option_string_actions if o.startswith("--")]
    for word in extra:
        if word.startswith("--"):
            close = difflib.get_close_matches(word.partition("=")[0], options, n=1, cutoff=0.6)
            if close:
                return f" (did you mean {close[0]}?)"
    return ""


def build_parser() -> argparse.ArgumentParser:
    """``mmpgo``'s parser: one subparser per module of :data:`COMMANDS`, each with ``run`` (and
    optionally ``configure``: the CPU devices, before JAX starts; ``preload``: modules the program
    imports up front) as defaults."""
    from .. import __version__

    parser = _Parser(prog="mmpgo", description="Distributed PGO by majorization minimization (JAX)")
    parser.add_argument("--version", action="version", version=f"mmpgo-jax {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """``mmpgo`` with ``argv`` (default ``sys.argv[1:]``); returns the exit status (0, 2 for bad
    input or options, 130 when interrupted).

    ``argv=None`` (the ``mmpgo`` program itself, and ``python -m mmpgo_jax.cli``): the process ends
    after the command, so the garbage collector is kept off while JAX, SciPy and the solver are
    imported (about 300 000 long-lived objects, which full collections would traverse again and
    again) and those objects are then frozen (:func:`gc.freeze`), as everything is again at the end
    so that the interpreter's shutdown does not traverse them (measured: benchmarks/end_to_end.md).
    A call with ``argv`` (tests, other programs) leaves the collector alone."""
    program = argv is None
    if program:
        gc.disable()
    try:
        try:
            args = build_parser().parse_args(argv)
        except SystemExit as exc:  # --help, or a bad option (reported in one line by _Parser.error)
            return exit_status(exc)
        args.argv = list(sys.argv[1:] if argv is None else argv)  # a --processes run relaunches it
        # numpy's floating-point warnings would add lines to the one-line errors: non-finite values are
        # checked explicitly (the reader's representability rules, the solvers' NonFiniteError)
        with cli_warnings(), np.errstate(all="ignore"):
            return _run(args, program=program)
    finally:
        if program:
            gc.freeze()
            gc.enable()


def _run(args, *, program: bool = False) -> int:
    configure = getattr(args, "configure", None)
    if configure is not None:  # before JAX starts its backends
        configure(args)
    if args.precision == "float64":
        from .._core.precision import enable_float64

        enable_float64()
    _use_compilation_cache(args)
    if getattr(args, "compile_mode", None) is not None:
        from .._core.compile_mode import set_compile_mode

        set_compile_mode(args.compile_mode)
    if program:
        preload = getattr(args, "preload", None)
        if preload is not None:
            preload()
        gc.freeze()  # what is loaded now lives until the end
        gc.enable()
    return run_reported(lambda: args.run(args))


def _use_compilation_cache(args) -> None:
    """The persistent compilation cache, on unless turned off; a folder that cannot be made only
    costs the speed-up (one warning line), never the run."""
    from .._core.compilation_cache import enable_compilation_cache

    if getattr(args, "no_compilation_cache", False):
        return
    try:
        enable_compilation_cache(getattr(args, "compilation_cache", None))
    except OSError as err:
        print(one_line(f"mmpgo: warning: compilation cache off: {err}"), file=sys.stderr)
