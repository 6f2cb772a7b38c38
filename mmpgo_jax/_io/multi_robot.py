"""Multi-robot inputs and per-robot outputs: robots from GTSAM symbol keys, a label file or one g2o
file per robot, and per-robot g2o / TUM files.

Every reader returns a :class:`~mmpgo_jax.G2OFile` whose ``robot_of_pose`` (n,) and
``robot_names`` (A,) say which robot owns each pose; the original vertex ids stay in
``vertex_ids`` and every writer uses them. Robots are numbered in the order of their names
(numerically when every name is an integer, else by character code), so one multi-robot graph
written in any of the three ways reads to the same partition. Input rules are those of the g2o
reader (:mod:`mmpgo_jax._io.g2o`): a problem is a :class:`~mmpgo_jax.G2OFormatError` naming file
and line; no measurement is dropped silently.

GTSAM symbol keys (``gtsam.Symbol('a', 12)``): a 64-bit key holds the robot character in its
top 8 bits and the pose index in the low 56 (gtsam/inference/Symbol.h: ``chrBits = 8``,
``indexBits = 56``), as in distributed-mapper's example data and Kimera-Multi's exports.
:func:`robots_from_symbols` requires every vertex id to be such a key with an ASCII letter or
digit as its character (g2o ids are read as signed 64-bit integers, so characters above 127
cannot occur).

Label files (:func:`read_robot_labels`): CSV lines ``vertex_id,robot``; blank lines and lines
starting with ``#`` are skipped, as is a first line whose first field is not an integer (a header
such as ``vertex_id,robot``). Every pose of the graph needs exactly one label; a label for a
vertex id the graph does not have is refused.

One g2o file per robot (:func:`read_robot_folder`, distributed-mapper's layout): every ``*.g2o``
file of a folder is one robot, named by the file name without ``.g2o`` (``fullGraph.g2o``, the
merged copy distributed-mapper writes beside the robots' files, is not read). A pose belongs to
the robot whose file has its VERTEX line: each vertex id needs exactly one VERTEX line in the
folder. Each file holds its robot's own edges and its inter-robot edges (those with one end in
another robot, named by that robot's vertex ids); every edge must have an end in its file's
robot. An inter-robot edge written in both robots' files counts once: the copies of edge ``i j``
(same direction) in the file of i's robot and in the file of j's robot are matched in file order
and must agree (measurement and information to a relative 1e-9; a different number of copies is
refused too), else the error names both locations. Edges ``i j`` and ``j i`` are two
measurements, and copies within one file are kept, as in a single g2o file.
"""

from __future__ import annotations

import contextlib
import os
import re
from pathlib import Path

import numpy as np

from .._core.pose_graph import PoseGraph, Poses
from .atomic import atomic_group, atomic_write
from .format import _G2O, G2OFormatError
from .g2o import g2o_lines, write_tum
from .reader import G2OFile, _read, _warn_indefinite

__all__ = [
    "SYMBOL_INDEX_BITS",
    "read_robot_folder",
    "read_robot_labels",
    "robots_from_symbols",
    "symbol_keys",
    "write_robot_folder",
    "write_robot_tum",
]

#: Bits of the pose index in a GTSAM symbol key (the robot character takes the top 8).
SYMBOL_INDEX_BITS = 56
_INDEX_MASK = (1 << SYMBOL_INDEX_BITS) - 1
#: Robot names that are safe as file names (per-robot outputs are named by robot).
_NAME_RE = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9_.-]*")
_NAME_CHARS = set("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789_.-")
#: Agreement required of the two copies of an inter-robot edge (relative).
COPY_RTOL = 1e-9
#: distributed-mapper's merged graph, written beside the robots' files.
_MERGED_NAME = "fullGraph.g2o"
#: The whole trajectory beside the per-robot TUM files.
WHOLE_TUM = "all_robots.tum"


def symbol_keys(chars, indices) -> np.ndarray:
    """GTSAM symbol keys (int64): ``chars`` (one-character strings, or their codes) in the top 8 bits,
    ``indices`` (0 .. 2^56 - 1) in the low 56; the two broadcast against each other."""
    c = np.asarray(chars)
    codes = c.astype("U1").view(np.uint32).reshape(c.shape).astype(np.int64) if c.dtype.kind == "U" else \
        c.astype(np.int64)
    idx = np.asarray(indices, dtype=np.int64)
    if np.any((codes <= 0) | (codes > 127)):
        raise ValueError("symbol characters must be ASCII (codes 1..127)")
    if np.any((idx < 0) | (idx > _INDEX_MASK)):
        raise ValueError(f"symbol indices must be between 0 and 2^{SYMBOL_INDEX_BITS} - 1")
    return (codes << SYMBOL_INDEX_BITS) | idx


def _name_order(names: list[str]) -> np.ndarray:
    """Rank of each (distinct) name: numerical when all are integers, else by character code."""
    keys = [int(n) for n in names] if all(re.fullmatch(r"[0-9]+", n) for n in names) else names
    order = sorted(range(len(names)), key=lambda k: keys[k])
    rank = np.empty(len(names), dtype=np.int64)
    rank[order] = np.arange(len(names))
    return rank


def _with_robots(g2o: G2OFile, robot_of_file_name: np.ndarray, names: list[str]) -> G2OFile:
    """``g2o`` with robots ``robot_of_file_name`` (indices into ``names``), renumbered by name order."""
    from dataclasses import replace

    rank = _name_order(names)
    ordered = np.asarray(names, dtype=object)[np.argsort(rank)]
    return replace(g2o, robot_of_pose=rank[robot_of_file_name], robot_names=tuple(ordered.tolist()))


def _first_by_line(mask: np.ndarray, lines: np.ndarray) -> int:
    """Index of the True entry of ``mask`` with the smallest line number."""
    idx = np.flatnonzero(mask)
    return int(idx[np.argmin(lines[idx])])


# ------------------------------------------------------------------------------------------------
# GTSAM symbol keys
# ------------------------------------------------------------------------------------------------


def symbol_names(ids) -> list[str] | None:
    """GTSAM's names of symbol keys ("a67" for ``Symbol('a', 67)``), or None unless every id is a
    symbol key whose character is an ASCII letter or digit."""
    ids = np.asarray(ids, dtype=np.int64)
    code = ids >> SYMBOL_INDEX_BITS
    if not np.all(_symbol_character(code)):
        return None
    return [f"{chr(c)}{k}" for c, k in zip(code.tolist(), (ids & _INDEX_MASK).tolist(), strict=True)]


def _symbol_character(code: np.ndarray) -> np.ndarray:
    return (((code >= ord("0")) & (code <= ord("9"))) | ((code >= ord("A")) & (code <= ord("Z")))
            | ((code >= ord("a")) & (code <= ord("z"))))


def robots_from_symbols(g2o: G2OFile) -> G2OFile:
    """``g2o`` with its robots read from GTSAM symbol keys (robot names: the characters).

    A vertex id that is not a symbol key with an ASCII letter or digit as its character is refused,
    naming the first line that uses it.
    """
    ids = np.asarray(g2o.vertex_ids, dtype=np.int64)
    code = ids >> SYMBOL_INDEX_BITS
    ok = _symbol_character(code)
    if not ok.all():
        lines = g2o.vertex_line if g2o.vertex_line is not None else np.zeros(len(ids), np.int64)
        k = _first_by_line(~ok, lines)
        c = int(code[k])
        why = ("its top 8 bits (the robot character) are 0: a plain integer id, not a symbol key" if c == 0 else
               f"its robot character (top 8 bits) is {c} (0x{c & 0xFF:02x}), not an ASCII letter or digit")
        raise G2OFormatError(g2o.path, None if g2o.vertex_line is None else int(lines[k]),
                             f"vertex id {int(ids[k])} is not a GTSAM symbol key: {why}")
    chars, robot = np.unique(code, return_inverse=True)
    return _with_robots(g2o, robot.reshape(-1), [chr(c) for c in chars.tolist()])


# ------------------------------------------------------------------------------------------------
# Label files
# ------------------------------------------------------------------------------------------------


def read_robot_labels(path, g2o: G2OFile) -> G2OFile:
    """``g2o`` with its robots from the label file ``path`` (``vertex_id,robot`` lines, see the module
    docstring); raises :class:`G2OFormatError` naming the label file's line, or the graph file's
    line of a pose without a label."""
    spath = os.fspath(path)
    try:
        text = Path(spath).read_bytes().decode("utf-8-sig")
    except FileNotFoundError:
        raise G2OFormatError(spath, None, "label file not found") from None
    except UnicodeDecodeError as exc:
        raise G2OFormatError(spath, None, f"label file is not UTF-8 text ({exc.reason})") from None
    except OSError as exc:
        raise G2OFormatError(spath, None, f"cannot read label file: {exc.strerror or exc}") from None
    rows = [(k, [f.strip() for f in ln.split(",")]) for k, ln in enumerate(text.splitlines(), 1)
            if ln.strip() and not ln.lstrip().startswith("#")]
    if rows and not re.fullmatch(r"[+-]?[0-9]+", rows[0][1][0]):
        rows = rows[1:]  # a header line
    if not rows:
        raise G2OFormatError(spath, None, "no labels: expected lines 'vertex_id,robot'")
    lines = np.array([k for k, _ in rows], dtype=np.int64)
    count = np.array([len(f) for _, f in rows])
    if np.any(count != 2):
        k = int(np.flatnonzero(count != 2)[0])
        raise G2OFormatError(spath, int(lines[k]),
                             f"expected 2 comma-separated fields 'vertex_id,robot', got {count[k]}")
    ids_text = [f[0] for _, f in rows]
    names_text = np.array([f[1] for _, f in rows])
    try:  # ASCII integers only (int() alone would take '1_000' and other digits)
        if set(" ".join(ids_text)) - set("0123456789+- "):
            raise ValueError
        vid = np.fromiter(map(int, ids_text), np.int64, len(ids_text))
    except (ValueError, OverflowError):
        bad = [not re.fullmatch(r"[+-]?[0-9]+", x) or not -(2**63) <= int(x) < 2**63 for x in ids_text]
        k = int(np.flatnonzero(bad)[0])
        raise G2OFormatError(spath, int(lines[k]), f"vertex id {ids_text[k][:40]!r} is not a 64-bit integer") from None
    bad_name = (np.char.str_len(names_text) == 0) | np.char.startswith(names_text, ".")
    if set("".join(names_text.tolist())) - _NAME_CHARS or bad_name.any():
        bad_name |= np.array([not _NAME_RE.fullmatch(x) for x in names_text.tolist()])
        k = int(np.flatnonzero(bad_name)[0])
        raise G2OFormatError(spath, int(lines[k]), f"robot name {names_text[k][:40]!r} must be letters, digits, '_', "
                             "'-' or '.' (not starting with '.'): per-robot output files are named by robot")
    names, robot = np.unique(names_text, return_inverse=True)
    # duplicates: the second label of a vertex id
    order = np.argsort(vid, kind="stable")
    dup = np.flatnonzero(vid[order][1:] == vid[order][:-1])
    if dup.size:
        second = order[dup + 1]
        k = int(second[np.argmin(lines[second])])
        first = int(order[np.searchsorted(vid[order], vid[k])])
        raise G2OFormatError(spath, int(lines[k]),
                             f"vertex id {vid[k]} is labelled again (first on line {lines[first]})")
    ids = np.asarray(g2o.vertex_ids, dtype=np.int64)
    pos = np.searchsorted(ids, vid)
    known = (pos < len(ids)) & (ids[np.minimum(pos, len(ids) - 1)] == vid)
    if not known.all():
        k = _first_by_line(~known, lines)
        raise G2OFormatError(spath, int(lines[k]), f"vertex id {vid[k]} is not a pose of {g2o.path}")
    labelled = np.zeros(len(ids), dtype=bool)
    labelled[pos] = True
    if not labelled.all():
        glines = g2o.vertex_line if g2o.vertex_line is not None else np.zeros(len(ids), np.int64)
        k = _first_by_line(~labelled, glines)
        raise G2OFormatError(g2o.path, None if g2o.vertex_line is None else int(glines[k]),
                             f"vertex id {ids[k]} has no label in {spath} "
                             f"({int((~labelled).sum())} of {len(ids)} poses have none)")
    robot_of_pose = np.empty(len(ids), dtype=np.int64)
    robot_of_pose[pos] = robot.reshape(-1)
    return _with_robots(g2o, robot_of_pose, names.tolist())


# ------------------------------------------------------------------------------------------------
# One g2o file per robot
# ------------------------------------------------------------------------------------------------


def robot_files(folder) -> list[Path]:
    """The robots' files of a per-robot folder (``*.g2o`` except ``fullGraph.g2o``), by name."""
    return sorted(p for p in Path(folder).glob("*.g2o") if p.name != _MERGED_NAME and not p.name.startswith("."))


def read_robot_folder(folder, *, dtype=None, strict_information: bool = False) -> G2OFile:
    """Read a folder with one g2o file per robot (see the module docstring) as one graph.

    The result's ``path`` is the folder; its edges are those of the files (inter-robot copies
    counted once) sorted by (tail, head) pose, ties in file-name and line order (a folder has no
    edge order of its own; :func:`write_robot_folder` of a graph in that order reads back to the
    same arrays); ``information`` as read, ``initial`` the VERTEX values.
    ``vertex_line`` / ``edge_line`` are None (the lines are in several files).
    """
    sfolder = os.fspath(folder)
    if not os.path.isdir(sfolder):
        raise G2OFormatError(sfolder, None, "not a folder")
    paths = robot_files(sfolder)
    if not paths:
        raise G2OFormatError(sfolder, None, "no robot files: the folder holds no *.g2o file")
    for p in paths:
        if not _NAME_RE.fullmatch(p.stem):
            raise G2OFormatError(str(p), None, "robot file names must be letters, digits, '_', '-' or '.' + '.g2o'")
    parts = [_read(p, dtype=dtype, strict_information=strict_information, family=_G2O, need="any", warn=False)
             for p in paths]
    dims = [g.dim for g in parts]
    if len(set(dims)) > 1:
        k = next(k for k, dm in enumerate(dims) if dm != dims[0])
        raise G2OFormatError(parts[k].path, int(parts[k].vertex_line.min()),
                             f"{dims[k]}D file in a folder whose file {paths[0].name} is {dims[0]}D")
    d = dims[0]
    F = len(parts)

    # ---- owners: the file with the VERTEX line
    file_of = lambda arrays: np.repeat(np.arange(F), [len(a) for a in arrays])  # noqa: E731
    v_ids = np.concatenate([g.vertex_ids[g.has_vertex] for g in parts])
    v_file = file_of([g.vertex_ids[g.has_vertex] for g in parts])
    v_line = np.concatenate([g.vertex_line[g.has_vertex] for g in parts])
    order = np.lexsort((v_file, v_ids))
    twice = np.flatnonzero(v_ids[order][1:] == v_ids[order][:-1])
    if twice.size:
        a, b = order[twice[0]], order[twice[0] + 1]
        raise G2OFormatError(f"{parts[v_file[a]].path}:{v_line[a]} and {parts[v_file[b]].path}", int(v_line[b]),
                             f"vertex id {v_ids[a]} has a VERTEX line in two robots' files "
                             "(a pose belongs to one robot)")
    vertex_ids = np.unique(np.concatenate([g.vertex_ids for g in parts]))
    owner = np.full(len(vertex_ids), -1, dtype=np.int64)
    vk = np.searchsorted(vertex_ids, v_ids)
    owner[vk] = v_file

    # ---- edges of all files, in global indices
    e_file = file_of([g.graph.i for g in parts])
    e_line = np.concatenate([g.edge_line for g in parts])
    gi = np.concatenate([np.searchsorted(vertex_ids, g.vertex_ids[np.asarray(g.graph.i)]) for g in parts])
    gj = np.concatenate([np.searchsorted(vertex_ids, g.vertex_ids[np.asarray(g.graph.j)]) for g in parts])
    orphan = owner[np.concatenate([gi, gj])] < 0
    if orphan.any():
        ends = np.concatenate([gi, gj])
        k = _first_by_line(orphan, np.concatenate([e_line, e_line]))
        f = np.concatenate([e_file, e_file])[k]
        raise G2OFormatError(parts[f].path, int(np.concatenate([e_line, e_line])[k]),
                             f"vertex id {vertex_ids[ends[k]]} has no VERTEX line in any robot's file "
                             "(a pose belongs to the robot whose file has its VERTEX line)")
    ri, rj = owner[gi], owner[gj]
    foreign = (ri != e_file) & (rj != e_file)
    if foreign.any():
        k = _first_by_line(foreign, e_line)
        raise G2OFormatError(parts[e_file[k]].path, int(e_line[k]),
                             f"edge {vertex_ids[gi[k]]} {vertex_ids[gj[k]]} has no pose of robot "
                             f"{paths[e_file[k]].stem!r} (its poses belong to {paths[ri[k]].stem!r} and "
                             f"{paths[rj[k]].stem!r})")
    R = np.concatenate([np.asarray(g.graph.R) for g in parts])
    t = np.concatenate([np.asarray(g.graph.t) for g in parts])
    kappa = np.concatenate([np.asarray(g.graph.kappa) for g in parts])
    tau = np.concatenate([np.asarray(g.graph.tau) for g in parts])
    info = np.concatenate([g.information for g in parts])
    keep = _drop_second_copies(gi, gj, ri, rj, e_file, e_line, R, t, info, parts, vertex_ids)
    # a folder has no edge order of its own: (tail, head), then file and line (lexsort is stable)
    keep = np.flatnonzero(keep)
    keep = keep[np.lexsort((gj[keep], gi[keep]))]

    fdt = np.asarray(parts[0].graph.kappa).dtype
    graph = PoseGraph.from_arrays(gi[keep], gj[keep], R[keep], t[keep], kappa[keep], tau[keep],
                                  num_poses=len(vertex_ids), dtype=fdt)
    vertex_R = np.concatenate([g.vertex_R[g.has_vertex] for g in parts])[np.argsort(vk)]
    vertex_t = np.concatenate([g.vertex_t[g.has_vertex] for g in parts])[np.argsort(vk)]
    fixed = np.zeros(len(vertex_ids), dtype=bool)
    fixed[np.searchsorted(vertex_ids, np.concatenate([g.vertex_ids[g.fixed] for g in parts]))] = True
    merged = G2OFile(
        path=sfolder, dim=d, graph=graph, vertex_ids=vertex_ids, information=info[keep],
        initial=Poses(vertex_R.astype(fdt), vertex_t.astype(fdt)), has_vertex=np.ones(len(vertex_ids), bool),
        fixed=fixed, num_indefinite_information=_count_indefinite(info[keep]),
        vertex_R=vertex_R, vertex_t=vertex_t,
    )
    _warn_indefinite(merged)
    return _with_robots(merged, owner, [p.stem for p in paths])


def _count_indefinite(info: np.ndarray) -> int:
    """Information matrices that are not positive definite, by the reader's rule (smallest eigenvalue
    <= k eps |largest| for a k x k matrix)."""
    if not len(info):
        return 0
    eig = np.linalg.eigvalsh(info)
    k = info.shape[-1]
    return int(np.count_nonzero(~(eig[:, 0] > k * np.finfo(np.float64).eps * np.abs(eig).max(axis=1))))


def _drop_second_copies(gi, gj, ri, rj, e_file, e_line, R, t, info, parts, vertex_ids) -> np.ndarray:
    """Mask of the edges to keep: an inter-robot edge copied in the head robot's file is dropped
    after checking it against the tail robot's copy (see the module docstring)."""
    m = len(gi)
    keep = np.ones(m, dtype=bool)
    inter = np.flatnonzero(ri != rj)
    if not inter.size:
        return keep
    _, pair = np.unique(np.stack([gi[inter], gj[inter]], 1), axis=0, return_inverse=True)
    pair = pair.reshape(-1)
    side = (e_file[inter] == rj[inter]).astype(np.int64)  # 0: the tail's file, 1: the head's
    group = 2 * pair + side
    order = np.lexsort((e_line[inter], group))
    counts = np.bincount(group, minlength=2 * (pair.max() + 1)).reshape(-1, 2)
    starts = np.concatenate([[0], np.cumsum(counts.reshape(-1))[:-1]])
    rank = np.empty(len(inter), dtype=np.int64)
    rank[order] = np.arange(len(inter)) - starts[group[order]]
    both = (counts > 0).all(axis=1)
    if not both.any():
        return keep

    def where(e: int) -> str:
        return f"{parts[e_file[e]].path}:{e_line[e]}"

    def edge(e: int) -> str:
        return f"inter-robot edge {vertex_ids[gi[e]]} {vertex_ids[gj[e]]}"

    uneven = both & (counts[:, 0] != counts[:, 1])
    sel = inter[np.flatnonzero(uneven[pair])]
    if sel.size:
        e = int(sel[np.argmin(e_line[sel])])
        p = pair[np.searchsorted(inter, e)]
        other = inter[(pair == p) & (side != side[np.searchsorted(inter, e)])][0]
        raise G2OFormatError(f"{where(e)} and {parts[e_file[other]].path}", int(e_line[other]),
                             f"{edge(e)} is written {counts[p, 0]} time(s) in its tail robot's file and "
                             f"{counts[p, 1]} in its head robot's: the copies cannot be matched")
    # match copy k of the tail's file with copy k of the head's file
    dup = np.flatnonzero(both[pair])
    a = inter[dup[side[dup] == 0]]
    b = inter[dup[side[dup] == 1]]
    ka = np.lexsort((rank[np.searchsorted(inter, a)], pair[np.searchsorted(inter, a)]))
    kb = np.lexsort((rank[np.searchsorted(inter, b)], pair[np.searchsorted(inter, b)]))
    a, b = a[ka], b[kb]
    flat = lambda x: x.reshape(len(x), -1)  # noqa: E731
    meas_a, meas_b = np.concatenate([flat(R[a]), flat(t[a])], 1), np.concatenate([flat(R[b]), flat(t[b])], 1)
    scale = np.maximum(np.abs(info[a]).max(axis=(1, 2)), np.abs(info[b]).max(axis=(1, 2)))
    agree = (np.abs(meas_a - meas_b) <= COPY_RTOL * (1 + np.maximum(np.abs(meas_a), np.abs(meas_b)))).all(axis=1) & (
        np.abs(flat(info[a]) - flat(info[b])) <= COPY_RTOL * scale[:, None]).all(axis=1)
    if not agree.all():
        k = _first_by_line(~agree, e_line[a])
        what = "measurement" if not np.allclose(meas_a[k], meas_b[k], rtol=COPY_RTOL, atol=COPY_RTOL) else \
            "information matrix"
        raise G2OFormatError(f"{where(a[k])} and {parts[e_file[b[k]]].path}", int(e_line[b[k]]),
                             f"the two copies of {edge(a[k])} disagree ({what} differs beyond a relative "
                             f"{COPY_RTOL:g})")
    keep[b] = False
    return keep


# ------------------------------------------------------------------------------------------------
# Per-robot outputs
# ------------------------------------------------------------------------------------------------


def _check_robots(n: int, robot_of_pose, robot_names) -> tuple[np.ndarray, list[str]]:
    rop = np.asarray(robot_of_pose, dtype=np.int64)
    if rop.shape != (n,):
        raise ValueError(f"robot_of_pose must have shape ({n},), got {rop.shape}")
    A = int(rop.max()) + 1
    names = [str(a) for a in range(A)] if robot_names is None else [str(x) for x in robot_names]
    if len(names) != A or len(set(names)) != A:
        raise ValueError(f"robot_names must be {A} distinct names, got {names!r}")
    bad = [x for x in names if not _NAME_RE.fullmatch(x)]
    if bad:
        raise ValueError(f"robot name {bad[0]!r} cannot name a file (letters, digits, '_', '-', '.')")
    return rop, names


@contextlib.contextmanager
def _output_folder(folder):
    """Create ``folder`` if needed; remove it again (when it was created and is empty) on failure."""
    folder = os.fspath(folder)
    created = not os.path.exists(folder)
    os.makedirs(folder, exist_ok=True)
    try:
        yield folder
    except BaseException:
        if created:
            with contextlib.suppress(OSError):
                os.rmdir(folder)
        raise


def write_robot_folder(folder, graph: PoseGraph, poses: Poses | None, *, robot_of_pose, robot_names=None,
                       vertex_ids=None, information=None, fixed=None) -> list[str]:
    """One g2o file per robot, ``<folder>/<robot name>.g2o``, in the layout :func:`read_robot_folder`
    reads (so the folder reads back to the same graph and robots): the VERTEX lines of the robot's
    poses (``poses``, e.g. an estimate; the identity when None, since a VERTEX line tells a pose's
    robot), FIX lines of its fixed poses, and every edge with an end in the robot (inter-robot edges
    in both robots' files). All files are written atomically, all or none; the folder is created if
    needed. A ``*.g2o`` file already in the folder that is not one of these robots' is refused
    (reading the folder back would add it). Returns the paths written.
    """
    n, d = graph.num_poses, graph.dim
    rop, names = _check_robots(n, robot_of_pose, robot_names)
    if poses is None:
        poses = Poses(np.broadcast_to(np.eye(d), (n, d, d)), np.zeros((n, d)))
    vertex_lines, edge_lines, fixed = g2o_lines(graph, poses, vertex_ids=vertex_ids, information=information,
                                                fixed=fixed)
    ids = np.arange(n, dtype=np.int64) if vertex_ids is None else np.asarray(vertex_ids, dtype=np.int64)
    targets = [os.path.join(os.fspath(folder), f"{x}.g2o") for x in names]
    if os.path.isdir(folder):
        stale = [p.name for p in robot_files(folder) if os.fspath(p) not in set(map(os.path.normpath, targets))]
        if stale:
            raise ValueError(f"{folder}: holds {stale[0]}, which is not one of this graph's robots; reading the folder "
                             "back would add it (write to an empty folder)")
    gi, gj = np.asarray(graph.i), np.asarray(graph.j)
    ri, rj = rop[gi], rop[gj]
    inter = np.flatnonzero(ri != rj)
    # incident edges per robot (each edge under its tail's robot, inter-robot edges also under the head's)
    owner = np.concatenate([ri, rj[inter]])
    edge = np.concatenate([np.arange(len(gi)), inter])
    order = np.lexsort((edge, owner))
    edges_of = np.split(edge[order], np.cumsum(np.bincount(owner, minlength=len(names)))[:-1])
    pose_order = np.argsort(rop, kind="stable")
    poses_of = np.split(pose_order, np.cumsum(np.bincount(rop, minlength=len(names)))[:-1])
    with _output_folder(folder), atomic_group():
        for target, own, inc in zip(targets, poses_of, edges_of, strict=True):  # one file per robot
            fix = own[fixed[own]]
            lines = [vertex_lines[k] for k in own.tolist()]
            if fix.size:
                lines.append("FIX " + " ".join(map(str, ids[fix].tolist())))
            lines += [edge_lines[k] for k in inc.tolist()]
            with atomic_write(target, "w") as fh:
                fh.write("\n".join(lines) + "\n")
    return targets


def write_robot_tum(folder, poses: Poses, *, robot_of_pose, robot_names=None, vertex_ids=None) -> list[str]:
    """One TUM trajectory per robot, ``<folder>/<robot name>.tum`` (its poses in ascending vertex id,
    indexed by vertex id), and the whole trajectory beside them, ``<folder>/all_robots.tum``
    (:func:`~mmpgo_jax.write_tum`), e.g. for ``evo_traj tum <folder>/*.tum``. Atomic, all or none;
    the folder is created if needed. Returns the paths written."""
    n = poses.R.shape[0]
    rop, names = _check_robots(n, robot_of_pose, robot_names)
    if WHOLE_TUM[:-4] in names:
        raise ValueError(f"a robot named {WHOLE_TUM[:-4]!r} would overwrite the whole trajectory's file")
    ids = np.arange(n, dtype=np.int64) if vertex_ids is None else np.asarray(vertex_ids, dtype=np.int64)
    R, t = np.asarray(poses.R), np.asarray(poses.t)
    pose_order = np.argsort(rop, kind="stable")
    poses_of = np.split(pose_order, np.cumsum(np.bincount(rop, minlength=len(names)))[:-1])
    written = []
    with _output_folder(folder), atomic_group():
        for name, own in zip(names, poses_of, strict=True):  # one file per robot
            path = os.path.join(folder, f"{name}.tum")
            write_tum(path, Poses(R[own], t[own]), vertex_ids=ids[own])
            written.append(path)
        whole = os.path.join(folder, WHOLE_TUM)
        write_tum(whole, Poses(R, t), vertex_ids=ids)
        written.append(whole)
    return written
