"""SE-Sync's measurement weights: kappa and tau from information matrices, and back.

The solver weighs each edge by two scalars, not a matrix, so the reader reduces every information
matrix as SE-Sync does (``read_g2o_file`` in ``C++/SE-Sync/src/SESync_utils.cpp`` of
github.com/david-m-rosen/SE-Sync): for SE2, tau = 2 / tr(inv(I[:2, :2])) and kappa = I33; for SE3,
tau = 3 / tr(inv(I[:3, :3])) and kappa = 3 / (2 tr(inv(I[3:, 3:]))). A writer without the file's
own matrices writes :func:`information_from_weights`, which this reduction maps back to the same
(kappa, tau), so a graph survives a write and a read.
"""

from __future__ import annotations

import numpy as np

from .format import _info_size

__all__ = ["information_from_weights", "sesync_weights"]


def information_from_weights(kappa, tau, dim: int) -> np.ndarray:
    """Isotropic information matrices that map back to (kappa, tau) under SE-Sync's convention.

    SE2: diag(tau, tau, kappa), shape (m, 3, 3). SE3: diag(tau, tau, tau, 2 kappa, 2 kappa,
    2 kappa), shape (m, 6, 6).
    """
    if dim not in (2, 3):
        raise ValueError(f"dim must be 2 or 3, got {dim}")
    kappa = np.asarray(kappa, dtype=np.float64).reshape(-1)
    tau = np.asarray(tau, dtype=np.float64).reshape(-1)
    if kappa.shape != tau.shape:
        raise ValueError(f"kappa and tau must have the same length, got {kappa.shape} and {tau.shape}")
    m = kappa.shape[0]
    k = _info_size(dim)
    info = np.zeros((m, k, k), dtype=np.float64)
    idx = np.arange(k)
    if dim == 2:
        info[:, idx, idx] = np.stack([tau, tau, kappa], 1)
    else:
        info[:, idx, idx] = np.stack([tau, tau, tau, 2 * kappa, 2 * kappa, 2 * kappa], 1)
    return info


def _inverse_trace(blocks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """tr(inv(B)) of a stack of square blocks, and a mask of the blocks whose inverse is not finite.

    ``np.linalg.inv`` (LAPACK LU, as Eigen's inverse in SE-Sync) on the whole stack; only when
    some block is exactly singular are those found (zero or non-finite determinant) and replaced
    by the identity, so that the others are still inverted in one call.
    """
    bad = np.zeros(blocks.shape[0], dtype=bool)
    try:
        inv = np.linalg.inv(blocks)
    except np.linalg.LinAlgError:
        det = np.linalg.det(blocks)
        bad = ~(np.isfinite(det) & (det != 0))
        blocks = np.where(bad[:, None, None], np.eye(blocks.shape[-1]), blocks)
        try:
            inv = np.linalg.inv(blocks)
        except np.linalg.LinAlgError:  # a zero pivot that the determinant did not show
            inv = np.empty_like(blocks)
            for r in range(blocks.shape[0]):
                try:
                    inv[r] = np.linalg.inv(blocks[r])
                except np.linalg.LinAlgError:
                    inv[r] = np.eye(blocks.shape[-1])
                    bad[r] = True
    bad |= ~np.isfinite(inv).all(axis=(1, 2))
    return np.trace(inv, axis1=1, axis2=2), bad


def sesync_weights(info: np.ndarray, dim: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(tau, tau_undefined, kappa, kappa_undefined)`` of (m, k, k) information matrices, unchecked.

    The ``*_undefined`` masks mark the matrices whose block (translation for tau, rotation for kappa
    in 3D) has no finite inverse; the values there, and any non-positive or overflowing weight, are
    left for the caller to refuse with a message naming the line.
    """
    d = dim
    with np.errstate(all="ignore"):
        tr_t, bad_t = _inverse_trace(info[:, :d, :d])
        tau = d / tr_t
        if d == 2:
            kappa, bad_k = info[:, 2, 2].copy(), np.zeros(info.shape[0], bool)
        else:
            tr_r, bad_k = _inverse_trace(info[:, 3:, 3:])
            kappa = 3.0 / (2.0 * tr_r)
    return tau, bad_t, kappa, bad_k
