"""Atomic file writing: write to a temporary file next to the target, fsync, then ``os.replace``.

Readers never see a half-written file, and a failed write leaves a pre-existing target untouched
(the temporary file is removed).
"""

from __future__ import annotations

import contextlib
import os
import stat
import tempfile
import threading
from collections.abc import Iterator
from typing import IO, Any

__all__ = ["atomic_write"]

_umask_lock = threading.Lock()


def _current_umask() -> int:
    with _umask_lock:
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


def _fsync_dir(directory: str) -> None:
    """Best effort: make the rename durable (not supported everywhere, e.g. on Windows)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_write(path, mode: str = "w", *, encoding: str | None = "utf-8", newline: str | None = "\n") -> Iterator[IO[Any]]:
    """Context manager yielding a file object whose content replaces ``path`` atomically on success.

    The data goes to a temporary file in the same directory (so that ``os.replace`` is a rename on
    one file system), which is flushed and fsynced before it replaces the target. If the body of
    the ``with`` block raises, the temporary file is removed, the target is left as it was, and the
    exception propagates. ``mode`` is ``"w"`` (text, ``encoding``/``newline`` apply) or ``"wb"``.
    The new file gets the permissions of the file it replaces, or the usual ``0o666 & ~umask``.
    """
    if mode not in ("w", "wb", "wt", "x", "xb", "xt"):
        raise ValueError(f"atomic_write supports write modes 'w'/'wb'/'x'/'xb' only, got {mode!r}")
    path = os.fspath(path)
    target = os.path.abspath(path)
    directory = os.path.dirname(target) or "."
    if "x" in mode and os.path.exists(target):
        raise FileExistsError(f"{path} already exists")
    binary = "b" in mode
    fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(target) + ".", suffix=".tmp", dir=directory)
    try:
        try:
            perm = stat.S_IMODE(os.stat(target).st_mode)
        except OSError:
            perm = 0o666 & ~_current_umask()
        os.chmod(tmp, perm)
        if binary:
            f = os.fdopen(fd, "wb")
        else:
            f = os.fdopen(fd, "w", encoding=encoding, newline=newline)
        fd = -1  # now owned by f
        with f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
        tmp = None
    finally:
        if fd >= 0:
            os.close(fd)
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
    _fsync_dir(directory)
