"""What every writer (g2o, TORO, TUM) shares: vertex ids and poses checked, rows of numbers formatted.

Floats are written as Python's ``repr`` (the shortest text that reads back as the same float), so
that a file written and read again gives the same graph bit for bit.
"""

from __future__ import annotations

import numpy as np

from .._core.pose_graph import Poses
from .format import _info_size


def writer_sizes(graph, vertex_ids) -> tuple[int, int, int, np.ndarray, int]:
    """(d, n, m, checked vertex ids, information entries per edge) of a graph about to be written."""
    d = graph.dim
    if d not in (2, 3):
        raise ValueError(f"only 2D and 3D graphs can be written, got dimension {d}")
    return d, graph.num_poses, graph.num_edges, _check_vertex_ids(vertex_ids, graph.num_poses), _info_size(d)


def _check_vertex_ids(vertex_ids, n: int) -> np.ndarray:
    if vertex_ids is None:
        return np.arange(n, dtype=np.int64)
    ids = np.asarray(vertex_ids)
    if ids.shape != (n,):
        raise ValueError(f"vertex_ids must have shape ({n},), got {ids.shape}")
    if not np.issubdtype(ids.dtype, np.integer) and not np.all(
        np.asarray(ids, dtype=np.float64) == np.round(np.asarray(ids, dtype=np.float64))
    ):
        raise ValueError("vertex_ids must be integers")
    ids = ids.astype(np.int64)
    if np.unique(ids).shape[0] != n:
        raise ValueError("vertex_ids must be unique")
    return ids


def _fmt_rows(ints: np.ndarray | None, floats: np.ndarray, prefix: str) -> list[str]:
    """Lines ``prefix int.. float..``; floats as Python repr (shortest exact round trip).

    One %-format of the whole block (the per-value work in C, no Python loop over lines)."""
    rows = floats.shape[0]
    if rows == 0:
        return []
    k_int = 0 if ints is None else ints.shape[1]
    fields = np.empty((rows, k_int + floats.shape[1]), dtype=object)
    if k_int:
        fields[:, :k_int] = ints.astype(np.int64)  # Python ints: %d prints them as str() does
    fields[:, k_int:] = floats.astype(np.float64)  # Python floats: %r is their repr
    line = prefix + " ".join(["%d"] * k_int + ["%r"] * floats.shape[1])
    return ("\n".join([line] * rows) % tuple(fields.ravel().tolist())).split("\n")


def _pose_arrays(poses: Poses, dim: int) -> tuple[np.ndarray, np.ndarray]:
    R = np.asarray(poses.R, dtype=np.float64)
    t = np.asarray(poses.t, dtype=np.float64)
    if R.ndim != 3 or R.shape[1:] != (dim, dim) or t.shape != (R.shape[0], dim):
        raise ValueError(f"poses must have R (n, {dim}, {dim}) and t (n, {dim}), got {R.shape} and {t.shape}")
    return R, t
