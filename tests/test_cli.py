"""End-to-end tests of the ``mmpgo`` command line, run as subprocesses (``python -m mmpgo_jax.cli``).

Each subprocess pays for importing JAX and compiling the solver, so the runs are few and small:
``solve`` on the tiny test files, ``info``, every bad file (run concurrently), the disconnected
graph with and without ``--largest-component``, ``bench --quick`` and a small ``demo`` from a copy
of the package with no data folder beside it.
"""

from __future__ import annotations

import concurrent.futures
import csv
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mmpgo_jax._io.g2o import read_g2o

REPO = Path(__file__).resolve().parents[1]
DATA = Path(__file__).resolve().parent / "data"
BAD = DATA / "bad"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"

# problems of the file as a whole: the message names the file but no line
FILE_LEVEL_PROBLEMS = {"empty.g2o", "comments_only.g2o", "no_edges.g2o"}
# a valid file that the CLI refuses to solve (tested separately)
NOT_A_FORMAT_ERROR = {"disconnected.g2o"}


def _env(**extra) -> dict:
    env = dict(os.environ)
    env.setdefault("JAX_PLATFORMS", "cpu")
    env["PYTHONUNBUFFERED"] = "1"
    env.update(extra)
    return env


def mmpgo(*args, cwd=None, env=None, timeout=300) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "mmpgo_jax.cli", *map(str, args)],
        check=False,
        cwd=cwd or REPO,
        env=env or _env(),
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def _ok(proc: subprocess.CompletedProcess) -> None:
    assert proc.returncode == 0, f"exit {proc.returncode}\nstdout:\n{proc.stdout}\nstderr:\n{proc.stderr}"
    assert "Traceback" not in proc.stderr, proc.stderr


def _no_temp_files(folder: Path) -> None:
    left = [p.name for p in folder.iterdir() if p.name.startswith(".") and p.name.endswith(".tmp")]
    assert not left, f"atomic_write left temporary files behind: {left}"


def _check_png(path: Path, min_bytes: int = 5000) -> None:
    assert path.is_file(), f"{path} was not written"
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC, f"{path} is not a PNG"
    assert len(data) > min_bytes, f"{path} is suspiciously small ({len(data)} bytes)"
    import matplotlib.image as mpimg

    img = mpimg.imread(path)
    assert img.ndim == 3 and img.shape[0] > 300 and img.shape[1] > 500


def _read_tum(path: Path) -> np.ndarray:
    rows = []
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        fields = line.split()
        assert len(fields) == 8, f"TUM line with {len(fields)} fields: {line!r}"
        rows.append([float(x) for x in fields])
    return np.asarray(rows)


def _read_history(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    for r in rows:
        for key, val in r.items():
            try:
                float(val)
            except ValueError:
                pytest.fail(f"{path.name}: column {key!r} holds a non-number {val!r}")
    return rows


# --------------------------------------------------------------------------------------------
# solve
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name, robots", [("noncontiguous2d.g2o", 2)])
def test_solve_writes_outputs(tmp_path, name, robots):
    src = DATA / name
    original = read_g2o(src)
    n, m = original.graph.num_poses, original.graph.num_edges
    out, tum, hist, plot = (tmp_path / f for f in ("est.g2o", "est.tum", "history.csv", "plot.png"))
    iters = 20
    proc = mmpgo("solve", src, "--robots", robots, "--iterations", iters, "--no-progress",
                 "--out", out, "--tum", tum, "--history", hist, "--plot", plot)
    _ok(proc)
    assert "f = 2F" in proc.stdout

    # g2o: reads back, same ids, edges and every pose has a VERTEX line
    back = read_g2o(out)
    assert back.graph.num_poses == n and back.graph.num_edges == m
    assert back.graph.dim == original.graph.dim
    np.testing.assert_array_equal(back.vertex_ids, original.vertex_ids)
    assert back.has_vertex.all()
    np.testing.assert_array_equal(np.asarray(back.graph.i), np.asarray(original.graph.i))
    np.testing.assert_array_equal(np.asarray(back.graph.j), np.asarray(original.graph.j))
    np.testing.assert_allclose(np.asarray(back.graph.kappa), np.asarray(original.graph.kappa), rtol=1e-9)

    # TUM: n lines of 8 numbers, the original ids, unit quaternions, positions = the g2o's
    T = _read_tum(tum)
    assert T.shape == (n, 8)
    np.testing.assert_array_equal(np.sort(T[:, 0]).astype(int), np.sort(original.vertex_ids))
    np.testing.assert_allclose(np.linalg.norm(T[:, 4:8], axis=1), 1.0, atol=1e-9)
    order = np.argsort(T[:, 0])
    pos = np.asarray(back.initial.t)[np.argsort(back.vertex_ids)]
    np.testing.assert_allclose(T[order, 1 : 1 + original.graph.dim], pos, atol=1e-9)

    # history: iterations + 1 rows of numbers, f non-increasing overall
    rows = _read_history(hist)
    assert len(rows) == iters + 1
    assert [int(r["iteration"]) for r in rows] == list(range(iters + 1))
    assert float(rows[-1]["f"]) <= float(rows[0]["f"]) + 1e-9

    _check_png(plot)
    _no_temp_files(tmp_path)


# --------------------------------------------------------------------------------------------
# info
# --------------------------------------------------------------------------------------------


def test_info_prints_dimensions_and_partition():
    proc = mmpgo("info", DATA / "noncontiguous2d.g2o", "--robots", 2)
    _ok(proc)
    out = proc.stdout
    g = read_g2o(DATA / "noncontiguous2d.g2o").graph
    assert re.search(r"\bd = 2\b", out)
    assert re.search(rf"\bn = {g.num_poses}\b", out)
    assert re.search(rf"\bm = {g.num_edges}\b", out)
    # partition table: a header and one row per robot
    lines = out.splitlines()
    head = next(i for i, line in enumerate(lines) if re.match(r"\s*robot\s+poses", line))
    assert "inter" in lines[head]
    rows = [line.split() for line in lines[head + 1 : head + 3]]
    assert [r[0] for r in rows] == ["0", "1"]
    assert sum(int(r[1]) for r in rows) == g.num_poses


# --------------------------------------------------------------------------------------------
# bad input: exit status 2, one line naming file (and line), no traceback
# --------------------------------------------------------------------------------------------

BAD_FILES = sorted(p.name for p in BAD.glob("*.g2o") if p.name not in NOT_A_FORMAT_ERROR)
# run as real subprocesses (each costs an interpreter and a JAX import); all files also run in-process
SUBPROCESS_BAD_FILES = ["empty.g2o", "field_count.g2o", "zero_quaternion.g2o"]


def _check_error_message(name: str, rc: int, stderr: str, stdout: str = "") -> None:
    path = BAD / name
    assert rc == 2, f"exit {rc}\nstdout:\n{stdout}\nstderr:\n{stderr}"
    assert "Traceback" not in stderr, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, f"expected a one-line message, got:\n{stderr}"
    msg = lines[0]
    prefix = f"mmpgo: error: {path}:"
    assert msg.startswith(prefix), msg
    rest = msg[len(prefix):]
    m = re.match(r"(\d+): \S", rest)
    if name in FILE_LEVEL_PROBLEMS:
        assert m is None and rest.startswith(" ") and len(rest.strip()) > 5, msg
    else:
        assert m is not None, f"no line number in: {msg}"
        line = int(m.group(1))
        text = path.read_text().splitlines()
        assert 1 <= line <= len(text) and text[line - 1].strip(), f"line {line} does not point into the file: {msg}"


def test_bad_files_exist():
    assert len(BAD_FILES) >= 10
    assert set(SUBPROCESS_BAD_FILES) <= set(BAD_FILES)


@pytest.fixture(scope="module")
def bad_runs():
    """``mmpgo info`` on a few bad files as subprocesses, concurrently (they mostly wait on imports)."""
    with concurrent.futures.ThreadPoolExecutor(max_workers=len(SUBPROCESS_BAD_FILES)) as pool:
        futures = {name: pool.submit(mmpgo, "info", BAD / name) for name in SUBPROCESS_BAD_FILES}
        return {name: f.result() for name, f in futures.items()}


@pytest.mark.parametrize("name", SUBPROCESS_BAD_FILES)
def test_bad_file_subprocess(bad_runs, name):
    proc = bad_runs[name]
    _check_error_message(name, proc.returncode, proc.stderr, proc.stdout)


@pytest.mark.parametrize("command", ["info", "solve"])
@pytest.mark.parametrize("name", BAD_FILES)
def test_bad_file_in_process(capsys, name, command):
    """Every bad file through ``cli.main`` (the code the subprocess runs), for both commands."""
    from mmpgo_jax.cli import main

    rc = main([command, str(BAD / name), "--no-progress"] if command == "solve" else [command, str(BAD / name)])
    captured = capsys.readouterr()
    _check_error_message(name, rc, captured.err, captured.out)


def test_disconnected_graph_needs_largest_component(tmp_path):
    src = BAD / "disconnected.g2o"
    proc = mmpgo("solve", src, "--robots", 2, "--iterations", 5, "--no-progress")
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("mmpgo: error: "), proc.stderr
    assert str(src) in lines[0] and "--largest-component" in lines[0]

    out = tmp_path / "largest.g2o"
    proc = mmpgo("solve", src, "--robots", 2, "--iterations", 5, "--no-progress", "--largest-component", "--out", out)
    _ok(proc)
    assert "largest component" in proc.stdout
    back = read_g2o(out)
    assert back.graph.num_poses == 3 and back.graph.num_edges == 2
    np.testing.assert_array_equal(np.sort(back.vertex_ids), [0, 1, 2])


# --------------------------------------------------------------------------------------------
# bench and demo
# --------------------------------------------------------------------------------------------


def test_bench_quick(tmp_path):
    out = tmp_path / "bench"
    proc = mmpgo("bench", "--quick", "--out-dir", out, "--no-progress", "--extra-methods", "rbcd++")
    _ok(proc)
    assert "| dataset |" in proc.stdout
    md = (out / "bench.md").read_text()
    for needle in ("bench --quick", "JAX", "backend", "f* ours", "ms/iter", "iters → 1e-3", "| MM |", "| AMM |",
                   "| RBCD++ |"):
        assert needle in md, f"{needle!r} missing from bench.md"
    with open(out / "bench.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    # DGS: the paper's third column; RBCD++: --extra-methods, without paper or code values
    assert {r["run"] for r in rows} == {"MM", "AMM", "AMM-alg2", "DGS", "RBCD++"}
    assert all(r["paper_f"] == "" and r["code_f"] == "" for r in rows if r["run"] == "RBCD++")
    assert all(int(r["k"]) == 100 for r in rows)
    for r in rows:
        assert float(r["f"]) >= float(r["fstar_used"]) * (1 - 1e-6)
    doc = json.loads((out / "bench.json").read_text())
    assert doc["complete"] is True and doc["iterations"] == 100 and len(doc["datasets"]) == 1
    ds = doc["datasets"][0]
    assert set(ds["runs"]) == {"MM", "AMM", "AMM-alg2", "DGS", "RBCD++"}
    assert len(ds["runs"]["MM"]["f_history"]) == 101
    assert doc["machine"]["cpu"] and doc["machine"]["jax"]
    if ds["name"] == "MITb":  # the paper's numbers are carried along; gaps use the registry's certified f*
        assert rows[0]["paper_f"] and rows[0]["fstar_sesync"]
        assert ds["fstar"]["source"] == "certified f* (registry)"
        dgs = next(r for r in rows if r["run"] == "DGS")  # printed 92.44; ours 92.63 (+0.2 %, benchmarks/dgs_paper.md)
        assert float(dgs["paper_f"]) == 92.44 and abs(float(dgs["rel_vs_paper"])) < 0.005
    _check_png(out / ds["figure"])
    _no_temp_files(out)


@pytest.mark.slow  # the no-data path of the CLI is in the default run through the demo test
def test_bench_quick_falls_back_to_cube(tmp_path):
    """With no benchmark data at all, --quick still exercises everything on a generated Cube dataset."""
    from mmpgo_jax._io.datasets import available_benchmarks

    if not available_benchmarks():
        pytest.skip("no data here: test_bench_quick already ran the fallback")
    empty = tmp_path / "empty-data"
    empty.mkdir()
    out = tmp_path / "bench"
    proc = mmpgo("bench", "--quick", "--out-dir", out, "--no-progress", env=_env(MMPGO_DATA=str(empty)))
    _ok(proc)
    assert "generated Cube dataset" in proc.stdout
    doc = json.loads((out / "bench.json").read_text())
    ds = doc["datasets"][0]
    assert ds["name"].startswith("cube") and ds["fstar"]["source"].startswith("ours")
    assert (out / "bench.md").is_file() and (out / "bench.csv").is_file()
    _check_png(out / ds["figure"])


def test_demo_without_data(tmp_path):
    """The demo needs no data: run it from a copy of the package with no ../shared beside it."""
    repo = tmp_path / "repo"
    shutil.copytree(REPO / "mmpgo_jax", repo / "mmpgo_jax", ignore=shutil.ignore_patterns("__pycache__"))
    empty = tmp_path / "empty-data"
    empty.mkdir()
    env = _env(MMPGO_DATA=str(empty))
    env.pop("PYTHONPATH", None)
    where = subprocess.run([sys.executable, "-c", "import mmpgo_jax; print(mmpgo_jax.__file__)"],
                           cwd=repo, env=env, capture_output=True, text=True, timeout=120, check=False)
    assert Path(where.stdout.strip()).resolve() == (repo / "mmpgo_jax" / "__init__.py").resolve(), where
    assert not (tmp_path / "shared").exists()

    out = tmp_path / "demo-out"
    proc = mmpgo("demo", "--poses", 300, "--iterations", 50, "--out-dir", out, "--no-progress", cwd=repo, env=env)
    _ok(proc)
    for needle in ("f*", "global optimum (certified)", "MM-PGO", "AMM-PGO", "ATE", "ms/it"):
        assert needle in proc.stdout, f"{needle!r} missing from the demo's output:\n{proc.stdout}"
    _check_png(out / "demo_trajectory.png")
    _check_png(out / "demo_convergence.png")
    back = read_g2o(out / "demo_result.g2o")
    assert back.graph.num_poses == 300 and back.has_vertex.all()
    rows = _read_history(out / "demo_history.csv")
    assert len(rows) == 51
    assert float(rows[-1]["f_amm"]) < float(rows[0]["f_amm"])
    _no_temp_files(out)


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["bench", "--datasets", "no-such-benchmark"], "no-such-benchmark"),
        (["bench", "--robots", "0"], "--robots"),
        (["demo", "--robots", "0"], "--robots"),
        (["demo", "--poses", "1"], "--poses"),
    ],
)
def test_bench_demo_bad_arguments(capsys, tmp_path, argv, needle):
    """Invalid bench/demo options end with exit status 2 and a one-line message, before any work."""
    from mmpgo_jax.cli import main

    rc = main([*argv, "--out-dir", str(tmp_path / "out"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("mmpgo: error: ") and needle in lines[0], err
    assert not (tmp_path / "out").exists()


def test_solve_reports_accuracy_with_ground_truth(tmp_path):
    """--ground-truth: ATE/RPE printed, equal to the library's; a wrong-size file is a clean error."""
    import mmpgo_jax as mm
    from mmpgo_jax._io.g2o import write_g2o

    mm.enable_float64()
    data = mm.cube_dataset(2, num_poses=120, grid=3)
    problem, truth = tmp_path / "cube.g2o", tmp_path / "truth.g2o"
    write_g2o(problem, data.graph, None)
    write_g2o(truth, data.graph, data.ground_truth)
    out = tmp_path / "est.g2o"
    proc = mmpgo("solve", problem, "--robots", 3, "--iterations", 10, "--no-progress", "--ground-truth", truth,
                 "--out", out)
    _ok(proc)
    ate = float(re.search(r"^ATE\s+(\S+) RMSE", proc.stdout, re.MULTILINE).group(1))
    est = read_g2o(out).initial
    assert ate == pytest.approx(mm.trajectory_accuracy(est, data.ground_truth).ate, rel=1e-5)
    assert re.search(r"^RPE\s+\S+ translation", proc.stdout, re.MULTILINE)

    small = tmp_path / "small.g2o"
    sub = mm.cube_dataset(2, num_poses=60, grid=3)
    write_g2o(small, sub.graph, sub.ground_truth)
    proc = mmpgo("solve", problem, "--iterations", 1, "--no-progress", "--ground-truth", small)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "ground-truth file" in proc.stderr and "small.g2o" in proc.stderr


def test_solve_reports_the_distributed_chordal_start(tmp_path):
    """--init distributed-chordal: the summary names the start's CG iterations per stage and how each
    stage applied Gamma, the numbers the library's start reports (``stats["distributed_chordal"]``)."""
    import mmpgo_jax as mm
    from mmpgo_jax._init.distributed_chordal import distributed_chordal_initialization
    from mmpgo_jax._io.g2o import write_g2o

    mm.enable_float64()
    data = mm.cube_dataset(2, num_poses=120, grid=3)
    problem = tmp_path / "cube.g2o"
    write_g2o(problem, data.graph, None)
    proc = mmpgo("solve", problem, "--robots", 3, "--iterations", 5, "--no-progress", "--init", "distributed-chordal")
    _ok(proc)
    graph = read_g2o(problem).graph
    _, info = distributed_chordal_initialization(graph, 3)
    line = (f"start       distributed chordal: {info.rotation_iterations} + {info.translation_iterations} CG "
            "iterations (rotations + translations), each robot's Gamma applied as dense inverses / dense inverses")
    assert line in proc.stdout
    stats = mm.solve(graph, 3, init="distributed-chordal", iterations=5).stats["distributed_chordal"]
    assert stats == dict(rotation_iterations=info.rotation_iterations,
                         translation_iterations=info.translation_iterations, factorizations=["dense", "dense"])
    assert "distributed_chordal" not in mm.solve(graph, 3, iterations=5).stats


def test_solve_certify_reports_global_optimum(tmp_path):
    """--certify on a converged centralized run prints the dual certificate's verdict."""
    import mmpgo_jax as mm
    from mmpgo_jax._io.g2o import write_g2o

    mm.enable_float64()
    data = mm.cube_dataset(2, num_poses=120, grid=3)
    problem = tmp_path / "cube.g2o"
    write_g2o(problem, data.graph, None)
    proc = mmpgo("solve", problem, "--robots", 1, "--iterations", 300, "--grad-tol", "1e-7", "--no-progress",
                 "--certify")
    _ok(proc)
    line = re.search(r"^certificate (.*)$", proc.stdout, re.MULTILINE).group(1)
    assert line.startswith("global optimum (certified)"), proc.stdout
    lam = float(re.search(r"lambda_min\(S\) = (\S+) ", line).group(1))
    eta = float(re.search(r"eta = ([0-9.e+-]+)", line).group(1))
    assert -eta <= lam <= eta


def test_optimum_command_writes_certified_optimum(tmp_path):
    """`mmpgo optimum`: centralized f*, its certificate, and the result file; bad --init is a clean error."""
    import mmpgo_jax as mm
    from mmpgo_jax._io.g2o import write_g2o

    mm.enable_float64()
    data = mm.cube_dataset(4, num_poses=150, grid=3)
    problem, out = tmp_path / "cube.g2o", tmp_path / "opt.g2o"
    write_g2o(problem, data.graph, data.ground_truth)
    proc = mmpgo("optimum", problem, "--init", "vertices", "--out", out)
    _ok(proc)
    f = float(re.search(r"^f\* = 2F\s+(\S+) ", proc.stdout, re.MULTILINE).group(1))
    assert "global optimum (certified)" in proc.stdout
    ref = mm.centralized_optimum(data.graph)
    assert f == pytest.approx(ref.f, rel=1e-9)
    back = read_g2o(out)
    assert back.has_vertex.all()
    assert float(mm.cost(back.graph, back.initial)) == pytest.approx(ref.f, rel=1e-9)
    _no_temp_files(tmp_path)

    proc = mmpgo("optimum", problem, "--init", "nowhere")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr and "--init" in proc.stderr


def test_version(capsys):
    """``mmpgo --version`` prints the installed version (the one pyproject.toml declares)."""
    import tomllib

    from mmpgo_jax.cli import main

    declared = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["project"]["version"]
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"mmpgo-jax {declared}"


@pytest.mark.slow  # 30 s; the default run keeps test_methods_registry's `mmpgo sweep --methods` and the library's sweep = solve checks
def test_sweep_command_matches_solve(tmp_path):
    """``mmpgo sweep``: every (method, robot count) of a file in one run, its CSV tables written
    together; the final f of each configuration is what ``solve`` gives for the same split."""
    import mmpgo_jax as mg

    cube = mg.cube_dataset(0, num_poses=60, grid=4)
    g2o = tmp_path / "cube60.g2o"
    mg.write_g2o(g2o, cube.graph, cube.ground_truth)
    out, configs = tmp_path / "sweep.csv", tmp_path / "configs.csv"
    proc = mmpgo("sweep", g2o, "-A", "2", "3", "-n", "6", "--robots-from", "metis", "--methods", "amm",
                 "--fstar", "centralized", "--out", out, "--configs", configs)
    _ok(proc)
    with open(out, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 2 * 7  # robot counts x (iterations + the start)
    with open(configs, newline="") as fh:
        finals = {(r["method"], int(r["robots"])): float(r["f"]) for r in csv.DictReader(fh)}
    graph = mg.read_g2o(g2o).graph
    for (method, robots), f in finals.items():
        ref = mg.solve(graph, mg.split_robots(graph, "metis", robots), method=method, iterations=6)
        assert abs(f - float(ref.history.f[-1])) <= 1e-9 * abs(f), (method, robots)
        assert f"| {method.upper()} | {robots} |" in proc.stdout
    assert all(float(r["relative_gap"]) >= -1e-9 for r in rows)
    _no_temp_files(tmp_path)


@pytest.mark.slow  # about 70 s on 2 cores (a child process compiles the robust sweep, then two solves)
def test_sweep_command_losses_and_outlier_rates(tmp_path):
    """``mmpgo sweep --losses ... --outlier-rates ...``: every (kernel, rate) in the tables, with
    precision / recall equal to those of solve on the graph add_outliers makes with the same seed."""
    import mmpgo_jax as mg
    from mmpgo_jax._experiments.outliers import add_outliers, outlier_scores

    cube = mg.cube_dataset(0, num_poses=40, grid=3)
    g2o = tmp_path / "cube40.g2o"
    mg.write_g2o(g2o, cube.graph, cube.ground_truth)
    out, configs = tmp_path / "sweep.csv", tmp_path / "configs.csv"
    proc = mmpgo("sweep", g2o, "-A", "2", "-n", "6", "--methods", "mm", "--losses", "huber", "tls",
                 "--outlier-rates", "0", "40", "--outlier-seed", "3", "--out", out, "--configs", configs)
    _ok(proc)
    assert "| loss | outlier rate % |" in proc.stdout and "| cube40@40% | MM | 2 | tls | 40 |" in proc.stdout
    with open(out, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 2 * 2 * 7 and {r["loss"] for r in rows} == {"huber", "tls"}
    with open(configs, newline="") as fh:
        table = {(r["graph"], r["loss"]): r for r in csv.DictReader(fh)}
    assert set(table) == {(f"cube40@{p}%", k) for p in (0, 40) for k in ("huber", "tls")}
    graph = mg.read_g2o(g2o).graph
    bad = add_outliers(graph, 0.4, reference=mg.chordal_initialization(graph), seed=3)
    assert bad.num_outliers > 0
    for kernel in ("huber", "tls"):
        row = table[("cube40@40%", kernel)]
        assert float(row["outlier_rate"]) == 0.4 and int(row["outliers"]) == bad.num_outliers
        ref = mg.solve(bad.graph, 2, method="mm", iterations=6, loss=kernel, start="gnc-chordal")  # as the sweep
        sc = outlier_scores(ref.inliers, bad.outlier)
        assert float(row["precision"]) == pytest.approx(sc.precision) and float(row["recall"]) == pytest.approx(sc.recall)
        # the default (inexact) inner solver rounds differently on the sweep's padded shape (see
        # tests/test_sweep.py): measured 3e-6 relative here, while a wrong graph or kernel is O(1)
        assert abs(float(row["f"]) - float(ref.history.f[-1])) <= 1e-4 * abs(float(row["f"]))
        assert table[("cube40@0%", kernel)]["recall"] == "1.0"  # nothing to find
    _no_temp_files(tmp_path)


def test_cpu_name_names_model_family_and_avx512():
    """The CPU as records name it: /proc/cpuinfo's model name with family, model and AVX-512 (or its
    absence) on Linux; the platform's processor name elsewhere."""
    from mmpgo_jax.cli.bench import cpu_name

    name = cpu_name()
    proc = Path("/proc/cpuinfo")
    if proc.is_file() and "model name" in proc.read_text():
        has = "avx512f" in proc.read_text().split()
        assert re.search(r"\(family \S+, model \S+, (no )?AVX-512\)$", name), name
        assert name.endswith("no AVX-512)") != has
    else:
        assert name
