"""The CLI honours FIX, writes results in the input's frame and matches pose files by vertex id."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mmpgo_jax import read_g2o, read_g2o_poses
from mmpgo_jax.cli import main

DATA = Path(__file__).parent / "data"
FIX = DATA / "fix2d.g2o"  # 12 poses, ids 100, 102, ..., FIX 110, first VERTEX at (2, 1, 0.5 rad)
FRAME = DATA / "frame2d.g2o"  # the same without the FIX line


def _vertex(path, vid):
    p = read_g2o_poses(path)
    k = int(np.flatnonzero(p.vertex_ids == vid)[0])
    return p.R[k], p.t[k]


def _error(capsys, rc):
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


@pytest.mark.parametrize("command", ["solve", "optimum"])
def test_fix_pose_stays_and_is_written_back(tmp_path, command, capsys):
    out = tmp_path / "out.g2o"
    extra = ["-A", "3", "-n", "40", "--no-progress"] if command == "solve" else ["--max-iterations", "200"]
    assert main([command, str(FIX), "--out", str(out), *extra]) == 0
    text = out.read_text()
    assert "FIX 110" in text.splitlines()
    R_in, t_in = _vertex(FIX, 110)
    R_out, t_out = _vertex(out, 110)
    np.testing.assert_allclose(t_out, t_in, atol=1e-12)
    np.testing.assert_allclose(R_out, R_in, atol=1e-12)
    assert read_g2o(out).fixed.sum() == 1
    if command == "optimum":  # one FIX pose only fixes the gauge: the certificate applies
        assert "certificate" in capsys.readouterr().out


@pytest.mark.parametrize("command", ["solve", "optimum"])
def test_result_is_in_the_input_frame(tmp_path, command):
    out, tum = tmp_path / "out.g2o", tmp_path / "traj.txt"
    extra = ["-A", "3", "-n", "40", "--no-progress"] if command == "solve" else ["--max-iterations", "200"]
    assert main([command, str(FRAME), "--out", str(out), "--tum", str(tum), *extra]) == 0
    R, t = _vertex(out, 100)
    np.testing.assert_allclose(t, [2.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(np.arctan2(R[1, 0], R[0, 0]), 0.5, atol=1e-12)
    first = tum.read_text().splitlines()[0].split()
    assert first[0] == "100" and abs(float(first[1]) - 2.0) < 1e-12 and abs(float(first[2]) - 1.0) < 1e-12


def _poses_only(src: Path, dst: Path, shift: int = 0) -> Path:
    lines = [ln for ln in src.read_text().splitlines() if ln.startswith("VERTEX")]
    if shift:
        lines = [" ".join([f.split()[0], str(int(f.split()[1]) + shift), *f.split()[2:]]) for f in lines]
    dst.write_text("\n".join(reversed(lines)) + "\n")  # any order: matched by id
    return dst


def test_init_and_ground_truth_files_are_matched_by_id(tmp_path, capsys):
    poses = _poses_only(FRAME, tmp_path / "poses.g2o")
    assert main(["solve", str(FRAME), "--init", str(poses), "-n", "0", "-A", "2", "--no-progress",
                 "--ground-truth", str(poses), "--out", str(tmp_path / "o.g2o")]) == 0
    out = capsys.readouterr().out
    assert "ATE         0 RMSE" in out or "ATE         " in out
    # 0 iterations from the file's own poses: the output is the input, in its own frame
    got = read_g2o_poses(tmp_path / "o.g2o")
    want = read_g2o_poses(FRAME)
    np.testing.assert_allclose(got.t, want.t, atol=1e-12)
    shifted = _poses_only(FRAME, tmp_path / "shifted.g2o", shift=1)
    for flag in ("--init", "--ground-truth"):
        rc = main(["solve", str(FRAME), flag, str(shifted), "-n", "0", "-A", "2", "--no-progress"])
        line = _error(capsys, rc)
        assert "missing vertex ids 100, 102, 104, 106, 108, ... (12 in all)" in line, line
        assert "vertex ids not in the graph 101, 103" in line, line
    assert not (tmp_path / "x.g2o").exists()


def test_non_finite_objective_writes_nothing(tmp_path, capsys):
    # float32 cannot hold f = sum kappa ||R_i R_ij - R_j||^2 with kappa = 1e38 and rotations off by 3 rad
    src = [ln.split() for ln in FRAME.read_text().splitlines()]
    for f in src:
        if f[0] == "EDGE_SE2":
            f[5], f[11] = "3.0", "1e38"
    path = tmp_path / "huge.g2o"
    path.write_text("\n".join(" ".join(f) for f in src) + "\n")
    out = tmp_path / "out.g2o"
    # a fresh process: the tests enable float64 globally
    proc = subprocess.run([sys.executable, "-m", "mmpgo_jax.cli", "solve", str(path), "--precision", "float32",
                           "--init", "vertices", "-A", "2", "-n", "5", "--no-progress", "--out", str(out)],
                          capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert lines[0].startswith("mmpgo: warning:") and "not positive definite" in lines[0]  # tiny tau vs kappa
    assert len(lines) == 2 and lines[1].startswith("mmpgo: error: f = inf at the start"), lines
    assert "nothing was written" in lines[1]
    assert not out.exists()
