"""Multi-robot inputs and outputs: GTSAM symbol keys, label files, one g2o file per robot, METIS
and random splits, TORO files, per-robot TUM / g2o outputs.

References are independent: the graph as generated (edges compared as sorted sets), hand-written
file lines with known layouts, explicit rotation matrices, brute-force loops over edges and poses.
"""

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest

import mmpgo_jax as mm
from mmpgo_jax._core.partition import metis_robots, partition_stats, random_robots, split_robots
from mmpgo_jax._core.pose_graph import PoseGraph, cost
from mmpgo_jax._io.g2o import G2OFormatError, read_toro, write_toro
from mmpgo_jax._io.multi_robot import (
    read_robot_folder,
    read_robot_labels,
    robots_from_symbols,
    symbol_keys,
    write_robot_folder,
    write_robot_tum,
)
from mmpgo_jax.cli import main

NAMES = np.array(["a", "b", "c"])


@pytest.fixture(scope="module")
def three_robots():
    """A 3-robot Cube graph (90 poses) with symbol keys, and its robot of each pose; edges in (tail,
    head) order, the order in which a per-robot folder is read."""
    ds = mm.cube_dataset(seed=3, grid=3, num_poses=90)
    g = ds.graph
    order = np.lexsort((np.asarray(g.j), np.asarray(g.i)))
    graph = PoseGraph.from_arrays(*(np.asarray(x)[order] for x in (g.i, g.j, g.R, g.t, g.kappa, g.tau)), 90)
    ds = dataclasses.replace(ds, graph=graph)
    rop = mm.contiguous_robots(90, 3)
    keys = symbol_keys(NAMES[rop], np.arange(90) - 30 * rop)
    return ds, rop, keys


def _edge_table(g2o):
    """Edges as rows (original ids, R, t, kappa, tau, information), sorted: order-free comparison."""
    g = g2o.graph
    ids = g2o.vertex_ids
    rows = np.concatenate([ids[np.asarray(g.i)][:, None].astype(float), ids[np.asarray(g.j)][:, None].astype(float),
                           np.asarray(g.R).reshape(g.num_edges, -1), np.asarray(g.t), np.asarray(g.kappa)[:, None],
                           np.asarray(g.tau)[:, None], g2o.information.reshape(g.num_edges, -1)], 1)
    return rows[np.lexsort(rows.T[::-1])]


def _write_three_ways(tmp_path, three_robots):
    ds, rop, keys = three_robots
    sym = tmp_path / "sym.g2o"
    mm.write_g2o(sym, ds.graph, ds.ground_truth, vertex_ids=keys)
    folder = tmp_path / "robots"
    write_robot_folder(folder, ds.graph, ds.ground_truth, robot_of_pose=rop, robot_names=NAMES, vertex_ids=keys)
    labels = tmp_path / "labels.csv"
    labels.write_text("vertex_id,robot\n# a comment\n" + "".join(f"{k},{r}\n" for k, r in zip(keys, NAMES[rop], strict=True)))
    return sym, folder, labels


def test_three_ways_read_to_the_same_graph_partition_and_f(tmp_path, three_robots):
    ds, rop, keys = three_robots
    sym, folder, labels = _write_three_ways(tmp_path, three_robots)
    reads = {"symbols": robots_from_symbols(mm.read_g2o(sym)),
             "files": read_robot_folder(folder),
             "labels": read_robot_labels(labels, mm.read_g2o(sym))}
    # each inter-robot edge is in both robots' files, and counts once
    inter = int(np.sum(rop[np.asarray(ds.graph.i)] != rop[np.asarray(ds.graph.j)]))
    assert inter > 0
    text = "".join(p.read_text() for p in sorted(folder.glob("*.g2o")))
    assert text.count("EDGE_SE3:QUAT") == ds.graph.num_edges + inter
    reference = _edge_table(reads["symbols"])
    fs = {}
    for how, g2o in reads.items():
        assert g2o.robot_names == ("a", "b", "c"), how
        np.testing.assert_array_equal(g2o.vertex_ids, np.sort(keys), err_msg=how)
        np.testing.assert_array_equal(g2o.robot_of_pose, rop, err_msg=how)  # keys ascend with the path here
        np.testing.assert_array_equal(_edge_table(g2o), reference, err_msg=how)
        for field in ("i", "j", "R", "t", "kappa", "tau"):  # the same arrays, order included
            np.testing.assert_array_equal(getattr(g2o.graph, field), getattr(reads["symbols"].graph, field))
        fs[how] = mm.solve(g2o.graph, g2o.robot_of_pose, method="mm", iterations=5, chunk_size=5,
                            init="vertices", initial=g2o.initial).f
    f_true = float(cost(ds.graph, ds.ground_truth))
    for how, g2o in reads.items():
        assert float(cost(g2o.graph, g2o.initial)) == pytest.approx(f_true, rel=1e-12)
        assert fs[how] == pytest.approx(fs["symbols"], rel=1e-12, abs=0), how


def _inter_edge_lines(folder, robot):
    """(line number, text) of the edge lines of ``robot``'s file naming another robot's pose."""
    out = []
    own = set()
    lines = (folder / f"{robot}.g2o").read_text().splitlines()
    for k, ln in enumerate(lines, 1):
        f = ln.split()
        if f[0].startswith("VERTEX"):
            own.add(f[1])
        elif f[0].startswith("EDGE") and not (f[1] in own and f[2] in own):
            out.append((k, ln))
    return out


def test_inconsistent_copy_of_an_inter_robot_edge_is_refused_with_both_locations(tmp_path, three_robots):
    _, folder, _ = _write_three_ways(tmp_path, three_robots)
    # the first inter-robot edge of b's file whose tail is a's pose: its other copy is in a's file
    a_ids = {ln.split()[1] for ln in (folder / "a.g2o").read_text().splitlines() if ln.startswith("VERTEX")}
    k_b, line_b = next((k, ln) for k, ln in _inter_edge_lines(folder, "b") if ln.split()[1] in a_ids)
    i, j = line_b.split()[1:3]
    k_a = next(k for k, ln in enumerate((folder / "a.g2o").read_text().splitlines(), 1)
               if ln.split()[:3] == ["EDGE_SE3:QUAT", i, j])
    lines = (folder / "b.g2o").read_text().splitlines()
    fields = lines[k_b - 1].split()
    fields[3] = repr(float(fields[3]) + 1e-3)  # x of the measurement
    lines[k_b - 1] = " ".join(fields)
    (folder / "b.g2o").write_text("\n".join(lines) + "\n")
    with pytest.raises(G2OFormatError) as err:
        read_robot_folder(folder)
    msg = str(err.value)
    assert msg.startswith(f"{folder / 'a.g2o'}:{k_a} and {folder / 'b.g2o'}:{k_b}: "), msg
    assert f"inter-robot edge {i} {j} disagree (measurement" in msg


def test_folder_input_rules(tmp_path, three_robots):
    _, folder, _ = _write_three_ways(tmp_path, three_robots)
    b = (folder / "b.g2o").read_text().splitlines()
    # a VERTEX line of a's pose in b's file: two owners
    a_vertex = (folder / "a.g2o").read_text().splitlines()[0]
    (folder / "b.g2o").write_text("\n".join([*b, a_vertex]) + "\n")
    with pytest.raises(G2OFormatError, match=r"a\.g2o:1 and .*b\.g2o:\d+: vertex id \d+ has a VERTEX line in two"):
        read_robot_folder(folder)
    # an extra copy in one file: the copies cannot be matched
    k, line = _inter_edge_lines(folder, "b")[0]
    (folder / "b.g2o").write_text("\n".join([*b, line]) + "\n")
    with pytest.raises(G2OFormatError, match="cannot be matched"):
        read_robot_folder(folder)
    # an edge of a's poses only, in c's file
    own_a = next(ln for ln in (folder / "a.g2o").read_text().splitlines()
                 if ln.startswith("EDGE") and ln not in dict(_inter_edge_lines(folder, "a")).values())
    (folder / "b.g2o").write_text("\n".join(b) + "\n")
    c = (folder / "c.g2o").read_text().splitlines()
    (folder / "c.g2o").write_text("\n".join([*c, own_a]) + "\n")
    with pytest.raises(G2OFormatError, match=rf"c\.g2o:{len(c) + 1}: edge .* has no pose of robot 'c'"):
        read_robot_folder(folder)


def test_symbol_and_label_errors_name_file_and_line(tmp_path, three_robots):
    ds, rop, keys = three_robots
    plain = tmp_path / "plain.g2o"
    mm.write_g2o(plain, ds.graph, None)  # ids 0..n-1: edges only, pose 0 first named on line 1
    with pytest.raises(G2OFormatError, match=r"plain\.g2o:1: vertex id 0 is not a GTSAM symbol key: its top 8 bits"):
        robots_from_symbols(mm.read_g2o(plain))
    g2o = mm.read_g2o(plain)
    labels = tmp_path / "l.csv"
    labels.write_text("0,a\n1,b\n0,c\n")
    with pytest.raises(G2OFormatError, match=r"l\.csv:3: vertex id 0 is labelled again \(first on line 1\)"):
        read_robot_labels(labels, g2o)
    labels.write_text("0,a\n999,b\n")
    with pytest.raises(G2OFormatError, match=r"l\.csv:2: vertex id 999 is not a pose of"):
        read_robot_labels(labels, g2o)
    labels.write_text("".join(f"{k},r{k % 2}\n" for k in range(89)))  # pose 89 unlabelled
    line = int(g2o.vertex_line[89])
    with pytest.raises(G2OFormatError, match=rf"plain\.g2o:{line}: vertex id 89 has no label in .*l\.csv"):
        read_robot_labels(labels, g2o)
    labels.write_text("0,a/b\n")
    with pytest.raises(G2OFormatError, match=r"l\.csv:1: robot name 'a/b' must be"):
        read_robot_labels(labels, g2o)
    # numeric names are numbered numerically
    labels.write_text("".join(f"{k},{10 if k < 45 else 9}\n" for k in range(90)))
    out = read_robot_labels(labels, g2o)
    assert out.robot_names == ("9", "10") and out.robot_of_pose[0] == 1


def test_metis_parts_are_balanced_and_cover_each_pose_once():
    g = mm.cube_dataset(seed=1, grid=5, num_poses=600).graph
    for A in (4, 6, 12):
        rop = metis_robots(g, A)
        assert rop.shape == (600,) and rop.dtype == np.int64
        counts = np.bincount(rop, minlength=A)
        assert counts.sum() == 600 and len(counts) == A and counts.min() > 0  # every pose once, no empty part
        assert counts.max() <= np.ceil(1.03 * 600 / A), counts  # METIS's k-way tolerance (ufactor 30)
        # parts are numbered by their first pose
        first = [int(np.flatnonzero(rop == a)[0]) for a in range(A)]
        assert first == sorted(first)
        np.testing.assert_array_equal(metis_robots(g, A), rop)  # deterministic for a seed
        part = mm.partition(g, "metis", parts=A)
        np.testing.assert_array_equal(np.asarray(part.robot_of_pose), rop)
    rnd = random_robots(600, 7, seed=2)
    assert sorted(np.bincount(rnd).tolist()) == sorted(np.bincount(mm.contiguous_robots(600, 7)).tolist())
    with pytest.raises(ValueError, match="needs parts="):
        split_robots(g, "metis")
    with pytest.raises(ValueError, match="unknown split"):
        split_robots(g, "spectral", 3)


def test_partition_stats_sent_and_received_brute_force():
    g = mm.cube_dataset(seed=2, grid=3, num_poses=80).graph
    rop = random_robots(80, 5, seed=1)
    st = partition_stats(g, rop)
    need = set()  # (receiver, pose of another robot) over the edges
    for i, j in zip(np.asarray(g.i).tolist(), np.asarray(g.j).tolist(), strict=True):
        if rop[i] != rop[j]:
            need |= {(rop[i], j), (rop[j], i)}
    recv = [sum(1 for r, _ in need if r == a) for a in range(5)]
    sent = [sum(1 for _, p in need if rop[p] == a) for a in range(5)]
    nbrs = [sorted({rop[p] for r, p in need if r == a}) for a in range(5)]
    assert st.received_poses.tolist() == recv and st.sent_poses.tolist() == sent
    assert [x.tolist() for x in st.neighbours] == nbrs
    assert st.sent_bytes(np.float32).tolist() == [s * 12 * 4 for s in sent]


# ------------------------------------------------------------------------------------------------
# TORO
# ------------------------------------------------------------------------------------------------


def test_toro_2d_layout_and_round_trip(tmp_path):
    f = tmp_path / "a.graph"
    # inf_ff inf_fs inf_ss inf_rr inf_fr inf_sr
    f.write_text("VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0.5\nEDGE2 0 1 1 0 0.5 4 1 3 7 0.5 0.25\n")
    g = read_toro(f)
    np.testing.assert_array_equal(g.information[0], [[4, 1, 0.5], [1, 3, 0.25], [0.5, 0.25, 7]])
    assert float(g.graph.kappa[0]) == 7.0
    assert float(g.graph.tau[0]) == pytest.approx(2 / np.trace(np.linalg.inv([[4, 1], [1, 3]])), rel=1e-15)
    ds = mm.grid_2d_dataset(seed=0, grid=5, num_poses=60)
    info = np.tile(np.array([[4, 1, 0.5], [1, 3, 0.25], [0.5, 0.25, 7.0]]), (ds.graph.num_edges, 1, 1))
    write_toro(f, ds.graph, ds.ground_truth, vertex_ids=np.arange(60) * 3, information=info)
    back = read_toro(f)
    np.testing.assert_array_equal(back.vertex_ids, np.arange(60) * 3)
    np.testing.assert_array_equal(back.information, info)
    np.testing.assert_allclose(np.asarray(back.graph.R), np.asarray(ds.graph.R), atol=1e-15)
    np.testing.assert_array_equal(np.asarray(back.graph.t), np.asarray(ds.graph.t))
    np.testing.assert_allclose(back.vertex_t, np.asarray(ds.ground_truth.t), atol=0)


def _rpy_matrix(r, p, y):
    Rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    Ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    Rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def test_toro_3d_layout_and_round_trip(tmp_path):
    f = tmp_path / "b.graph"
    upper = np.diag([5.0, 5, 5, 9, 9, 9])[np.triu_indices(6)]
    f.write_text("VERTEX3 0 0 0 0 0.1 0.2 0.3\nEDGE3 0 1 1 2 3 0.3 -0.2 1.1 " + " ".join(map(repr, upper.tolist())) + "\n")
    g = read_toro(f)
    np.testing.assert_allclose(np.asarray(g.graph.R[0]), _rpy_matrix(0.3, -0.2, 1.1), atol=1e-15)
    np.testing.assert_allclose(g.vertex_R[0], _rpy_matrix(0.1, 0.2, 0.3), atol=1e-15)
    # isotropic information w in angles -> kappa = 2 w (as g2o's quaternion information 4 w gives)
    assert float(g.graph.kappa[0]) == pytest.approx(18.0, rel=1e-15)
    assert float(g.graph.tau[0]) == pytest.approx(5.0, rel=1e-15)
    ds = mm.cube_dataset(seed=0, grid=3, num_poses=50)  # lattice poses: pitch = +-90 degrees occurs
    a = tmp_path / "c.g2o"
    mm.write_g2o(a, ds.graph, ds.ground_truth)
    ref = mm.read_g2o(a)
    write_toro(f, ref.graph, ref.initial, information=ref.information)
    back = read_toro(f)
    np.testing.assert_allclose(back.information, ref.information, rtol=1e-15)
    np.testing.assert_array_equal(np.asarray(back.graph.kappa), np.asarray(ref.graph.kappa))
    np.testing.assert_allclose(np.asarray(back.graph.R), np.asarray(ref.graph.R), atol=1e-14)
    np.testing.assert_allclose(back.vertex_R, ref.vertex_R, atol=1e-14)
    np.testing.assert_array_equal(back.vertex_t, ref.vertex_t)


def test_toro_input_rules(tmp_path):
    f = tmp_path / "bad.graph"
    f.write_text("VERTEX2 0 0 0 0\nEDGE2 0 1 1 0 0 1 0 1 nan 0 0\n")
    with pytest.raises(G2OFormatError, match=r"bad\.graph:2: EDGE2: field 9 \(I33\) is not finite"):
        read_toro(f)
    f.write_text("EDGE2 0 1 1 0 0 1 0 1 0 0 0\n")
    with pytest.raises(G2OFormatError, match=r"bad\.graph:1: EDGE2: information matrix is not positive definite: "
                                             r"diagonal entry I33 = 0\.0"):
        read_toro(f)
    f.write_text("EDGE2 0 1 1 0 0 1 0 1 1 0 0\nFIX 0\n")
    with pytest.raises(G2OFormatError, match=r"bad\.graph:2: unknown tag 'FIX' \(expected EDGE2, VERTEX2, EDGE3"):
        read_toro(f)
    f.write_text("EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n")
    with pytest.raises(G2OFormatError, match=r"bad\.graph:1: unknown tag 'EDGE_SE2'"):
        read_toro(f)


# ------------------------------------------------------------------------------------------------
# Per-robot outputs
# ------------------------------------------------------------------------------------------------


def _read_tum(path):
    rows = np.loadtxt(path, ndmin=2)
    return rows[:, 0].astype(np.int64), rows[:, 1:]


def test_per_robot_tum_files_read_back_with_the_whole_trajectory(tmp_path, three_robots):
    ds, rop, keys = three_robots
    written = write_robot_tum(tmp_path / "tum", ds.ground_truth, robot_of_pose=rop, robot_names=NAMES, vertex_ids=keys)
    assert [p.rsplit("/", 1)[1] for p in written] == ["a.tum", "b.tum", "c.tum", "all_robots.tum"]
    whole_ids, whole = _read_tum(tmp_path / "tum" / "all_robots.tum")
    mm.write_tum(tmp_path / "whole.tum", ds.ground_truth, vertex_ids=keys)
    np.testing.assert_array_equal(whole, _read_tum(tmp_path / "whole.tum")[1])
    parts = [_read_tum(tmp_path / "tum" / f"{x}.tum") for x in NAMES]
    for x, (ids, _) in zip(NAMES, parts, strict=True):
        assert set((ids >> 56).tolist()) == {ord(x)}
    ids = np.concatenate([p[0] for p in parts])
    rows = np.concatenate([p[1] for p in parts])
    order = np.argsort(ids)
    np.testing.assert_array_equal(ids[order], whole_ids)
    np.testing.assert_array_equal(rows[order], whole)


def test_out_dir_refuses_a_stale_robot_file_and_writes_nothing(tmp_path, three_robots):
    ds, rop, keys = three_robots
    folder = tmp_path / "out"
    folder.mkdir()
    (folder / "z.g2o").write_text("old\n")
    with pytest.raises(ValueError, match=r"holds z\.g2o, which is not one of this graph's robots"):
        write_robot_folder(folder, ds.graph, ds.ground_truth, robot_of_pose=rop, robot_names=NAMES, vertex_ids=keys)
    assert sorted(p.name for p in folder.iterdir()) == ["z.g2o"]


def test_cli_multi_robot_example(tmp_path, capsys):
    """The README's commands on datasets/cube3_symbols.g2o (few iterations)."""
    from conftest import REPO

    example = REPO / "datasets" / "cube3_symbols.g2o"
    assert main(["info", str(example)]) == 0
    assert "GTSAM symbol keys of 3 robots (a, b, c)" in capsys.readouterr().out
    assert main(["info", str(example), "--robots-from", "symbols"]) == 0
    out = capsys.readouterr().out
    table = [ln.split() for ln in out.splitlines() if re.match(r"^\s+[abc]\s+\d+", ln)]
    assert [r[0] for r in table] == ["a", "b", "c"] and sum(int(r[1]) for r in table) == 300
    tum, robots = tmp_path / "tum", tmp_path / "robots"
    assert main(["solve", str(example), "--robots-from", "symbols", "-n", "0", "--no-progress",
                 "--tum-dir", str(tum), "--out-dir", str(robots), "--tum", str(tmp_path / "all.tum")]) == 0
    out = capsys.readouterr().out
    assert "3 robots (from symbols)" in out
    np.testing.assert_array_equal(np.loadtxt(tum / "all_robots.tum"), np.loadtxt(tmp_path / "all.tum"))
    back = read_robot_folder(robots)
    ref = robots_from_symbols(mm.read_g2o(example))
    np.testing.assert_allclose(_edge_table(back), _edge_table(ref), rtol=1e-12, atol=1e-15)  # via quaternions
    np.testing.assert_array_equal(back.robot_of_pose, ref.robot_of_pose)
    assert main(["info", str(example), "--robots-from", "metis", "-A", "3"]) == 0
    out = capsys.readouterr().out
    assert "3 robots (METIS parts)" in out
    labels = tmp_path / "labels.csv"
    labels.write_text("".join(f"{k},r{k % 2}\n" for k in ref.vertex_ids.tolist()))
    assert main(["info", str(example), "--labels", str(labels)]) == 0
    assert "2 robots (from labels)" in capsys.readouterr().out
    # the folder as FILE: robots from its files
    assert main(["info", str(robots)]) == 0
    assert "3 robots (from files)" in capsys.readouterr().out
    # --robots applies to blocks / metis / random only
    assert main(["info", str(example), "--robots-from", "symbols", "--robots", "3"]) == 2
    assert "--robots applies to --robots-from blocks, metis or random" in capsys.readouterr().err
    assert main(["info", str(example), "--robots-from", "files"]) == 2
    assert "is a file; give a folder" in capsys.readouterr().err



# The generator's numbers go through BLAS matrix products (the Cube's random walk, the odometry
# chains composed over 100 poses per robot, rotation -> quaternion), whose kernels OpenBLAS picks
# per processor: the committed files match this generator byte for byte only under some kernels.
# Measured on one machine (2026-12-03, AMD EPYC Zen 4) with OPENBLAS_CORETYPE set to each kernel:
# Haswell and Zen give the committed bytes, SkylakeX (the default there, AVX-512) changes 496
# numbers by at most 3.9e-16 and Sandybridge 1483 by at most 3.6e-15. 1e-11 (relative and absolute)
# leaves three orders of margin over that and still catches any change of the generator itself (its
# smallest deliberate change, one noise draw, moves values by ~1e-3).
GENERATOR_TOLERANCE = 1e-11


def _assert_same_g2o(written: Path, committed: Path) -> None:
    """Same lines, tags and vertex ids exactly; every number to GENERATOR_TOLERANCE."""
    ours, theirs = (p.read_text().splitlines() for p in (written, committed))
    assert len(ours) == len(theirs), written.name
    for k, (a, b) in enumerate(zip(ours, theirs, strict=True)):
        ta, tb = a.split(), b.split()
        ids = 1 + (2 if ta[0].startswith("EDGE") else 1 if ta[0].startswith("VERTEX") else len(ta))
        where = f"{written.name}:{k + 1}"
        assert len(ta) == len(tb) and ta[:ids] == tb[:ids], where
        np.testing.assert_allclose(np.array(ta[ids:], float), np.array(tb[ids:], float), rtol=GENERATOR_TOLERANCE,
                                   atol=GENERATOR_TOLERANCE, err_msg=where)


def test_example_is_what_its_generator_writes(tmp_path):
    """datasets/cube3_symbols.g2o is reproducible from its committed generator, on any CPU (the
    numbers to GENERATOR_TOLERANCE, not byte for byte: see there)."""
    import runpy

    from conftest import REPO

    script = runpy.run_path(str(REPO / "datasets" / "make_multi_robot_example.py"))
    assert script["main"]([str(tmp_path)]) == 0
    for name in ("cube3_symbols.g2o", "cube3_ground_truth.g2o"):
        _assert_same_g2o(tmp_path / name, REPO / "datasets" / name)
    g2o = robots_from_symbols(mm.read_g2o(tmp_path / "cube3_symbols.g2o"))
    assert g2o.robot_names == ("a", "b", "c") and np.bincount(g2o.robot_of_pose).tolist() == [100, 100, 100]


@pytest.mark.slow  # four compilations (about 20 s)
def test_sweep_split_matches_solve_on_that_partition(three_robots):
    """sweep(split=...) runs each split's partition: a METIS copy and an array split of one graph in
    one sweep give the histories of solve() on those partitions."""
    ds, rop, _ = three_robots
    res = mm.sweep({"metis": ds.graph, "data": ds.graph}, robots=[3], methods=("mm",), iterations=4, chunk_size=4,
                   split={"metis": "metis", "data": rop}, group_by="robots", max_batch_configs=1)
    assert res.configs[0]["robots"] == 3 and res.configs[1]["robots"] == 3
    for name, robots in (("metis", mm.partition(ds.graph, "metis", parts=3)), ("data", rop)):
        ref = mm.solve(ds.graph, robots, method="mm", iterations=4, chunk_size=4, frame="raw")
        np.testing.assert_allclose(res.history(name, 3, "mm"), ref.history.f, rtol=1e-9)


def test_sweep_split_is_checked_before_any_work(three_robots):
    ds, rop, _ = three_robots
    with pytest.raises(ValueError, match="unknown split 'spectral'"):
        mm.sweep({"x": ds.graph}, robots=[3], split="spectral")
    with pytest.raises(ValueError, match=r"robots .* own no pose"):
        mm.sweep({"x": ds.graph}, robots=[3], split={"x": rop + 1})
