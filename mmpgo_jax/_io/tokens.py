"""The tokeniser: a file's bytes -> per-tag token arrays -> int64 ids and float64 values.

Vectorised over the bytes (no Python loop over lines) because benchmark files have millions of
lines: token boundaries from an ASCII-whitespace mask, the line of each token by a search among the
newlines, tags compared as byte windows, and the id / value fields of each tag's lines joined into
one byte string that is checked (one C-level character-set check) and converted (one ``int`` /
``float`` pass) at once. The regular expressions and per-line work only run on the slow path that
locates the offending line and field, so that every error still names them.
"""

from __future__ import annotations

import re

import numpy as np

from .format import _G2O, G2OFormatError, _Family, _Format

# Fields quoted in error messages are shortened to this many characters.
_SHOW_MAX = 40

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
