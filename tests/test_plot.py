"""``mmpgo solve --plot FILE`` and the figure it draws (mmpgo_jax._experiments.plots, issue 33):

* the file is written in the format its extension names (jpg, pdf, svg, png, ...), atomically;
  an extension matplotlib cannot write is refused in one line (exit 2) before anything is read;
* the figure: the start and the result side by side (robots coloured, loop closures and
  inter-robot edges drawn, a 3D graph's x-y top view named in the x label), the relative gap with
  its 1e-2 / 1e-3 / 1e-4 levels labelled and y limits holding the curve and the levels, a legend,
  and a title naming the benchmark (or the file) and the method.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from matplotlib.collections import LineCollection

from mmpgo_jax import cube_dataset, read_g2o, solve
from mmpgo_jax._experiments.plots import check_figure_path, save_solve_figure, solve_figure, solve_start
from mmpgo_jax.cli import inputs, main

DATA = Path(__file__).resolve().parent / "data"
TINY = DATA / "tiny2d.g2o"
SOLVE = ["solve", str(TINY), "--robots", "2", "--iterations", "5", "--no-progress", "--no-compilation-cache"]
MAGIC = {"png": b"\x89PNG\r\n\x1a\n", "jpg": b"\xff\xd8", "jpeg": b"\xff\xd8", "pdf": b"%PDF", "svg": b"<?xml"}


@pytest.fixture(scope="module")
def cube():
    """A small 3D graph with loop closures and inter-robot edges, solved for a few iterations."""
    graph = cube_dataset(0, grid=3, num_poses=60, loop_closure_prob=0.3).graph
    robots = np.repeat(np.arange(3), 20)
    result = solve(graph, robots, iterations=5)
    return graph, result, solve_start(graph, robots)


def _titles(fig) -> list[str]:
    return [ax.get_title() for ax in fig.axes]


def _panel(fig, name: str):
    (ax,) = [ax for ax in fig.axes if ax.get_title().startswith(name)]
    return ax


# --------------------------------------------------------------------------------------------
# the file
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("ext", ["jpg", "pdf", "svg", "png"])
def test_cli_writes_the_format_of_the_extension(tmp_path, capsys, ext):
    path = tmp_path / f"plot.{ext}"
    rc = main([*SOLVE, "--plot", str(path)])
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert path.read_bytes().startswith(MAGIC[ext])
    assert f"wrote {path}" in out.out
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no temporary file left


def test_unsupported_extension_is_refused_before_reading(tmp_path, capsys, monkeypatch):
    def must_not_run(*args, **kwargs):
        raise AssertionError("the input was read before the --plot extension was checked")

    monkeypatch.setattr(inputs, "load_for_solve", must_not_run)
    path = tmp_path / "plot.xyz"
    rc = main([*SOLVE, "--plot", str(path)])
    cap = capsys.readouterr()
    assert rc == 2
    (line,) = cap.err.splitlines()
    assert line.startswith(f"mmpgo: error: --plot {path}: unsupported extension '.xyz'"), line
    assert all(ext in line for ext in ("png", "jpg", "pdf", "svg")), line
    assert cap.out == "" and not path.exists()


def test_figure_path_formats(tmp_path):
    assert check_figure_path("a/b.JPG") == "jpg"  # case does not matter
    assert check_figure_path("plot") == "png"  # no extension: matplotlib's default
    assert check_figure_path(tmp_path / "x.tiff") == "tiff"
    with pytest.raises(ValueError, match=r"^figure x\.txt: unsupported extension '\.txt' \(matplotlib writes .*png"):
        check_figure_path("x.txt")


def test_save_replaces_a_file_atomically(tmp_path, cube):
    graph, result, start = cube
    path = tmp_path / "fig.pdf"
    path.write_text("old")
    save_solve_figure(path, graph, result, start=start)
    assert path.read_bytes().startswith(b"%PDF")
    assert [p.name for p in tmp_path.iterdir()] == ["fig.pdf"]


# --------------------------------------------------------------------------------------------
# the figure
# --------------------------------------------------------------------------------------------


def test_start_and_result_side_by_side(cube):
    graph, result, start = cube
    fig = solve_figure(graph, result, start=start, fstar=float(result.f) * 0.999, title="cube.g2o")
    f = np.asarray(result.history.f)
    for name, poses, value in (("start", start, f[0]), ("result", result.poses, f[-1])):
        ax = _panel(fig, name)
        assert f"{value:.7g}" in ax.get_title()
        assert "top view" in ax.get_xlabel()  # 3D poses, drawn from above
        assert ax.get_aspect() == 1.0
        robot_lines = [ln for ln in ax.get_lines() if ln.get_linestyle() == "-"]
        assert len(robot_lines) >= 3  # one per robot
        # the positions drawn are those of the panel's poses (x-y)
        drawn = np.concatenate([ln.get_xydata() for ln in robot_lines])
        np.testing.assert_allclose(np.sort(drawn[:, 0]), np.sort(np.asarray(poses.t)[:, 0]))
        assert len([c for c in ax.collections if isinstance(c, LineCollection)]) == 2  # loop closures, inter-robot
        (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
        t = np.asarray(poses.t)
        assert x0 < t[:, 0].min() and t[:, 0].max() < x1 and y0 < t[:, 1].min() and t[:, 1].max() < y1
    assert not np.allclose(np.asarray(start.t), np.asarray(result.poses.t))  # two different trajectories
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert {"robot 0 (20 poses)", "robot 1 (20 poses)", "robot 2 (20 poses)", "pose 0"} <= set(labels)
    assert any(lab.startswith("loop closures (") for lab in labels)
    assert any(lab.startswith("inter-robot edges (") for lab in labels)


def test_start_is_the_solvers_start(cube):
    graph, result, start = cube
    from mmpgo_jax._core.pose_graph import cost

    assert float(cost(graph, start)) == pytest.approx(float(result.history.f[0]), rel=1e-9)


def test_gap_panel_labels_the_levels_and_fits_them(cube):
    graph, result, start = cube
    f = np.asarray(result.history.f)
    fstar = float(f[-1]) * (1 - 1e-5)
    fig = solve_figure(graph, result, start=start, fstar=fstar, fstar_label="certified f*")
    ax = _panel(fig, "relative gap to the certified f*")
    assert {"1e-2", "1e-3", "1e-4"} <= {t.get_text() for t in ax.texts}
    gap = (f - fstar) / fstar
    lo, hi = ax.get_ylim()
    assert lo < min(gap.min(), 1e-4) and max(gap.max(), 1e-2) < hi
    assert hi < 10 * max(gap.max(), 1e-2) and lo > min(gap.min(), 1e-4) / 10  # no empty decades
    assert [a.get_xlabel() for a in fig.axes].count("iteration") == 1  # the flat linear f panel is gone


def test_without_fstar_or_start(cube):
    graph, result, _ = cube
    fig = solve_figure(graph, result)  # e.g. the demo, a file that is not a benchmark
    assert [t.split(":")[0] for t in _titles(fig)] == ["result", "objective f = 2F"]
    assert not _panel(fig, "objective").texts  # no tolerance levels without f*


def test_title_names_the_file_and_the_method(cube):
    graph, result, start = cube
    title = solve_figure(graph, result, start=start, title="cube.g2o").get_suptitle()
    assert title.startswith("cube.g2o\n") and "AMM-PGO" in title and "3 robots" in title


def test_title_names_the_registered_benchmark(benchmark_file):
    graph = read_g2o(benchmark_file("MIT.g2o")).graph
    result = solve(graph, 10, iterations=2)
    title = solve_figure(graph, result, title="MIT.g2o").get_suptitle()
    assert title.startswith("MITb (MIT.g2o)\n"), title
    # a file of that name that is not the benchmark keeps its own name
    small = read_g2o(TINY).graph
    assert solve_figure(small, solve(small, 2, iterations=2), title="MIT.g2o").get_suptitle().startswith(
        "MIT.g2o\n")


def test_2d_axes_label():
    graph = read_g2o(TINY).graph
    result = solve(graph, 2, iterations=2)
    fig = solve_figure(graph, result, start=solve_start(graph, np.array([0, 0, 1, 1])))
    assert [ax.get_xlabel() for ax in fig.axes[:2]] == ["x [m]", "x [m]"]
