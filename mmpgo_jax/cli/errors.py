"""How ``mmpgo`` reports: :class:`CLIError`, one-line error and warning messages, and the exit
statuses of a command. Every other module of the command line imports this one, so it imports
none of them at module level (only :mod:`.progress`, to draw a warning beside a progress bar)."""

from __future__ import annotations

import contextlib
import os
import re
import sys
import warnings

from .._core.messages import shorten_words


class CLIError(Exception):
    """An error to report to the user without a traceback."""


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


def exit_status(exc: SystemExit) -> int:
    """The exit status of argparse's ``SystemExit`` (--help: 0, a bad option: 2)."""
    if exc.code is None:
        return 0
    return exc.code if isinstance(exc.code, int) else 2


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
