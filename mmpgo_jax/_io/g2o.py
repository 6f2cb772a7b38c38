"""Reading and writing g2o pose-graph files, and TUM trajectory export.

Supported lines (anything else is an error):

- ``EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33``
- ``VERTEX_SE2 id x y theta``
- ``EDGE_SE3:QUAT i j x y z qx qy qz qw`` + the 21 entries of the upper triangle of the 6x6
  information matrix, row by row (translation block first, then rotation)
- ``VERTEX_SE3:QUAT id x y z qx qy qz qw``
- ``FIX id ...``, blank lines, and comment lines (first field starts with ``#``).

Measurement weights follow SE-Sync's convention (SE-Sync's g2o reader, ``read_g2o_file`` in
``C++/SE-Sync/src/SESync_utils.cpp`` of github.com/david-m-rosen/SE-Sync; Rosen, Carlone, Bandeira
and Leonard, "SE-Sync: a certifiably correct algorithm for synchronization over the special
Euclidean group", IJRR 38(2-3), 2019): for SE2, tau = 2 / tr(inv(I[:2, :2]))
and kappa = I33; for SE3, tau = 3 / tr(inv(I[:3, :3])) and kappa = 3 / (2 tr(inv(I[3:, 3:]))).
Vertex ids are remapped to 0..n-1 in ascending order of the original id; the original ids are
kept in :attr:`G2OFile.vertex_ids` and written back by :func:`write_g2o`.

Input rules
-----------

Lines and fields

- The file is read as bytes; a UTF-8 byte order mark at the start is skipped. Lines end with
  LF or CRLF. Fields are separated by ASCII whitespace only (space, tab, CR, VT, FF): other
  (Unicode) spaces are part of a field.
- Blank lines and lines whose first field starts with ``#`` are ignored. Any other line must
  start with one of the tags above and have exactly that tag's number of fields. 2D and 3D
  tags cannot be mixed.

Numbers (the syntax of C ``strtod`` / ``strtol``, ASCII only, as read by SE-Sync's
C++ stream extraction in the C locale)

- Values: ``[+-]?([0-9]+(\\.[0-9]*)?|\\.[0-9]+)([eE][+-]?[0-9]+)?``. Refused, as "not a
  number": digit-group underscores (``1_016.030``), non-ASCII digits (fullwidth ``１``,
  Arabic-Indic ``٣``), hexadecimal, and everything else. ``nan`` and ``inf`` / ``infinity``
  (any case, signed) are refused as "not finite"; a number whose magnitude overflows float64
  (``1e400``) is refused as "out of range". Values that underflow read as 0 or a subnormal
  (allowed in measurements and VERTEX values; information entries have their own rule below).
- Vertex ids (edges, VERTEX and FIX lines): ASCII integers ``[+-]?digits``; an id outside the
  int64 range is refused as "out of range", anything else as "not an integer vertex id".
- Fields quoted in messages are shortened to their first 40 characters, followed by ``…`` and
  their length.

Values

- Edges: no self-loops (i == j). Duplicate edges are kept. Duplicate VERTEX ids are refused.
  FIX ids must name a vertex that has a VERTEX or EDGE line.
- Quaternions (edges and VERTEX_SE3:QUAT) are normalised without overflow or underflow: divided
  by their largest absolute component first, then by their norm (so a quaternion scaled by 1e200
  reads as the unscaled one). A quaternion whose norm (computed that way) is below
  ``QUATERNION_NORM_MIN`` = 1e-12, all-subnormal ones included, is refused as "zero norm".
- Translations: refused when ``|t|^2`` (VERTEX and edge) or ``tau |t|^2`` (edge; and, in
  :func:`read_g2o`, a VERTEX translation with the tau of every edge at that vertex) is not
  representable (larger than the float dtype's maximum): the squared residuals must be
  representable.
- Information matrices (SE-Sync's convention, which uses them as they are even when they are
  indefinite, as about 30 % of the 3D benchmark "cubicle"'s are). An edge is accepted when

  1. every diagonal entry is positive;
  2. every nonzero entry has a magnitude between ``INFORMATION_MIN`` = 1e-300 and
     ``INFORMATION_MAX`` = 1e300 (subnormal entries and entries so large that products in the
     weights or the weighted squared residuals overflow are refused);
  3. the translation block (and, in 3D, the rotation block) has a finite inverse, and the
     weights kappa and tau computed from it are positive, finite and between ``WEIGHT_MIN`` =
     1e-300 and ``WEIGHT_MAX`` = 1e300 (and, for a float32 graph, within float32's normal
     range). A 2D block with I12^2 >= I11 I22 gives tau <= 0 or a singular block and is refused.

  The matrices that pass but are not positive definite (smallest eigenvalue <= k eps |largest|
  for a k x k matrix) are counted in :attr:`G2OFile.num_indefinite_information`, and
  :func:`read_g2o` emits one :class:`G2OWarning` per file saying how many. With
  ``read_g2o(path, strict_information=True)`` every such matrix is refused instead ("information
  matrix is not positive definite").

Parsing is vectorised over the bytes of the file (no Python loop over lines): token boundaries
from an ASCII-whitespace mask, the line of each token by a search among the newlines, tags compared
as byte windows, and the id / value fields of each tag's lines joined into one byte string that is
checked (one C-level character-set check) and converted (one ``int`` / ``float`` pass) at once;
the regular expressions are only used on the slow path that locates the offending field, and
per-line work is only done to locate the offending line when a check fails. Every
malformed input raises :class:`G2OFormatError` with the file, the 1-based line number and a
specific description of the problem: the earliest line with a problem, and on that line the
first failing check (in the order: field syntax, finite values, self-loop, quaternion, |t|^2,
information diagonal, information entry range, positive definiteness when strict, tau, kappa,
tau |t|^2).
"""

from __future__ import annotations

import math
import os
import re
import warnings
from dataclasses import dataclass

import numpy as np

from .._core.gauge import FixedPoses
from .._core.geometry import angle_2d, rotation_to_quaternion
from .._core.pose_graph import PoseGraph, Poses
from .._core.precision import default_float_dtype, to_device
from .atomic import atomic_write

__all__ = [
    "G2OFile",
    "G2OFormatError",
    "G2OPoses",
    "G2OWarning",
    "information_from_weights",
    "read_g2o",
    "read_g2o_poses",
    "read_toro",
    "write_g2o",
    "write_toro",
    "write_tum",
]

# Quaternions with a norm below this cannot be normalised meaningfully.
QUATERNION_NORM_MIN = 1e-12
# Nonzero information entries must lie in this magnitude range (no subnormals, no overflow).
INFORMATION_MIN = 1e-300
INFORMATION_MAX = 1e300
# The weights kappa and tau must lie in this range.
WEIGHT_MIN = 1e-300
WEIGHT_MAX = 1e300
# Fields quoted in error messages are shortened to this many characters.
_SHOW_MAX = 40


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


@dataclass(frozen=True, eq=False)
class G2OFile:
    """The content of a g2o file.

    ``graph`` uses internal pose indices 0..n-1; ``vertex_ids[k]`` is the original g2o id of
    internal pose k (ascending). ``information`` holds the full symmetric information matrices as
    read ((m, 3, 3) for SE2, (m, 6, 6) for SE3). ``initial`` holds the VERTEX estimates when every
    pose has a VERTEX line (else None; ``has_vertex`` says which do). ``fixed`` marks poses named
    in FIX lines. ``num_indefinite_information`` counts the information matrices that are not
    positive definite (accepted under SE-Sync's convention, see the module docstring).
    ``vertex_R`` (n, d, d) and ``vertex_t`` (n, d), float64, hold the VERTEX value of every pose
    that has a VERTEX line, and the identity / zero for the others (always filled by
    :func:`read_g2o`). ``vertex_line`` (n,) is the first line naming each pose and ``edge_line``
    (m,) the line of each edge (1-based; None for graphs not read from one file). Multi-robot inputs
    (:mod:`mmpgo_jax._io.multi_robot`) set ``robot_of_pose`` (n,) (robots 0..A-1) and
    ``robot_names`` (A names, e.g. GTSAM symbol characters or file names).
    """

    path: str | None
    dim: int
    graph: PoseGraph
    vertex_ids: np.ndarray
    information: np.ndarray
    initial: Poses | None
    has_vertex: np.ndarray
    fixed: np.ndarray
    num_indefinite_information: int = 0
    vertex_R: np.ndarray | None = None
    vertex_t: np.ndarray | None = None
    vertex_line: np.ndarray | None = None
    edge_line: np.ndarray | None = None
    robot_of_pose: np.ndarray | None = None
    robot_names: tuple[str, ...] | None = None

    @property
    def num_poses(self) -> int:
        return self.graph.num_poses

    @property
    def num_robots(self) -> int | None:
        """Robots named by the data (None when the file carries none)."""
        return None if self.robot_names is None else len(self.robot_names)

    @property
    def num_edges(self) -> int:
        return self.graph.num_edges

    def _vertex_values(self) -> tuple[np.ndarray, np.ndarray]:
        n, d = self.num_poses, self.dim
        if self.vertex_R is not None:
            return self.vertex_R, self.vertex_t
        return np.broadcast_to(np.eye(d), (n, d, d)), np.zeros((n, d))

    @property
    def fixed_poses(self) -> FixedPoses | None:
        """The FIX poses at their VERTEX values (the identity where a FIX pose has none), or None."""
        if not self.fixed.any():
            return None
        R, t = self._vertex_values()
        idx = np.flatnonzero(self.fixed)
        return FixedPoses(idx, R[idx], t[idx])

    @property
    def frame(self) -> FixedPoses:
        """The frame results are expressed in: the FIX poses if any, else the first pose (smallest
        id) at its VERTEX value, or at the identity when it has no VERTEX line."""
        fixed = self.fixed_poses
        if fixed is not None:
            return fixed
        R, t = self._vertex_values()
        return FixedPoses([0], R[:1], t[:1])


@dataclass(frozen=True, eq=False)
class G2OPoses:
    """The VERTEX lines of a g2o file (:func:`read_g2o_poses`).

    ``vertex_ids`` (k,) int64 ascending, ``R`` (k, d, d) and ``t`` (k, d) float64.
    """

    path: str
    dim: int
    vertex_ids: np.ndarray
    R: np.ndarray
    t: np.ndarray

    @property
    def num_poses(self) -> int:
        return int(self.vertex_ids.shape[0])


# ----------------------------------------------------------------------------------------------
# Line formats


def _upper_names(k: int) -> list[str]:
    return [f"I{r + 1}{c + 1}" for r in range(k) for c in range(r, k)]


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


# ----------------------------------------------------------------------------------------------
# Weights


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


# ----------------------------------------------------------------------------------------------
# Reader: tokens and numbers

# (unambiguous, with possessive quantifiers: linear time even on a field of megabytes)
_NUMBER_RE = re.compile(rb"[+-]?(?:[0-9]++(?:\.[0-9]*+)?|\.[0-9]++)(?:[eE][+-]?[0-9]++)?")
_NONFINITE_RE = re.compile(rb"[+-]?(?:nan|inf|infinity)", re.IGNORECASE)
_INTEGER_RE = re.compile(rb"[+-]?[0-9]++")
# The characters of ASCII numbers / integers (and the space that joins tokens): a group of lines
# whose joined fields contain nothing else takes the fast path (float / int of each field, which
# on these characters accept exactly the syntax of _NUMBER_RE / _INTEGER_RE).
_NUMBER_CHARS = b"0123456789+-.eE "
_INTEGER_CHARS = b"0123456789+- "
_INT64_MIN, _INT64_MAX = -(2**63), 2**63 - 1


def _show(tok) -> str:
    """A field for a message: its repr, shortened to its first characters (and its length) if long."""
    s = tok.decode("utf-8", errors="replace") if isinstance(tok, (bytes, bytearray)) else str(tok)
    if len(s) <= _SHOW_MAX:
        return repr(s)
    return f"{s[:_SHOW_MAX]!r}… ({len(s)} characters)"


def _parse_id(tok: bytes) -> int | str:
    """An ASCII int64 vertex id, or the problem with it ("is ...")."""
    if not _INTEGER_RE.fullmatch(tok):
        return f"is not an integer vertex id: {_show(tok)}"
    if len(tok.lstrip(b"+-").lstrip(b"0")) <= 19:
        v = int(tok)
        if _INT64_MIN <= v <= _INT64_MAX:
            return v
    return f"is out of range: {_show(tok)} (vertex ids must fit in a signed 64-bit integer)"


class _Rows:
    """The fields (tag excluded) of a group's lines as lists of bytes, built on demand from the token
    positions (only for messages and the slow path of :func:`_convert`)."""

    __slots__ = ("data", "ends", "first", "nf", "starts")

    def __init__(self, data: bytes, starts: np.ndarray, ends: np.ndarray, first: np.ndarray, nf: int):
        self.data, self.starts, self.ends, self.first, self.nf = data, starts, ends, first, nf

    def __len__(self) -> int:
        return int(self.first.shape[0])

    def __getitem__(self, r: int) -> list[bytes]:
        i = int(self.first[r])
        sl = slice(i, i + self.nf)
        return [self.data[a:b] for a, b in zip(self.starts[sl].tolist(), self.ends[sl].tolist(), strict=True)]

    def __iter__(self):
        return (self[r] for r in range(len(self)))


class _Group:
    """The lines of one tag: line numbers, fields (tag excluded) and the id / value fields joined
    by spaces (``id_blob``, ``val_blob``), then the checked arrays."""

    __slots__ = ("fmt", "id_blob", "ids", "info", "kappa", "lines", "ok", "pd", "quat", "rows", "tau", "tn2",
                 "val_blob", "vals")

    def __init__(self, fmt: _Format):
        self.fmt = fmt
        self.lines: list[int] = []
        self.rows: _Rows | list = []
        self.id_blob = self.val_blob = b""


def _convert(group: _Group, problems: list) -> None:
    """Convert a group's tokens to ids (int64) and values (float64), vectorised.

    The first row that cannot be converted is reported in ``problems``; it and the rows after it
    are masked out in ``group.ok`` (any problem there is on a later line).
    """
    fmt = group.fmt
    k = len(group.rows)
    nid, nval = fmt.num_ids, len(fmt.fields) - fmt.num_ids
    group.ok = np.ones(k, dtype=bool)
    if not group.id_blob.translate(None, _INTEGER_CHARS) and not group.val_blob.translate(None, _NUMBER_CHARS):
        id_toks, val_toks = group.id_blob.split(), group.val_blob.split()
        try:
            group.ids = np.fromiter(map(int, id_toks), np.int64, k * nid).reshape(k, nid)
            group.vals = np.fromiter(map(float, val_toks), np.float64, k * nval).reshape(k, nval)
            return
        except (ValueError, OverflowError):
            pass
    # Slow path: locate the first offending field.
    ids = np.zeros((k, nid), dtype=np.int64)
    vals = np.zeros((k, nval), dtype=np.float64)
    for r, (line, row) in enumerate(zip(group.lines, group.rows, strict=True)):
        for f, tok in enumerate(row):
            where = f"{fmt.tag}: field {f + 1} ({fmt.fields[f]})"
            if f < nid:
                v = _parse_id(tok)
                if isinstance(v, int):
                    ids[r, f] = v
                    continue
                problem = f"{where} {v}"
            elif _NUMBER_RE.fullmatch(tok) or _NONFINITE_RE.fullmatch(tok):
                vals[r, f - nid] = float(tok)  # non-finite values are reported by _check_values
                continue
            else:
                problem = f"{where} is not a number: {_show(tok)}"
            problems.append((line, problem))
            group.ok[r:] = False
            group.ids, group.vals = ids, vals
            return
    group.ids, group.vals = ids, vals


def _first(mask: np.ndarray) -> int | None:
    idx = np.flatnonzero(mask)
    return int(idx[0]) if idx.size else None


def _g(x) -> str:
    return f"{float(x):.6g}"


# ----------------------------------------------------------------------------------------------
# Reader: checks


@dataclass(frozen=True)
class _Limits:
    """What the float dtype of the result can represent (squared residuals, weights)."""

    dtype_name: str
    square_max: float  # |t|^2 and tau |t|^2 must not exceed this
    weight_min: float
    weight_max: float

    @staticmethod
    def of(dtype) -> _Limits:
        fi = np.finfo(dtype)
        return _Limits(
            np.dtype(dtype).name,
            float(fi.max),
            max(WEIGHT_MIN, float(fi.tiny)),
            min(WEIGHT_MAX, float(fi.max)),
        )


def _scaled(fmt: _Format, v: int) -> str:
    """A note for messages on TORO 3D information entries, which are checked after scaling."""
    if not fmt.euler or not fmt.is_edge or _TORO_INFO_SCALE[v - fmt.information_start] == 1:
        return ""
    return f" (after scaling by {_TORO_INFO_SCALE[v - fmt.information_start]:g} to g2o's quaternion coordinates)"


def _check_values(group: _Group, problems: list, strict: bool, limits: _Limits) -> None:
    """Value checks of one group (vectorised); fills the group's quaternions, weights, ...

    In each line the checks run in this order and only the first failure is reported: finite
    values, self-loop, quaternion norm, |t|^2, information diagonal, information entry range,
    positive definiteness (``strict`` only), translation-block inverse and tau, rotation-block
    inverse and kappa, tau |t|^2.
    """
    fmt, vals = group.fmt, group.vals
    nid, d = fmt.num_ids, fmt.dim
    k = vals.shape[0]
    ok = group.ok
    lines = group.lines
    if k == 0:
        ksz = _info_size(d)
        group.quat, group.tn2, group.info = np.zeros((0, 4)), np.zeros(0), np.zeros((0, ksz, ksz))
        group.kappa, group.tau, group.pd = np.zeros(0), np.zeros(0), np.ones(0, dtype=bool)
        return

    def report(bad: np.ndarray, message) -> None:
        nonlocal ok
        bad = bad & ok
        r = _first(bad)
        if r is not None:
            problems.append((lines[r], f"{fmt.tag}: {message(r)}"))
            ok = ok & ~bad  # later checks are meaningless on such rows

    def name(v: int) -> str:  # value index (g2o layout) -> field name
        return fmt.fields[fmt.field_of(v)]

    def token(r: int, v: int) -> bytes:
        return group.rows[r][fmt.field_of(v)]

    with np.errstate(all="ignore"):
        finite = np.isfinite(vals)

        def nonfinite_message(r: int) -> str:
            v = int(np.flatnonzero(~finite[r])[0])  # in the file's layout
            tok = group.rows[r][v + nid]
            if _NUMBER_RE.fullmatch(tok):
                return (f"field {v + nid + 1} ({fmt.fields[v + nid]}) is out of range (its magnitude overflows "
                        f"float64): {_show(tok)}")
            return f"field {v + nid + 1} ({fmt.fields[v + nid]}) is not finite: {float(vals[r, v])!r}"

        report(~finite.all(axis=1), nonfinite_message)
        vals = fmt.to_g2o(np.where(ok[:, None], vals, 0.0))
        group.vals = vals
        if fmt.is_edge:
            report(group.ids[:, 0] == group.ids[:, 1], lambda r: f"self-loop edge (i == j == {group.ids[r, 0]})")

        # quaternions: divide by the largest |component|, then by the norm
        if d == 3:
            q = vals[:, 3:7]
            scale = np.abs(q).max(axis=1)
            qs = q / np.where(scale > 0, scale, 1.0)[:, None]
            qn = np.sqrt(np.einsum("ka,ka->k", qs, qs))  # in [1, 2] when scale > 0
            qnorm = scale * qn
            report(
                ~(qnorm >= QUATERNION_NORM_MIN),
                lambda r: (
                    f"quaternion (qx, qy, qz, qw) has zero norm "
                    f"(|q| = {qnorm[r]:.3g} < {QUATERNION_NORM_MIN:g}), cannot be normalised"
                ),
            )
            group.quat = qs / np.where(qn > 0, qn, 1.0)[:, None]

        # translations: the squared norm must be representable
        t = vals[:, :d]
        tn2 = np.einsum("ka,ka->k", t, t)
        names = ", ".join(fmt.fields[nid : nid + d])

        def too_large(r: int, what: str) -> str:
            return (
                f"translation ({names}) is too large: {what} overflows {limits.dtype_name} "
                f"(|t| = {math.hypot(*t[r].tolist()):.3g}"
            )

        report(~(tn2 <= limits.square_max), lambda r: too_large(r, f"|t|^2 = {tn2[r]:.3g}") + ")")
        group.tn2 = tn2
        if not fmt.is_edge:
            group.ok = ok
            return

        # information matrices
        ksz = _info_size(d)
        start = fmt.information_start
        upper = vals[:, start:]
        diag_pos = np.array([v for v, (r, c) in enumerate(zip(*np.triu_indices(ksz), strict=True)) if r == c])
        diag = upper[:, diag_pos]

        def diag_message(r: int) -> str:
            c = int(np.flatnonzero(~(diag[r] > 0))[0])
            v = start + int(diag_pos[c])
            tok = token(r, v)
            mantissa = tok.lower().split(b"e")[0]
            under = " (it underflows to 0)" if diag[r, c] == 0 and re.search(rb"[1-9]", mantissa) else ""
            return (
                f"information matrix is not positive definite: diagonal entry {name(v)} = "
                f"{float(diag[r, c])!r} is not positive{under}{_scaled(fmt, v)}"
            )

        report(~(diag > 0).all(axis=1), diag_message)
        mag = np.abs(upper)
        small = (mag != 0) & (mag < INFORMATION_MIN)
        large = mag > INFORMATION_MAX

        def range_message(r: int) -> str:
            c = int(np.flatnonzero(small[r] | large[r])[0])
            x = float(upper[r, c])
            if small[r, c]:
                why = f"is nonzero but below {INFORMATION_MIN:g} in magnitude (subnormal or underflowing)"
            else:
                why = (f"is above {INFORMATION_MAX:g} in magnitude (the weights or the weighted squared residuals "
                       "overflow)")
            return f"information entry {name(start + c)} = {x!r} {why}{_scaled(fmt, start + c)}"

        report((small | large).any(axis=1), range_message)
        info = _upper_to_full(np.where(ok[:, None], upper, 0.0), ksz)
        info[~ok] = np.eye(ksz)
        eig = np.linalg.eigvalsh(info)
        tol = ksz * np.finfo(np.float64).eps * np.abs(eig).max(axis=1)
        not_pd = ~(eig[:, 0] > tol)
        if strict:
            report(
                not_pd,
                lambda r: (
                    f"information matrix is not positive definite "
                    f"(eigenvalues {np.array2string(eig[r], precision=4, separator=', ')})"
                ),
            )

        def weight_checks(weight, bad_inverse, symbol: str, formula: str, block: str) -> None:
            report(
                bad_inverse,
                lambda r: (
                    f"the block {block} of the information matrix is singular or its inverse is not "
                    f"representable (not positive definite): {symbol} = {formula} is undefined"
                ),
            )
            report(
                ~(weight > 0),
                lambda r: (
                    f"SE-Sync weight {symbol} = {formula} = {_g(weight[r])} is not positive "
                    f"(the information matrix is not positive definite)"
                ),
            )
            report(
                ~((weight >= limits.weight_min) & (weight <= limits.weight_max)),
                lambda r: (
                    f"SE-Sync weight {symbol} = {formula} = {_g(weight[r])} is not representable: weights "
                    f"must be finite and between {limits.weight_min:g} and {limits.weight_max:g} "
                    f"({limits.dtype_name})"
                ),
            )

        tr_t, bad_t = _inverse_trace(info[:, :d, :d])
        tau = d / tr_t
        weight_checks(tau, bad_t, "tau", f"{d} / tr(inv(I[:{d}, :{d}]))", f"I[:{d}, :{d}]")
        if d == 2:
            kappa = info[:, 2, 2].copy()
            weight_checks(kappa, np.zeros(k, bool), "kappa", "I33", "I33")
        else:
            tr_r, bad_r = _inverse_trace(info[:, 3:, 3:])
            kappa = 3.0 / (2.0 * tr_r)
            weight_checks(kappa, bad_r, "kappa", "3 / (2 tr(inv(I[3:, 3:])))", "I[3:, 3:]")
        wt = tau * tn2
        report(
            ~(wt <= limits.square_max),
            lambda r: too_large(r, f"tau |t|^2 = {wt[r]:.3g}") + f", tau = {_g(tau[r])})",
        )
    group.info, group.kappa, group.tau = info, kappa, tau
    group.pd = ~not_pd
    group.ok = ok


# ----------------------------------------------------------------------------------------------
# Reader: files


def _read_bytes(spath: str) -> bytes:
    try:
        with open(spath, "rb") as fh:
            return fh.read()
    except FileNotFoundError:
        raise G2OFormatError(spath, None, "file not found") from None
    except IsADirectoryError:
        raise G2OFormatError(spath, None, "is a directory, not a g2o file") from None
    except OSError as exc:
        raise G2OFormatError(spath, None, f"cannot read file: {exc.strerror or exc}") from None


# ASCII whitespace (the separators of bytes.split()): space, \t, \n, \v, \f, \r
_WS = np.zeros(256, dtype=bool)
_WS[[9, 10, 11, 12, 13, 32]] = True


_TO_SPACE = bytes.maketrans(b"\t\n\x0b\x0c\r", b"     ")


def _joined(buf: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bytes:
    """The byte ranges ``buf[lo[r]:hi[r] + 1]`` (ascending, disjoint, each ending in whitespace)
    concatenated, with ASCII whitespace turned into spaces: fields separated by spaces.

    A boolean run-length mask (``np.repeat``) and one gather; no per-line work.
    """
    if lo.size == 0:
        return b""
    bounds = np.stack([lo, hi + 1], 1).ravel()
    runs = np.diff(bounds, prepend=0, append=buf.shape[0])
    keep = np.repeat(np.arange(runs.shape[0]) % 2 == 1, runs)
    return buf[keep].tobytes().translate(_TO_SPACE)


def _tokenise(spath: str, data: bytes, family: _Family = _G2O):
    """Split into lines and ASCII-whitespace fields; check tags, field counts and mixed dimensions.

    Vectorised over the bytes of the file: token boundaries from a whitespace table, the line of
    each token by a search among the newlines, tags compared as byte windows; no Python loop over
    lines (only over the few FIX lines). The first problem (in line order) is raised.
    Returns ``(groups, fix_lines, dim)`` (``dim`` None when there are no VERTEX / EDGE lines).
    """
    if data.startswith(b"\xef\xbb\xbf"):
        data = data[3:]
    groups = {tag.encode("ascii"): _Group(fmt) for tag, fmt in family.formats.items()}
    buf = np.frombuffer(data + b"\n", dtype=np.uint8)
    tok = (buf != 32) & ((buf < 9) | (buf > 13))  # not ASCII whitespace (_WS)
    starts = np.flatnonzero(tok[1:] & ~tok[:-1]) + 1
    if tok[0]:
        starts = np.concatenate([[0], starts])
    ends = np.flatnonzero(~tok[1:] & tok[:-1]) + 1  # one past each token (buf ends with whitespace)
    if starts.size == 0:
        return groups, [], None
    tline = np.searchsorted(np.flatnonzero(buf == 10), starts)  # 0-based line of each token
    first = np.flatnonzero(np.concatenate([[True], tline[1:] != tline[:-1]]))  # first token of each line
    ntok = np.diff(np.append(first, starts.size))
    lineno = tline[first] + 1
    s0, len0 = starts[first], ends[first] - starts[first]

    tags = list(family.formats)
    width = max(len(t) for t in [*tags, "FIX"])
    win = buf[np.minimum(s0[:, None] + np.arange(width), buf.shape[0] - 1)]

    def is_tag(tag: str) -> np.ndarray:
        tb = np.frombuffer(tag.encode("ascii"), dtype=np.uint8)
        return (len0 == tb.shape[0]) & (win[:, : tb.shape[0]] == tb).all(axis=1)

    code = np.full(first.shape[0], -1, dtype=np.int64)
    for c, tag in enumerate(tags):  # a loop over the few tags
        code[is_tag(tag)] = c
    comment = buf[s0] == 0x23  # '#'
    fix = is_tag("FIX") & family.fix
    nfields = np.array([len(family.formats[t].fields) for t in tags])
    dims = np.array([family.formats[t].dim for t in tags])

    known = code >= 0
    unknown = ~known & ~comment & ~fix
    fix_empty = fix & (ntok < 2)
    count_bad = known & (ntok - 1 != nfields[np.maximum(code, 0)])
    pose = np.flatnonzero(known)
    dim = None if pose.size == 0 else int(dims[code[pose[0]]])
    mixed = known & ~count_bad & (dims[np.maximum(code, 0)] != dim)
    bad = _first(unknown | fix_empty | count_bad | mixed)
    if bad is not None:
        line = int(lineno[bad])
        if unknown[bad]:
            tag = data[int(s0[bad]) : int(s0[bad] + len0[bad])]
            raise G2OFormatError(spath, line, f"unknown tag {_show(tag)} (expected {family.known})")
        if fix_empty[bad]:
            raise G2OFormatError(spath, line, "FIX line names no vertex id")
        fmt = family.formats[tags[code[bad]]]
        if count_bad[bad]:
            raise G2OFormatError(
                spath,
                line,
                f"wrong number of fields for {fmt.tag}: expected {len(fmt.fields)} after the tag, "
                f"got {int(ntok[bad]) - 1}",
            )
        first_tag = family.formats[tags[code[pose[0]]]].tag
        raise G2OFormatError(
            spath,
            line,
            f"mixed 2D and 3D tags: {fmt.tag} here, but {first_tag} on line {int(lineno[pose[0]])}",
        )

    for c, tag in enumerate(tags):
        rows = np.flatnonzero(code == c)
        if rows.size == 0:
            continue
        group = groups[tag.encode("ascii")]
        fmt = group.fmt
        nid, nf = fmt.num_ids, len(fmt.fields)
        f1 = first[rows] + 1  # token index of each line's first field
        group.lines = lineno[rows].tolist()
        group.rows = _Rows(data, starts, ends, f1, nf)
        group.id_blob = _joined(buf, starts[f1], ends[f1 + nid - 1])  # the id fields of each line
        group.val_blob = _joined(buf, starts[f1 + nid], ends[f1 + nf - 1])  # the value fields
    fix_lines = [(int(lineno[r]), _Rows(data, starts, ends, first[r : r + 1] + 1, int(ntok[r]) - 1)[0])
                 for r in np.flatnonzero(fix).tolist()]  # the few FIX lines
    return groups, fix_lines, dim


@dataclass
class _Parsed:
    dim: int
    edges: _Group
    vertices: _Group
    vertex_ids: np.ndarray  # sorted unique ids of all VERTEX and EDGE lines
    fixed: np.ndarray  # (n,) bool


def _parse(spath: str, *, need: str, strict: bool, limits: _Limits, family: _Family = _G2O) -> _Parsed:
    """Read, tokenise, convert and check a g2o (or TORO) file; raise the earliest problem.

    ``need`` is "edges" (:func:`read_g2o`), "vertices" (:func:`read_g2o_poses`) or "any" (a robot's
    file of a multi-robot folder: VERTEX lines, EDGE lines or both).
    """
    groups, fix_lines, dim = _tokenise(spath, _read_bytes(spath), family)
    if dim is None:
        raise G2OFormatError(spath, None, "empty file: no VERTEX or EDGE lines")
    eg, vg = groups[family.edge_tag[dim].encode()], groups[family.vertex_tag[dim].encode()]
    if need == "edges" and not eg.rows:
        raise G2OFormatError(spath, None, f"no edges: the file has no {eg.fmt.tag} lines")
    if need == "vertices" and not vg.rows:
        raise G2OFormatError(spath, None, f"no poses: the file has no {vg.fmt.tag} lines")

    # ---- convert and check (vectorised); report the earliest problem in the file
    problems: list[tuple[int, str]] = []
    for g in (eg, vg):
        _convert(g, problems)
        _check_values(g, problems, strict, limits)
    if vg.rows:
        vid = vg.ids[:, 0]
        okr = np.flatnonzero(vg.ok)
        _, first_row, inv = np.unique(vid[okr], return_index=True, return_inverse=True)
        dup = _first(first_row[inv] != np.arange(okr.shape[0]))  # the first repeat among the checked rows
        if dup is not None:
            r, r0 = int(okr[dup]), int(okr[first_row[inv[dup]]])
            problems.append(
                (vg.lines[r], f"duplicate {vg.fmt.tag} id {int(vid[r])} (already defined on line {vg.lines[r0]})")
            )
    if eg.rows and vg.rows:
        _check_vertex_residuals(eg, vg, problems, limits)
    fix_ids: list[tuple[int, list[int]]] = []
    for lineno, toks in fix_lines:
        ids = []
        for f, tok in enumerate(toks):
            v = _parse_id(tok)
            if isinstance(v, str):
                problems.append((lineno, f"FIX: field {f + 1} {v}"))
                break
            ids.append(v)
        fix_ids.append((lineno, ids))
    if problems:
        line, problem = min(problems, key=lambda p: p[0])
        raise G2OFormatError(spath, line, problem)

    # ---- ids
    vertex_ids = np.unique(np.concatenate([eg.ids.ravel(), vg.ids[:, 0]]))
    n = vertex_ids.shape[0]
    fixed = np.zeros(n, dtype=bool)
    if fix_ids:
        fid = np.array([v for _, ids in fix_ids for v in ids], dtype=np.int64)  # the few FIX lines' ids
        fline = np.repeat([line for line, _ in fix_ids], [len(ids) for _, ids in fix_ids])
        k = np.minimum(np.searchsorted(vertex_ids, fid), n - 1)
        missing = _first(vertex_ids[k] != fid)
        if missing is not None:
            raise G2OFormatError(spath, int(fline[missing]),
                                 f"FIX names vertex id {int(fid[missing])}, which has no VERTEX or EDGE line")
        fixed[k] = True
    return _Parsed(dim, eg, vg, vertex_ids.astype(np.int64), fixed)


def _check_vertex_residuals(eg: _Group, vg: _Group, problems: list, limits: _Limits) -> None:
    """A VERTEX translation t must keep tau |t|^2 representable for every edge at that vertex."""
    vok = np.flatnonzero(vg.ok)
    eok = np.flatnonzero(eg.ok)
    if not vok.size or not eok.size:
        return
    vid = vg.ids[vok, 0]
    order = np.argsort(vid, kind="stable")
    svid = vid[order]
    worst: tuple[int, int, int] | None = None  # (vertex line, vertex row, edge row)
    with np.errstate(all="ignore"):
        for end in (0, 1):
            e_ids = eg.ids[eok, end]
            pos = np.minimum(np.searchsorted(svid, e_ids), svid.size - 1)
            found = svid[pos] == e_ids
            vrow = vok[order[pos]]
            bad = found & ~(eg.tau[eok] * vg.tn2[vrow] <= limits.square_max)
            if bad.any():
                b = np.flatnonzero(bad)
                best = b[np.argmin(np.asarray(vg.lines)[vrow[b]])]
                cand = (vg.lines[vrow[best]], int(vrow[best]), int(eok[best]))
                worst = cand if worst is None or cand[0] < worst[0] else worst
    if worst is None:
        return
    line, r, e = worst
    d = vg.fmt.dim
    t = vg.vals[r, :d]
    names = ", ".join(vg.fmt.fields[1 : 1 + d])
    tau = float(eg.tau[e])
    problems.append(
        (
            line,
            (
                f"{vg.fmt.tag}: translation ({names}) is too large: tau |t|^2 = {tau * float(vg.tn2[r]):.3g} "
                f"overflows {limits.dtype_name} for the edge on line {eg.lines[e]} "
                f"(|t| = {math.hypot(*t.tolist()):.3g}, tau = {_g(tau)})"
            ),
        )
    )


def _rotations(group: _Group) -> np.ndarray:
    """float64 rotation matrices of a checked group: from angles [2D] or normalised quaternions [3D].

    The same formulas as :func:`~mmpgo_jax._core.geometry.rotation_2d` / ``quaternion_to_rotation``, in numpy.
    """
    if group.fmt.dim == 2:
        theta = group.vals[:, 2]
        c, s = np.cos(theta), np.sin(theta)
        return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    x, y, z, w = group.quat.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def read_g2o(path, *, dtype=None, strict_information: bool = False) -> G2OFile:
    """Read a 2D (SE2) or 3D (SE3:QUAT) g2o file; raises :class:`G2OFormatError` on bad input.

    Float arrays of the graph and the initial poses use the JAX default float dtype unless
    ``dtype`` is given; ``information``, ``vertex_R`` and ``vertex_t`` are always float64. The
    input rules are those of the module docstring: information matrices that are not positive
    definite but give positive, finite SE-Sync weights are accepted, counted in
    ``num_indefinite_information`` and reported by one :class:`G2OWarning`; with
    ``strict_information=True`` they are refused.
    """
    return _read(path, dtype=dtype, strict_information=strict_information, family=_G2O)


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


def _read(path, *, dtype, strict_information: bool, family: _Family, need: str = "edges",
          warn: bool = True) -> G2OFile:
    """``need="any"``: a robot's file of a multi-robot folder, which may hold VERTEX lines only."""
    spath = os.fspath(path)
    fdt = np.dtype(dtype or default_float_dtype())
    p = _parse(spath, need=need, strict=strict_information, limits=_Limits.of(fdt), family=family)
    out = _build(spath, p, fdt)
    if warn:
        _warn_indefinite(out)
    return out


def _warn_indefinite(g2o: G2OFile) -> None:
    if g2o.num_indefinite_information:
        warnings.warn(
            G2OWarning(f"{g2o.path}: {g2o.num_indefinite_information} of {g2o.num_edges} information matrices are "
                       "not positive definite; SE-Sync weights used"),
            stacklevel=4,  # the caller of read_g2o / read_toro
        )


def _build(spath: str, p: _Parsed, fdt) -> G2OFile:
    """The :class:`G2OFile` of a parsed, checked file."""
    dim, eg, vg, vertex_ids = p.dim, p.edges, p.vertices, p.vertex_ids
    n = vertex_ids.shape[0]

    # ---- measurements and weights
    ei = np.searchsorted(vertex_ids, eg.ids[:, 0]) if eg.rows else np.zeros(0, np.int64)
    ej = np.searchsorted(vertex_ids, eg.ids[:, 1]) if eg.rows else np.zeros(0, np.int64)
    Rm = _rotations(eg) if eg.rows else np.zeros((0, dim, dim))
    graph = PoseGraph.from_arrays(ei, ej, Rm, eg.vals[:, :dim], eg.kappa, eg.tau, num_poses=n, dtype=fdt)

    # ---- VERTEX values; the first line naming each vertex
    has_vertex = np.zeros(n, dtype=bool)
    vertex_R = np.broadcast_to(np.eye(dim), (n, dim, dim)).copy()
    vertex_t = np.zeros((n, dim))
    vertex_line = np.full(n, np.iinfo(np.int64).max, dtype=np.int64)
    edge_line = np.asarray(eg.lines, dtype=np.int64)
    np.minimum.at(vertex_line, ei, edge_line)
    np.minimum.at(vertex_line, ej, edge_line)
    if vg.rows:
        k = np.searchsorted(vertex_ids, vg.ids[:, 0])
        has_vertex[k] = True
        vertex_R[k] = _rotations(vg)
        vertex_t[k] = vg.vals[:, :dim]
        np.minimum.at(vertex_line, k, np.asarray(vg.lines, dtype=np.int64))
    initial = None
    if has_vertex.all():
        initial = Poses(to_device(vertex_R, fdt), to_device(vertex_t, fdt))
    return G2OFile(
        path=spath,
        dim=dim,
        graph=graph,
        vertex_ids=vertex_ids,
        information=eg.info,
        initial=initial,
        has_vertex=has_vertex,
        fixed=p.fixed,
        num_indefinite_information=int(np.count_nonzero(~eg.pd)),
        vertex_R=vertex_R,
        vertex_t=vertex_t,
        vertex_line=vertex_line,
        edge_line=edge_line,
    )


def read_g2o_poses(path) -> G2OPoses:
    """The VERTEX lines of a g2o file, e.g. an initial estimate or a ground truth.

    The same tokeniser and checks as :func:`read_g2o` (number syntax, duplicate ids, quaternions,
    overflow, FIX lines); the file needs no EDGE lines, but EDGE lines that are there are
    validated as by :func:`read_g2o` (no :class:`G2OWarning` is emitted for their information
    matrices). A file without VERTEX lines is refused ("no poses"). Poses are returned in
    ascending vertex-id order, in float64.
    """
    spath = os.fspath(path)
    p = _parse(spath, need="vertices", strict=False, limits=_Limits.of(np.float64))
    vg = p.vertices
    order = np.argsort(vg.ids[:, 0], kind="stable")
    return G2OPoses(
        path=spath,
        dim=p.dim,
        vertex_ids=vg.ids[order, 0].astype(np.int64),
        R=_rotations(vg)[order],
        t=np.ascontiguousarray(vg.vals[order, : p.dim]),
    )


# ----------------------------------------------------------------------------------------------
# Writers


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


def write_g2o(path, graph: PoseGraph, poses: Poses | None, *, vertex_ids=None, information=None, fixed=None) -> None:
    """Write ``graph`` (and VERTEX lines for ``poses``) as a g2o file, atomically.

    Edges are written with the original ids ``vertex_ids[i]`` (default 0..n-1) and with the
    information matrices ``information`` ((m, 3, 3) / (m, 6, 6), e.g. the file's own) or, when not
    given, :func:`information_from_weights` of the graph's weights. Floats are written with full
    round-trip precision. ``poses`` may be None (no VERTEX lines); ``fixed`` (n,) bool adds a FIX
    line.
    """
    vertex_lines, edge_lines, fixed = g2o_lines(graph, poses, vertex_ids=vertex_ids, information=information,
                                                fixed=fixed)
    ids = _check_vertex_ids(vertex_ids, graph.num_poses)
    fix_lines = ["FIX " + " ".join(map(str, ids[fixed].tolist()))] if fixed.any() else []
    with atomic_write(path, "w") as f:
        f.write("\n".join(vertex_lines + fix_lines + edge_lines))
        f.write("\n")


def g2o_lines(graph: PoseGraph, poses: Poses | None, *, vertex_ids=None, information=None,
              fixed=None) -> tuple[list[str], list[str], np.ndarray]:
    """The VERTEX lines (one per pose, [] without ``poses``) and EDGE lines (one per edge) of
    :func:`write_g2o`, and the (n,) fixed mask (checked; all False when ``fixed`` is None)."""
    d = graph.dim
    if d not in (2, 3):
        raise ValueError(f"only 2D and 3D graphs can be written, got dimension {d}")
    n, m = graph.num_poses, graph.num_edges
    ids = _check_vertex_ids(vertex_ids, n)
    ksz = _info_size(d)
    if information is None:
        info = information_from_weights(np.asarray(graph.kappa), np.asarray(graph.tau), d)
    else:
        info = np.asarray(information, dtype=np.float64)
        if info.shape != (m, ksz, ksz):
            raise ValueError(f"information must have shape ({m}, {ksz}, {ksz}), got {info.shape}")
    Rm = np.asarray(graph.R, dtype=np.float64)
    tm = np.asarray(graph.t, dtype=np.float64)
    ei, ej = ids[np.asarray(graph.i)], ids[np.asarray(graph.j)]
    if d == 2:
        meas = np.concatenate([tm, angle_2d(Rm)[:, None]], 1)
    else:
        meas = np.concatenate([tm, rotation_to_quaternion(Rm).reshape(m, 4)], 1)
    edge_lines = _fmt_rows(np.stack([ei, ej], 1), np.concatenate([meas, _full_to_upper(info)], 1), _EDGE_TAG[d] + " ")

    vertex_lines: list[str] = []
    if poses is not None:
        R, t = _pose_arrays(poses, d)
        if R.shape[0] != n:
            raise ValueError(f"poses has {R.shape[0]} poses, the graph {n}")
        if d == 2:
            vals = np.concatenate([t, angle_2d(R)[:, None]], 1)
        else:
            vals = np.concatenate([t, rotation_to_quaternion(R).reshape(n, 4)], 1)
        vertex_lines = _fmt_rows(ids[:, None], vals, _VERTEX_TAG[d] + " ")
    fixed = np.zeros(n, dtype=bool) if fixed is None else np.asarray(fixed, dtype=bool)
    if fixed.shape != (n,):
        raise ValueError(f"fixed must have shape ({n},), got {fixed.shape}")
    return vertex_lines, edge_lines, fixed


def write_tum(path, poses: Poses, *, vertex_ids=None, timestamps=None) -> None:
    """Write poses as a TUM trajectory ``index tx ty tz qx qy qz qw``, one line per pose, atomically.

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
        lines = _fmt_rows(None, np.concatenate([ts[:, None], vals], 1), "")
    else:
        ids = _check_vertex_ids(vertex_ids, n)
        lines = _fmt_rows(ids[:, None], vals, "")
    with atomic_write(path, "w") as f:
        f.write("\n".join(lines))
        f.write("\n")


def write_toro(path, graph: PoseGraph, poses: Poses | None, *, vertex_ids=None, information=None) -> None:
    """Write ``graph`` (and VERTEX2 / VERTEX3 lines for ``poses``) as a TORO ``.graph`` file,
    atomically: the layout :func:`read_toro` reads (information in TORO's order, and for 3D in
    roll/pitch/yaw coordinates: D^-1 I D^-1 of the g2o-layout ``information``, D = diag(1, 1, 1, 2,
    2, 2)); ``vertex_ids`` and ``information`` as for :func:`write_g2o`. TORO has no FIX lines.
    """
    d = graph.dim
    if d not in (2, 3):
        raise ValueError(f"only 2D and 3D graphs can be written, got dimension {d}")
    n, m = graph.num_poses, graph.num_edges
    ids = _check_vertex_ids(vertex_ids, n)
    ksz = _info_size(d)
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
