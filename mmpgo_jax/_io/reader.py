"""The reader pipeline shared by g2o and TORO files: path -> bytes -> tokens -> checked values -> G2OFile.

Both formats differ only in their line tables (:mod:`~mmpgo_jax._io.format`), so one pipeline reads
both, with the same input rules and the same messages: :mod:`~mmpgo_jax._io.tokens` splits and
converts, :mod:`~mmpgo_jax._io.checks` checks, and the earliest problem in the file is raised as
one :class:`~mmpgo_jax._io.format.G2OFormatError`.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass

import numpy as np

from .._core.gauge import FixedPoses
from .._core.pose_graph import PoseGraph, Poses
from .._core.precision import default_float_dtype, to_device
from .checks import _check_duplicate_ids, _check_values, _check_vertex_residuals, _fix_ids, _Limits
from .format import _G2O, G2OFormatError, G2OWarning, _Family
from .tokens import _convert, _first, _Group, _tokenise


@dataclass(frozen=True, eq=False)
class G2OFile:
    """The content of a g2o file.

    ``graph`` uses internal pose indices 0..n-1; ``vertex_ids[k]`` is the original g2o id of
    internal pose k (ascending). ``information`` holds the full symmetric information matrices as
    read ((m, 3, 3) for SE2, (m, 6, 6) for SE3). ``initial`` holds the VERTEX estimates when every
    pose has a VERTEX line (else None; ``has_vertex`` says which do). ``fixed`` marks poses named
    in FIX lines. ``num_indefinite_information`` counts the information matrices that are not
    positive definite (accepted under SE-Sync's convention, see :mod:`mmpgo_jax._io.g2o`).
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
        _check_duplicate_ids(vg, problems)
    if eg.rows and vg.rows:
        _check_vertex_residuals(eg, vg, problems, limits)
    fix_ids = _fix_ids(fix_lines, problems)
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
