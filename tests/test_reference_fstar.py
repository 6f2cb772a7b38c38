"""The reference f* of every relative gap: the registry's certified optimum where it has one (12
digits, ``benchmarks/certified_optimum.py``), else the published, rounded value; printed and
plotted gaps say which. Independent checks: the published values (SE-Sync's, the paper's) the
certified ones must round to, and our own centralized solve."""

from __future__ import annotations

import dataclasses
import json
from importlib import resources
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

import mmpgo_jax as mm
from mmpgo_jax import BENCHMARKS, FStarReference
from mmpgo_jax._experiments.plots import plot_convergence, printed_half_unit
from mmpgo_jax.cli import main
from mmpgo_jax.cli.inputs import reference_fstar

SHIPPED = [b for b in BENCHMARKS.values() if b.availability == "shipped"]


def _registry_json() -> dict:
    return json.loads(resources.files("mmpgo_jax").joinpath("benchmarks.json").read_text(encoding="utf-8"))


@pytest.mark.parametrize("info", SHIPPED, ids=lambda b: b.name)
def test_registry_holds_a_certified_optimum(info):
    cert = info.ours_certificate
    assert info.ours_fstar is not None and cert is not None
    assert cert["certified"] and cert["negative_eigenvalues"] == 0 and cert["min_eigenvalue"] >= -cert["eta"]
    assert cert["grad_norm"] <= 1e-6
    assert info.certified_fstar == info.ours_fstar
    # the published values are the same optimum, rounded to the digits they print
    if info.sesync_fstar is not None:
        digits = len(f"{info.sesync_fstar:.7g}".replace(".", "").lstrip("0").rstrip("0")) or 1
        assert abs(info.ours_fstar - info.sesync_fstar) <= printed_half_unit(info.sesync_fstar, max(digits, 6)) + 1e-12
    if info.paper_fstar is not None:
        assert abs(info.ours_fstar - info.paper_fstar) <= printed_half_unit(info.paper_fstar, 4)


def test_registry_records_how_the_optima_were_made():
    run = _registry_json()["ours_fstar_run"]
    assert run["command"].startswith("python benchmarks/certified_optimum.py") and run["date"][:4].isdigit()


def test_reference_selection_and_labels():
    mit = BENCHMARKS["MITb"]
    ref = mit.fstar_reference
    assert (ref.source, ref.label, ref.value) == ("certified", "certified f*", mit.ours_fstar)
    assert mit.fstar == mit.ours_fstar
    assert [r.source for r in mit.fstar_references] == ["certified", "sesync", "paper"]
    # a run the certificate did not confirm is never the reference: the published value is
    uncertified = dataclasses.replace(mit, ours_certificate={"certified": False})
    assert uncertified.certified_fstar is None
    assert uncertified.fstar_reference == FStarReference(61.1541, "sesync")
    assert uncertified.fstar_reference.label == "published f* (SE-Sync, rounded)"
    paper_only = BENCHMARKS["ais2klinik"]  # not shipped: no optimum of ours, no SE-Sync value
    assert paper_only.fstar_reference == FStarReference(188.5, "paper")
    assert paper_only.fstar_reference.label == "published f* (paper, 4 digits)"
    assert dataclasses.replace(paper_only, paper_fstar=None).fstar_reference is None


def test_sphere_gap_is_negative_only_against_the_rounded_value():
    # the case: f at (or near) the optimum is below SE-Sync's rounded 1687.01
    sphere = BENCHMARKS["sphere"]
    published = FStarReference(sphere.sesync_fstar, "sesync")
    assert published.gap(sphere.ours_fstar) < -1e-6
    assert sphere.fstar_reference.gap(sphere.ours_fstar) == 0.0


def test_centralized_optimum_matches_the_registry(benchmark_file):
    path = benchmark_file("MIT.g2o")
    res = mm.centralized_optimum(mm.read_g2o(path).graph, chunk_size=1)
    ref = BENCHMARKS["MITb"].fstar_reference
    assert ref.source == "certified"
    assert abs(ref.gap(res.f)) <= 1e-10  # the registry's 12 digits
    assert ref.gap(res.f) >= -1e-12  # never below the certified optimum


@pytest.mark.slow
def test_sphere_optimum_gap_is_not_negative(benchmark_file):
    res = mm.centralized_optimum(mm.read_g2o(benchmark_file("sphere2500.g2o")).graph, chunk_size=1)
    sphere = BENCHMARKS["sphere"]
    assert sphere.fstar_reference.gap(res.f) >= -1e-12
    assert FStarReference(sphere.sesync_fstar, "sesync").gap(res.f) < 0  # what the rounded value gave


def test_cli_solve_says_which_reference(benchmark_file, capsys):
    path = benchmark_file("tinyGrid3D.g2o")
    assert main(["solve", str(path), "-A", "2", "--robots-from", "metis", "-n", "0", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "2 robots (METIS parts)" in out  # the split and the reference, side by side
    ref = BENCHMARKS["tinyGrid3D"].fstar_reference
    assert f"f*          {ref.value:.12g} (certified f*)" in out
    gap_line = next(line for line in out.splitlines() if line.startswith("gap "))
    assert gap_line.endswith("relative to the certified f*")
    assert float(gap_line.split()[1]) >= 0


def test_cli_reference_only_for_the_registered_problem():
    def loaded(name, n, keep=None):
        return SimpleNamespace(path=Path("/data") / name, graph=SimpleNamespace(num_poses=n), keep=keep)

    assert reference_fstar(loaded("MIT.g2o", 808)) == BENCHMARKS["MITb"].fstar_reference
    assert reference_fstar(loaded("my_graph.g2o", 808)) is None  # not a benchmark
    assert reference_fstar(loaded("MIT.g2o", 700, keep=np.arange(700))) is None  # --largest-component part
    assert reference_fstar(loaded("MIT.g2o", 5)) is None  # another graph under a benchmark's name


def _axes():
    fig = Figure()
    FigureCanvasAgg(fig)
    return fig.add_subplot()


def test_plot_draws_every_printed_value_within_the_run():
    fstar = 31.7037158836  # CSAIL: every printed value (31.7) lies below f*
    f = fstar * (1 + np.geomspace(1e-2, 1e-9, 301))
    paper = {100: 31.7, 250: 31.7, 1000: 31.7}
    ax = _axes()
    plot_convergence(ax, {"MM-PGO": f}, fstar, references={"MM-PGO (paper)": paper}, printed_digits=4)
    assert ax.get_xlim()[1] == pytest.approx(300 * 1.02)  # the axis ends with the run
    (bars,) = ax.containers
    x, y = bars.lines[0].get_data()
    np.testing.assert_array_equal(x, [100, 250])  # every printed value within the run, none dropped
    top = (31.705 - fstar) / fstar  # 31.7 stands for [31.695, 31.705)
    segments = bars.lines[2][0].get_segments()
    assert [s[1][1] for s in segments] == pytest.approx([top, top])
    (legend,) = [t.get_text() for t in ax.get_legend().get_texts() if "paper" in t.get_text()]
    assert "k = 1000 after this run" in legend
    # without printed digits, values at or below f* are left out, and the legend says so
    ax = _axes()
    plot_convergence(ax, {"MM-PGO": f}, fstar, references={"MM-PGO (paper)": paper})
    assert len(ax.containers[0].lines[0].get_data()[0]) == 0
    assert any("2 pt(s) ≤ f* not shown" in t.get_text() for t in ax.get_legend().get_texts())
