"""One BLAS thread for host-side factorizations (the centralized Newton steps, the per-robot
preconditioner's dense factors): their operations are small or memory-bound, where OpenBLAS's
threads only add synchronization, and they would compete with XLA's own threads.

Only OpenBLAS and BLIS (NumPy's and SciPy's BLAS from wheels) are limited, not MKL: PARDISO
(:mod:`._core.sparse`) runs on MKL's threads, and a PARDISO factorization whose thread count
changes between its analysis and its numeric phase crashes the process (measured)."""

from __future__ import annotations

import functools

from threadpoolctl import ThreadpoolController

__all__ = ["one_blas_thread"]


@functools.cache
def _controller() -> ThreadpoolController:
    # found once: scanning the loaded libraries takes ~2 ms, more than a whole solve of a tiny graph
    return ThreadpoolController()


def one_blas_thread():
    """Context manager: OpenBLAS / BLIS (those loaded at first use) limited to one thread inside."""
    return _controller().select(internal_api=["openblas", "blis"]).limit(limits=1)
