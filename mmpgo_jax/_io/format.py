"""The line formats of g2o and TORO files: tags, fields, value layouts, limits and the errors.

One table per family, shared by the tokeniser (tags and field counts), the value checks (field
names in messages, the limits) and the writers (tags, TORO's order of values), so that a reader
and its writer cannot disagree on a layout. The input rules themselves are documented in
:mod:`mmpgo_jax._io.g2o`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Quaternions with a norm below this cannot be normalised meaningfully.
QUATERNION_NORM_MIN = 1e-12
# Nonzero information entries must lie in this magnitude range (no subnormals, no overflow).
INFORMATION_MIN = 1e-300
INFORMATION_MAX = 1e300
# The weights kappa and tau must lie in this range.
WEIGHT_MIN = 1e-300
WEIGHT_MAX = 1e300


class G2OFormatError(ValueError):
    """A malformed (or unreadable) g2o file.

    Attributes: ``path`` (str), ``line`` (1-based line number, or None when the problem concerns
    the whole file) and ``problem`` (what is wrong). ``str(err)`` is ``"path:line: problem"``
    (``"path: problem"`` without a line).
    """

    def __init__(self, path, line: int | None, problem: str):
        self.path = str(path)
        self.line = None if line is None else int(line)
        self.problem = str(problem)
        where = self.path if self.line is None else f"{self.path}:{self.line}"
        super().__init__(f"{where}: {self.problem}")

    def __reduce__(self):
        return (type(self), (self.path, self.line, self.problem))


class G2OWarning(UserWarning):
    """A g2o file that is read, but with a caveat (e.g. indefinite information matrices)."""


def _upper_names(k: int) -> list[str]:
    return [f"I{r + 1}{c + 1}" for r in range(k) for c in range(r, k)]


def _info_size(dim: int) -> int:
    return 3 if dim == 2 else 6


def _upper_to_full(upper: np.ndarray, k: int) -> np.ndarray:
    """(m, k(k+1)/2) row-major upper triangles -> (m, k, k) symmetric matrices."""
    r, c = np.triu_indices(k)
    full = np.zeros((upper.shape[0], k, k), dtype=np.float64)
    full[:, r, c] = upper
    full[:, c, r] = upper
    return full


def _full_to_upper(full: np.ndarray) -> np.ndarray:
    k = full.shape[-1]
    r, c = np.triu_indices(k)
    return full[:, r, c]


# A small rotation of angle theta about u has quaternion vector part sin(theta/2) u ~ theta u / 2, so
# information in angle coordinates I_a becomes D I_a D, D = diag(1, 1, 1, 2, 2, 2), in g2o's (qx, qy, qz).
_TORO_SCALE = np.array([1.0, 1.0, 1.0, 2.0, 2.0, 2.0])
_TORO_INFO_SCALE = np.outer(_TORO_SCALE, _TORO_SCALE)[np.triu_indices(6)]


def _rpy_to_quaternion(rpy: np.ndarray) -> np.ndarray:
    """(k, 3) roll, pitch, yaw -> (k, 4) unit quaternions (x, y, z, w) of Rz(yaw) Ry(pitch) Rx(roll)."""
    h = 0.5 * rpy
    cr, cp, cy = np.cos(h).T
    sr, sp, sy = np.sin(h).T
    return np.stack([sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy,
                     cr * cp * cy + sr * sp * sy], 1)


@dataclass(frozen=True)
class _Format:
    tag: str
    dim: int
    is_edge: bool
    fields: tuple[str, ...]  # names of the fields after the tag
    # TORO lines: ``source[v]`` = the value index in the file of value v of the g2o layout (None:
    # the same layout); ``euler``: roll, pitch, yaw instead of a quaternion (3D)
    source: tuple[int, ...] | None = None
    euler: bool = False

    @property
    def num_ids(self) -> int:
        return 2 if self.is_edge else 1

    def field_of(self, v: int) -> int:
        """Index among the fields after the tag of value ``v`` of the g2o layout (ids excluded)."""
        return self.num_ids + (v if self.source is None else self.source[v])

    def to_g2o(self, vals: np.ndarray) -> np.ndarray:
        """(k, values) as in the file -> the g2o layout of this line type (TORO: see :func:`read_toro`)."""
        if self.euler:
            d = 3
            t, rpy, rest = vals[:, :d], vals[:, d:d + 3], vals[:, d + 3:]
            if self.is_edge:  # rotation block from roll/pitch/yaw angles to g2o's (qx, qy, qz)
                rest = rest * _TORO_INFO_SCALE
            return np.concatenate([t, _rpy_to_quaternion(rpy), rest], 1)
        return vals if self.source is None else vals[:, list(self.source)]

    @property
    def information_start(self) -> int:
        """Index (among the values, ids excluded) of I11 (edges only)."""
        return 3 if self.dim == 2 else 7


_FORMATS = {
    f.tag: f
    for f in (
        _Format("EDGE_SE2", 2, True, ("i", "j", "dx", "dy", "dtheta", *_upper_names(3))),
        _Format("VERTEX_SE2", 2, False, ("id", "x", "y", "theta")),
        _Format(
            "EDGE_SE3:QUAT", 3, True, ("i", "j", "x", "y", "z", "qx", "qy", "qz", "qw", *_upper_names(6))
        ),
        _Format("VERTEX_SE3:QUAT", 3, False, ("id", "x", "y", "z", "qx", "qy", "qz", "qw")),
    )
}
_EDGE_TAG = {2: "EDGE_SE2", 3: "EDGE_SE3:QUAT"}
_VERTEX_TAG = {2: "VERTEX_SE2", 3: "VERTEX_SE3:QUAT"}

# TORO (.graph): EDGE2's information is inf_ff inf_fs inf_ss inf_rr inf_fr inf_sr, i.e. I11 I12 I22
# I33 I13 I23 (g2o: I11 I12 I13 I22 I23 I33); EDGE3's is the 6x6 upper triangle, row by row, in
# (x, y, z, roll, pitch, yaw) coordinates.
_TORO_FORMATS = {
    f.tag: f
    for f in (
        _Format("EDGE2", 2, True, ("i", "j", "dx", "dy", "dtheta", "I11", "I12", "I22", "I33", "I13", "I23"),
                source=(0, 1, 2, 3, 4, 7, 5, 8, 6)),
        _Format("VERTEX2", 2, False, ("id", "x", "y", "theta")),
        _Format("EDGE3", 3, True, ("i", "j", "x", "y", "z", "roll", "pitch", "yaw", *_upper_names(6)),
                source=(0, 1, 2, 3, 3, 3, 3, *range(6, 27)), euler=True),
        _Format("VERTEX3", 3, False, ("id", "x", "y", "z", "roll", "pitch", "yaw"), source=(0, 1, 2, 3, 3, 3, 3),
                euler=True),
    )
}


@dataclass(frozen=True)
class _Family:
    """The line types of one file format."""

    name: str
    formats: dict
    edge_tag: dict  # dim -> tag
    vertex_tag: dict
    fix: bool  # FIX lines allowed

    @property
    def known(self) -> str:
        return ", ".join(self.formats) + (" or FIX" if self.fix else "")


_G2O = _Family("g2o", _FORMATS, _EDGE_TAG, _VERTEX_TAG, True)
_TORO = _Family("TORO", _TORO_FORMATS, {2: "EDGE2", 3: "EDGE3"}, {2: "VERTEX2", 3: "VERTEX3"}, False)
