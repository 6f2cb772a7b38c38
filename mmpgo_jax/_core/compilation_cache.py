"""JAX's persistent compilation cache, for processes that solve the same shapes again.

Every new process compiles the outer loop again (one to a few seconds); with the persistent cache
a second run of the same shapes and configuration structure loads the compiled code from disk.
The library never turns it on by itself (it is a global JAX setting): call
:func:`enable_compilation_cache`. The ``mmpgo`` CLI does, unless ``--no-compilation-cache`` or
``MMPGO_COMPILATION_CACHE=off``.

Where: ``MMPGO_COMPILATION_CACHE`` when it names a folder, else ``$XDG_CACHE_HOME/mmpgo-jax/jax``
(``~/.cache/mmpgo-jax/jax`` without XDG_CACHE_HOME). The cache holds only compiled programs (keyed
by JAX on the program, the JAX version and the device); deleting the folder is always safe.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax

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
