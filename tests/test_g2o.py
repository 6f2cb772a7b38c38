"""g2o reader/writer, TUM export, error messages and atomic writes."""

from __future__ import annotations

import contextlib
import os
import pickle
import re
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import mmpgo_jax._io.g2o as g2o_mod
from mmpgo_jax._core.geometry import random_rotations, rotation_2d
from mmpgo_jax._core.pose_graph import PoseGraph, Poses, connected_components
from mmpgo_jax._io.atomic import atomic_write
from mmpgo_jax._io.g2o import (
    G2OFile,
    G2OFormatError,
    information_from_weights,
    read_g2o,
    write_g2o,
    write_tum,
)

DATA = Path(__file__).resolve().parent / "data"
BAD = DATA / "bad"


# ----------------------------------------------------------------------------------------------
# helpers


def sesync_weights(info: np.ndarray, dim: int):
    """SE-Sync's convention, written out independently of the reader."""
    kappa, tau = [], []
    for I in info:
        if dim == 2:
            tau.append(2.0 / np.trace(np.linalg.inv(I[:2, :2])))
            kappa.append(I[2, 2])
        else:
            tau.append(3.0 / np.trace(np.linalg.inv(I[:3, :3])))
            kappa.append(3.0 / (2.0 * np.trace(np.linalg.inv(I[3:, 3:]))))
    return np.array(kappa), np.array(tau)


def temp_files(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir() if p.name.endswith(".tmp"))


# ----------------------------------------------------------------------------------------------
# errors

BAD_CASES = {
    # file: (distinctive substring, line)
    "unknown_tag.g2o": ("unknown tag 'VERTEX_XY'", 3),
    "field_count.g2o": ("wrong number of fields for EDGE_SE2: expected 11 after the tag, got 10", 2),
    "field_count_se3.g2o": ("wrong number of fields for EDGE_SE3:QUAT: expected 30 after the tag, got 29", 4),
    "non_numeric.g2o": ("field 4 (dy) is not a number: 'abc'", 2),
    "non_integer_id.g2o": ("field 2 (j) is not an integer vertex id: '2.5'", 2),
    "nan_value.g2o": ("field 5 (dtheta) is not finite: nan", 3),
    "inf_value.g2o": ("VERTEX_SE2: field 2 (x) is not finite: inf", 2),
    # I12^2 > I11 I22 (2D) / an indefinite translation block with tr(inv) < 0 (3D): tau < 0
    "not_pd_se2.g2o": (
        (
            "EDGE_SE2: SE-Sync weight tau = 2 / tr(inv(I[:2, :2])) = -300 is not positive "
            "(the information matrix is not positive definite)"
        ),
        3,
    ),
    "not_pd_se3.g2o": ("EDGE_SE3:QUAT: SE-Sync weight tau = 3 / tr(inv(I[:3, :3])) = -52.9412 is not positive", 2),
    "nonpositive_diagonal.g2o": (
        "EDGE_SE3:QUAT: information matrix is not positive definite: diagonal entry I44 = 0.0 is not positive",
        2,
    ),
    "information_subnormal.g2o": ("EDGE_SE2: information entry I11 = 1e-308 is nonzero but below 1e-300", 3),
    "information_overflow.g2o": ("EDGE_SE2: information entry I11 = 1e+302 is above 1e+300 in magnitude", 3),
    "underscore_number.g2o": ("EDGE_SE3:QUAT: field 3 (x) is not a number: '1_016.030'", 3),
    "underscore_id.g2o": ("VERTEX_SE2: field 1 (id) is not an integer vertex id: '1_0'", 2),
    "id_out_of_range.g2o": ("EDGE_SE2: field 2 (j) is out of range: '99999999999999999999'", 2),
    "value_out_of_range.g2o": ("VERTEX_SE2: field 2 (x) is out of range (its magnitude overflows float64): '1e400'", 2),
    "translation_overflow.g2o": ("EDGE_SE3:QUAT: translation (x, y, z) is too large: |t|^2 = inf overflows float64", 3),
    "vertex_translation_overflow.g2o": (
        "VERTEX_SE3:QUAT: translation (x, y, z) is too large: |t|^2 = inf overflows float64",
        2,
    ),
    "zero_quaternion.g2o": ("EDGE_SE3:QUAT: quaternion (qx, qy, qz, qw) has zero norm", 3),
    "zero_quaternion_vertex.g2o": ("VERTEX_SE3:QUAT: quaternion (qx, qy, qz, qw) has zero norm", 2),
    "self_loop.g2o": ("self-loop edge (i == j == 2)", 3),
    "mixed_dims.g2o": ("mixed 2D and 3D tags: EDGE_SE3:QUAT here, but VERTEX_SE2 on line 1", 3),
    "empty.g2o": ("empty file", None),
    "comments_only.g2o": ("empty file", None),
    "no_edges.g2o": ("no edges", None),
    "duplicate_vertex.g2o": ("duplicate VERTEX_SE2 id 0 (already defined on line 1)", 3),
    "fix_unknown_id.g2o": ("FIX names vertex id 7", 2),
    "fix_non_integer.g2o": ("FIX: field 1 is not an integer vertex id: 'zero'", 2),
}
VALID_IN_BAD = {"disconnected.g2o"}  # well-formed; connectivity is the caller's business


def test_every_bad_file_has_a_case():
    names = {p.name for p in BAD.glob("*.g2o")}
    assert names == set(BAD_CASES) | VALID_IN_BAD


@pytest.mark.parametrize("name", sorted(BAD_CASES))
def test_bad_file_message(name):
    substring, line = BAD_CASES[name]
    path = BAD / name
    with pytest.raises(G2OFormatError) as info:
        read_g2o(path)
    err = info.value
    assert substring in err.problem, str(err)
    assert err.line == line
    assert err.path == str(path)
    where = f"{path}:{line}" if line is not None else f"{path}"
    assert str(err) == f"{where}: {err.problem}"
    assert isinstance(err, ValueError)


def test_missing_file_and_directory(tmp_path):
    with pytest.raises(G2OFormatError, match="file not found") as info:
        read_g2o(tmp_path / "nope.g2o")
    assert info.value.line is None
    assert str(info.value) == f"{tmp_path / 'nope.g2o'}: file not found"
    with pytest.raises(G2OFormatError, match="is a directory"):
        read_g2o(tmp_path)


def test_error_pickles_and_formats():
    err = G2OFormatError("a.g2o", 7, "bad thing")
    assert str(err) == "a.g2o:7: bad thing"
    err2 = pickle.loads(pickle.dumps(err))
    assert (err2.path, err2.line, err2.problem) == ("a.g2o", 7, "bad thing")
    assert str(G2OFormatError("a.g2o", None, "x")) == "a.g2o: x"


def test_earliest_problem_is_reported(tmp_path):
    # a NaN in an edge on line 3 and a non-numeric vertex field on line 2: line 2 wins,
    # even though edges are checked first and the vertex group needs the slow path.
    p = tmp_path / "two_problems.g2o"
    p.write_text(
        "VERTEX_SE2 0 0 0 0\n"
        "VERTEX_SE2 1 x 0 0\n"
        "EDGE_SE2 0 1 1 0 nan 1 0 0 1 0 1\n"
        "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"
    )
    with pytest.raises(G2OFormatError) as info:
        read_g2o(p)
    assert info.value.line == 2 and "field 2 (x) is not a number" in info.value.problem
    # a later bad row in a group whose earlier row fails conversion is not reported first
    p.write_text(
        "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"
        "EDGE_SE2 0 1 1 0 0 -1 0 0 1 0 1\n"
        "EDGE_SE2 0 1 1 0 zz 1 0 0 1 0 1\n"
    )
    with pytest.raises(G2OFormatError) as info:
        read_g2o(p)
    assert info.value.line == 2 and "not positive definite" in info.value.problem


def test_singular_information_is_rejected(tmp_path):
    p = tmp_path / "singular.g2o"
    # rank-deficient 3x3 (rows 1 and 2 equal): the 2x2 translation block is singular too
    p.write_text("EDGE_SE2 0 1 1 0 0 1 1 0 1 0 5\n")
    with pytest.raises(G2OFormatError, match="not positive definite"):
        read_g2o(p)


# ----------------------------------------------------------------------------------------------
# valid small files


def test_tiny2d():
    f = read_g2o(DATA / "tiny2d.g2o")
    assert isinstance(f, G2OFile)
    assert f.dim == 2 and f.graph.num_poses == 4 and f.graph.num_edges == 4
    np.testing.assert_array_equal(f.vertex_ids, [0, 1, 2, 3])
    assert f.vertex_ids.dtype == np.int64
    assert f.initial is not None and f.has_vertex.all() and not f.fixed.any()
    np.testing.assert_allclose(np.asarray(f.initial.t[2]), [2.0, 0.1])
    np.testing.assert_allclose(np.asarray(f.initial.R[3]), np.asarray(rotation_2d(1.6)), atol=1e-15)
    np.testing.assert_allclose(np.asarray(f.graph.R[2]), np.asarray(rotation_2d(1.4)), atol=1e-15)
    np.testing.assert_allclose(np.asarray(f.graph.t[3]), [-2.0, -1.0])
    assert f.information.shape == (4, 3, 3)
    np.testing.assert_array_equal(f.information[2], [[50, 5, 0], [5, 20, 0], [0, 0, 400]])
    assert f.graph.R.dtype == jnp.float64  # conftest enables x64
    np.testing.assert_array_equal(np.asarray(f.graph.i), [0, 1, 2, 3])
    np.testing.assert_array_equal(np.asarray(f.graph.j), [1, 2, 3, 0])


def test_tiny3d_quaternions_are_normalised():
    f = read_g2o(DATA / "tiny3d.g2o")
    assert f.dim == 3 and f.graph.num_poses == 3 and f.graph.num_edges == 3
    R = np.asarray(f.graph.R)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)
    R0 = np.asarray(f.initial.R)
    np.testing.assert_allclose(np.linalg.det(R0), 1.0, atol=1e-14)
    assert f.information.shape == (3, 6, 6)
    np.testing.assert_array_equal(f.information, np.swapaxes(f.information, 1, 2))
    assert f.information[1, 0, 1] == 1.0 and f.information[1, 3, 4] == 10.0


def test_noncontiguous_ids_comments_fix_duplicates():
    f = read_g2o(DATA / "noncontiguous2d.g2o")
    np.testing.assert_array_equal(f.vertex_ids, [5, 7, 42, 1000])
    # edges in internal indices; the duplicate edge 7 -> 1000 is kept
    np.testing.assert_array_equal(np.asarray(f.graph.i), [2, 1, 1, 3])
    np.testing.assert_array_equal(np.asarray(f.graph.j), [1, 3, 3, 0])
    assert f.graph.num_edges == 4
    np.testing.assert_array_equal(f.has_vertex, [False, True, True, True])
    assert f.initial is None  # pose 5 has no VERTEX line
    np.testing.assert_array_equal(f.fixed, [False, False, True, False])


def test_crlf_fix_and_unnormalised_vertex_quaternion():
    f = read_g2o(DATA / "comments3d.g2o")
    np.testing.assert_array_equal(f.vertex_ids, [10, 20, 30])
    np.testing.assert_array_equal(f.fixed, [True, False, True])
    assert f.initial is not None
    # vertex 30 has quaternion (0, 0, 0, 2): identity after normalisation
    np.testing.assert_allclose(np.asarray(f.initial.R[2]), np.eye(3), atol=1e-15)
    np.testing.assert_allclose(np.asarray(f.initial.t[1]), [0.5, 0.5, 0.0])


def test_disconnected_file_reads_and_has_two_components():
    f = read_g2o(BAD / "disconnected.g2o")
    comps = connected_components(f.graph.num_poses, f.graph.i, f.graph.j)
    assert len(comps) == 2
    assert [list(f.vertex_ids[c]) for c in comps] == [[0, 1, 2], [10, 11]]


def test_dtype_argument():
    f = read_g2o(DATA / "tiny3d.g2o", dtype=jnp.float32)
    assert f.graph.R.dtype == jnp.float32 and f.graph.kappa.dtype == jnp.float32
    assert f.initial.t.dtype == jnp.float32
    assert f.information.dtype == np.float64


# ----------------------------------------------------------------------------------------------
# weights


def test_weights_se2_hand_computed(tmp_path):
    # I[:2,:2] = [[4, 1], [1, 2]]: inv has trace (2 + 4) / 7 = 6/7  ->  tau = 2 / (6/7) = 7/3
    p = tmp_path / "w2.g2o"
    p.write_text("EDGE_SE2 0 1 1 2 0.3 4 1 0.5 2 0.3 7\n")
    f = read_g2o(p)
    assert float(f.graph.tau[0]) == pytest.approx(7 / 3, rel=1e-15)
    assert float(f.graph.kappa[0]) == 7.0
    np.testing.assert_array_equal(f.information[0], [[4, 1, 0.5], [1, 2, 0.3], [0.5, 0.3, 7]])


def test_weights_se3_hand_computed(tmp_path):
    # translation block diag(2, 4, 8): tr inv = 0.875 -> tau = 3 / 0.875 = 24/7
    # rotation block [[3, 1, 0], [1, 3, 0], [0, 0, 5]]: tr inv = 6/8 + 1/5 = 0.95 -> kappa = 3 / 1.9 = 30/19
    # (coupling terms I14 = 0.1, I26 = -0.2 are not used by the weights)
    I = np.zeros((6, 6))
    I[:3, :3] = np.diag([2.0, 4.0, 8.0])
    I[3:, 3:] = [[3, 1, 0], [1, 3, 0], [0, 0, 5]]
    I[0, 3] = I[3, 0] = 0.1
    I[1, 5] = I[5, 1] = -0.2
    upper = I[np.triu_indices(6)]
    p = tmp_path / "w3.g2o"
    p.write_text("EDGE_SE3:QUAT 0 1 1 2 3 0 0 0.3 0.9 " + " ".join(repr(float(x)) for x in upper) + "\n")
    f = read_g2o(p)
    assert float(f.graph.tau[0]) == pytest.approx(24 / 7, rel=1e-15)
    assert float(f.graph.kappa[0]) == pytest.approx(30 / 19, rel=1e-15)
    np.testing.assert_array_equal(f.information[0], I)


@pytest.mark.parametrize("dim", [2, 3])
def test_information_from_weights_maps_back(dim):
    rng = np.random.default_rng(0)
    kappa = rng.uniform(0.01, 1e4, 50)
    tau = rng.uniform(0.01, 1e4, 50)
    info = information_from_weights(kappa, tau, dim)
    assert info.shape == (50, 3, 3) if dim == 2 else (50, 6, 6)
    k2, t2 = sesync_weights(info, dim)
    np.testing.assert_allclose(k2, kappa, rtol=1e-14)
    np.testing.assert_allclose(t2, tau, rtol=1e-14)


# ----------------------------------------------------------------------------------------------
# round trips


def random_problem(seed: int, dim: int, n: int, m: int):
    rng = np.random.default_rng(seed)
    ids = rng.choice(10**6, size=n, replace=False).astype(np.int64)  # non-contiguous, unordered
    i = rng.integers(0, n, m)
    j = (i + rng.integers(1, n, m)) % n  # never a self-loop
    R = random_rotations(rng, (m,), dim)
    if m:
        R[0] = np.diag([-1.0, -1.0] + [1.0] * (dim - 2))  # a rotation by pi (quaternion w = 0)
    t = rng.standard_normal((m, dim)) * 10.0 ** rng.uniform(-3, 3, (m, 1))
    k = 3 if dim == 2 else 6
    A = rng.standard_normal((m, k, k)) * 10.0 ** rng.uniform(-1, 2, (m, 1, 1))
    info = A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(k)
    kappa, tau = sesync_weights(info, dim)
    graph = PoseGraph.from_arrays(i, j, R, t, kappa, tau, num_poses=n)
    poses = Poses(
        jnp.asarray(random_rotations(rng, (n,), dim)),
        jnp.asarray(rng.standard_normal((n, dim)) * 100.0),
    )
    return ids, graph, poses, info


def check_round_trip(path, ids, graph, poses, info, expect_info):
    f = read_g2o(path)
    n, m, dim = graph.num_poses, graph.num_edges, graph.dim
    assert f.dim == dim and f.graph.num_poses == n and f.graph.num_edges == m
    np.testing.assert_array_equal(f.vertex_ids, np.sort(ids))
    # internal index in the file -> internal index in the original graph
    perm = np.argsort(ids)
    np.testing.assert_array_equal(ids[perm[np.asarray(f.graph.i)]], ids[np.asarray(graph.i)])
    np.testing.assert_array_equal(ids[perm[np.asarray(f.graph.j)]], ids[np.asarray(graph.j)])
    np.testing.assert_allclose(np.asarray(f.graph.R), np.asarray(graph.R), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(f.graph.t), np.asarray(graph.t), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(f.graph.kappa), np.asarray(graph.kappa), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(f.graph.tau), np.asarray(graph.tau), rtol=1e-12)
    np.testing.assert_allclose(f.information, expect_info, rtol=1e-12, atol=0)
    assert f.initial is not None and f.has_vertex.all()
    np.testing.assert_allclose(np.asarray(f.initial.R), np.asarray(poses.R)[perm], rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(f.initial.t), np.asarray(poses.t)[perm], rtol=1e-12, atol=1e-12)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    seed=st.integers(0, 2**32 - 1),
    dim=st.sampled_from([2, 3]),
    n=st.integers(2, 9),
    m=st.integers(1, 20),
    with_info=st.booleans(),
)
def test_round_trip_property(tmp_path, seed, dim, n, m, with_info):
    ids, graph, poses, info = random_problem(seed, dim, n, m)
    path = tmp_path / f"rt_{seed}_{dim}.g2o"
    if with_info:
        write_g2o(path, graph, poses, vertex_ids=ids, information=info)
        expect = info
    else:
        write_g2o(path, graph, poses, vertex_ids=ids)
        expect = information_from_weights(graph.kappa, graph.tau, dim)
    check_round_trip(path, ids, graph, poses, info, expect)
    assert temp_files(tmp_path) == []


@pytest.mark.parametrize("name", ["tiny2d.g2o", "tiny3d.g2o", "noncontiguous2d.g2o", "comments3d.g2o"])
def test_file_round_trip_is_exact(tmp_path, name):
    f = read_g2o(DATA / name)
    out = tmp_path / name
    write_g2o(out, f.graph, f.initial, vertex_ids=f.vertex_ids, information=f.information, fixed=f.fixed)
    g = read_g2o(out)
    np.testing.assert_array_equal(g.vertex_ids, f.vertex_ids)
    np.testing.assert_array_equal(g.information, f.information)
    np.testing.assert_array_equal(g.fixed, f.fixed)
    np.testing.assert_array_equal(np.asarray(g.graph.i), np.asarray(f.graph.i))
    np.testing.assert_array_equal(np.asarray(g.graph.j), np.asarray(f.graph.j))
    np.testing.assert_allclose(np.asarray(g.graph.R), np.asarray(f.graph.R), atol=1e-15)
    np.testing.assert_array_equal(np.asarray(g.graph.t), np.asarray(f.graph.t))
    np.testing.assert_array_equal(np.asarray(g.graph.kappa), np.asarray(f.graph.kappa))
    np.testing.assert_array_equal(np.asarray(g.graph.tau), np.asarray(f.graph.tau))


def test_write_defaults_and_text_format(tmp_path):
    _, graph, poses, _ = random_problem(3, 2, 3, 4)
    out = tmp_path / "plain.g2o"
    write_g2o(out, graph, poses)  # ids 0..n-1, isotropic information
    lines = out.read_text().splitlines()
    assert [ln.split()[0] for ln in lines] == ["VERTEX_SE2"] * 3 + ["EDGE_SE2"] * 4
    assert [int(ln.split()[1]) for ln in lines[:3]] == [0, 1, 2]
    assert all(len(ln.split()) == 12 for ln in lines[3:])
    f = read_g2o(out)
    np.testing.assert_array_equal(f.vertex_ids, [0, 1, 2])
    # without poses: edges only
    write_g2o(out, graph, None)
    assert all(ln.startswith("EDGE_SE2 ") for ln in out.read_text().splitlines())


def test_writer_validates_arguments(tmp_path):
    ids, graph, poses, info = random_problem(4, 3, 4, 5)
    out = tmp_path / "x.g2o"
    with pytest.raises(ValueError, match="vertex_ids"):
        write_g2o(out, graph, poses, vertex_ids=ids[:2])
    with pytest.raises(ValueError, match="unique"):
        write_g2o(out, graph, poses, vertex_ids=np.zeros(4, int))
    with pytest.raises(ValueError, match="information"):
        write_g2o(out, graph, poses, information=info[:, :3, :3])
    assert not out.exists()


# ----------------------------------------------------------------------------------------------
# TUM


def test_tum_3d(tmp_path):
    ids, _, poses, _ = random_problem(5, 3, 6, 3)
    out = tmp_path / "traj.txt"
    write_tum(out, poses, vertex_ids=ids)
    rows = [ln.split() for ln in out.read_text().splitlines()]
    assert len(rows) == 6 and all(len(r) == 8 for r in rows)
    assert [int(r[0]) for r in rows] == ids.tolist()
    vals = np.array([[float(x) for x in r[1:]] for r in rows])
    np.testing.assert_array_equal(vals[:, :3], np.asarray(poses.t))
    from mmpgo_jax._core.geometry import quaternion_to_rotation

    np.testing.assert_allclose(np.asarray(quaternion_to_rotation(vals[:, 3:])), np.asarray(poses.R), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(vals[:, 3:], axis=1), 1.0, atol=1e-15)


def test_tum_2d_with_timestamps(tmp_path):
    theta = np.array([0.0, 0.5, -2.0, np.pi])
    poses = Poses(rotation_2d(jnp.asarray(theta)), jnp.asarray(np.arange(8.0).reshape(4, 2)))
    out = tmp_path / "traj2d.txt"
    ts = np.array([1305031102.175304, 1305031102.2, 1305031102.3, 1305031103.0])
    write_tum(out, poses, timestamps=ts)
    vals = np.array([[float(x) for x in ln.split()] for ln in out.read_text().splitlines()])
    np.testing.assert_array_equal(vals[:, 0], ts)
    np.testing.assert_array_equal(vals[:, 1:3], np.arange(8.0).reshape(4, 2))
    np.testing.assert_array_equal(vals[:, 3], 0.0)
    np.testing.assert_array_equal(vals[:, 4:6], 0.0)
    angle = 2 * np.arctan2(vals[:, 6], vals[:, 7])
    np.testing.assert_allclose(np.cos(angle), np.cos(theta), atol=1e-14)
    np.testing.assert_allclose(np.sin(angle), np.sin(theta), atol=1e-14)
    write_tum(out, poses)  # default index 0..n-1
    assert [ln.split()[0] for ln in out.read_text().splitlines()] == ["0", "1", "2", "3"]


# ----------------------------------------------------------------------------------------------
# atomic writes


def test_atomic_write_failure_keeps_target(tmp_path):
    target = tmp_path / "out.g2o"
    target.write_text("old content\n")
    with pytest.raises(RuntimeError, match="boom"), atomic_write(target) as f:
        f.write("partial new content")
        raise RuntimeError("boom")
    assert target.read_text() == "old content\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.g2o"]
    # a failing write to a new target leaves nothing
    with pytest.raises(RuntimeError), atomic_write(tmp_path / "new.g2o", "wb") as f:
        f.write(b"x")
        raise RuntimeError("boom")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.g2o"]


def test_atomic_write_success_replaces_and_keeps_mode(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    os.chmod(target, 0o640)
    with atomic_write(target) as f:
        f.write("new")
    assert target.read_text() == "new"
    assert (os.stat(target).st_mode & 0o777) == 0o640
    with atomic_write(tmp_path / "b.bin", "wb") as f:
        f.write(b"\x00\x01")
    assert (tmp_path / "b.bin").read_bytes() == b"\x00\x01"
    assert temp_files(tmp_path) == []
    with pytest.raises(ValueError), atomic_write(target, "a"):
        pass


def test_write_g2o_failure_mid_write_keeps_target(tmp_path, monkeypatch):
    target = tmp_path / "graph.g2o"
    target.write_text("precious\n")

    class Failing:
        def __init__(self, f):
            self.f = f

        def write(self, s):
            self.f.write(s[: len(s) // 2])
            raise OSError(28, "No space left on device")

    @contextlib.contextmanager
    def failing_atomic_write(path, mode="w"):
        with atomic_write(path, mode) as f:
            yield Failing(f)

    monkeypatch.setattr(g2o_mod, "atomic_write", failing_atomic_write)
    _, graph, poses, _ = random_problem(1, 3, 4, 6)
    with pytest.raises(OSError, match="No space left"):
        write_g2o(target, graph, poses)
    with pytest.raises(OSError, match="No space left"):
        write_tum(target, poses)
    assert target.read_text() == "precious\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["graph.g2o"]


# ----------------------------------------------------------------------------------------------
# real benchmark files

# name: (d, n, m), as in datasets/README.txt
BENCHMARKS = {
    "ais2klinik.g2o": (2, 15115, 16727),
    "city10000.g2o": (2, 10000, 20687),
    "CSAIL.g2o": (2, 1045, 1172),
    "M3500.g2o": (2, 3500, 5453),
    "intel.g2o": (2, 1728, 2512),
    "MIT.g2o": (2, 808, 827),
    "sphere2500.g2o": (3, 2500, 4949),
    "torus3D.g2o": (3, 5000, 9048),
    "parking-garage.g2o": (3, 1661, 6275),
    "cubicle.g2o": (3, 5750, 16869),
    "grid3D.g2o": (3, 8000, 22236),
    "rim.g2o": (3, 10195, 29743),
    "manhattan.g2o": (2, 3500, 5453),
    "kitti_00.g2o": (2, 4541, 4677),
    "kitti_02.g2o": (2, 4661, 4703),
    "kitti_05.g2o": (2, 2761, 2826),
    "smallGrid3D.g2o": (3, 125, 297),
    "tinyGrid3D.g2o": (3, 9, 11),
    "sphere_bignoise_vertex3.g2o": (3, 2200, 8647),
}


def test_readme_table_matches(benchmark_file):
    readme = benchmark_file("README.txt")
    table = {}
    for line in readme.read_text().splitlines():
        m = re.match(r"^(\S+\.g2o)\s+(\d)\s+(\d+)\s+(\d+)\s", line)
        if m:
            table[m.group(1)] = tuple(int(x) for x in m.groups()[1:])
    assert table == BENCHMARKS


@pytest.mark.parametrize("name", sorted(BENCHMARKS))
def test_benchmark_sizes(benchmark_file, name):
    f = read_g2o(benchmark_file(name))
    assert (f.dim, f.graph.num_poses, f.graph.num_edges) == BENCHMARKS[name]
    assert f.information.shape == (f.graph.num_edges,) + ((3, 3) if f.dim == 2 else (6, 6))
    assert np.all(np.asarray(f.graph.kappa) > 0) and np.all(np.asarray(f.graph.tau) > 0)
    np.testing.assert_array_equal(f.vertex_ids, np.arange(f.graph.num_poses))


def test_m3500_weights(benchmark_file):
    f = read_g2o(benchmark_file("M3500.g2o"))
    # diagonal information with I11 = I22 (mostly 44.72136 / 44.72136 / 44.72136): tau = I11, kappa = I33
    np.testing.assert_allclose(np.asarray(f.graph.tau), f.information[:, 0, 0], rtol=1e-14)
    np.testing.assert_array_equal(np.asarray(f.graph.kappa), f.information[:, 2, 2])
    assert np.sum(np.asarray(f.graph.kappa) == 44.72136) == 4357 + 960


@pytest.mark.parametrize("name", ["torus3D.g2o", "city10000.g2o"])
def test_large_files_read_fast(benchmark_file, name):
    path = benchmark_file(name)
    best = np.inf
    for _ in range(2):
        t0 = time.perf_counter()
        read_g2o(path)
        best = min(best, time.perf_counter() - t0)
    assert best < 1.0, f"{name} took {best:.2f} s"
