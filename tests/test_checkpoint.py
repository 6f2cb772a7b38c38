"""Checkpoints: a run interrupted and resumed from its checkpoint equals the uninterrupted run.

The interrupted runs are stopped by a callback after some chunks (as a crash would, after the
last checkpoint); the resumed runs must reproduce the uninterrupted one's f history (to 1e-12,
here bit for bit) and final poses. Also: the Python API (solve, solve_sharded), ``mmpgo solve
--checkpoint/--resume`` (one process and two), refusals of other problems' checkpoints in one
line, and atomic writes.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

import mmpgo_jax as mm
from mmpgo_jax._mm.checkpoint import CheckpointError, load
from mmpgo_jax.cli import main
from mmpgo_jax.sharding import run_multiprocess, solve_sharded

ITERATIONS, CHUNK, EVERY, STOP = 60, 10, 2, 30  # checkpoints at 20 and 40; interrupted at 30


@pytest.fixture(scope="module")
def cube():
    return mm.cube_dataset(0, num_poses=120, grid=4).graph


def _stop_at(k_stop):
    return lambda k, f: k >= k_stop


def _same_run(a, b):
    assert a.iterations == b.iterations
    np.testing.assert_allclose(a.history.f, b.history.f, rtol=1e-12, atol=0)
    np.testing.assert_allclose(a.history.grad_norm, b.history.grad_norm, rtol=1e-12, atol=0)
    np.testing.assert_array_equal(a.history.restarts, b.history.restarts)
    for k in ("R", "t"):
        x, y = np.asarray(getattr(a.poses, k)), np.asarray(getattr(b.poses, k))
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-12 * max(1.0, np.abs(x).max()))


@pytest.mark.parametrize("options", [dict(method="amm"), dict(method="mm", loss="huber", init="chordal")], ids=["amm", "mm-huber"])
def test_resume_equals_uninterrupted_run(tmp_path, cube, options):
    ck = tmp_path / "run.ckpt"
    opts = dict(iterations=ITERATIONS, chunk_size=CHUNK, **options)
    full = mm.solve(cube, 4, **opts)
    cut = mm.solve(cube, 4, callback=_stop_at(STOP), checkpoint=ck, checkpoint_every=EVERY, **opts)
    assert cut.iterations == STOP and cut.stop_reason == "callback"
    snap = load(ck)
    assert snap.iterations == 20  # the last checkpoint before the interruption
    np.testing.assert_array_equal(snap.history.f, cut.history.f[:21])
    resumed = mm.solve(cube, 4, resume=ck, checkpoint=ck, checkpoint_every=EVERY, **opts)
    _same_run(full, resumed)
    assert np.array_equal(full.history.f, resumed.history.f)  # in fact bit for bit
    assert load(ck).iterations == 40  # the resumed run went on writing at the same iterations
    if options.get("loss") == "huber":
        np.testing.assert_array_equal(full.weights, resumed.weights)


def test_resume_with_a_larger_budget_continues(tmp_path, cube):
    ck = tmp_path / "ck.npz"
    mm.solve(cube, 4, iterations=40, chunk_size=CHUNK, checkpoint=ck, checkpoint_every=EVERY)
    assert load(ck).iterations == 20  # never at the end of a run
    longer = mm.solve(cube, 4, iterations=ITERATIONS, chunk_size=CHUNK, resume=ck)
    _same_run(mm.solve(cube, 4, iterations=ITERATIONS, chunk_size=CHUNK), longer)


def test_solve_sharded_resume_equals_uninterrupted_run(tmp_path, cube):
    ck = tmp_path / "sharded.npz"
    opts = dict(iterations=ITERATIONS, chunk_size=CHUNK, devices=1)
    full = solve_sharded(cube, 4, **opts)
    solve_sharded(cube, 4, callback=_stop_at(STOP), checkpoint=ck, checkpoint_every=EVERY, **opts)
    _same_run(full, solve_sharded(cube, 4, resume=ck, **opts))
    with pytest.raises(CheckpointError, match=r"\(layout: not the same\)"):  # the sharded layout is its own
        mm.solve(cube, 4, iterations=ITERATIONS, chunk_size=CHUNK, resume=ck)


def test_resume_refuses_another_problem(tmp_path, cube):
    ck = tmp_path / "ck.npz"
    mm.solve(cube, 4, iterations=30, chunk_size=CHUNK, checkpoint=ck, checkpoint_every=1)
    for options, part in [(dict(robots=5), "robots"), (dict(chunk_size=5), "chunk size"),
                          (dict(xi=1e-2), "method and settings"), (dict(method="mm"), "method and settings"),
                          (dict(loss="cauchy"), "start, loss"), (dict(init="odometry"), "start")]:
        kwargs = dict(dict(robots=4, iterations=30, chunk_size=CHUNK), **options)
        with pytest.raises(CheckpointError, match=rf"is of another problem \({part}: not the same\)"):
            mm.solve(cube, kwargs.pop("robots"), resume=ck, **kwargs)
    other = mm.cube_dataset(1, num_poses=120, grid=4).graph
    with pytest.raises(CheckpointError, match=r"\(graph"):
        mm.solve(other, 4, iterations=30, chunk_size=CHUNK, resume=ck)
    with pytest.raises(CheckpointError, match="at iteration 20, past this run's budget of 10"):
        mm.solve(cube, 4, iterations=10, chunk_size=CHUNK, resume=ck)
    (tmp_path / "text.npz").write_text("not a checkpoint\n")
    with pytest.raises(CheckpointError, match="not an mmpgo checkpoint"):
        mm.solve(cube, 4, iterations=30, chunk_size=CHUNK, resume=tmp_path / "text.npz")
    np.savez(tmp_path / "plain.npz", a=np.zeros(3))
    with pytest.raises(CheckpointError, match="no format entry"):
        mm.solve(cube, 4, iterations=30, chunk_size=CHUNK, resume=tmp_path / "plain.npz")
    with pytest.raises(CheckpointError, match="no such file"):
        mm.solve(cube, 4, iterations=30, chunk_size=CHUNK, resume=tmp_path / "missing.npz")
    with pytest.raises(ValueError, match="checkpoint_every"):
        mm.solve(cube, 4, iterations=30, chunk_size=CHUNK, checkpoint=ck, checkpoint_every=0)


def test_checkpoint_write_is_atomic(tmp_path, cube, monkeypatch):
    """A write that fails leaves the previous checkpoint whole and no temporary file."""
    ck = tmp_path / "ck.npz"
    mm.solve(cube, 4, iterations=30, chunk_size=CHUNK, checkpoint=ck, checkpoint_every=1)
    before = ck.read_bytes()

    def broken(fh, **arrays):
        fh.write(b"PK\x03\x04 half a zip")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "savez", broken)
    with pytest.raises(OSError, match="No space left"):
        mm.solve(cube, 4, iterations=30, chunk_size=CHUNK, checkpoint=ck, checkpoint_every=1)
    assert ck.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["ck.npz"]


# ------------------------------------------------------------------------------------------------
# mmpgo solve --checkpoint / --resume
# ------------------------------------------------------------------------------------------------


def _history(path):
    return np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)


def _cube_file(tmp_path, cube):
    src = tmp_path / "cube.g2o"
    mm.write_g2o(src, cube, None)
    return src


def test_cli_checkpoint_and_resume(tmp_path, cube, capsys):
    src = _cube_file(tmp_path, cube)
    ck, h = tmp_path / "ck.npz", tmp_path / "h{}.csv"
    base = ["solve", str(src), "--robots", "4", "--chunk", str(CHUNK), "--no-progress", "--no-compilation-cache"]
    # an "interrupted" run: 40 of the 60 iterations, checkpoints every 2 chunks (the last at 20)
    assert main([*base, "-n", "40", "--checkpoint", str(ck), "--checkpoint-every", "2"]) == 0
    assert load(ck).iterations == 20
    assert main([*base, "-n", "60", "--resume", str(ck), "--history", str(h).format(1)]) == 0
    assert main([*base, "-n", "60", "--history", str(h).format(2)]) == 0
    a, b = _history(str(h).format(1)), _history(str(h).format(2))
    assert a.shape == b.shape == (61, b.shape[1])
    np.testing.assert_allclose(a[:, 1], b[:, 1], rtol=1e-12, atol=0)
    capsys.readouterr()
    # another problem's checkpoint: one line, exit status 2
    assert main([*base, "-n", "60", "--robots", "5", "--resume", str(ck)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"mmpgo: error: checkpoint {ck} is of another problem (robots")
    # --checkpoint is an output: checked before anything is read or solved
    assert main([*base, "-n", "60", "--checkpoint", str(tmp_path / "no" / "ck.npz")]) == 2
    assert "--checkpoint" in capsys.readouterr().err


def test_two_process_checkpoint_and_resume(tmp_path, cube):
    """A 2-process run's checkpoint (gathered from both processes, written by process 0) resumes,
    on 2 processes, to the same run: run A does 40 iterations writing a checkpoint at 20; run B
    resumes that checkpoint and must reproduce A's iterations 21..40."""
    src = _cube_file(tmp_path, cube)
    ck = tmp_path / "ck.npz"
    base = ["solve", str(src), "--robots", "8", "--method", "mm", "-n", "40", "--chunk", str(CHUNK), "--no-progress",
            "--no-compilation-cache"]
    env = dict(os.environ, XLA_FLAGS="--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true")
    a = run_multiprocess([*base, "--checkpoint", str(ck), "--checkpoint-every", "2", "--history",
                          str(tmp_path / "a.csv")], processes=2, timeout_s=170, env=env)
    assert a.ok, a.failure or a.outputs
    assert load(ck).iterations == 20
    b = run_multiprocess([*base, "--resume", str(ck), "--history", str(tmp_path / "b.csv")], processes=2,
                         timeout_s=170, env=env)
    assert b.ok, b.failure or b.outputs
    ha, hb = _history(tmp_path / "a.csv"), _history(tmp_path / "b.csv")
    assert ha.shape == hb.shape and ha.shape[0] == 41
    np.testing.assert_allclose(ha[:, 1], hb[:, 1], rtol=1e-12, atol=0)
