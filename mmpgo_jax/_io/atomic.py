"""Atomic file writing: write to a temporary file next to the target, fsync, then ``os.replace``.

Readers never see a half-written file, and a failed write leaves a pre-existing target untouched
(the temporary file is removed). Writing through a symbolic link replaces the link's (final)
target, with the temporary file in the target's folder, and keeps the link.

:func:`atomic_group` makes several files all-or-none: inside it, every :func:`atomic_write`
writes and fsyncs its temporary file as usual but defers the final rename until the group exits
without an exception; then all files are renamed into place together. If any write (or any other
code in the group) fails, every temporary file is removed and no target changes. Writers that call
``atomic_write(path)`` internally (``write_g2o``, ``write_tum``, the plots) are grouped without any
change to their signatures.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import stat
import tempfile
import threading
from collections.abc import Iterator
from typing import IO, Any

__all__ = ["AtomicGroup", "atomic_group", "atomic_write"]

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


def _unlink_quietly(path: str) -> None:
    with contextlib.suppress(OSError):
        os.unlink(path)


def _naming(exc: OSError, path: str) -> OSError:
    """``exc`` reworded to name ``path`` (the target) instead of a temporary file."""
    if exc.errno is None:
        return exc
    return type(exc)(exc.errno, exc.strerror or str(exc), path)


class AtomicGroup:
    """The deferred renames of an :func:`atomic_group` (temporary file -> target)."""

    def __init__(self) -> None:
        self._pending: dict[str, str] = {}  # resolved target -> its temporary file

    def __len__(self) -> int:
        return len(self._pending)

    @property
    def targets(self) -> list[str]:
        """Resolved paths that :meth:`commit` will replace, in the order they were written."""
        return list(self._pending)

    def add(self, tmp: str, target: str) -> None:
        """Defer ``os.replace(tmp, target)``; a later write to the same target supersedes it."""
        old = self._pending.pop(target, None)
        if old is not None:
            _unlink_quietly(old)
        self._pending[target] = tmp

    def rollback(self) -> None:
        """Remove every temporary file; no target changes."""
        pending, self._pending = self._pending, {}
        for tmp in pending.values():
            _unlink_quietly(tmp)

    def commit(self) -> None:
        """Rename every temporary file onto its target.

        Each pre-existing target is first hard-linked to a backup (where the file system allows
        it), so that if a rename fails half-way (which needs a concurrent change of the folder),
        the targets already replaced are restored and new ones removed.
        """
        pending, self._pending = self._pending, {}
        existed: dict[str, bool] = {}
        backups: dict[str, str] = {}
        done: list[str] = []
        try:
            for target, tmp in pending.items():
                existed[target] = os.path.lexists(target)
                if existed[target]:
                    with contextlib.suppress(OSError):
                        os.link(target, tmp + ".bak")
                        backups[target] = tmp + ".bak"
            for target, tmp in pending.items():
                try:
                    os.replace(tmp, target)
                except OSError as exc:
                    raise _naming(exc, target) from None
                done.append(target)
        except BaseException:
            for target in reversed(done):
                with contextlib.suppress(OSError):
                    if target in backups:
                        os.replace(backups.pop(target), target)
                    elif not existed[target]:
                        os.unlink(target)
            for target, tmp in pending.items():
                if target not in done:
                    _unlink_quietly(tmp)
            raise
        finally:
            for backup in backups.values():
                _unlink_quietly(backup)
        for directory in dict.fromkeys(os.path.dirname(t) for t in done):
            _fsync_dir(directory)


_GROUP: contextvars.ContextVar[AtomicGroup | None] = contextvars.ContextVar("mmpgo_atomic_group", default=None)


@contextlib.contextmanager
def atomic_group() -> Iterator[AtomicGroup]:
    """Context manager: the :func:`atomic_write` calls inside it (in this thread / context) take
    effect together when it exits normally, or not at all when it exits with an exception.

    A nested ``atomic_group`` joins the outer one (everything commits when the outermost exits).
    """
    outer = _GROUP.get()
    if outer is not None:
        yield outer
        return
    group = AtomicGroup()
    token = _GROUP.set(group)
    try:
        yield group
    except BaseException:
        _GROUP.reset(token)
        group.rollback()
        raise
    _GROUP.reset(token)
    group.commit()


def resolve_target(path) -> str:
    """The file that writing to ``path`` changes: absolute, with symbolic links resolved."""
    return os.path.realpath(os.path.abspath(os.fspath(path)))


@contextlib.contextmanager
def atomic_write(
    path, mode: str = "w", *, encoding: str | None = "utf-8", newline: str | None = "\n"
) -> Iterator[IO[Any]]:
    """Context manager yielding a file object whose content replaces ``path`` atomically on success.

    The data goes to a temporary file in the target's directory (so that ``os.replace`` is a
    rename on one file system), which is flushed and fsynced before it replaces the target. If
    ``path`` is a symbolic link, the target is the file it points to (the link stays a link). If
    the body of the ``with`` block raises, the temporary file is removed, the target is left as it
    was, and the exception propagates. ``mode`` is ``"w"`` (text, ``encoding``/``newline`` apply)
    or ``"wb"`` (``"x"``/``"xb"``: fail if the target exists); the target must not be a directory
    or other non-regular file (a device, FIFO). The new file gets the permissions
    of the file it replaces, or the usual ``0o666 & ~umask``. Inside an :func:`atomic_group` the
    final rename waits for the group.
    """
    if mode not in ("w", "wb", "wt", "x", "xb", "xt"):
        raise ValueError(f"atomic_write supports write modes 'w'/'wb'/'x'/'xb' only, got {mode!r}")
    path = os.fspath(path)
    target = resolve_target(path)
    directory = os.path.dirname(target) or "."
    if "x" in mode and os.path.exists(target):
        raise FileExistsError(f"{path} already exists")
    if os.path.isdir(target):
        raise IsADirectoryError(f"{path}: is a directory")
    if os.path.exists(target) and not os.path.isfile(target):
        # renaming onto a device, FIFO or socket would replace that special file itself
        raise OSError(f"{path}: not a regular file (atomic_write replaces the file as a whole)")
    binary = "b" in mode
    try:
        fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(target) + ".", suffix=".tmp", dir=directory)
    except OSError as exc:
        raise _naming(exc, path) from None
    group = _GROUP.get()
    try:
        try:
            perm = stat.S_IMODE(os.stat(target).st_mode)
        except OSError:
            perm = 0o666 & ~_current_umask()
        os.chmod(tmp, perm)
        f = os.fdopen(fd, "wb") if binary else os.fdopen(fd, "w", encoding=encoding, newline=newline)
        fd = -1  # now owned by f
        with f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        if group is not None:
            group.add(tmp, target)
        else:
            try:
                os.replace(tmp, target)
            except OSError as exc:
                raise _naming(exc, path) from None
        tmp = None
    finally:
        if fd >= 0:
            os.close(fd)
        if tmp is not None:
            _unlink_quietly(tmp)
    if group is None:
        _fsync_dir(directory)
