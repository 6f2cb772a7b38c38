"""The vectorised g2o / TORO tokeniser against a per-line reference on random files."""

import numpy as np
import pytest

from mmpgo_jax._io import g2o as G


def _reference(spath, data, family):
    """Per-line tokeniser (the straightforward loop the vectorised one replaces)."""
    if data.startswith(b"\xef\xbb\xbf"):
        data = data[3:]
    groups = {tag.encode(): ([], []) for tag in family.formats}
    fix_lines, dim, dim_first = [], None, None
    for lineno, raw in enumerate(data.split(b"\n"), 1):
        toks = raw.split()
        if not toks or toks[0][0] == 0x23:
            continue
        tag = toks[0]
        if tag not in groups:
            if tag == b"FIX" and family.fix:
                if len(toks) < 2:
                    raise G.G2OFormatError(spath, lineno, "FIX line names no vertex id")
                fix_lines.append((lineno, toks[1:]))
                continue
            raise G.G2OFormatError(spath, lineno, f"unknown tag {G._show(tag)} (expected {family.known})")
        fmt = family.formats[tag.decode()]
        if len(toks) - 1 != len(fmt.fields):
            raise G.G2OFormatError(spath, lineno, f"wrong number of fields for {fmt.tag}: expected "
                                   f"{len(fmt.fields)} after the tag, got {len(toks) - 1}")
        if dim is None:
            dim, dim_first = fmt.dim, (lineno, fmt.tag)
        elif dim != fmt.dim:
            raise G.G2OFormatError(spath, lineno, f"mixed 2D and 3D tags: {fmt.tag} here, but {dim_first[1]} "
                                   f"on line {dim_first[0]}")
        groups[tag][0].append(lineno)
        groups[tag][1].append(toks[1:])
    return groups, fix_lines, dim


_WS = [b" ", b"\t", b"  ", b"\r", b"\x0b", b"\x0c", b" \t "]


def _random_file(rng, family, bad_rate):
    tags = list(family.formats)
    dim = int(rng.integers(2, 4))
    ok_tags = [t for t in tags if family.formats[t].dim == dim]
    lines = []
    for _ in range(int(rng.integers(0, 25))):
        kind = rng.random()
        if kind < 0.1:
            lines.append(b"")
            continue
        if kind < 0.15:
            lines.append(b"# comment " + bytes(rng.integers(33, 127, 3).astype(np.uint8)))
            continue
        if kind < 0.2 and family.fix:
            toks = [b"FIX"] + [str(int(v)).encode() for v in rng.integers(0, 5, int(rng.integers(0, 3)))]
        else:
            tag = tags[int(rng.integers(len(tags)))] if rng.random() < bad_rate else ok_tags[int(rng.integers(2))]
            nf = len(family.formats[tag].fields) + (int(rng.integers(-1, 2)) if rng.random() < bad_rate else 0)
            toks = [tag.encode()] + [repr(float(x)).encode() for x in rng.standard_normal(max(nf, 0))]
            if rng.random() < bad_rate:
                toks[0] = rng.choice([b"EDGE", b"edge_se2", b"VERTEX_SE2x", b"#x", b"\xe3\x80\x80"])
        sep = [_WS[int(rng.integers(len(_WS)))] for _ in toks]
        line = b"".join(s + t for s, t in zip(sep, toks, strict=True))
        if rng.random() < 0.3:
            line += _WS[int(rng.integers(len(_WS)))]
        if rng.random() < 0.2:
            line += b"\r"
        lines.append(line)
    data = b"\n".join(lines) + (b"\n" if rng.random() < 0.5 else b"")
    return (b"\xef\xbb\xbf" if rng.random() < 0.1 else b"") + data


@pytest.mark.parametrize("family", [G._G2O, G._TORO], ids=["g2o", "toro"])
def test_tokenise_matches_per_line_reference(family):
    rng = np.random.default_rng(7)
    outcomes = set()
    for trial in range(400):
        data = _random_file(rng, family, bad_rate=0.0 if trial % 2 else 0.05)
        try:
            ref = _reference("f.g2o", data, family)
        except G.G2OFormatError as exc:
            with pytest.raises(G.G2OFormatError) as got:
                G._tokenise("f.g2o", data, family)
            assert str(got.value) == str(exc)
            outcomes.add("error")
            continue
        groups, fix_lines, dim = G._tokenise("f.g2o", data, family)
        ref_groups, ref_fix, ref_dim = ref
        assert dim == ref_dim
        assert [(n, list(t)) for n, t in fix_lines] == ref_fix
        for tag, (lines, rows) in ref_groups.items():
            g = groups[tag]
            nid = g.fmt.num_ids
            assert g.lines == lines
            assert list(g.rows) == rows
            assert g.id_blob.split() == [t for r in rows for t in r[:nid]]
            assert g.val_blob.split() == [t for r in rows for t in r[nid:]]
            assert not set(g.id_blob + g.val_blob) & set(b"\t\n\r\x0b\x0c")  # fields joined by spaces
        outcomes.add("ok")
    assert outcomes == {"ok", "error"}
