"""The methods by name (``mmpgo_jax._solve.methods``): the registry's solvers, ``solve(method=...)``,
``sweep(methods=...)`` with RBCD / RBCD++ beside AMM, and ``mmpgo solve --method``."""

from __future__ import annotations

import equinox as eqx
import numpy as np
import pytest

import mmpgo_jax as mm
from mmpgo_jax._baselines.rbcd import RBCD
from mmpgo_jax._experiments.sweep import TRACE_COUNTS, sweep
from mmpgo_jax._mm.solvers import AMM, MM, as_solver
from mmpgo_jax._solve.methods import METHOD_NAMES, method_label, method_name, solver_for
from mmpgo_jax.cli import main

TINY = "tests/data/tiny2d.g2o"


def _dgs_available() -> bool:
    try:
        solver_for("dgs")
    except ValueError as err:
        assert str(err).startswith("DGS is not available as a solver yet")
        return False
    return True


@pytest.fixture(scope="module")
def graph():
    return mm.cube_dataset(0, num_poses=40, grid=3).graph


def test_names_give_their_solvers():
    assert METHOD_NAMES[:4] == ("mm", "amm", "rbcd", "rbcd++") and METHOD_NAMES[-1] == "dgs"
    # mm / amm exactly as as_solver makes them (the solve shortcut's solvers, bit for bit)
    for name, cls in (("mm", MM), ("amm", AMM)):
        s = solver_for(name)
        assert type(s) is cls and eqx.tree_equal(s, as_solver(method=name))
    assert solver_for("amm", xi=0.1, restart="paper").config.restart == "paper"
    for name in METHOD_NAMES:
        if name in ("mm", "amm", "dgs"):
            continue
        s = solver_for(name)
        assert isinstance(s, RBCD)
        assert s.accelerated == ("++" in name)
        assert s.selection == (name.split("-", 1)[1] if "-" in name else "greedy")
        assert method_name(s) == name  # the key results use
    assert method_name(RBCD(selection="parallel", accelerated=True)) == "rbcd++-parallel"
    given = RBCD(seed=3)
    assert solver_for(given) is given
    assert [method_label(n) for n in ("mm", "amm", "rbcd++", "rbcd-parallel", "dgs")] == [
        "MM-PGO", "AMM-PGO", "RBCD++", "RBCD (parallel)", "DGS"]
    if _dgs_available():
        assert method_name(solver_for("dgs")) == "dgs"


def test_bad_names_and_shortcuts_are_refused():
    with pytest.raises(ValueError, match="unknown method 'gd': use one of mm, amm, rbcd"):
        solver_for("gd")
    with pytest.raises(TypeError, match="method must be a method name"):
        solver_for(3)
    with pytest.raises(ValueError, match=r"restart applies to the methods 'mm' and 'amm' only, not to 'rbcd\+\+'"):
        solver_for("rbcd++", restart="paper")
    with pytest.raises(ValueError, match="xi, subproblem apply to the methods"):
        solver_for(RBCD(), xi=0.1, subproblem=mm.SubproblemConfig())


def test_solve_by_name_equals_the_solver(graph):
    kw = dict(iterations=6, chunk_size=3, stop_when_stalled=False)
    by_name = mm.solve(graph, 3, method="rbcd++", **kw)
    by_solver = mm.solve(graph, 3, solver=RBCD(accelerated=True), **kw)
    np.testing.assert_array_equal(by_name.history.f, by_solver.history.f)
    np.testing.assert_array_equal(np.asarray(by_name.poses.t), np.asarray(by_solver.poses.t))
    assert method_name(by_name.solver) == "rbcd++" and by_name.config is None
    with pytest.raises(ValueError, match="restart applies to the methods 'mm' and 'amm' only, not to 'rbcd'"):
        mm.solve(graph, 3, method="rbcd", restart="paper", **kw)
    with pytest.raises(ValueError, match="loss 'huber': the method 'rbcd' minimises the least-squares F only"):
        mm.solve(graph, 3, method="rbcd", loss="huber", **kw)
    with pytest.raises(ValueError, match="give method inside the solver"):
        mm.solve(graph, 3, method="rbcd", solver=RBCD(), **kw)


def test_dgs_by_name_runs_or_says_why(graph):
    if _dgs_available():
        r = mm.solve(graph, 3, method="dgs", iterations=4, chunk_size=2)
        assert method_name(r.solver) == "dgs" and np.isfinite(r.f)
    else:
        with pytest.raises(ValueError, match="DGS is not available as a solver yet"):
            mm.solve(graph, 3, method="dgs", iterations=4)


def test_sweep_of_rbcd_plus_plus_matches_solve(graph):
    """RBCD++ (its restart a while_loop under vmap) over robot counts 2 and 3 in one batch: each
    configuration's f history equals its solve's (the default run's share of the test below)."""
    res = sweep({"g": graph}, [2, 3], methods="rbcd++", iterations=4, chunk_size=4, group_by="method")
    assert res.groups[0]["configs"] == 2 and res.groups[0]["batches"] == 1
    for a in (2, 3):
        ref = mm.solve(graph, a, solver=RBCD(accelerated=True), iterations=4, chunk_size=4, stop_when_stalled=False)
        np.testing.assert_allclose(res.history("g", a, "rbcd++"), ref.history.f, rtol=1e-10, atol=0)


@pytest.mark.slow  # four methods, each compiled for the sweep and for two solves: ~1-2 min
def test_sweep_of_amm_and_rbcd_matches_solve(graph):
    """Each method its own compiled batch (robot counts 2 and 3 padded into one vmapped batch), every
    configuration's f history equal to its solve's; results keyed by the method names."""
    its, robots = 6, [2, 3]
    before = dict(TRACE_COUNTS)
    methods = ("amm", "rbcd", "rbcd++", *(("dgs",) if _dgs_available() else ()))
    res = sweep({"g": graph}, robots, methods=methods, iterations=its, chunk_size=3, group_by="method")
    assert res.methods == list(methods)
    assert [g["method"] for g in res.groups] == list(methods)
    assert all(g["configs"] == 2 and g["batches"] == 1 and g["A"] == 3 for g in res.groups)
    for m in res.methods:
        assert TRACE_COUNTS[m] - before.get(m, 0) <= 1  # one trace per method (0: a cache hit)
        for a in robots:
            ref = mm.solve(graph, a, method=m, iterations=its, chunk_size=3, stop_when_stalled=False)
            np.testing.assert_allclose(res.history("g", a, m), ref.history.f, rtol=1e-10, atol=0, err_msg=f"{m} {a}")
            assert method_name(res.results[("g", a, m)].solver) == m


def test_sweep_method_names_and_options_are_checked(graph):
    with pytest.raises(ValueError, match="two methods of the sweep are named 'rbcd'"):
        sweep(graph, [2], methods=(RBCD(), RBCD(seed=1)), iterations=1)
    with pytest.raises(ValueError, match="two methods of the sweep are named 'rbcd'"):
        sweep(graph, [2], methods=("rbcd", RBCD(inner=mm.SubproblemConfig())), iterations=1)
    with pytest.raises(ValueError, match=r"a sequence of xi .* 'rbcd' keeps its own settings"):
        sweep(graph, [2], methods=("amm", "rbcd"), xi=[1e-3, 1e-2], iterations=1)
    with pytest.raises(ValueError, match="restart applies to the methods 'amm' given by name"):
        sweep(graph, [2], methods=("mm", "rbcd"), restart="paper", iterations=1)
    with pytest.raises(ValueError, match="xi applies to the methods 'mm' and 'amm' given by name"):
        sweep(graph, [2], methods=("rbcd++",), xi=0.1, iterations=1)
    with pytest.raises(ValueError, match="the method 'rbcd' minimises the least-squares F only"):
        sweep(graph, [2], methods=("amm", "rbcd"), loss=["l2", "huber"], iterations=1)
    with pytest.raises(ValueError, match="unknown method 'gd'"):
        sweep(graph, [2], methods=("gd",), iterations=1)


@pytest.mark.slow  # two more compilations of the sweep's chunk
def test_sweep_mapping_labels_two_rbcd_solvers(graph):
    res = sweep(graph, [2], methods={"greedy": RBCD(), "seeded": RBCD(selection="uniform", seed=5)}, iterations=2,
                chunk_size=2)
    assert res.methods == ["greedy", "seeded"]
    ref = mm.solve(graph, 2, solver=RBCD(selection="uniform", seed=5), iterations=2, chunk_size=2,
                   stop_when_stalled=False)
    np.testing.assert_allclose(res.history("graph0", 2, "seeded"), ref.history.f, rtol=1e-10)


def test_cli_solve_method_rbcd(capsys):
    assert main(["solve", TINY, "-A", "2", "--method", "rbcd", "-n", "20", "--no-progress",
                 "--no-compilation-cache"]) == 0
    out = capsys.readouterr().out
    assert "method      RBCD, 2 robots" in out


def test_cli_baseline_options_refused_in_one_line(capsys):
    for argv, message in (
        (["--restart", "paper", "--method", "rbcd"], "--restart applies to --method amm, not rbcd"),
        (["--xi", "0.1", "--method", "rbcd++"], "--xi applies to --method mm and amm, not rbcd++"),
        (["--loss", "huber", "--method", "rbcd"], "--loss huber: --method rbcd minimises the least-squares F only"),
        (["--restart", "paper", "--method", "mm"], "--restart applies to --method amm, not mm"),
    ):
        assert main(["solve", TINY, "-A", "2", "-n", "2", "--no-progress", *argv]) == 2
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and err[0].startswith("mmpgo: error: ") and message in err[0], err


def test_cli_solve_dgs(capsys):
    rc = main(["solve", TINY, "-A", "2", "--method", "dgs", "-n", "5", "--no-progress", "--no-compilation-cache"])
    cap = capsys.readouterr()
    if _dgs_available():
        assert rc == 0 and "method      DGS, 2 robots" in cap.out
    else:
        assert rc == 2 and cap.err.strip() == ("mmpgo: error: DGS is not available as a solver yet (mmpgo_jax.dgs "
                                               "runs it on its own)")


def test_cli_sweep_methods(capsys):
    assert main(["sweep", TINY, "-A", "2", "-n", "4", "--methods", "amm", "rbcd", "--fstar", "none",
                 "--no-progress", "--no-compilation-cache"]) == 0
    out = capsys.readouterr().out
    assert "| tiny2d | AMM | 2 |" in out and "| tiny2d | RBCD | 2 |" in out
    for argv, message in ((["--methods", "rbcd", "--restart", "paper"], "--restart applies to amm"),
                          (["--methods", "mm", "rbcd", "--losses", "huber"],
                           "--losses huber: rbcd minimises the least-squares F only")):
        assert main(["sweep", TINY, "-A", "2", "-n", "2", *argv]) == 2
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and err[0].startswith("mmpgo: error: ") and message in err[0], err


@pytest.mark.skipif(not _dgs_available(), reason="DGS is not a solver yet")
def test_sweep_of_dgs_ends_each_history_where_its_rule_held():
    """DGS's own stopping rule holds at different iterations for 2 and 3 robots of one batch: each
    configuration's history ends where its rule held, equal to its solve's."""
    graph = mm.read_g2o(TINY).graph
    res = sweep({"t": graph}, [2, 3], methods="dgs", iterations=40, chunk_size=10, group_by="method")
    lengths = set()
    for a in (2, 3):
        ref = mm.solve(graph, a, method="dgs", iterations=40, chunk_size=10, stop_when_stalled=False)
        got = res.results[("t", a, "dgs")]
        assert got.result == ref.result == mm.RESULTS.converged
        np.testing.assert_allclose(got.history.f, ref.history.f, rtol=1e-10, atol=0)
        lengths.add(len(got.history.f))
    assert len(lengths) == 2  # the two configurations stopped at different iterations
