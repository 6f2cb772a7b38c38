"""TORO ``.graph`` files: the reader (the g2o reader's pipeline with TORO's line table) and the writer.

TORO stores 2D information in another order and 3D rotations as roll, pitch, yaw with information
in those angles; both are mapped to g2o's layout on reading (:mod:`~mmpgo_jax._io.format`) and back
on writing, so everything downstream sees one layout.
"""

from __future__ import annotations

import numpy as np

from .._core.geometry import angle_2d
from .._core.pose_graph import PoseGraph, Poses
from .atomic import atomic_write
from .format import _TORO, _TORO_FORMATS, _TORO_INFO_SCALE, _full_to_upper
from .reader import G2OFile, _read
from .rows import _fmt_rows, _pose_arrays, writer_sizes
from .weights import information_from_weights

__all__ = ["read_toro", "write_toro"]


def read_toro(path, *, dtype=None, strict_information: bool = False) -> G2OFile:
    """Read a TORO ``.graph`` file (``VERTEX2`` / ``EDGE2`` or ``VERTEX3`` / ``EDGE3``), with the
    input rules of :func:`read_g2o` (no FIX lines: TORO has none).

    ``EDGE2 i j dx dy dtheta inf_ff inf_fs inf_ss inf_rr inf_fr inf_sr``: the information matrix
    is [[ff, fs, fr], [fs, ss, sr], [fr, sr, rr]] (f forward = x, s sideward = y, r rotation), the
    g2o matrix of ``EDGE_SE2`` in another order (g2o: I11 I12 I13 I22 I23 I33).
    ``EDGE3 i j x y z roll pitch yaw`` + the 21 entries of the 6x6 upper triangle, row by row, in
    (x, y, z, roll, pitch, yaw) coordinates; R = Rz(yaw) Ry(pitch) Rx(roll) (as GTSAM's
    ``Rot3::Ypr``). g2o's ``EDGE_SE3:QUAT`` information is in (x, y, z, qx, qy, qz) coordinates,
    and near the measurement a rotation by the small angles a has (qx, qy, qz) ~ a / 2, so the
    file's matrix I becomes D I D with D = diag(1, 1, 1, 2, 2, 2) before SE-Sync's weights are
    computed (an isotropic rotation information w in angles gives kappa = 2 w, as g2o's 4 w does).
    ``VERTEX3 id x y z roll pitch yaw``. The result's ``information`` is in g2o's layout.
    """
    return _read(path, dtype=dtype, strict_information=strict_information, family=_TORO)


def _rotation_to_rpy(R: np.ndarray) -> np.ndarray:
    """(k, 3, 3) rotations -> (k, 3) roll, pitch, yaw with R = Rz(yaw) Ry(pitch) Rx(roll).

    Yaw is taken from R Rx(roll)^T Ry(pitch)^T, so that the three angles rebuild R to rounding even
    near pitch = +-90 degrees, where roll and yaw are not determined separately.
    """
    roll = np.arctan2(R[:, 2, 1], R[:, 2, 2])
    pitch = np.arctan2(-R[:, 2, 0], np.hypot(R[:, 2, 1], R[:, 2, 2]))
    cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    # first column and second row-first entry of R Rx(roll)^T Ry(pitch)^T = Rz(yaw)
    m00 = cp * R[:, 0, 0] + sp * (sr * R[:, 0, 1] + cr * R[:, 0, 2])
    m10 = cp * R[:, 1, 0] + sp * (sr * R[:, 1, 1] + cr * R[:, 1, 2])
    yaw = np.arctan2(m10, m00)
    return np.stack([roll, pitch, yaw], 1)


def write_toro(path, graph: PoseGraph, poses: Poses | None, *, vertex_ids=None, information=None) -> None:
    """Write ``graph`` (and VERTEX2 / VERTEX3 lines for ``poses``) as a TORO ``.graph`` file,
    atomically: the layout :func:`read_toro` reads (information in TORO's order, and for 3D in
    roll/pitch/yaw coordinates: D^-1 I D^-1 of the g2o-layout ``information``, D = diag(1, 1, 1, 2,
    2, 2)); ``vertex_ids`` and ``information`` as for :func:`write_g2o`. TORO has no FIX lines.
    """
    d, n, m, ids, ksz = writer_sizes(graph, vertex_ids)
    info = information_from_weights(np.asarray(graph.kappa), np.asarray(graph.tau), d) if information is None \
        else np.asarray(information, dtype=np.float64)
    if info.shape != (m, ksz, ksz):
        raise ValueError(f"information must have shape ({m}, {ksz}, {ksz}), got {info.shape}")
    Rm = np.asarray(graph.R, dtype=np.float64)
    tm = np.asarray(graph.t, dtype=np.float64)
    ei, ej = ids[np.asarray(graph.i)], ids[np.asarray(graph.j)]
    fmt = _TORO_FORMATS[_TORO.edge_tag[d]]
    if d == 2:
        upper = _full_to_upper(info)
        values = np.concatenate([tm, angle_2d(Rm)[:, None], upper], 1)
        order = np.empty(len(fmt.source), dtype=np.int64)
        order[list(fmt.source)] = np.arange(len(fmt.source))  # file position -> g2o layout position
        values = values[:, order]
    else:
        values = np.concatenate([tm, _rotation_to_rpy(Rm), _full_to_upper(info) / _TORO_INFO_SCALE], 1)
    edge_lines = _fmt_rows(np.stack([ei, ej], 1), values, fmt.tag + " ")
    vertex_lines: list[str] = []
    if poses is not None:
        R, t = _pose_arrays(poses, d)
        if R.shape[0] != n:
            raise ValueError(f"poses has {R.shape[0]} poses, the graph {n}")
        rot = angle_2d(R)[:, None] if d == 2 else _rotation_to_rpy(R)
        vertex_lines = _fmt_rows(ids[:, None], np.concatenate([t, rot], 1), _TORO.vertex_tag[d] + " ")
    with atomic_write(path, "w") as f:
        f.write("\n".join(vertex_lines + edge_lines))
        f.write("\n")
