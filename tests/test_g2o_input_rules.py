"""The g2o reader's input rules (see the docstring of ``mmpgo_jax._io.g2o``).

Information matrices (SE-Sync's convention: indefinite matrices with positive weights are used,
with one warning), the C strtod / strtol number syntax, overflow and underflow, poses-only files
(:func:`read_g2o_poses`), the per-pose VERTEX values, and a property test that layout variations
(CRLF, tabs, comments, BOM, trailing spaces) do not change what is read.
"""

from __future__ import annotations

import time
import warnings
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mmpgo_jax._core.geometry import (
    quaternion_to_rotation,
    random_rotations,
    rotation_2d,
    rotation_to_quaternion,
)
from mmpgo_jax._io.g2o import (
    G2OFile,
    G2OFormatError,
    G2OPoses,
    G2OWarning,
    read_g2o,
    read_g2o_poses,
)

DATA = Path(__file__).resolve().parent / "data"

I3_SE3 = "10 0 0 0 0 0 10 0 0 0 0 10 0 0 0 10 0 0 10 0 10"  # upper triangle of 10 * eye(6)
E2 = "EDGE_SE2 0 1 1.0 0.0 0.1 100 0 0 100 0 1000"


def write(tmp_path: Path, text: str, name: str = "f.g2o", encoding: str = "utf-8") -> Path:
    p = tmp_path / name
    p.write_bytes(text.encode(encoding))
    return p


def refused(path, **kwargs) -> G2OFormatError:
    with pytest.raises(G2OFormatError) as info:
        read_g2o(path, **kwargs)
    return info.value


def read_quietly(path, **kwargs) -> G2OFile:
    """read_g2o, failing on any warning."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return read_g2o(path, **kwargs)


def sesync_weights(info: np.ndarray, dim: int):
    """SE-Sync's convention (SE-Sync's g2o reader), one matrix at a time, independently of the reader."""
    kappa, tau = [], []
    for I in info:
        if dim == 2:
            tau.append(2.0 / np.trace(np.linalg.inv(I[:2, :2])))
            kappa.append(I[2, 2])
        else:
            tau.append(3.0 / np.trace(np.linalg.inv(I[:3, :3])))
            kappa.append(3.0 / (2.0 * np.trace(np.linalg.inv(I[3:, 3:]))))
    return np.array(kappa), np.array(tau)


def upper(I: np.ndarray) -> str:
    return " ".join(repr(float(x)) for x in I[np.triu_indices(I.shape[0])])


def edge3(i, j, t=(1.0, 0.0, 0.0), q=(0.0, 0.0, 0.0, 1.0), info=None) -> str:
    info = 10.0 * np.eye(6) if info is None else info
    return f"EDGE_SE3:QUAT {i} {j} " + " ".join(map(repr, map(float, (*t, *q)))) + " " + upper(info)


def edge2(i, j, t=(1.0, 0.0), theta=0.1, info=None) -> str:
    info = np.diag([100.0, 100.0, 1000.0]) if info is None else info
    return f"EDGE_SE2 {i} {j} {t[0]!r} {t[1]!r} {theta!r} " + upper(info)


# ----------------------------------------------------------------------------------------------
# 1. information matrices


def test_indefinite_3d_file_is_accepted_with_one_warning():
    path = DATA / "indefinite3d.g2o"
    with pytest.warns(G2OWarning) as record:
        f = read_g2o(path)
    ours = [w for w in record if issubclass(w.category, G2OWarning)]
    assert len(ours) == 1
    assert str(ours[0].message) == (
        f"{path}: 3 of 6 information matrices are not positive definite; SE-Sync weights used"
    )
    assert ours[0].filename == __file__  # stacklevel=2: the caller's line
    # independent count and weights
    info = f.information
    assert info.shape == (6, 6, 6)
    indefinite = np.linalg.eigvalsh(info)[:, 0] < 0
    np.testing.assert_array_equal(np.flatnonzero(indefinite), [1, 3, 4])
    assert f.num_indefinite_information == int(indefinite.sum()) == 3
    kappa, tau = sesync_weights(info, 3)
    assert np.all(kappa > 0) and np.all(tau > 0)
    np.testing.assert_allclose(np.asarray(f.graph.kappa), kappa, rtol=1e-14)
    np.testing.assert_allclose(np.asarray(f.graph.tau), tau, rtol=1e-14)
    # the matrices are kept as read
    assert info[1, 0, 1] == 15.0 and info[3, 0, 3] == 30.0 and info[3, 1, 4] == -25.0 and info[4, 1, 2] == -7.5


def test_indefinite_3d_file_strict_is_refused():
    path = DATA / "indefinite3d.g2o"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning on the way to the error
        err = refused(path, strict_information=True)
    assert err.line == 10  # the first indefinite matrix
    assert err.problem.startswith("EDGE_SE3:QUAT: information matrix is not positive definite (eigenvalues [")


@pytest.mark.parametrize(
    "name, dim, count", [("indefinite_se2.g2o", 2, 1), ("indefinite_se3.g2o", 3, 1), ("indefinite3d.g2o", 3, 3)]
)
def test_former_bad_files_are_accepted(name, dim, count):
    """indefinite_se2/se3.g2o were tests/data/bad/not_pd_se2/se3.g2o (refused before SE-Sync's rule)."""
    with pytest.warns(G2OWarning, match=f"{count} of "):
        f = read_g2o(DATA / name)
    assert f.dim == dim and f.num_indefinite_information == count
    kappa, tau = sesync_weights(f.information, dim)
    np.testing.assert_array_equal(np.asarray(f.graph.kappa), kappa)
    np.testing.assert_allclose(np.asarray(f.graph.tau), tau, rtol=1e-15)
    with pytest.raises(G2OFormatError, match="information matrix is not positive definite"):
        read_g2o(DATA / name, strict_information=True)


def test_positive_definite_file_has_no_warning():
    for name in ("tiny2d.g2o", "tiny3d.g2o", "comments3d.g2o"):
        f = read_quietly(DATA / name)
        assert f.num_indefinite_information == 0
        f = read_quietly(DATA / name, strict_information=True)
        assert f.num_indefinite_information == 0


def test_2d_indefinite_translation_block_is_refused(tmp_path):
    # I12^2 > I11 I22: tau = 2 (I11 I22 - I12^2) / (I11 + I22) < 0
    p = write(tmp_path, f"{E2}\nEDGE_SE2 1 2 1 0 0 4 3 0 2 0 5\n")
    err = refused(p)
    assert err.line == 2
    assert err.problem == (
        "EDGE_SE2: SE-Sync weight tau = 2 / tr(inv(I[:2, :2])) = -0.333333 is not positive "
        "(the information matrix is not positive definite)"
    )
    # I12^2 == I11 I22: singular translation block
    p = write(tmp_path, "EDGE_SE2 0 1 1 0 0 4 2 0 1 0 5\n")
    err = refused(p)
    assert err.line == 1 and "the block I[:2, :2] of the information matrix is singular" in err.problem
    assert "tau = 2 / tr(inv(I[:2, :2])) is undefined" in err.problem


def test_3d_weights_not_positive_are_refused(tmp_path):
    I = 10.0 * np.eye(6)
    I[3, 4] = I[4, 3] = 20.0
    I[5, 5] = 100.0  # rotation block [[10, 20, 0], [20, 10, 0], [0, 0, 100]]: tr inv = 1/30 - 1/10 + 1/100 < 0
    p = write(tmp_path, edge3(0, 1) + "\n" + edge3(1, 2, info=I) + "\n")
    err = refused(p)
    assert err.line == 2
    assert err.problem.startswith("EDGE_SE3:QUAT: SE-Sync weight kappa = 3 / (2 tr(inv(I[3:, 3:]))) = -")
    assert "is not positive" in err.problem


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("value", [0.0, -1.0, -0.0])
def test_nonpositive_diagonal_is_refused(tmp_path, dim, value):
    k = 3 if dim == 2 else 6
    for c in range(k):
        I = np.eye(k) * 50.0
        I[c, c] = value
        line = edge2(0, 1, info=I) if dim == 2 else edge3(0, 1, info=I)
        err = refused(write(tmp_path, line + "\n"))
        tag = "EDGE_SE2" if dim == 2 else "EDGE_SE3:QUAT"
        assert err.line == 1
        assert err.problem == (
            f"{tag}: information matrix is not positive definite: diagonal entry I{c + 1}{c + 1} = "
            f"{value!r} is not positive"
        )


def test_diagonal_that_underflows_to_zero_says_so(tmp_path):
    err = refused(write(tmp_path, "EDGE_SE2 0 1 1 0 0 1e-400 0 0 1 0 1\n"))
    assert "diagonal entry I11 = 0.0 is not positive (it underflows to 0)" in err.problem


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("scale, needle", [(1e300, "is above 1e+300 in magnitude"), (1e-310, "below 1e-300")])
def test_information_scaled_to_overflow_or_underflow_is_refused(tmp_path, dim, scale, needle):
    k = 3 if dim == 2 else 6
    I = np.diag(np.arange(2.0, 2.0 + k)) * scale
    line = edge2(0, 1, info=I) if dim == 2 else edge3(0, 1, info=I)
    err = refused(write(tmp_path, f"# scaled by {scale:g}\n{line}\n"))
    assert err.line == 2 and needle in err.problem and "information entry I11 = " in err.problem
    # the same matrix unscaled is fine
    line = edge2(0, 1, info=I / scale) if dim == 2 else edge3(0, 1, info=I / scale)
    read_quietly(write(tmp_path, line + "\n"))


def test_subnormal_off_diagonal_information_is_refused(tmp_path):
    err = refused(write(tmp_path, "EDGE_SE2 0 1 1 0 0 4 1e-310 0 2 0 5\n"))
    assert err.problem == (
        "EDGE_SE2: information entry I12 = 1e-310 is nonzero but below 1e-300 in magnitude (subnormal or underflowing)"
    )


def test_weights_must_be_representable(tmp_path):
    # entries within range, but tau = 2 (I11 I22 - I12^2) / (I11 + I22) = 3.8e-301 is below 1e-300
    err = refused(write(tmp_path, "EDGE_SE2 0 1 1 0 0 2e-300 1.8e-300 0 2e-300 0 1\n"))
    assert err.problem.startswith(
        "EDGE_SE2: SE-Sync weight tau = 2 / tr(inv(I[:2, :2])) = 3.8e-301 is not representable"
    )
    assert err.problem.endswith("weights must be finite and between 1e-300 and 1e+300 (float64)")
    I = 10.0 * np.eye(6)
    I[3:, 3:] = np.eye(3) * 1e-300
    err = refused(write(tmp_path, edge3(0, 1, info=I) + "\n"))
    assert "SE-Sync weight kappa = 3 / (2 tr(inv(I[3:, 3:]))) = 5e-301 is not representable" in err.problem
    # float32 graphs: weights must be in float32's normal range (these are fine in float64)
    p = write(tmp_path, "EDGE_SE2 0 1 1 0 0 1e-40 0 0 1e-40 0 1e-40\n")
    read_quietly(p)
    err = refused(p, dtype=jnp.float32)
    assert "SE-Sync weight tau = 2 / tr(inv(I[:2, :2])) = 1e-40 is not representable" in err.problem
    assert "(float32)" in err.problem


# ----------------------------------------------------------------------------------------------
# 2. number syntax

GOOD_VALUES = ["1", "+1", "-1.", ".5", "-.5", "1e5", "1E+5", "-1.5e-3", "007", "0.000", "+0", "1.e2"]
BAD_VALUES = [
    "1_016.030",
    "1_0",
    "\uff11",  # fullwidth 1
    "\u0663",  # Arabic-Indic 3
    "\u0661.\u0665",
    "0x10",
    "0x1p3",
    "1e",
    ".",
    "e5",
    "1.2.3",
    "+-1",
    "1e5.0",
    "1,5",
    "\u00bd",
    "1\u00a0",  # no-break space is not a separator
    "abc",
    "nan1",
    "1d5",
]


@pytest.mark.parametrize("tok", GOOD_VALUES)
def test_number_syntax_accepted(tmp_path, tok):
    p = write(tmp_path, f"EDGE_SE3:QUAT 0 1 {tok} 0 0 0 0 0 1 {I3_SE3}\n")
    f = read_quietly(p)
    assert float(f.graph.t[0, 0]) == float(tok)


@pytest.mark.parametrize("tok", BAD_VALUES)
def test_number_syntax_refused(tmp_path, tok):
    p = write(tmp_path, f"VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nEDGE_SE3:QUAT 0 1 {tok} 0 0 0 0 0 1 {I3_SE3}\n")
    err = refused(p)
    assert err.line == 2
    assert err.problem == f"EDGE_SE3:QUAT: field 3 (x) is not a number: {tok!r}"


@pytest.mark.parametrize("tok", ["nan", "NaN", "-nan", "inf", "-inf", "+Infinity", "INF"])
def test_nan_and_inf_are_not_finite(tmp_path, tok):
    p = write(tmp_path, f"VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 {tok} 0\n{E2}\n")
    err = refused(p)
    assert err.line == 2 and err.problem == f"VERTEX_SE2: field 3 (y) is not finite: {float(tok)!r}"


@pytest.mark.parametrize("tok", ["1e400", "-1e999", "1" * 400])
def test_value_overflow_is_out_of_range(tmp_path, tok):
    p = write(tmp_path, f"EDGE_SE2 0 1 1 {tok} 0 100 0 0 100 0 1000\n")
    err = refused(p)
    assert err.line == 1
    assert err.problem.startswith("EDGE_SE2: field 4 (dy) is out of range (its magnitude overflows float64): ")


def test_value_underflow_reads_as_zero_or_subnormal(tmp_path):
    f = read_quietly(write(tmp_path, "EDGE_SE2 0 1 1e-400 1e-310 0 100 0 0 100 0 1000\n"))
    assert float(f.graph.t[0, 0]) == 0.0 and float(f.graph.t[0, 1]) == 1e-310


@pytest.mark.parametrize("tok", ["1_0", "\uff11", "\u0663", "1.0", "1e3", "0x1", "+", "-", "１２", "1\u00a0"])
def test_id_syntax_refused(tmp_path, tok):
    p = write(tmp_path, f"{E2}\nEDGE_SE2 {tok} 1 1 0 0 100 0 0 100 0 1000\n")
    err = refused(p)
    assert err.line == 2 and err.problem == f"EDGE_SE2: field 1 (i) is not an integer vertex id: {tok!r}"


@pytest.mark.parametrize(
    "tok", ["9223372036854775808", "-9223372036854775809", "99999999999999999999", "1" * 5000, "-" + "9" * 30]
)
def test_id_out_of_range(tmp_path, tok):
    p = write(tmp_path, f"VERTEX_SE2 {tok} 0 0 0\n{E2}\n")
    err = refused(p)
    assert err.line == 1 and err.problem.startswith("VERTEX_SE2: field 1 (id) is out of range: ")
    assert err.problem.endswith("(vertex ids must fit in a signed 64-bit integer)")
    assert "not an integer" not in err.problem


def test_id_syntax_accepted(tmp_path):
    lo, hi = -(2**63), 2**63 - 1
    p = write(tmp_path, f"EDGE_SE2 +5 007 1 0 0 100 0 0 100 0 1000\nEDGE_SE2 {lo} {hi} 1 0 0 100 0 0 100 0 1000\n")
    f = read_quietly(p)
    np.testing.assert_array_equal(f.vertex_ids, [lo, 5, 7, hi])


@pytest.mark.parametrize("tok, kind", [("1_0", "is not an integer vertex id"),
                                       ("\uff11", "is not an integer vertex id"),
                                       ("99999999999999999999", "is out of range")])
def test_fix_id_syntax(tmp_path, tok, kind):
    err = refused(write(tmp_path, f"{E2}\nFIX 0 {tok}\n"))
    assert err.line == 2 and err.problem.startswith(f"FIX: field 2 {kind}: {tok!r}")


def test_long_fields_are_shortened_in_messages(tmp_path):
    tok = "1" * 3_000_000 + "x"
    t0 = time.perf_counter()
    err = refused(write(tmp_path, f"EDGE_SE2 0 1 {tok} 0 0 100 0 0 100 0 1000\n"))
    assert time.perf_counter() - t0 < 5.0  # the syntax check is linear in the field's length
    assert err.problem == f"EDGE_SE2: field 3 (dx) is not a number: {'1' * 40!r}… (3000001 characters)"
    assert len(str(err)) < 200 + len(str(err.path))
    err = refused(write(tmp_path, "EDGE_SE2 0 " + "7" * 100_000 + " 1 0 0 100 0 0 100 0 1000\n"))
    assert err.problem == (f"EDGE_SE2: field 2 (j) is out of range: {'7' * 40!r}… (100000 characters) "
                           "(vertex ids must fit in a signed 64-bit integer)")
    err = refused(write(tmp_path, "V" * 10_000 + " 1 2\n"))
    assert err.problem.startswith(f"unknown tag {'V' * 40!r}… (10000 characters) (expected")


def test_only_ascii_whitespace_separates_fields(tmp_path):
    # vertical tab and form feed are C isspace; the no-break space and the ideographic space are not
    f = read_quietly(write(tmp_path, "EDGE_SE2\x0b0 1\x0c1 0 0 100 0 0 100 0 1000\n"))
    assert f.num_edges == 1
    err = refused(write(tmp_path, "EDGE_SE2 0 1 1\u00a00 0 100 0 0 100 0 1000\n"))
    assert err.problem == "wrong number of fields for EDGE_SE2: expected 11 after the tag, got 10"
    err = refused(write(tmp_path, "EDGE_SE2\u30000 1 1 0 0 100 0 0 100 0 1000\n"))
    tag = "EDGE_SE2\u30000"
    assert err.problem.startswith(f"unknown tag {tag!r} (expected")


def test_invalid_utf8_is_reported_not_crashed(tmp_path):
    p = tmp_path / "latin1.g2o"
    p.write_bytes(b"# caf\xe9 comment is fine\nEDGE_SE2 0 1 1\xe9 0 0 100 0 0 100 0 1000\n")
    err = refused(p)
    assert err.line == 2 and err.problem == "EDGE_SE2: field 3 (dx) is not a number: '1\ufffd'"


# ----------------------------------------------------------------------------------------------
# 3. overflow and underflow


def quat_rows(q) -> str:
    return " ".join(repr(float(x)) for x in q)


@pytest.mark.parametrize("scale", [1e200, -1e300, 1.5e308, 1e-11, 3.0])
def test_scaled_quaternions_read_as_the_unscaled_one(tmp_path, scale):
    def text(q):
        return (
            f"VERTEX_SE3:QUAT 0 0 0 0 {quat_rows(q)}\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
            f"EDGE_SE3:QUAT 0 1 1 0 0 {quat_rows(q)} {I3_SE3}\n"
        )

    q = np.array([0.1, -0.2, 0.3, 0.9])
    ref = read_quietly(write(tmp_path, text(q), "unscaled.g2o"))
    R = np.asarray(ref.graph.R[0])
    np.testing.assert_allclose(R, np.asarray(quaternion_to_rotation(q / np.linalg.norm(q))), rtol=0, atol=1e-14)
    assert np.all(np.isfinite(q * scale))
    p = write(tmp_path, text(q * scale))
    f = read_quietly(p)
    np.testing.assert_allclose(np.asarray(f.graph.R[0]), R, rtol=0, atol=1e-15)
    np.testing.assert_allclose(f.vertex_R[0], R, rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(f.initial.R[0]), R, rtol=0, atol=1e-15)
    np.testing.assert_allclose(read_g2o_poses(p).R[0], R, rtol=0, atol=1e-15)
    # also in a float32 graph (normalised in float64 first, so nothing overflows)
    f32 = read_quietly(p, dtype=jnp.float32)
    np.testing.assert_allclose(np.asarray(f32.graph.R[0]), R, rtol=0, atol=1e-7)


@pytest.mark.parametrize("q", [(1e-310, 1e-310, 0.0, 1e-310), (0.0, 0.0, 0.0, 5e-324), (1e-13, 0, 0, 0), (0, 0, 0, 0)])
def test_tiny_quaternions_are_refused_as_zero_norm(tmp_path, q):
    for text, tag, line in [
        (f"VERTEX_SE3:QUAT 0 0 0 0 {quat_rows(q)}\n" + edge3(0, 1) + "\n", "VERTEX_SE3:QUAT", 1),
        (edge3(0, 1) + "\nEDGE_SE3:QUAT 1 2 1 0 0 " + quat_rows(q) + " " + I3_SE3 + "\n", "EDGE_SE3:QUAT", 2),
    ]:
        err = refused(write(tmp_path, text))
        assert err.line == line
        assert err.problem.startswith(f"{tag}: quaternion (qx, qy, qz, qw) has zero norm (|q| = ")
        assert err.problem.endswith("< 1e-12), cannot be normalised")


def test_edge_translation_overflow_is_refused(tmp_path):
    err = refused(write(tmp_path, edge3(0, 1) + "\n" + edge3(1, 2, t=(0.0, 1e200, 0.0)) + "\n"))
    assert err.line == 2
    assert err.problem == ("EDGE_SE3:QUAT: translation (x, y, z) is too large: |t|^2 = inf overflows float64 "
                           "(|t| = 1e+200)")
    err = refused(write(tmp_path, edge2(0, 1, t=(-1e200, 0.0)) + "\n"))
    assert err.problem == "EDGE_SE2: translation (dx, dy) is too large: |t|^2 = inf overflows float64 (|t| = 1e+200)"
    # |t|^2 = 1e300 is representable, tau |t|^2 = 1e310 is not
    I = np.eye(6) * 1e10
    err = refused(write(tmp_path, edge3(0, 1, t=(1e150, 0.0, 0.0), info=I) + "\n"))
    assert err.problem == (
        "EDGE_SE3:QUAT: translation (x, y, z) is too large: tau |t|^2 = inf overflows float64 "
        "(|t| = 1e+150, tau = 1e+10)"
    )
    # fine with a small weight
    read_quietly(write(tmp_path, edge3(0, 1, t=(1e150, 0.0, 0.0), info=np.eye(6) * 1e-3) + "\n"))


def test_vertex_translation_overflow_is_refused(tmp_path):
    err = refused(write(tmp_path, "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 1e200 0\n" + E2 + "\n"))
    assert err.line == 2
    assert err.problem == "VERTEX_SE2: translation (x, y) is too large: |t|^2 = inf overflows float64 (|t| = 1e+200)"
    # |t|^2 = 1e300 fits, but tau |t|^2 for the edge at that vertex (tau = 1e10) does not
    text = (
        "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 1e150 0\nVERTEX_SE2 2 0 0 0\n"
        "EDGE_SE2 0 2 1 0 0 1 0 0 1 0 1\nEDGE_SE2 0 1 1 0 0 1e10 0 0 1e10 0 1\n"
    )
    err = refused(write(tmp_path, text))
    assert err.line == 2
    assert err.problem.startswith(
        "VERTEX_SE2: translation (x, y) is too large: tau |t|^2 = inf overflows float64 for the edge on line 5"
    )
    # read_g2o_poses refuses the first, and (validating the edges like read_g2o) the second
    with pytest.raises(G2OFormatError, match=r"\|t\|\^2 = inf overflows"):
        read_g2o_poses(write(tmp_path, "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 1e200 0\n"))
    with pytest.raises(G2OFormatError, match="for the edge on line 5"):
        read_g2o_poses(write(tmp_path, text))
    # a float32 graph: |t|^2 must fit in float32
    p = write(tmp_path, "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 1e20 0\nEDGE_SE2 0 1 1.0 0.0 0.1 1e-10 0 0 1e-10 0 1\n")
    read_quietly(p)
    err = refused(p, dtype=jnp.float32)
    assert err.line == 2 and "overflows float32" in err.problem


# ----------------------------------------------------------------------------------------------
# 4. poses-only files


def test_read_g2o_poses_poses_only(tmp_path):
    text = (
        "# a ground truth: no edges\n"
        "VERTEX_SE3:QUAT 7 1 2 3 0 0 0 2\n"
        "VERTEX_SE3:QUAT -3 0 0 0 0.1 0.2 0.3 0.9\r\n"
        "VERTEX_SE3:QUAT 5 4 5 6 0 0 0.0998334 0.9950042\n"
    )
    p = write(tmp_path, text)
    with pytest.raises(G2OFormatError, match="no edges: the file has no EDGE_SE3:QUAT lines"):
        read_g2o(p)
    f = read_g2o_poses(p)
    assert isinstance(f, G2OPoses) and f.path == str(p) and f.dim == 3 and f.num_poses == 3
    np.testing.assert_array_equal(f.vertex_ids, [-3, 5, 7])
    assert f.vertex_ids.dtype == np.int64 and f.R.dtype == np.float64 and f.t.dtype == np.float64
    assert f.R.shape == (3, 3, 3) and f.t.shape == (3, 3)
    np.testing.assert_array_equal(f.t, [[0, 0, 0], [4, 5, 6], [1, 2, 3]])
    q = np.array([0.1, 0.2, 0.3, 0.9])
    np.testing.assert_allclose(f.R[0], np.asarray(quaternion_to_rotation(q / np.linalg.norm(q))), atol=1e-15)
    np.testing.assert_allclose(f.R[2], np.eye(3), atol=0)


def test_read_g2o_poses_matches_read_g2o():
    for name in ("tiny2d.g2o", "tiny3d.g2o", "comments3d.g2o", "noncontiguous2d.g2o"):
        g = read_quietly(DATA / name)
        p = read_g2o_poses(DATA / name)
        k = np.searchsorted(g.vertex_ids, p.vertex_ids)
        assert g.has_vertex[k].all() and k.size == g.has_vertex.sum()
        np.testing.assert_array_equal(p.R, g.vertex_R[k])
        np.testing.assert_array_equal(p.t, g.vertex_t[k])


def test_read_g2o_poses_refusals(tmp_path):
    with pytest.raises(G2OFormatError) as info:
        read_g2o_poses(DATA / "bad" / "disconnected.g2o")  # edges only
    assert info.value.line is None and info.value.problem == "no poses: the file has no VERTEX_SE2 lines"
    with pytest.raises(G2OFormatError, match="empty file"):
        read_g2o_poses(DATA / "bad" / "empty.g2o")
    with pytest.raises(G2OFormatError, match="file not found"):
        read_g2o_poses(tmp_path / "missing.g2o")
    cases = {
        "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 0 1 0 0\n": (2, "duplicate VERTEX_SE2 id 0 (already defined on line 1)"),
        "VERTEX_SE2 0 1_0 0 0\n": (1, "VERTEX_SE2: field 2 (x) is not a number: '1_0'"),
        "VERTEX_SE2 \uff11 0 0 0\n": (1, "VERTEX_SE2: field 1 (id) is not an integer vertex id: '\uff11'"),
        "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 0\n": (1, "VERTEX_SE3:QUAT: quaternion (qx, qy, qz, qw) has zero norm"),
        "VERTEX_SE2 0 0 0 nan\n": (1, "VERTEX_SE2: field 4 (theta) is not finite: nan"),
        "VERTEX_SE2 0 0 0 0\nFIX 3\n": (2, "FIX names vertex id 3, which has no VERTEX or EDGE line"),
        # edges, when present, are validated as by read_g2o
        "VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 0 1 0 0 1 0 0 1 0 1\n": (2, "self-loop edge"),
        "VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 0 4 3 0 2 0 5\n": (2, "is not positive"),
        "VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 0\n": (2, "wrong number of fields for EDGE_SE2"),
    }
    for text, (line, needle) in cases.items():
        with pytest.raises(G2OFormatError) as info:
            read_g2o_poses(write(tmp_path, text))
        assert info.value.line == line and needle in info.value.problem, (text, str(info.value))


def test_read_g2o_poses_with_indefinite_edges_does_not_warn():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        p = read_g2o_poses(DATA / "indefinite3d.g2o")
    np.testing.assert_array_equal(p.vertex_ids, np.arange(5))


# ----------------------------------------------------------------------------------------------
# 5. per-pose VERTEX values


def test_vertex_values_for_every_pose():
    f = read_quietly(DATA / "noncontiguous2d.g2o", dtype=jnp.float32)
    assert f.initial is None  # pose 5 has no VERTEX line
    np.testing.assert_array_equal(f.has_vertex, [False, True, True, True])
    assert f.vertex_R.dtype == np.float64 and f.vertex_t.dtype == np.float64
    assert f.vertex_R.shape == (4, 2, 2) and f.vertex_t.shape == (4, 2)
    np.testing.assert_array_equal(f.vertex_R[0], np.eye(2))
    np.testing.assert_array_equal(f.vertex_t[0], [0.0, 0.0])
    rows = {}
    for line in (DATA / "noncontiguous2d.g2o").read_text().splitlines():
        tok = line.split()
        if tok and tok[0] == "VERTEX_SE2":
            rows[int(tok[1])] = [float(x) for x in tok[2:]]
    for k, vid in enumerate(f.vertex_ids.tolist()):
        if vid in rows:
            x, y, th = rows[vid]
            np.testing.assert_array_equal(f.vertex_t[k], [x, y])
            np.testing.assert_allclose(f.vertex_R[k], np.asarray(rotation_2d(th)), atol=1e-15)


def test_vertex_values_equal_initial():
    for name in ("tiny2d.g2o", "tiny3d.g2o", "comments3d.g2o"):
        f = read_quietly(DATA / name)
        assert f.initial is not None and f.has_vertex.all()
        np.testing.assert_array_equal(f.vertex_R, np.asarray(f.initial.R))
        np.testing.assert_array_equal(f.vertex_t, np.asarray(f.initial.t))


def test_no_vertex_lines_gives_identity_values():
    f = read_quietly(DATA / "bad" / "disconnected.g2o")
    assert not f.has_vertex.any() and f.initial is None
    np.testing.assert_array_equal(f.vertex_R, np.broadcast_to(np.eye(2), (5, 2, 2)))
    np.testing.assert_array_equal(f.vertex_t, np.zeros((5, 2)))


# ----------------------------------------------------------------------------------------------
# property: layout variations read to identical results


def random_file(seed: int, dim: int, n: int, m: int) -> list[list[str]]:
    """Fields of a valid random g2o file: VERTEX lines for a random subset of poses, random edges
    with random SPD information matrices, floats written with full round-trip precision."""
    rng = np.random.default_rng(seed)
    ids = rng.choice(10**6, size=n, replace=False) - 1000
    rows = []
    with_vertex = rng.random(n) < 0.7
    Rv = random_rotations(rng, (n,), dim)
    for k in np.flatnonzero(with_vertex):
        t = rng.standard_normal(dim) * 10.0 ** rng.uniform(-3, 3)
        if dim == 2:
            vals = [*t, float(np.arctan2(Rv[k, 1, 0], Rv[k, 0, 0]))]
            rows.append(["VERTEX_SE2", str(ids[k]), *map(repr, map(float, vals))])
        else:
            q = rotation_to_quaternion(Rv[k]) * rng.uniform(0.5, 2.0)
            rows.append(["VERTEX_SE3:QUAT", str(ids[k]), *map(repr, map(float, [*t, *q]))])
    ksz = 3 if dim == 2 else 6
    for _ in range(m):
        i, j = rng.choice(n, 2, replace=False)
        R = random_rotations(rng, (), dim)
        t = rng.standard_normal(dim) * 10.0 ** rng.uniform(-3, 3)
        A = rng.standard_normal((ksz, ksz)) * 10.0 ** rng.uniform(-1, 2)
        I = A @ A.T + 0.1 * np.eye(ksz)
        up = [float(x) for x in I[np.triu_indices(ksz)]]
        if dim == 2:
            meas = [*t, float(np.arctan2(R[1, 0], R[0, 0]))]
            rows.append(["EDGE_SE2", str(ids[i]), str(ids[j]), *map(repr, map(float, meas + up))])
        else:
            meas = [*t, *rotation_to_quaternion(R)]
            rows.append(["EDGE_SE3:QUAT", str(ids[i]), str(ids[j]), *map(repr, map(float, meas + up))])
    rng.shuffle(rows)
    if rng.random() < 0.5:  # FIX a pose that has a VERTEX or EDGE line
        rows.append(["FIX", rows[int(rng.integers(len(rows)))][1]])
    return rows


def render(rows, *, crlf=False, seps=(" ",), indent=False, comments=False, bom=False, trailing="", seed=0) -> bytes:
    """The file's text: line ends, separators, leading whitespace, comment / blank lines, BOM."""
    rng = np.random.default_rng(seed)
    out = []
    for fields in rows:
        if comments and rng.random() < 0.3:
            out.append(str(rng.choice(["# a comment", "#", "  #EDGE_SE2 nonsense 1_0 \uff11", "   ", "\t", ""])))
        line = fields[0]
        for f in fields[1:]:
            line += seps[rng.integers(len(seps))] + f
        lead = str(rng.choice(["", " ", "\t", " \t"])) if indent else ""
        out.append(lead + line + trailing)
    if comments:
        out.append("# trailing comment without a newline")
    text = ("\r\n" if crlf else "\n").join(out) + ("" if comments else ("\r\n" if crlf else "\n"))
    return (b"\xef\xbb\xbf" if bom else b"") + text.encode("utf-8")


def same(a: G2OFile, b: G2OFile) -> None:
    np.testing.assert_array_equal(a.vertex_ids, b.vertex_ids)
    for x, y in [
        (a.graph.i, b.graph.i),
        (a.graph.j, b.graph.j),
        (a.graph.R, b.graph.R),
        (a.graph.t, b.graph.t),
        (a.graph.kappa, b.graph.kappa),
        (a.graph.tau, b.graph.tau),
    ]:
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    np.testing.assert_array_equal(a.information, b.information)
    np.testing.assert_array_equal(a.has_vertex, b.has_vertex)
    np.testing.assert_array_equal(a.fixed, b.fixed)
    np.testing.assert_array_equal(a.vertex_R, b.vertex_R)
    np.testing.assert_array_equal(a.vertex_t, b.vertex_t)
    assert a.num_indefinite_information == b.num_indefinite_information == 0


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    seed=st.integers(0, 2**32 - 1),
    dim=st.sampled_from([2, 3]),
    n=st.integers(2, 6),
    m=st.integers(1, 10),
    crlf=st.booleans(),
    seps=st.sampled_from([(" ",), ("\t",), ("  ", " \t "), (" ", "\t", "   ")]),
    indent=st.booleans(),
    comments=st.booleans(),
    bom=st.booleans(),
    trailing=st.sampled_from(["", " ", "\t", "  \t"]),
)
def test_layout_variations_read_identically(tmp_path, seed, dim, n, m, crlf, seps, indent, comments, bom, trailing):
    rows = random_file(seed, dim, n, m)
    plain = tmp_path / "plain.g2o"
    plain.write_bytes(render(rows))
    varied = tmp_path / "varied.g2o"
    varied.write_bytes(
        render(rows, crlf=crlf, seps=seps, indent=indent, comments=comments, bom=bom, trailing=trailing, seed=seed)
    )
    a = read_quietly(plain)
    b = read_quietly(varied)
    same(a, b)
    # and the weights are SE-Sync's
    kappa, tau = sesync_weights(a.information, dim)
    np.testing.assert_allclose(np.asarray(a.graph.kappa), kappa, rtol=1e-13)
    np.testing.assert_allclose(np.asarray(a.graph.tau), tau, rtol=1e-13)
    if a.has_vertex.any():
        pa, pb = read_g2o_poses(plain), read_g2o_poses(varied)
        np.testing.assert_array_equal(pa.vertex_ids, pb.vertex_ids)
        np.testing.assert_array_equal(pa.R, pb.R)
        np.testing.assert_array_equal(pa.t, pb.t)
