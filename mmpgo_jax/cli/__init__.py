"""The ``mmpgo`` command line: ``info``, ``solve``, ``optimum``, ``demo`` and ``bench``.

Bad input never ends in a traceback: g2o format problems, missing files and invalid options are
reported as ONE line ``mmpgo: error: ...`` (naming file and line where there is one; at most about
300 characters, long tokens shortened in the middle with "…") with exit status 2. Input rules:

* FILE is a path when it has a directory part, starts with ``~`` or ``.``, or exists; a path is
  never replaced by a benchmark of the same name. Only a bare name (``MITb``, ``city``, a file
  name absent from the working directory) is looked up in the data folder, and the command then
  prints ``using PATH (benchmark NAME)``.
* Every numeric option is checked when it is parsed (range in the message, exit status 2).
* The output files (--out, --tum, --history, --plot) are checked before anything is read or
  solved (folder exists and is writable, not a directory, no two the same file), and written
  all-or-none: each to a temporary file, renamed into place only when all succeeded. Writing
  through a symbolic link replaces the link's target and keeps the link.
* Warnings of the reader (``G2OWarning``) and other ``UserWarning``s of mmpgo_jax are shown as one
  line ``mmpgo: warning: ...`` on stderr.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import math
import os
import re
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._core.messages import join_items, shorten_words


class CLIError(Exception):
    """An error to report to the user without a traceback."""


# ------------------------------------------------------------------------------------------------
# One-line messages
# ------------------------------------------------------------------------------------------------

MAX_MESSAGE = 300  # characters of an error or warning message (after "mmpgo: error: ")
MAX_TOKEN = 120  # longer words (paths, file content) are shortened in the middle
_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f]")


def _shorten(text: str, limit: int) -> str:
    if len(text) <= limit:
        return text
    head = (limit - 1) // 2
    return text[:head] + "…" + text[len(text) - (limit - 1 - head):]


def one_line(message, limit: int = MAX_MESSAGE) -> str:
    """``message`` as one line of at most ``limit`` characters: whitespace runs (newlines included)
    become one space, control characters '?', words longer than :data:`MAX_TOKEN` are shortened in
    the middle with "…", and then whole words are dropped from the middle of the text (never a cut
    inside a name)."""
    text = str(message)
    words = [_shorten(_CONTROL.sub("?", w), MAX_TOKEN) for w in text.split()]
    return shorten_words(" ".join(words), limit)


def print_error(message) -> None:
    print(f"mmpgo: error: {one_line(message)}", file=sys.stderr, flush=True)


def _is_mmpgo_warning(category, filename) -> bool:
    if not issubclass(category, UserWarning):
        return False
    if any(c.__name__ == "G2OWarning" for c in category.__mro__):
        return True
    package = os.path.dirname(os.path.dirname(os.path.abspath(__file__))) + os.sep  # mmpgo_jax/
    return os.path.abspath(str(filename)).startswith(package)


@contextlib.contextmanager
def cli_warnings():
    """Show the reader's ``G2OWarning`` and any other ``UserWarning`` raised from inside mmpgo_jax
    as one line ``mmpgo: warning: ...`` on stderr (no source line); other warnings as usual."""
    with warnings.catch_warnings():
        original = warnings.showwarning

        def show(message, category, filename, lineno, file=None, line=None):
            if _is_mmpgo_warning(category, filename):
                from .progress import write_line

                write_line(f"mmpgo: warning: {one_line(message)}", sys.stderr)
            else:
                original(message, category, filename, lineno, file, line)

        warnings.showwarning = show
        yield


def _exit_status(exc: SystemExit) -> int:
    if exc.code is None:
        return 0
    return exc.code if isinstance(exc.code, int) else 2


# ------------------------------------------------------------------------------------------------
# Option types: every number is checked when it is parsed
# ------------------------------------------------------------------------------------------------

INT_MAX = 2**31 - 1  # iteration counts end up in int32 arrays in float32 mode


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


def _range_text(low, high, *, strict_low: bool = False) -> str:
    if high is None:
        return f"{'>' if strict_low else '>='} {low:g}" if isinstance(low, float) else f">= {low}"
    return f"between {low} and {high}"


def int_in(low: int, high: int | None = None):
    """argparse ``type``: an integer with ``low <= value (<= high)``."""

    def parse(text: str) -> int:
        try:
            value = int(text, 10)
        except (TypeError, ValueError):
            value = None
        if value is None or value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"must be an integer {_range_text(low, high)}, got {text!r}")
        return value

    parse.__name__ = "integer"
    return parse


def finite_float(low: float, *, strict: bool = False):
    """argparse ``type``: a finite number ``>= low`` (``> low`` with ``strict``)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except (TypeError, ValueError):
            value = math.nan
        if not math.isfinite(value) or value < low or (strict and value == low):
            raise argparse.ArgumentTypeError(
                f"must be a finite number {_range_text(float(low), None, strict_low=strict)}, got {text!r}")
        return value

    parse.__name__ = "number"
    return parse


def host_port(text: str) -> str:
    """argparse ``type``: ``HOST:PORT`` with a port between 1 and 65535."""
    host, sep, port = text.rpartition(":")
    ok = bool(sep and host.strip("[]") and port.isdigit() and 1 <= int(port) <= 65535)
    if not ok:
        raise argparse.ArgumentTypeError(f"must be HOST:PORT with PORT between 1 and 65535, got {text!r}")
    return text


ROBOTS = int_in(1)
ITERATIONS = int_in(0, INT_MAX)


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", help="folder with benchmark g2o files (default: $MMPGO_DATA, else ../shared/datasets)")
    p.add_argument(
        "--precision",
        choices=("float64", "float32"),
        default="float64",
        help="floating-point precision (default float64, as the paper and SE-Sync)",
    )
    cache = p.add_mutually_exclusive_group()
    cache.add_argument("--compilation-cache", metavar="DIR",
                       help="folder of JAX's persistent compilation cache (default: $MMPGO_COMPILATION_CACHE, "
                            "else ~/.cache/mmpgo-jax/jax): a second run of the same shapes skips compilation")
    cache.add_argument("--no-compilation-cache", action="store_true",
                       help="compile afresh, write no cache (also: MMPGO_COMPILATION_CACHE=off)")


def _add_solver_options(p: argparse.ArgumentParser) -> None:
    from .robots import add_robots_from

    p.add_argument("--robots", "-A", type=ROBOTS, default=None,
                   help="number of robots, >= 1 and at most the number of poses (for --robots-from blocks, metis, "
                        "random; default 10)")
    add_robots_from(p)
    p.add_argument("--method", choices=("amm", "mm"), default="amm", help="AMM-PGO (default) or MM-PGO")
    p.add_argument("--iterations", "-n", type=ITERATIONS, default=1000,
                   help="at most this many outer iterations, >= 0 (default 1000); the run stops earlier when f "
                        "moves only by rounding (see --all-iterations) or at --grad-tol")
    p.add_argument("--all-iterations", action="store_true",
                   help="run every one of --iterations even once f moves only by rounding (fixed-length histories)")
    p.add_argument(
        "--init",
        default=None,
        help="start: chordal (default for least squares), gnc-chordal (default for a robust --loss: GNC-TLS with "
             "chordal stages, not bent by outliers), distributed-chordal, vertices, odometry, or a .g2o/.npz file "
             "of poses",
    )
    p.add_argument("--restart", choices=("adaptive", "average", "paper"), default="adaptive",
                   help="AMM restart rule (default adaptive; see README)")
    p.add_argument("--xi", type=finite_float(0.0), default=1e-3,
                   help="proximal weight xi of Eq. (13), finite and >= 0 (default 1e-3)")
    p.add_argument("--grad-tol", type=finite_float(0.0, strict=True), default=None,
                   help="stop when ||grad F|| falls below this (finite, > 0)")
    p.add_argument("--chunk", type=int_in(1, INT_MAX), default=50,
                   help="iterations per compiled chunk, >= 1 (progress granularity; default 50)")
    p.add_argument("--largest-component", action="store_true", help="solve only the largest connected component")
    p.add_argument("--no-progress", action="store_true", help="do not show a progress bar")


def _add_robust_options(p: argparse.ArgumentParser) -> None:
    from .._mm.robust import LOSSES

    g = p.add_argument_group("robust losses (outlier loop closures)")
    g.add_argument("--loss", choices=LOSSES, default="l2",
                   help="kernel of the robust objective (default l2, least squares), started from the GNC start "
                        "(--init gnc-chordal); odometry edges (consecutive poses) always keep weight 1")
    g.add_argument("--gnc", action="store_true",
                   help="tls, geman-mcclure: run GNC's stages inside the distributed solver (fully distributed, "
                        "from the chordal start; less reliable than the default GNC start, see README)")
    g.add_argument("--loss-scale", metavar="C", type=finite_float(0.0, strict=True), default=None,
                   help="scale c of the kernel in residual units, > 0 (default: sqrt of the 0.99 chi-square quantile "
                        "with d(d+1)/2 degrees of freedom: 3.37 in 2D, 4.10 in 3D)")
    g.add_argument("--edge-weights", metavar="OUT.csv",
                   help="write every edge's final weight and inlier flag as CSV (i, j, weight, inlier; original ids)")
    g.add_argument("--drop-outliers", action="store_true",
                   help="--out / --out-dir keep only the inlier edges (by default every edge is written)")


def _add_strict(p: argparse.ArgumentParser) -> None:
    p.add_argument("--strict-information", action="store_true",
                   help="refuse information matrices that are not positive definite (default: warn and use "
                        "SE-Sync's isotropic weights)")


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__
    from .robots import FILE_HELP, add_robots_from

    parser = _Parser(prog="mmpgo", description="Distributed PGO by majorization minimization (JAX)")
    parser.add_argument("--version", action="version", version=f"mmpgo-jax {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("info", help="describe a pose graph and its partition among robots")
    p.add_argument("file", help=FILE_HELP)
    p.add_argument("--robots", "-A", type=ROBOTS, default=None,
                   help="also describe the split among A robots (1 .. number of poses)")
    add_robots_from(p)
    _add_strict(p)
    _add_common(p)

    p = sub.add_parser("solve", help="run MM-PGO / AMM-PGO on a g2o file")
    p.add_argument("file", help=FILE_HELP)
    _add_solver_options(p)
    p.add_argument("--out", "-o", help="write the estimate as g2o (VERTEX lines + the original edges)")
    p.add_argument("--tum", help="write the estimate as a TUM trajectory (index tx ty tz qx qy qz qw)")
    p.add_argument("--tum-dir", metavar="DIR",
                   help="write one TUM trajectory per robot, DIR/<robot>.tum, and the whole one, DIR/all_robots.tum")
    p.add_argument("--out-dir", metavar="DIR",
                   help="write the estimate as one g2o file per robot, DIR/<robot>.g2o (the per-robot folder layout, "
                        "which reads back with --robots-from files)")
    p.add_argument("--history", help="write the per-iteration history as CSV")
    p.add_argument("--plot", help="write convergence and trajectory plots to this PNG")
    p.add_argument(
        "--certify",
        action="store_true",
        help="check global optimality of the result (SE-Sync's dual certificate; meaningful at a critical point)",
    )
    p.add_argument(
        "--ground-truth",
        help="poses to compare with (.g2o VERTEX lines or .npz with R, t): reports ATE and RPE after rigid alignment",
    )
    _add_robust_options(p)
    _add_strict(p)
    _add_common(p)
    from .sharded import add_checkpoint_options, add_cli_options, add_threads_option

    add_checkpoint_options(p)
    add_threads_option(p)
    add_cli_options(p)

    p = sub.add_parser("optimum", help="centralized optimum f* of a g2o file, with its global-optimality certificate")
    p.add_argument("file", help=FILE_HELP)  # read as solve reads it (TORO, per-robot folders too)
    p.add_argument("--init", default="chordal",
                   help="start: chordal (default), vertices, odometry, or a .g2o/.npz file")
    p.add_argument("--grad-tol", type=finite_float(0.0, strict=True), default=1e-6,
                   help="stop when ||grad F|| falls below this (finite, > 0; default 1e-6)")
    p.add_argument("--max-iterations", type=int_in(1, INT_MAX), default=5000,
                   help="at most this many iterations, >= 1 (default 5000)")
    p.add_argument("--no-certify", action="store_true", help="skip the dual certificate")
    p.add_argument("--out", "-o", help="write the optimum as g2o (VERTEX lines + the original edges)")
    p.add_argument("--tum", help="write the optimum as a TUM trajectory")
    p.add_argument("--largest-component", action="store_true", help="solve only the largest connected component")
    p.add_argument("--no-progress", action="store_true", help="do not show a progress bar")
    _add_strict(p)
    _add_common(p)

    p = sub.add_parser("demo", help="run AMM-PGO on a generated Cube dataset (no download needed)")
    p.add_argument("--out-dir", default="mmpgo-demo", help="folder for the plots and results (default ./mmpgo-demo)")
    p.add_argument("--poses", type=int_in(2, INT_MAX), default=1000,
                   help="poses of the generated Cube dataset, >= 2 (default 1000)")
    p.add_argument("--robots", "-A", type=ROBOTS, default=10, help="robots, 1 .. --poses (default 10)")
    p.add_argument("--iterations", "-n", type=ITERATIONS, default=300, help="outer iterations, >= 0 (default 300)")
    p.add_argument("--seed", type=int_in(0), default=0, help="seed of the generated dataset, >= 0 (default 0)")
    p.add_argument("--no-progress", action="store_true")
    _add_common(p)

    from .sharded import add_threads_option

    p = sub.add_parser("bench", help="reproduce the paper's Tables I/II on the available datasets")
    p.add_argument("--quick", action="store_true", help="a small run for CI: one small dataset, few iterations")
    p.add_argument("--datasets", nargs="*", help="benchmark names (default: all available)")
    p.add_argument("--iterations", "-n", type=int_in(1, INT_MAX), default=1000,
                   help="outer iterations, >= 1 (default 1000)")
    p.add_argument("--robots", "-A", type=ROBOTS, default=10, help="robots, >= 1 (default 10)")
    add_robots_from(p, ("blocks", "metis", "random"))
    add_threads_option(p)
    p.add_argument("--out-dir", default="bench-results", help="folder for the Markdown, CSV and JSON tables")
    p.add_argument("--no-progress", action="store_true")
    _add_common(p)

    from .sweep import add_sweep_parser

    add_sweep_parser(sub, add_common=_add_common, robots_type=ROBOTS, iterations_type=int_in(1, INT_MAX))
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
            return _exit_status(exc)
        # numpy's floating-point warnings would add lines to the one-line errors: non-finite values are
        # checked explicitly (the reader's representability rules, the solvers' NonFiniteError)
        with cli_warnings(), np.errstate(all="ignore"):
            return _run(args, argv, program=program)
    finally:
        if program:
            gc.freeze()
            gc.enable()


# The modules a command needs beyond the parser's: imported up front by the program (with the
# collector off, see main); each command imports them again where it uses them.
_COMMAND_MODULES = {"solve": ("mmpgo_jax._mm.solve", "mmpgo_jax._io.g2o", "mmpgo_jax.cli.robots",
                              "mmpgo_jax.cli.progress")}


def _run(args, argv, *, program: bool = False) -> int:
    if args.command in ("solve", "bench"):
        from .sharded import configure_cpu_devices

        configure_cpu_devices(args)
    if args.precision == "float64":
        from .._core.precision import enable_float64

        enable_float64()
    _use_compilation_cache(args)
    if program:
        import importlib

        for module in _COMMAND_MODULES.get(args.command, ()):
            importlib.import_module(module)
        gc.freeze()  # what is loaded now lives until the end
        gc.enable()
    return run_reported(lambda: _dispatch(args, argv))


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


def _dispatch(args, argv) -> int:
    if args.command == "info":
        return _cmd_info(args)
    if args.command == "solve":
        from .sharded import cli_solve, wants_sharding

        if wants_sharding(args):
            if args.ground_truth:
                raise CLIError("--ground-truth is not available with --devices / --processes")
            return cli_solve(args, sys.argv[1:] if argv is None else argv)
        return _cmd_solve(args)
    if args.command == "optimum":
        return _cmd_optimum(args)
    if args.command == "demo":
        from .demo import run_demo

        return run_demo(args)
    if args.command == "bench":
        from .bench import run_bench

        return run_bench(args)
    if args.command == "sweep":
        from .sweep import run_sweep

        return run_sweep(args, _resolve_file)
    return 0


def run_reported(command) -> int:
    """``command()``'s exit status, with bad input reported as one line ``mmpgo: error: ...`` (2),
    an interrupt (130) and a closed output pipe, e.g. ``mmpgo info FILE | head`` (141)."""
    from .._io.datasets import DatasetNotFoundError
    from .._io.g2o import G2OFormatError

    try:
        return command()
    except BrokenPipeError:  # the reader left: nothing to report
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except (G2OFormatError, DatasetNotFoundError, CLIError, ValueError, OSError) as err:
        print_error(err)
        return 2
    except KeyboardInterrupt:
        print("mmpgo: interrupted", file=sys.stderr)
        return 130


def _resolve_file(name: str, data: str | None, *, announce: bool = True) -> Path:
    """The g2o file of a FILE argument (see :func:`~mmpgo_jax.find_benchmark`: a path
    is only a path; a bare name is looked up in the data folder). ``announce``: print ``using
    PATH (benchmark NAME)`` when the data folder supplied the file."""
    from .._io.datasets import benchmark_info, find_benchmark, names_a_path
    from .._io.multi_robot import robot_files

    folder = Path(name).expanduser()
    if names_a_path(name) and folder.is_dir() and robot_files(folder):
        return folder  # one g2o file per robot
    path = find_benchmark(name, data)
    if announce and not names_a_path(name):
        info = benchmark_info(name)
        print(f"using {path} ({f'benchmark {info.name}' if info is not None else 'from the data folder'})", flush=True)
    return path


def read_input(path, args=None):
    """The graph of the FILE argument (:func:`mmpgo_jax.cli.robots.read_input`)."""
    from .robots import read_input as read

    return read(path, args)


_OUTPUTS = (("out", "--out"), ("tum", "--tum"), ("history", "--history"), ("plot", "--plot"),
            ("edge_weights", "--edge-weights"), ("checkpoint", "--checkpoint"))
def check_outputs(args) -> None:
    """Refuse unusable output paths before any work: for each of --out, --tum, --history, --plot
    that is set, its folder must exist and be writable, the path must not be a directory (nor a
    device or other non-regular file), and no two may be the same file (symbolic links resolved)."""
    from .._io.atomic import resolve_target
    from .robots import check_output_dirs

    check_output_dirs(args)
    seen: dict = {}
    for attr, flag in _OUTPUTS:
        value = getattr(args, attr, None)
        if value is None:
            continue
        value = os.fspath(value)
        if value == "":
            raise CLIError(f"{flag}: empty file name")
        target = resolve_target(value)
        shown = f"{flag} {value}"
        if os.path.isdir(target):
            raise CLIError(f"{shown}: is a directory")
        if os.path.exists(target) and not os.path.isfile(target):
            raise CLIError(f"{shown}: not a regular file (outputs replace the file as a whole)")
        folder = os.path.dirname(target)
        named = folder if os.path.islink(value) else (os.path.dirname(value) or ".")
        if not os.path.exists(folder):
            raise CLIError(f"{shown}: folder {named!r} does not exist")
        if not os.path.isdir(folder):
            raise CLIError(f"{shown}: {named!r} is not a folder")
        if not os.access(folder, os.W_OK | os.X_OK):
            raise CLIError(f"{shown}: folder {named!r} is not writable")
        keys = [target]
        with contextlib.suppress(OSError):
            st = os.stat(target)
            keys.append((st.st_dev, st.st_ino))  # hard links to one file
        for key in keys:
            if key in seen:
                raise CLIError(f"{seen[key]} and {shown}: the same file")
            seen[key] = shown
    if getattr(args, "plot", None):  # an image format matplotlib cannot write is refused before the solve
        from .._experiments.plots import check_figure_path

        check_figure_path(args.plot, "--plot")


def _describe_components(graph, vertex_ids=None) -> tuple[list[np.ndarray], str]:
    from .._core.pose_graph import connected_components

    comps = connected_components(graph.num_poses, np.asarray(graph.i), np.asarray(graph.j))
    if len(comps) == 1:
        return comps, "connected"
    ids = np.arange(graph.num_poses) if vertex_ids is None else np.asarray(vertex_ids)
    parts = ", ".join(f"{len(c)} poses (vertex ids {ids[c[0]]}..{ids[c[-1]]})" for c in comps[:5])
    more = f", and {len(comps) - 5} more" if len(comps) > 5 else ""
    return comps, f"NOT connected: {len(comps)} components: {parts}{more}"


def _cmd_info(args) -> int:
    from .robots import DEFAULT_ROBOTS, print_robot_table, print_symbol_hint, robot_split

    path = _resolve_file(args.file, args.data)
    g2o = read_input(path, args)
    g = g2o.graph
    if args.robots is not None and not 1 <= args.robots <= g.num_poses:
        raise CLIError(f"--robots must be between 1 and the number of poses ({g.num_poses}), got {args.robots}")
    kappa, tau = np.asarray(g.kappa), np.asarray(g.tau)
    _, conn = _describe_components(g, g2o.vertex_ids)
    ids = g2o.vertex_ids
    print(f"file        {path}")
    print(f"dimension   d = {g.dim}")
    remapped = "" if ids[-1] == len(ids) - 1 and ids[0] == 0 else f"  (ids {ids[0]}..{ids[-1]}, remapped)"
    print(f"poses       n = {g.num_poses}" + remapped)
    print(f"edges       m = {g.num_edges}")
    print(f"kappa       {kappa.min():.6g} .. {kappa.max():.6g}")
    print(f"tau         {tau.min():.6g} .. {tau.max():.6g}")
    print(f"graph       {conn}")
    print(f"vertices    {int(g2o.has_vertex.sum())} VERTEX lines, {int(g2o.fixed.sum())} fixed")
    dtype = np.float32 if args.precision == "float32" else np.float64
    if args.robots or args.robots_from or args.labels or g2o.robot_names is not None:
        rop, names, label = robot_split(args, g2o)
        print_robot_table(g, rop, names, label, dtype)
    else:  # the split `mmpgo solve FILE` would run, so that info describes what solve does
        print_symbol_hint(g2o)
        if g.num_poses >= DEFAULT_ROBOTS:
            rop, names, label = robot_split(args, g2o)
            print_robot_table(g, rop, names, f"{label}, the default of mmpgo solve", dtype)
    return 0


@dataclass(frozen=True, eq=False)
class LoadedInput:
    """The FILE of ``solve`` / ``optimum``, ready to solve: the graph (its largest component with
    --largest-component), the original ids and information, the VERTEX estimates, the FIX poses and
    the frame results are written in (the FIX pose, else the first pose at its VERTEX value)."""

    path: Path
    g2o: object  # the G2OFile as read
    keep: np.ndarray | None  # the poses kept (--largest-component), None: all
    graph: object
    vertex_ids: np.ndarray
    information: np.ndarray
    initial: object
    fixed: object  # FixedPoses | None
    frame: object  # FixedPoses
    components: list
    robot_of_pose: np.ndarray | None = None  # the split the options ask for (None: not resolved)
    robot_names: list | None = None
    robots_label: str = ""

    @property
    def fixed_mask(self) -> np.ndarray:
        return np.zeros(self.graph.num_poses, bool) if self.fixed is None else self.fixed.mask(self.graph.num_poses)

    def poses_file(self, file, what: str):
        """Poses of a --init / --ground-truth file, matched to this graph by vertex id."""
        from .._core.pose_graph import Poses
        from .._init.chordal import load_poses

        full = load_poses(self.g2o.graph, file, vertex_ids=self.g2o.vertex_ids, what=what)
        return full if self.keep is None else Poses(full.R[self.keep], full.t[self.keep])

    def start(self, init: str | None, methods: tuple[str, ...]):
        """``init`` for the solver: a method name, the poses of a file, or None (the solver's default)."""
        if init is None or init in methods:
            return init
        if not Path(init).is_file():
            raise CLIError(f"--init {init!r}: not a known method ({', '.join(methods)}) nor a file")
        return self.poses_file(init, "--init file")


def _largest_component(g2o, comp: np.ndarray):
    """A G2OFile's graph, information and VERTEX estimates restricted to the poses ``comp``."""
    from .._core.pose_graph import PoseGraph, Poses

    g = g2o.graph
    new_index = np.full(g.num_poses, -1)
    new_index[comp] = np.arange(len(comp))
    keep = new_index[np.asarray(g.i)] >= 0
    sub = PoseGraph.from_arrays(
        new_index[np.asarray(g.i)[keep]],
        new_index[np.asarray(g.j)[keep]],
        np.asarray(g.R)[keep],
        np.asarray(g.t)[keep],
        np.asarray(g.kappa)[keep],
        np.asarray(g.tau)[keep],
        len(comp),
        dtype=np.asarray(g.kappa).dtype,
    )
    initial = None
    if g2o.initial is not None:
        initial = Poses(g2o.initial.R[comp], g2o.initial.t[comp])
    return sub, g2o.information[keep], initial


def _load_for_solve(args, *, announce: bool = True) -> LoadedInput:
    """The :class:`LoadedInput` of ``args.file``; refuses a disconnected graph unless
    ``--largest-component``. ``announce``: print the component note."""
    from .._core.gauge import FixedPoses

    path = _resolve_file(args.file, args.data, announce=False)
    g2o = read_input(path, args)
    comps, conn = _describe_components(g2o.graph, g2o.vertex_ids)
    from .robots import robot_split

    splits = hasattr(args, "robots_from")  # solve: the robots; optimum: one robot
    if len(comps) == 1:
        robots = robot_split(args, g2o) if splits else (None, None, "")
        return LoadedInput(path, g2o, None, g2o.graph, g2o.vertex_ids, g2o.information, g2o.initial,
                           g2o.fixed_poses, g2o.frame, comps, *robots)
    if not args.largest_component:
        raise CLIError(
            f"{path}: the pose graph is {conn}. Each component is only determined up to its own "
            "rigid transform, so the problem is ill-posed; pass --largest-component to solve the "
            "largest one (the others are left out of the result)."
        )
    keep = np.asarray(comps[0])
    graph, information, initial = _largest_component(g2o, keep)
    fixed = None if g2o.fixed_poses is None else g2o.fixed_poses.restrict(keep)
    frame = fixed or FixedPoses([0], g2o.vertex_R[keep[:1]], g2o.vertex_t[keep[:1]])
    if announce:
        from .progress import write_line

        write_line(f"note: solving the largest component only ({graph.num_poses} of {g2o.graph.num_poses} poses)")
    robots = robot_split(args, g2o, graph, keep) if splits else (None, None, "")
    return LoadedInput(path, g2o, keep, graph, g2o.vertex_ids[keep], information, initial, fixed, frame, comps,
                       *robots)


_SOLVE_STARTS = ("chordal", "distributed-chordal", "gnc-chordal", "vertices", "odometry")
_OPTIMUM_STARTS = ("chordal", "vertices", "odometry")


def _cmd_solve(args) -> int:
    from .._mm.robust import GNC_LOSSES
    from .._mm.solve import solve
    from .progress import progress_bar
    from .sharded import thread_devices

    args.file = str(_resolve_file(args.file, args.data))
    check_outputs(args)
    if args.loss == "l2" and (args.edge_weights or args.drop_outliers or args.loss_scale is not None or args.gnc):
        flag = ("--edge-weights" if args.edge_weights else "--drop-outliers" if args.drop_outliers
                else "--gnc" if args.gnc else "--loss-scale")
        raise CLIError(f"{flag} needs a robust --loss (huber, cauchy, geman-mcclure, welsch or tls)")
    if args.gnc and args.loss not in GNC_LOSSES:
        raise CLIError(f"--gnc applies to --loss {' and '.join(GNC_LOSSES)}, not {args.loss}")
    with progress_bar(f"{args.method.upper()}-PGO", args.iterations, disable=args.no_progress,
                      show_gradient=args.grad_tol is not None) as progress:
        progress.phase("reading")
        t = time.perf_counter()
        data = _load_for_solve(args)
        ground_truth = data.poses_file(args.ground_truth, "--ground-truth file") if args.ground_truth else None
        read = time.perf_counter() - t
        options = solve_options(args, data)
        devices = thread_devices(args, data.graph.num_poses, int(np.max(data.robot_of_pose)) + 1)
        if devices is None:
            result = solve(data.graph, data.robot_of_pose, monitor=progress, ground_truth=ground_truth, **options)
        else:
            from .._distributed.solve import solve_sharded

            result = solve_sharded(data.graph, data.robot_of_pose, devices=devices, monitor=progress,
                                   ground_truth=ground_truth, **options)
    fstar = reference_fstar(data)
    _print_summary(result, fstar, data)
    if devices is not None:
        print(f"threads     {len(devices)} (the robots split over {len(devices)} CPU devices)")
    t = time.perf_counter()
    finish_solve(args, data, result, fstar)
    print_timing(result, read=read, write=time.perf_counter() - t)
    return 0


def reference_fstar(data: LoadedInput):
    """The f* that gaps of a solve of ``data`` are measured against (the registry's
    :attr:`~mmpgo_jax.BenchmarkInfo.fstar_reference`: certified where it can be), or None for a
    file that is not a benchmark or a problem it does not describe (a part of the graph)."""
    from .._io.datasets import benchmark_info

    info = benchmark_info(data.path.name)
    if info is None or data.keep is not None or info.num_poses != data.graph.num_poses:
        return None
    return info.fstar_reference


def solve_options(args, data: LoadedInput) -> dict:
    """The keyword arguments of ``solve`` / ``solve_sharded`` from ``mmpgo solve``'s options (the
    start resolved, FIX poses and the input's frame; the robots are ``data.robot_of_pose``)."""
    from .._mm.robust import GNCConfig
    from .sharded import checkpoint_options

    robust = {} if getattr(args, "loss", "l2") == "l2" else dict(loss=args.loss, loss_scale=args.loss_scale)
    if robust and getattr(args, "gnc", False):
        robust["gnc"] = GNCConfig()
    return dict(method=args.method, iterations=args.iterations, init=data.start(args.init, _SOLVE_STARTS),
                initial=data.initial, xi=args.xi, restart=args.restart, chunk_size=args.chunk,
                grad_tol=args.grad_tol, stop_when_stalled=not args.all_iterations, fixed=data.fixed,
                frame=data.frame, **robust, **checkpoint_options(args))


def _print_certificate(data: LoadedInput, poses, *, hint: bool) -> None:
    from .._experiments.certificate import certify

    if data.fixed is not None and len(data.fixed) > 1:
        print(f"certificate not applicable: {len(data.fixed)} FIX poses constrain the problem "
              "(the dual certificate covers PGO with at most one fixed pose)")
        return
    cert = certify(data.graph, poses)
    print(f"certificate {cert.summary()}")
    if hint and not cert.certified:
        print("            (the certificate decides only at a critical point: run to a tight --grad-tol, "
              "e.g. --robots 1)")


def _write_estimate(args, data: LoadedInput, poses, inliers=None) -> list[str]:
    """--out (g2o, with the FIX lines), --tum, --tum-dir and --out-dir files of an estimate; returns
    the paths written. ``inliers`` (m,) bool: the edges to write (all when None)."""
    from .._io.g2o import write_g2o, write_tum
    from .._io.multi_robot import write_robot_folder, write_robot_tum

    written = []
    robots = dict(robot_of_pose=data.robot_of_pose, robot_names=data.robot_names, vertex_ids=data.vertex_ids)
    graph, information = data.graph, data.information
    if inliers is not None:  # --drop-outliers
        graph = graph.select_edges(inliers)
        information = None if information is None else np.asarray(information)[inliers]
    if getattr(args, "tum_dir", None):
        written += write_robot_tum(args.tum_dir, poses, **robots)
    if getattr(args, "out_dir", None):
        written += write_robot_folder(args.out_dir, graph, poses, information=information,
                                      fixed=data.fixed_mask, **robots)
    if args.out:
        write_g2o(args.out, graph, poses, vertex_ids=data.vertex_ids, information=information,
                  fixed=data.fixed_mask)
        written.append(args.out)
    if args.tum:
        write_tum(args.tum, poses, vertex_ids=data.vertex_ids)
        written.append(args.tum)
    return written


def finish_solve(args, data: LoadedInput, result, fstar) -> None:
    """After a solve (single- or multi-device): --certify, then the --out/--tum/--history/--plot
    files, all or none (:func:`~mmpgo_jax._io.atomic.atomic_group`). ``fstar``: the
    :class:`~mmpgo_jax.FStarReference` of the plot's gaps, or None."""
    from .._io.atomic import atomic_group

    if args.certify:
        _print_certificate(data, result.poses, hint=True)
    keep = result.inliers if getattr(args, "drop_outliers", False) else None
    with atomic_group():
        written = _write_estimate(args, data, result.poses, keep)
        if getattr(args, "edge_weights", None):
            write_edge_weights_csv(args.edge_weights, data, result)
            written.append(args.edge_weights)
        if args.history:
            write_history_csv(args.history, result)
            written.append(args.history)
        if args.plot:
            from .._experiments.plots import save_solve_figure

            save_solve_figure(args.plot, data.graph, result, fstar=None if fstar is None else fstar.value,
                              fstar_label="f*" if fstar is None else fstar.label, title=data.path.name,
                              start=result.start)
            written.append(args.plot)
    for path in written:  # only now are they in place
        print(f"wrote {path}")


def _cmd_optimum(args) -> int:
    from .._io.atomic import atomic_group
    from .._io.datasets import benchmark_info
    from .._mm.solve import centralized_optimum
    from .progress import progress_bar

    args.file = str(_resolve_file(args.file, args.data))
    check_outputs(args)
    # float64: the gradient is checked after every Newton step (the bar moves with each, and the solve
    # stops at the first ||grad F|| <= tol); float32's stall rule compares f over chunks of 25
    chunk = 1 if args.precision == "float64" else 25
    with progress_bar("optimum", None, disable=args.no_progress, show_gradient=True) as progress:
        progress.phase("reading")
        data = _load_for_solve(args)
        init = data.start(args.init, _OPTIMUM_STARTS)
        res = centralized_optimum(data.graph, init=init, initial=data.initial, grad_tol=args.grad_tol,
                                  max_iterations=args.max_iterations, fixed=data.fixed, frame=data.frame,
                                  monitor=progress, chunk_size=chunk)
    h = res.history
    total = res.init_seconds + res.compile_seconds + res.solve_seconds
    print(f"f* = 2F      {res.f:.12g} ({res.iterations} iterations, {res.stop_description}, "
          f"||grad F|| = {h.grad_norm[-1]:.2e}, {total:.1f} s)")
    info = benchmark_info(data.path.name) if reference_fstar(data) is not None else None
    for ref in () if info is None else info.fstar_references:
        print(f"registry    {ref.value:.12g}, {ref.label} of {info.name}: relative difference {ref.gap(res.f):+.1e}")
    if not args.no_certify:
        _print_certificate(data, res.poses, hint=False)
    with atomic_group():
        written = _write_estimate(args, data, res.poses)
    for path in written:
        print(f"wrote {path}")
    return 0


def _rejected_lines(result, data: LoadedInput | None) -> str:
    """"; lines 12, 40 and 3 more of FILE" for the rejected edges, when they come from one file as read."""
    lines = None if data is None or data.keep is not None else getattr(data.g2o, "edge_line", None)
    rejected = np.flatnonzero(~np.asarray(result.inliers))
    if lines is None or len(rejected) == 0 or len(lines) != len(result.inliers):
        return ""
    which = "line" if len(rejected) == 1 else "lines"
    return f"; {which} {join_items(lines[rejected].tolist(), 60)} of {data.path.name}"


def _print_summary(result, fstar, data: LoadedInput | None = None) -> None:
    """The result of a solve; ``fstar``: the :class:`~mmpgo_jax.FStarReference` of its gap, or None."""
    h = result.history
    split = f" ({data.robots_label})" if data is not None and data.robots_label else ""
    restart = f", restart={result.config.restart}" if result.config.method == "amm" else ""  # MM has none
    print(f"method      {result.config.method.upper()}-PGO, {result.partition.num_robots} robots{split}{restart}")
    print(f"iterations  {h.iterations} ({result.stop_description})")
    print(f"f = 2F      {h.f[0]:.6f} -> {h.f[-1]:.6f}")
    if fstar is not None:
        print(f"f*          {fstar.value:.12g} ({fstar.label})")
        print(f"gap         {fstar.gap(h.f[-1]):.3e} = (f - f*)/f*, relative to the {fstar.label}")
    print(f"|grad F|    {h.grad_norm[-1]:.3e}")
    if result.loss is not None:
        rejected = int((~result.inliers).sum())
        gnc = f", GNC {result.stats['gnc_stages']} stages" if bool(result.loss.use_gnc) else ""
        print(f"loss        {result.loss.name} (c = {float(result.loss.scale):.4g}{gnc}): {rejected} of "
              f"{len(result.inliers)} edges rejected (f = sum of rho(r^2)){_rejected_lines(result, data)}")
    if result.accuracy is not None:
        a = result.accuracy
        print(f"ATE         {a.ate:.6g} RMSE, {a.ate_max:.6g} max (positions after rigid alignment); "
              f"rotation {a.rotation_deg:.4g} deg RMSE")
        print(f"RPE         {a.rpe_translation:.6g} translation, {a.rpe_rotation_deg:.4g} deg rotation "
              "(consecutive poses, RMSE)")


def print_timing(result, *, read: float, write: float) -> None:
    """The time line: every phase of the run, in the order it ran."""
    if "initialize_seconds" in result.stats:
        setup = f"initialize {result.initialize_seconds:.2f} s, build {result.build_seconds:.2f} s"
    else:
        setup = f"initialize and build {result.init_seconds:.2f} s"
    print(f"time        read {read:.2f} s, {setup}, compile {result.compile_seconds:.2f} s, "
          f"iterations {result.solve_seconds:.2f} s ({result.ms_per_iteration:.2f} ms/iteration), write {write:.2f} s")


def write_edge_weights_csv(path, data: LoadedInput, result) -> None:
    """One line per edge of a robust solve: original ids i, j, final weight, inlier 0/1; for GTSAM
    symbol keys also their names (i_symbol, j_symbol: "a67" for Symbol('a', 67))."""
    from .._io.atomic import atomic_write
    from .._io.multi_robot import symbol_names

    ids = np.asarray(data.vertex_ids)
    i, j = np.asarray(data.graph.i), np.asarray(data.graph.j)
    names = symbol_names(ids)
    rows = zip(ids[i].tolist(), ids[j].tolist(), result.weights, result.inliers, strict=True)
    lines = [f"{a},{b},{float(w)!r},{int(k)}" for a, b, w, k in rows]
    if names is not None:
        lines = [f"{line},{names[a]},{names[b]}" for line, a, b in zip(lines, i.tolist(), j.tolist(), strict=True)]
    with atomic_write(path) as fh:
        fh.write("i,j,weight,inlier" + (",i_symbol,j_symbol" if names is not None else "") + "\n")
        fh.writelines(line + "\n" for line in lines)


def write_history_csv(path, result) -> None:
    from .._io.atomic import atomic_write

    h = result.history
    with atomic_write(path) as fh:
        fh.write("iteration,f,grad_norm,restarts\n")
        for k in range(len(h.f)):
            fh.write(f"{k},{float(h.f[k])!r},{float(h.grad_norm[k])!r},{int(h.restarts[k].sum())}\n")

