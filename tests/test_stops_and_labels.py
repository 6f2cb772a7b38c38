"""A run whose iterations change f only by rounding stops and says so (iterations are an upper
bound); the CLI's labels say what they measure: no restart rule for MM, a sweep's batch time
apart from a configuration's share, the split ``solve`` would use in ``info``, and GTSAM symbol
names beside raw keys in the edge-weights CSV."""

import csv
import re

import numpy as np
import pytest

import mmpgo_jax as mm
from mmpgo_jax._io.multi_robot import symbol_keys, symbol_names
from mmpgo_jax._mm.driver import RESULTS, STALL_EPS, Termination
from mmpgo_jax.cli import main


def _chunks(*arrays, dtype=np.float64):
    return [np.asarray(a, dtype) for a in arrays]


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_stall_rule_is_relative_to_the_precision(dtype):
    t = Termination(200, 3)
    eps = np.finfo(dtype).eps
    f0 = 1000.0
    g = [np.ones(1, dtype), np.ones(3, dtype)]
    within = f0 * (1 - 0.5 * STALL_EPS * eps)
    assert t(_chunks([f0], [within, f0, within], dtype=dtype), g) is RESULTS.stalled
    beyond = f0 * (1 - 4 * STALL_EPS * eps)  # one iteration of the chunk moved f beyond rounding
    assert t(_chunks([f0], [f0, beyond, f0], dtype=dtype), g) is None
    assert Termination(200, 3, stop_when_stalled=False)(_chunks([f0], [f0, f0, f0], dtype=dtype), g) is None
    assert "only by rounding" in RESULTS.stalled.describe(t)
    with pytest.raises(ValueError, match="stop_when_stalled must be True or False"):
        Termination(10, stop_when_stalled=1)


@pytest.fixture(scope="module")
def at_optimum():
    graph = mm.cube_dataset(seed=0, grid=3, num_poses=60).graph  # float64: conftest
    return graph, mm.centralized_optimum(graph).poses


def test_solve_from_a_critical_point_stops_after_one_chunk(at_optimum):
    graph, optimum = at_optimum
    res = mm.solve(graph, 3, init=optimum, iterations=200, chunk_size=20, frame="raw")
    assert res.result is RESULTS.stalled and res.iterations == 20
    assert "stationary" in res.stop_description
    full = mm.solve(graph, 3, init=optimum, iterations=60, chunk_size=20, frame="raw", stop_when_stalled=False)
    assert full.iterations == 60 and full.result is RESULTS.iterations
    np.testing.assert_array_equal(full.history.f[:21], res.history.f)  # the same run, cut short
    # a run that still makes progress is not cut: from the chordal start it runs its budget
    moving = mm.solve(graph, 3, iterations=40, chunk_size=20, frame="raw")
    assert moving.iterations == 40


def test_cli_stops_when_stalled_and_all_iterations_runs_them(tmp_path, at_optimum, capsys):
    graph, optimum = at_optimum
    path = tmp_path / "g.g2o"
    mm.write_g2o(path, graph, optimum)
    assert main(["solve", str(path), "-A", "3", "--init", str(path), "-n", "100", "--chunk", "10", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"^iterations  10 \(stationary: f moved by at most 100 x machine epsilon", out, re.M), out
    assert main(["solve", str(path), "-A", "3", "--init", str(path), "-n", "30", "--chunk", "10", "--no-progress",
                 "--all-iterations", "--method", "mm"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"^iterations  30 \(budget of 30 iterations reached\)", out, re.M)
    assert re.search(r"^method      MM-PGO, 3 robots \(contiguous blocks\)$", out, re.M)  # MM has no restart rule


def test_amm_summary_names_its_restart_rule(tmp_path, at_optimum, capsys):
    graph, optimum = at_optimum
    path = tmp_path / "g.g2o"
    mm.write_g2o(path, graph, optimum)
    assert main(["solve", str(path), "-A", "3", "-n", "2", "--no-progress", "--restart", "average"]) == 0
    assert re.search(r"^method      AMM-PGO, 3 robots \(contiguous blocks\), restart=average$",
                     capsys.readouterr().out, re.M)


def test_info_shows_the_split_solve_would_use(capsys, tmp_path, at_optimum):
    graph, optimum = at_optimum
    path = tmp_path / "g.g2o"
    mm.write_g2o(path, graph, optimum)
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "partition   10 robots (contiguous blocks, the default of mmpgo solve)" in out
    table = [ln.split() for ln in out.splitlines() if re.match(r"^\s+\d+\s+\d+\s+\d+", ln)]
    assert len(table) == 10 and sum(int(r[1]) for r in table) == graph.num_poses


def test_sweep_table_separates_batch_time_from_a_configurations_share(tmp_path, at_optimum, capsys):
    graph, optimum = at_optimum
    path = tmp_path / "g.g2o"
    mm.write_g2o(path, graph, optimum)
    assert main(["sweep", str(path), "-A", "2", "3", "-n", "4", "--methods", "mm", "--no-progress"]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("|")]
    head = [c.strip() for c in lines[0].strip("|").split("|")]
    assert head[-3:] == ["in batch", "batch ms/it", "ms/it share"]
    for row in lines[2:]:
        cells = [c.strip() for c in row.strip("|").split("|")]
        batch, whole, share = int(cells[-3]), float(cells[-2]), float(cells[-1])
        assert batch >= 1 and whole == pytest.approx(batch * share, rel=0.02, abs=0.011)


def test_symbol_names():
    keys = symbol_keys(np.array(["a", "b", "Z"]), np.array([67, 0, 2**56 - 1]))
    assert symbol_names(keys) == ["a67", "b0", f"Z{2**56 - 1}"]
    assert symbol_names(np.array([0, 1, 2])) is None  # plain integer ids


def test_edge_weights_csv_names_symbols(tmp_path, capsys):
    from conftest import REPO

    out = tmp_path / "w.csv"
    assert main(["solve", str(REPO / "datasets" / "cube3_symbols.g2o"), "--robots-from", "symbols", "--loss", "tls",
                 "--init", "gnc-chordal", "-n", "1", "--no-progress", "--edge-weights", str(out)]) == 0
    assert re.search(r"edges rejected \(f = sum of rho\(r\^2\)\)(; lines? [\d, ]+(and \d+ more )?of cube3_symbols\.g2o)?$",
                     capsys.readouterr().out, re.M)
    rows = list(csv.DictReader(out.open()))
    assert list(rows[0]) == ["i", "j", "weight", "inlier", "i_symbol", "j_symbol"]
    for r in rows:
        for end in "ij":
            key = int(r[end])
            assert r[f"{end}_symbol"] == f"{chr(key >> 56)}{key & (2**56 - 1)}"
