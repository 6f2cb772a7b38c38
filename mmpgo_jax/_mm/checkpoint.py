"""Checkpoints of a driven run: the solver state between two chunks, the history so far, the start.

A checkpoint is an ``.npz`` file (numpy's zip of arrays, read back without pickle) written with
:func:`~mmpgo_jax._io.atomic.atomic_write`, so that a reader, or a resume after a crash during
the write, never sees half a file: it is the previous checkpoint or the new one. It holds

* ``format`` (:data:`FORMAT`), ``iterations`` (k, the outer iterations done) and ``chunk_size``;
* ``f``, ``grad_norm``, ``restarts``: the :class:`~mmpgo_jax.History` of iterations 0..k;
* ``state_<i>``: the leaves of the :class:`~mmpgo_jax.MMState` after k iterations, exactly (same
  dtypes, so a resumed run computes the same numbers bit for bit);
* ``X0_R``, ``X0_t``: the start poses (the two-level preconditioner is built from them, so a
  resume rebuilds the same problem from them instead of computing the start again);
* ``key_<part>``: a SHA-256 of each part of the problem's identity (:func:`identity`: graph,
  robots, start, method and settings, loss, fixed poses, chunk size, precision, layout), so that
  resuming a checkpoint of another problem is refused with a message naming what differs.

The iteration budget is not part of the identity: a run resumed with a larger ``iterations``
continues further. Checkpoints are written after every ``every``-th chunk (counted from iteration
0, so a resumed run writes at the same iterations) from which the run goes on, never at its end.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import zipfile
from collections.abc import Callable

import jax
import numpy as np

from .._io.atomic import atomic_write
from .driver import History

__all__ = ["FORMAT", "CheckpointError", "Checkpointer", "Snapshot", "identity", "load", "restore_state"]

FORMAT = "mmpgo-checkpoint/2"  # 2: MMState holds f_start, f_best and resets (rise_limit)
# Chunks between checkpoints. Every chunk: the runs that need checkpoints are the long ones, whose
# chunks are long (10^6 poses: 9 s per iteration, 7.5 minutes per chunk of 50) against writing
# the state (about 0.5 GB there, seconds); on small graphs a chunk's checkpoint costs milliseconds.
DEFAULT_EVERY = 1

# The parts of a problem's identity, in the words the refusal uses.
PARTS = ("graph", "robots", "start", "method and settings", "loss", "fixed poses", "chunk size", "precision",
         "layout")


class CheckpointError(ValueError):
    """A checkpoint cannot be resumed: not a checkpoint, or one of another problem (one line)."""


def _feed(h, obj) -> None:
    """Hash ``obj``: arrays by dtype, shape and bytes; dataclasses (equinox modules included,
    static fields too) by type and fields; containers by their items; anything else by repr."""
    if obj is None or isinstance(obj, (bool, str)):
        h.update(f"{type(obj).__name__}:{obj!r};".encode())
    elif isinstance(obj, (int, float, complex, np.ndarray, np.generic, jax.Array)):
        a = np.ascontiguousarray(np.asarray(obj))
        h.update(f"a:{a.dtype.str}:{a.shape};".encode())
        h.update(a.tobytes())
    elif isinstance(obj, dict):
        h.update(b"{")
        for k in sorted(obj, key=str):
            _feed(h, str(k))
            _feed(h, obj[k])
        h.update(b"}")
    elif isinstance(obj, (list, tuple)):
        h.update(f"{type(obj).__name__}[".encode())
        for x in obj:
            _feed(h, x)
        h.update(b"]")
    elif dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        h.update(f"{type(obj).__qualname__}(".encode())
        for field in dataclasses.fields(obj):
            _feed(h, field.name)
            _feed(h, getattr(obj, field.name))
        h.update(b")")
    else:
        h.update(f"{type(obj).__qualname__}:{obj!r};".encode())


def digest(obj) -> str:
    """SHA-256 (hex) of ``obj`` as :func:`_feed` reads it."""
    h = hashlib.sha256()
    _feed(h, obj)
    return h.hexdigest()


def identity(*, graph, robot_of_pose, num_robots: int, start, config, loss, fixed, chunk_size: int,
             precision, layout) -> dict[str, str]:
    """The digests of a run's identity, one per :data:`PARTS` entry."""
    parts = dict(zip(PARTS, (graph, (np.asarray(robot_of_pose), int(num_robots)), start, config, loss, fixed,
                             int(chunk_size), str(np.dtype(precision)), layout), strict=True))
    return {k: digest(v) for k, v in parts.items()}


def _key_name(part: str) -> str:
    return "key_" + part.replace(" ", "_")


@dataclasses.dataclass(frozen=True)
class Snapshot:
    """A checkpoint read back: ``iterations`` done, its history, the state's leaves and the start."""

    path: str
    iterations: int
    chunk_size: int
    history: History
    state_leaves: list
    X0: tuple  # (R (n, d, d), t (n, d)) host arrays
    keys: dict  # part -> digest (see identity)

    def check(self, key: dict[str, str], iterations: int) -> None:
        """Refuse (:class:`CheckpointError`) a checkpoint of another problem (``key`` is the
        resuming run's :func:`identity`) or one past the resuming run's iteration budget."""
        differ = [p for p in PARTS if self.keys.get(p) != key[p]]
        if differ:
            raise CheckpointError(
                f"checkpoint {self.path} is of another problem ({', '.join(differ)}: not the same); resume "
                "with the input, robots, method, options and devices of the run that wrote it")
        if self.iterations > iterations:
            raise CheckpointError(f"checkpoint {self.path} is at iteration {self.iterations}, past this run's "
                                  f"budget of {iterations} iterations")


def load(path) -> Snapshot:
    """Read the checkpoint at ``path`` (:class:`CheckpointError` when it is not one)."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise CheckpointError(f"checkpoint {path}: no such file")
    if os.path.isdir(path):
        raise CheckpointError(f"checkpoint {path}: is a directory")
    if not zipfile.is_zipfile(path):
        raise CheckpointError(f"checkpoint {path}: not an mmpgo checkpoint (not an .npz file)")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
        raise CheckpointError(f"checkpoint {path}: not a readable mmpgo checkpoint ({err})") from None
    fmt = str(data.get("format", ""))
    if fmt != FORMAT:
        what = f"format {fmt!r}, expected {FORMAT!r}" if fmt else "no format entry"
        raise CheckpointError(f"checkpoint {path}: not an mmpgo checkpoint of this version ({what})")
    try:
        count = int(data["state_leaves"])
        keys = {p: str(data[_key_name(p)]) for p in PARTS}
        snap = Snapshot(
            path=path,
            iterations=int(data["iterations"]),
            chunk_size=int(data["chunk_size"]),
            history=History(data["f"], data["grad_norm"], data["restarts"]),
            state_leaves=[data[f"state_{i}"] for i in range(count)],
            X0=(data["X0_R"], data["X0_t"]),
            keys=keys,
        )
    except KeyError as err:
        raise CheckpointError(f"checkpoint {path}: incomplete (no {err.args[0]!r} entry)") from None
    if snap.history.iterations != snap.iterations:
        raise CheckpointError(f"checkpoint {path}: its history holds {snap.history.iterations} iterations, "
                              f"its header {snap.iterations}")
    return snap


def restore_state(snapshot: Snapshot, template):
    """The checkpoint's state, with the pytree structure of ``template`` (a state of the resuming
    run: same structure, shapes and dtypes, else :class:`CheckpointError`); host arrays."""
    leaves, treedef = jax.tree.flatten(template)
    saved = snapshot.state_leaves
    if len(saved) != len(leaves):
        raise CheckpointError(f"checkpoint {snapshot.path}: its state has {len(saved)} arrays, this run's "
                              f"{len(leaves)}")
    for k, (a, b) in enumerate(zip(saved, leaves, strict=True)):
        shape, dtype = tuple(np.shape(b)), np.dtype(getattr(b, "dtype", np.asarray(b).dtype))
        if a.shape != shape or a.dtype != dtype:
            raise CheckpointError(f"checkpoint {snapshot.path}: state array {k} is {a.dtype}{list(a.shape)}, "
                                  f"this run's {dtype}{list(shape)}")
    return jax.tree.unflatten(treedef, saved)


class Checkpointer:
    """Writes a run's checkpoint to ``path`` after every ``every``-th chunk the run goes on from.

    ``key``: the run's :func:`identity`; ``X0``: its start poses (Poses or (R, t)); ``to_host(state)``:
    the state's leaves as numpy arrays (in a multi-process run a collective that every process
    calls); ``write``: whether this process writes the file (process 0 of a multi-process run).
    It is :func:`~mmpgo_jax._mm.driver.drive`'s ``checkpoint``: called with the iterations done,
    the chunk length, the state and the history so far (lists of chunks, as the driver keeps it).
    """

    def __init__(self, path, every: int, key: dict[str, str], X0, *, chunk_size: int,
                 to_host: Callable | None = None, write: bool = True):
        if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 1:
            raise ValueError(f"checkpoint_every must be an integer >= 1, got {every!r}")
        self.path = os.fspath(path)
        if self.path == "":
            raise ValueError("checkpoint: empty file name")
        self.every = int(every)
        self.key = key
        self.X0 = tuple(np.asarray(x) for x in ((X0.R, X0.t) if hasattr(X0, "R") else X0))
        self.chunk_size = int(chunk_size)
        self.to_host = to_host or (lambda state: [np.asarray(x) for x in jax.device_get(jax.tree.leaves(state))])
        self.write = write
        self.written = 0  # checkpoints written (tests, stats)

    def __call__(self, done: int, length: int, state, fs: list, gs: list, rs: list) -> None:
        if (done // length) % self.every:
            return
        leaves = self.to_host(state)  # every process (a collective in a multi-process run)
        if not self.write:
            return
        arrays = {f"state_{i}": np.asarray(x) for i, x in enumerate(leaves)}
        arrays.update({_key_name(p): np.asarray(v) for p, v in self.key.items()})
        arrays.update(
            format=np.asarray(FORMAT), iterations=np.asarray(done), chunk_size=np.asarray(self.chunk_size),
            state_leaves=np.asarray(len(leaves)), f=np.concatenate(fs, -1), grad_norm=np.concatenate(gs, -1),
            restarts=np.concatenate(rs, -2), X0_R=self.X0[0], X0_t=self.X0[1],
        )
        with atomic_write(self.path, "wb") as fh:
            np.savez(fh, **arrays)
        self.written += 1

