"""TUM trajectories (``index tx ty tz qx qy qz qw``), the format of trajectory tools such as evo.

Only the lines: :func:`~mmpgo_jax._io.g2o.write_tum` writes them atomically, the way
:func:`~mmpgo_jax._io.g2o.write_g2o` writes :func:`~mmpgo_jax._io.g2o.g2o_lines`, so that every
writer of the public API shares one file-writing path.
"""

from __future__ import annotations

import numpy as np

from .._core.geometry import angle_2d, rotation_to_quaternion
from .._core.pose_graph import Poses
from .rows import _check_vertex_ids, _fmt_rows, _pose_arrays

__all__ = ["tum_lines"]


def tum_lines(poses: Poses, *, vertex_ids=None, timestamps=None) -> list[str]:
    """The lines ``index tx ty tz qx qy qz qw`` of a TUM trajectory, one per pose.

    The index is the original vertex id (``vertex_ids``, default 0..n-1) or, if given, the
    timestamp. 2D poses get tz = 0 and a quaternion about the z axis.
    """
    d = poses.dim
    if d not in (2, 3):
        raise ValueError(f"only 2D and 3D poses can be written, got dimension {d}")
    R, t = _pose_arrays(poses, d)
    n = R.shape[0]
    if d == 2:
        half = 0.5 * angle_2d(R)
        z = np.zeros(n)
        q = np.stack([z, z, np.sin(half), np.cos(half)], 1)
        t = np.concatenate([t, z[:, None]], 1)
    else:
        q = rotation_to_quaternion(R).reshape(n, 4)
    vals = np.concatenate([t, q], 1)
    if timestamps is not None:
        ts = np.asarray(timestamps, dtype=np.float64).reshape(-1)
        if ts.shape != (n,):
            raise ValueError(f"timestamps must have shape ({n},), got {ts.shape}")
        return _fmt_rows(None, np.concatenate([ts[:, None], vals], 1), "")
    return _fmt_rows(_check_vertex_ids(vertex_ids, n)[:, None], vals, "")
