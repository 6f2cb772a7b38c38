"""Explicit numerical precision.

The paper, SE-Sync and the authors' C++ code use float64. JAX defaults to float32 and we never
flip that global flag silently on import: call :func:`enable_float64` (or set the environment
variable ``JAX_ENABLE_X64=1``) before building graphs when results are compared with the paper.
The ``mmpgo`` CLI does this itself unless ``--precision float32`` is given.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def enable_float64() -> None:
    """Switch JAX to 64-bit floats for this process (call before creating arrays)."""
    jax.config.update("jax_enable_x64", True)


def float64_enabled() -> bool:
    return bool(jax.config.jax_enable_x64)


def default_float_dtype():
    """The float dtype new arrays get: float64 when enabled, else float32 (no JAX dispatch)."""
    return jax.dtypes.canonicalize_dtype(jnp.float64)


def to_device(x, dtype=None) -> jax.Array:
    """A host array (cast to ``dtype`` on the host) on the default device, with the dtype JAX's
    precision setting gives it. ``jax.device_put`` is a plain transfer; ``jnp.asarray`` of a host
    array compiles a small program the first time each shape is seen (1-15 ms per shape: a
    dozen of them in the set-up of every run)."""
    return jax.device_put(np.asarray(x, dtype))


def array_module(*arrays):
    """jax.numpy when any argument is a JAX array or tracer, else numpy: host callers (set-up,
    decisions between runs) compute in NumPy, where op-by-op JAX would compile a small program for
    every operation and every new shape."""
    return jnp if any(isinstance(a, jax.Array) for a in arrays) else np
