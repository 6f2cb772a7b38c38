"""Reading and writing g2o pose-graph files: the public entry points of the file formats.

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

Layers (private modules of :mod:`mmpgo_jax._io`, each used by the one after it):
:mod:`~mmpgo_jax._io.format` (line tables of g2o and TORO, limits, :class:`G2OFormatError`),
:mod:`~mmpgo_jax._io.tokens` (bytes -> token arrays -> ids and values, vectorised),
:mod:`~mmpgo_jax._io.weights` (SE-Sync's kappa and tau from information matrices and back),
:mod:`~mmpgo_jax._io.checks` (the value rules above, one message per problem),
:mod:`~mmpgo_jax._io.reader` (the pipeline shared with TORO: path -> :class:`G2OFile`), then the
formats: this module (g2o), :mod:`~mmpgo_jax._io.toro` and :mod:`~mmpgo_jax._io.tum`, whose writers
share :mod:`~mmpgo_jax._io.rows`. The names of those modules that other code uses are importable
from here too.
"""

from __future__ import annotations

import os

import numpy as np

from .._core.geometry import angle_2d, rotation_to_quaternion
from .._core.pose_graph import PoseGraph, Poses
from .atomic import atomic_write
from .checks import _Limits
from .format import (  # noqa: F401 (limits and the families are re-exported: this module documents them)
    _EDGE_TAG,
    _G2O,
    _TORO,
    _VERTEX_TAG,
    INFORMATION_MAX,
    INFORMATION_MIN,
    QUATERNION_NORM_MIN,
    WEIGHT_MAX,
    WEIGHT_MIN,
    G2OFormatError,
    G2OWarning,
    _full_to_upper,
    _info_size,
)
from .reader import G2OFile, G2OPoses, _parse, _read, _rotations
from .rows import _check_vertex_ids, _fmt_rows, _pose_arrays, writer_sizes
from .tokens import _show, _tokenise  # noqa: F401 (tests reach the tokeniser through this module)
from .toro import read_toro, write_toro
from .tum import tum_lines
from .weights import information_from_weights

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
    d, n, m, ids, ksz = writer_sizes(graph, vertex_ids)
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
    lines = tum_lines(poses, vertex_ids=vertex_ids, timestamps=timestamps)
    with atomic_write(path, "w") as f:
        f.write("\n".join(lines))
        f.write("\n")
