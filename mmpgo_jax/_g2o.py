"""Reading and writing g2o pose-graph files, and TUM trajectory export.

Supported lines (anything else is an error):

- ``EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33``
- ``VERTEX_SE2 id x y theta``
- ``EDGE_SE3:QUAT i j x y z qx qy qz qw`` + the 21 entries of the upper triangle of the 6x6
  information matrix, row by row (translation block first, then rotation)
- ``VERTEX_SE3:QUAT id x y z qx qy qz qw``
- ``FIX id ...``, blank lines, and comment lines starting with ``#``.

Measurement weights follow SE-Sync (NOTES §1): for SE2, tau = 2 / tr(inv(I[:2, :2])) and
kappa = I33; for SE3, tau = 3 / tr(inv(I[:3, :3])) and kappa = 3 / (2 tr(inv(I[3:, 3:]))).
Vertex ids are remapped to 0..n-1 in ascending order of the original id; the original ids are
kept in :attr:`G2OFile.vertex_ids` and written back by :func:`write_g2o`.

Parsing tokenises each line once in Python and converts and checks the numbers with vectorised
numpy operations; per-line work is only done to locate the offending line when a check fails.
Every malformed input raises :class:`G2OFormatError` with the file, the 1-based line number and a
specific description of the problem.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from ._atomic import atomic_write
from ._geometry import quaternion_to_rotation, rotation_2d, rotation_to_quaternion
from ._pose_graph import PoseGraph, Poses

__all__ = [
    "G2OFile",
    "G2OFormatError",
    "information_from_weights",
    "read_g2o",
    "write_g2o",
    "write_tum",
]

# Quaternions with a norm below this cannot be normalised meaningfully.
QUATERNION_NORM_MIN = 1e-12


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


@dataclass(frozen=True, eq=False)
class G2OFile:
    """The content of a g2o file.

    ``graph`` uses internal pose indices 0..n-1; ``vertex_ids[k]`` is the original g2o id of
    internal pose k (ascending). ``information`` holds the full symmetric information matrices as
    read ((m, 3, 3) for SE2, (m, 6, 6) for SE3). ``initial`` holds the VERTEX estimates when every
    pose has a VERTEX line (else None; ``has_vertex`` says which do). ``fixed`` marks poses named
    in FIX lines.
    """

    path: str | None
    dim: int
    graph: PoseGraph
    vertex_ids: np.ndarray
    information: np.ndarray
    initial: Poses | None
    has_vertex: np.ndarray
    fixed: np.ndarray

    @property
    def num_poses(self) -> int:
        return self.graph.num_poses

    @property
    def num_edges(self) -> int:
        return self.graph.num_edges


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

    @property
    def num_ids(self) -> int:
        return 2 if self.is_edge else 1


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
_KNOWN = ", ".join(_FORMATS) + " or FIX"


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


def _weights(info: np.ndarray, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """SE-Sync's (kappa, tau) from full information matrices (NOTES §1)."""
    if dim == 2:
        tau = 2.0 / np.trace(np.linalg.inv(info[:, :2, :2]), axis1=1, axis2=2)
        kappa = info[:, 2, 2].copy()
    else:
        tau = 3.0 / np.trace(np.linalg.inv(info[:, :3, :3]), axis1=1, axis2=2)
        kappa = 3.0 / (2.0 * np.trace(np.linalg.inv(info[:, 3:, 3:]), axis1=1, axis2=2))
    return kappa, tau


def information_from_weights(kappa, tau, dim: int) -> np.ndarray:
    """Isotropic information matrices that map back to (kappa, tau) under NOTES §1.

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


# ----------------------------------------------------------------------------------------------
# Reader


class _Group:
    """The lines of one tag: line numbers and token lists (tag excluded)."""

    __slots__ = ("fmt", "lines", "rows", "ids", "vals", "ok")

    def __init__(self, fmt: _Format):
        self.fmt = fmt
        self.lines: list[int] = []
        self.rows: list[list[str]] = []


def _is_int_token(tok: str) -> bool:
    try:
        int(tok)
    except ValueError:
        return False
    return True


def _convert(group: _Group, problems: list) -> None:
    """Convert a group's tokens to ids (int64) and values (float64), vectorised.

    Rows that cannot be converted are reported in ``problems`` and masked out in ``group.ok``.
    """
    fmt = group.fmt
    k = len(group.rows)
    nid, nval = fmt.num_ids, len(fmt.fields) - fmt.num_ids
    group.ok = np.ones(k, dtype=bool)
    try:
        ids = np.fromiter(map(int, (t for r in group.rows for t in r[:nid])), np.int64, k * nid)
        vals = np.fromiter(map(float, (t for r in group.rows for t in r[nid:])), np.float64, k * nval)
        group.ids = ids.reshape(k, nid)
        group.vals = vals.reshape(k, nval)
        return
    except (ValueError, OverflowError):
        pass
    # Slow path: locate the offending rows.
    ids = np.zeros((k, nid), dtype=np.int64)
    vals = np.zeros((k, nval), dtype=np.float64)
    for r, (line, row) in enumerate(zip(group.lines, group.rows)):
        for f, tok in enumerate(row):
            name = fmt.fields[f]
            if f < nid:
                try:
                    ids[r, f] = int(tok)
                    continue
                except (ValueError, OverflowError):
                    kind = "not an integer" if not _is_int_token(tok) else "out of range"
                    problems.append((line, f"{fmt.tag}: field {f + 1} ({name}) is {kind} vertex id: {tok!r}"))
            else:
                try:
                    vals[r, f - nid] = float(tok)
                    continue
                except ValueError:
                    problems.append((line, f"{fmt.tag}: field {f + 1} ({name}) is not a number: {tok!r}"))
            group.ok[r] = False
            break
    group.ids, group.vals = ids, vals


def _first(mask: np.ndarray) -> int | None:
    idx = np.flatnonzero(mask)
    return int(idx[0]) if idx.size else None


def _check_values(group: _Group, problems: list) -> None:
    """Non-finite values, self-loops, zero quaternions, non-positive-definite information."""
    fmt, ok, vals = group.fmt, group.ok, group.vals
    nid = fmt.num_ids
    k = vals.shape[0]
    if k == 0:
        return

    def report(bad: np.ndarray, message) -> None:
        r = _first(bad & ok)
        if r is not None:
            problems.append((group.lines[r], message(r)))

    finite = np.isfinite(vals)
    if not finite.all():
        bad_rows = ~finite.all(axis=1)
        r = _first(bad_rows & ok)
        if r is not None:
            f = int(np.flatnonzero(~finite[r])[0])
            problems.append(
                (group.lines[r], f"{fmt.tag}: field {f + nid + 1} ({fmt.fields[f + nid]}) is not finite: {float(vals[r, f])!r}")
            )
        ok = ok & ~bad_rows  # later checks are meaningless on such rows
    if fmt.is_edge:
        report(
            group.ids[:, 0] == group.ids[:, 1],
            lambda r: f"{fmt.tag}: self-loop edge (i == j == {group.ids[r, 0]})",
        )
    if fmt.dim == 3:
        qnorm = np.linalg.norm(vals[:, 3:7], axis=1)  # x y z qx qy qz qw, edges and vertices
        report(
            qnorm < QUATERNION_NORM_MIN,
            lambda r: (
                f"{fmt.tag}: quaternion (qx, qy, qz, qw) has zero norm "
                f"(|q| = {qnorm[r]:.3g} < {QUATERNION_NORM_MIN:g}), cannot be normalised"
            ),
        )
    if fmt.is_edge:
        ksz = _info_size(fmt.dim)
        start = 3 if fmt.dim == 2 else 7
        info = _upper_to_full(np.where(ok[:, None], vals[:, start:], 0.0), ksz)
        info[~ok] = np.eye(ksz)
        eig = np.linalg.eigvalsh(info)
        tol = ksz * np.finfo(np.float64).eps * np.abs(eig).max(axis=1)
        report(
            ~(eig[:, 0] > tol),
            lambda r: (
                f"{fmt.tag}: information matrix is not positive definite "
                f"(eigenvalues {np.array2string(eig[r], precision=4, separator=', ')})"
            ),
        )
    group.ok = ok


def read_g2o(path, *, dtype=None) -> G2OFile:
    """Read a 2D (SE2) or 3D (SE3:QUAT) g2o file; raises :class:`G2OFormatError` on bad input.

    Float arrays of the graph and the initial poses use the JAX default float dtype unless
    ``dtype`` is given; ``information`` is always float64.
    """
    spath = os.fspath(path)
    try:
        with open(spath, "rb") as fh:
            data = fh.read()
    except FileNotFoundError:
        raise G2OFormatError(spath, None, "file not found") from None
    except IsADirectoryError:
        raise G2OFormatError(spath, None, "is a directory, not a g2o file") from None
    except OSError as exc:
        raise G2OFormatError(spath, None, f"cannot read file: {exc.strerror or exc}") from None
    text = data.decode("utf-8-sig", errors="replace")

    groups = {tag: _Group(fmt) for tag, fmt in _FORMATS.items()}
    fix_lines: list[tuple[int, list[str]]] = []
    dim = None
    dim_first: tuple[int, str] | None = None  # (line, tag) of the first pose line
    # ---- tokenise (and check tags, field counts and mixed dimensions) in file order
    for lineno, raw in enumerate(text.split("\n"), 1):
        toks = raw.split()
        if not toks:
            continue
        tag = toks[0]
        if tag[0] == "#":
            continue
        group = groups.get(tag)
        if group is None:
            if tag == "FIX":
                if len(toks) < 2:
                    raise G2OFormatError(spath, lineno, "FIX line names no vertex id")
                fix_lines.append((lineno, toks[1:]))
                continue
            raise G2OFormatError(spath, lineno, f"unknown tag {tag!r} (expected {_KNOWN})")
        fmt = group.fmt
        if len(toks) - 1 != len(fmt.fields):
            raise G2OFormatError(
                spath,
                lineno,
                f"wrong number of fields for {tag}: expected {len(fmt.fields)} after the tag, got {len(toks) - 1}",
            )
        if dim != fmt.dim:
            if dim is None:
                dim, dim_first = fmt.dim, (lineno, tag)
            else:
                raise G2OFormatError(
                    spath,
                    lineno,
                    f"mixed 2D and 3D tags: {tag} here, but {dim_first[1]} on line {dim_first[0]}",
                )
        group.lines.append(lineno)
        group.rows.append(toks[1:])

    if dim is None:
        raise G2OFormatError(spath, None, "empty file: no VERTEX or EDGE lines")
    eg, vg = groups[_EDGE_TAG[dim]], groups[_VERTEX_TAG[dim]]
    if not eg.rows:
        raise G2OFormatError(spath, None, f"no edges: the file has no {eg.fmt.tag} lines")

    # ---- convert and check (vectorised); report the earliest problem in the file
    problems: list[tuple[int, str]] = []
    for g in (eg, vg):
        _convert(g, problems)
        _check_values(g, problems)
    if vg.rows:
        vid = vg.ids[:, 0]
        if np.unique(vid).shape[0] < vid.shape[0]:
            seen: dict[int, int] = {}
            for r, v in enumerate(vid.tolist()):
                if not vg.ok[r]:
                    continue
                if v in seen:
                    problems.append(
                        (vg.lines[r], f"duplicate {vg.fmt.tag} id {v} (already defined on line {vg.lines[seen[v]]})")
                    )
                    break
                seen[v] = r
    for lineno, toks in fix_lines:
        for f, tok in enumerate(toks):
            if not _is_int_token(tok):
                problems.append((lineno, f"FIX: field {f + 1} is not an integer vertex id: {tok!r}"))
                break
    if problems:
        line, problem = min(problems, key=lambda p: p[0])
        raise G2OFormatError(spath, line, problem)

    # ---- remap ids
    edge_ids = eg.ids
    vertex_ids = np.unique(np.concatenate([edge_ids.ravel(), vg.ids[:, 0] if vg.rows else np.zeros(0, np.int64)]))
    n = vertex_ids.shape[0]
    ei = np.searchsorted(vertex_ids, edge_ids[:, 0])
    ej = np.searchsorted(vertex_ids, edge_ids[:, 1])
    fixed = np.zeros(n, dtype=bool)
    for lineno, toks in fix_lines:
        for tok in toks:
            v = int(tok)
            k = int(np.searchsorted(vertex_ids, v))
            if k >= n or vertex_ids[k] != v:
                raise G2OFormatError(spath, lineno, f"FIX names vertex id {v}, which has no VERTEX or EDGE line")
            fixed[k] = True

    # ---- measurements and weights
    ev = eg.vals
    vv = vg.vals if vg.rows else np.zeros((0, len(vg.fmt.fields) - 1))
    m = ev.shape[0]
    ksz = _info_size(dim)
    if dim == 2:
        t_meas = ev[:, 0:2]
        rots = _rotations(2, np.concatenate([ev[:, 2], vv[:, 2]]))
        info = _upper_to_full(ev[:, 3:], ksz)
    else:
        t_meas = ev[:, 0:3]
        rots = _rotations(3, np.concatenate([ev[:, 3:7], vv[:, 3:7]]))
        info = _upper_to_full(ev[:, 7:], ksz)
    R_meas = rots[:m]
    kappa, tau = _weights(info, dim)
    fdt = dtype or jnp.asarray(0.0).dtype
    graph = PoseGraph.from_arrays(ei, ej, R_meas, t_meas, kappa, tau, num_poses=n, dtype=fdt)

    # ---- initial estimates
    has_vertex = np.zeros(n, dtype=bool)
    initial = None
    if vg.rows:
        k = np.searchsorted(vertex_ids, vg.ids[:, 0])
        has_vertex[k] = True
        if has_vertex.all():
            R0 = np.empty((n, dim, dim))
            t0 = np.empty((n, dim))
            R0[k] = rots[m:]
            t0[k] = vv[:, 0:dim]
            initial = Poses(jnp.asarray(R0, fdt), jnp.asarray(t0, fdt))

    return G2OFile(
        path=spath,
        dim=dim,
        graph=graph,
        vertex_ids=vertex_ids.astype(np.int64),
        information=info,
        initial=initial,
        has_vertex=has_vertex,
        fixed=fixed,
    )


_jit_rotation_2d = jax.jit(rotation_2d)
_jit_quaternion_to_rotation = jax.jit(quaternion_to_rotation)


def _bucket(k: int) -> int:
    """Pad batch sizes to powers of two (at least 64) so that compiled helpers are reused."""
    return max(64, 1 << max(k - 1, 0).bit_length())


def _rotations(dim: int, params: np.ndarray) -> np.ndarray:
    """Rotation matrices from angles (k,) [2D] or (x, y, z, w) quaternions (k, 4) [3D].

    Uses the geometry helpers (jitted, on the host CPU device, batch padded to a power of two so
    that reading many files compiles only a handful of times). The result is float64 when x64 is
    enabled, else float32 (the dtype the graph is built with anyway).
    """
    k = params.shape[0]
    size = _bucket(k)
    if dim == 2:
        padded = np.zeros(size)
        padded[:k] = params
        fn = _jit_rotation_2d
    else:
        padded = np.zeros((size, 4))
        padded[:, 3] = 1.0
        padded[:k] = params
        fn = _jit_quaternion_to_rotation
    cpu = jax.local_devices(backend="cpu")[0]
    dt = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    out = fn(jax.device_put(padded.astype(dt), cpu))
    return np.asarray(out)[:k]


# ----------------------------------------------------------------------------------------------
# Writers


def _check_vertex_ids(vertex_ids, n: int) -> np.ndarray:
    if vertex_ids is None:
        return np.arange(n, dtype=np.int64)
    ids = np.asarray(vertex_ids)
    if ids.shape != (n,):
        raise ValueError(f"vertex_ids must have shape ({n},), got {ids.shape}")
    if not np.issubdtype(ids.dtype, np.integer):
        if not np.all(np.asarray(ids, dtype=np.float64) == np.round(np.asarray(ids, dtype=np.float64))):
            raise ValueError("vertex_ids must be integers")
    ids = ids.astype(np.int64)
    if np.unique(ids).shape[0] != n:
        raise ValueError("vertex_ids must be unique")
    return ids


def _fmt_rows(ints: np.ndarray | None, floats: np.ndarray, prefix: str) -> list[str]:
    """Lines ``prefix int.. float..``; floats as Python repr (shortest exact round trip)."""
    fl = floats.tolist()
    if ints is None:
        return [prefix + " ".join(map(repr, row)) for row in fl]
    il = ints.tolist()
    return [prefix + " ".join(map(str, a)) + " " + " ".join(map(repr, b)) for a, b in zip(il, fl)]


def _pose_arrays(poses: Poses, dim: int) -> tuple[np.ndarray, np.ndarray]:
    R = np.asarray(poses.R, dtype=np.float64)
    t = np.asarray(poses.t, dtype=np.float64)
    if R.ndim != 3 or R.shape[1:] != (dim, dim) or t.shape != (R.shape[0], dim):
        raise ValueError(f"poses must have R (n, {dim}, {dim}) and t (n, {dim}), got {R.shape} and {t.shape}")
    return R, t


def _angles(R: np.ndarray) -> np.ndarray:
    """Planar rotation angles, in float64 on the host (same formula as ``_geometry.angle_2d``)."""
    return np.arctan2(R[..., 1, 0], R[..., 0, 0])


def write_g2o(path, graph: PoseGraph, poses: Poses | None, *, vertex_ids=None, information=None, fixed=None) -> None:
    """Write ``graph`` (and VERTEX lines for ``poses``) as a g2o file, atomically.

    Edges are written with the original ids ``vertex_ids[i]`` (default 0..n-1) and with the
    information matrices ``information`` ((m, 3, 3) / (m, 6, 6), e.g. the file's own) or, when not
    given, :func:`information_from_weights` of the graph's weights. Floats are written with full
    round-trip precision. ``poses`` may be None (no VERTEX lines); ``fixed`` (n,) bool adds a FIX
    line.
    """
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
        meas = np.concatenate([tm, _angles(Rm)[:, None]], 1)
    else:
        meas = np.concatenate([tm, rotation_to_quaternion(Rm).reshape(m, 4)], 1)
    edge_lines = _fmt_rows(np.stack([ei, ej], 1), np.concatenate([meas, _full_to_upper(info)], 1), _EDGE_TAG[d] + " ")

    vertex_lines: list[str] = []
    if poses is not None:
        R, t = _pose_arrays(poses, d)
        if R.shape[0] != n:
            raise ValueError(f"poses has {R.shape[0]} poses, the graph {n}")
        if d == 2:
            vals = np.concatenate([t, _angles(R)[:, None]], 1)
        else:
            vals = np.concatenate([t, rotation_to_quaternion(R).reshape(n, 4)], 1)
        vertex_lines = _fmt_rows(ids[:, None], vals, _VERTEX_TAG[d] + " ")
    fix_lines: list[str] = []
    if fixed is not None:
        fixed = np.asarray(fixed, dtype=bool)
        if fixed.shape != (n,):
            raise ValueError(f"fixed must have shape ({n},), got {fixed.shape}")
        if fixed.any():
            fix_lines = ["FIX " + " ".join(map(str, ids[fixed].tolist()))]

    with atomic_write(path, "w") as f:
        f.write("\n".join(vertex_lines + fix_lines + edge_lines))
        f.write("\n")


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
        half = 0.5 * _angles(R)
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
