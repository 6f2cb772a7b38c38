"""JAX's persistent compilation cache, for processes that solve the same shapes again.

Every new process traces and compiles the outer loop again (one to a few seconds); with the
persistent cache a second run of the same shapes and configuration structure loads the compiled
code from disk, and (:func:`compile_exported`) the traced program as well: a ``jax.export``
serialization of it, keyed by this package's source, the JAX version, the device, the static
arguments and the argument shapes, so that a warm run neither traces nor compiles.
The library never turns it on by itself (it is a global JAX setting): call
:func:`enable_compilation_cache`. The ``mmpgo`` CLI does, unless ``--no-compilation-cache`` or
``MMPGO_COMPILATION_CACHE=off``.

Where: ``MMPGO_COMPILATION_CACHE`` when it names a folder, else ``$XDG_CACHE_HOME/mmpgo-jax/jax``
(``~/.cache/mmpgo-jax/jax`` without XDG_CACHE_HOME). The cache holds only compiled programs (keyed
by JAX on the program, the JAX version and the device); deleting the folder is always safe.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import jax
import numpy as np

from .compile_mode import compile_lowered

ENV = "MMPGO_COMPILATION_CACHE"
_OFF = {"off", "0", "no", "false", "none"}


def default_cache_dir() -> Path | None:
    """The folder the CLI uses, from ``MMPGO_COMPILATION_CACHE`` and XDG; None when the
    environment turns the cache off (``MMPGO_COMPILATION_CACHE=off``, ``0``, ``no``, ``false``)."""
    value = os.environ.get(ENV)
    if value is not None and value.strip().lower() in _OFF | {""}:
        return None
    if value:
        return Path(value).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base).expanduser() / "mmpgo-jax" / "jax"


def enable_compilation_cache(path: str | os.PathLike | None = None) -> Path | None:
    """Turn JAX's persistent compilation cache on for this process, in ``path`` (default:
    :func:`default_cache_dir`). Every compiled program is cached, however fast it compiled. Returns
    the folder, or None when ``path`` is None and the environment turns the cache off."""
    folder = Path(path).expanduser() if path is not None else default_cache_dir()
    if folder is None:
        return None
    folder.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return folder


def compilation_cache_dir() -> Path | None:
    """The folder of the persistent cache this process uses, or None when it is off."""
    value = jax.config.jax_compilation_cache_dir
    return Path(value) if value else None


# --- traced programs, serialized with jax.export (beside the compiled ones) ---------------------

_SOURCE_DIGEST: str | None = None


def _source_digest() -> str:
    """A digest of this package's Python sources: a changed solver never reuses an old program."""
    global _SOURCE_DIGEST
    if _SOURCE_DIGEST is None:
        h = hashlib.sha256()
        root = Path(__file__).resolve().parents[1]
        for f in sorted(root.rglob("*.py")):
            h.update(f.relative_to(root).as_posix().encode())
            h.update(f.read_bytes())
        _SOURCE_DIGEST = h.hexdigest()
    return _SOURCE_DIGEST


def _program_key(name: str, args, static) -> str:
    leaves, treedef = jax.tree.flatten(args)
    h = hashlib.sha256()
    for part in (_source_digest(), jax.__version__, jax.default_backend(), name, repr(static), str(treedef)):
        h.update(part.encode())
        h.update(b"\0")
    for x in leaves:
        h.update(f"{np.shape(x)}|{getattr(x, 'dtype', type(x))}|{getattr(x, 'weak_type', None)};".encode())
        sharding = getattr(x, "sharding", None)
        if len(getattr(sharding, "device_set", ())) > 1:  # a program over several devices: its layout too
            ids = sorted(d.id for d in sharding.device_set)
            h.update(f"{sharding!r}|{ids};".encode())
    return h.hexdigest()


def compile_exported(fn, args: tuple, static_argnums: tuple[int, ...], out_structure, options: dict | None = None):
    """``fn`` (a function of ``args``; the positions ``static_argnums`` are hashable static
    values) compiled for ``args``, with its traced program kept in the persistent cache: the first
    call traces and serializes it (``jax.export``), later processes deserialize it instead of
    tracing. ``out_structure`` is a pytree with the structure of ``fn``'s result (rebuilt from the
    flat outputs). Arguments sharded over several devices of this process (``shard_map``
    programs) keep their layout: it is part of the key, and the deserialized program takes and
    returns the same shardings. Returns a callable of the non-static arguments, or None when the
    persistent cache is off or the program spans several processes (the caller compiles as usual).
    ``options``: XLA compiler options (:func:`~mmpgo_jax._core.compile_mode.compiler_options`)."""
    folder = compilation_cache_dir()
    dynamic = tuple(a for i, a in enumerate(args) if i not in static_argnums)
    leaves, in_tree = jax.tree.flatten(dynamic)
    if folder is None or jax.process_count() > 1:
        return None
    static = tuple(args[i] for i in static_argnums)
    path = folder / "exported" / f"{_program_key(getattr(fn, '__name__', 'fn'), dynamic, static)}.bin"
    out_tree = jax.tree.structure(out_structure)
    exported = None
    if path.is_file():
        try:
            exported = jax.export.deserialize(bytearray(path.read_bytes()))
        except Exception:
            exported = None
    if exported is None:
        def flat(*values):
            full = list(jax.tree.unflatten(in_tree, values))
            for i, v in zip(static_argnums, static, strict=True):
                full.insert(i, v)
            return jax.tree.leaves(fn(*full))

        exported = jax.export.export(jax.jit(flat))(*leaves)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".{os.getpid()}.tmp")
            tmp.write_bytes(exported.serialize())
            os.replace(tmp, path)
        except OSError:  # a read-only cache costs only the speed-up
            pass
    compiled = compile_lowered(jax.jit(exported.call).lower(*leaves), options)

    def call(*values):
        return jax.tree.unflatten(out_tree, compiled(*jax.tree.leaves(values)))

    return call
