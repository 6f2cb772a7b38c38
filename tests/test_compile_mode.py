"""The compile mode: which programs compile the fast way, the setting's sources and checks, the
fallback when XLA no longer knows the option, and the same solution either way."""

import re
from pathlib import Path
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mmpgo_jax as mm
from mmpgo_jax._core import compile_mode as cm
from mmpgo_jax._core.partition import partition

TINY = Path(__file__).parent / "data" / "tiny2d.g2o"


@pytest.fixture
def mode():
    """Restore the process's mode after a test that sets it."""
    yield
    cm._mode = None


def test_auto_compiles_small_programs_fast(mode, monkeypatch):
    monkeypatch.delenv(cm.ENV, raising=False)
    assert cm.compile_mode() == "auto"
    assert cm.compiler_options(cm.FAST_COMPILE_SLOTS) == {"xla_cpu_use_fusion_emitters": False}
    assert cm.compiler_options(cm.FAST_COMPILE_SLOTS + 1) is None
    assert cm.compiler_options(None) is None  # size unknown: XLA's defaults


def test_a_program_run_once_compiles_at_llvm_level_0_the_fast_way_only(mode, monkeypatch):
    monkeypatch.delenv(cm.ENV, raising=False)
    once = cm.compiler_options(cm.FAST_COMPILE_SLOTS, once=True)
    assert once == {"xla_cpu_use_fusion_emitters": False, "xla_backend_optimization_level": 0}
    assert cm.compiler_options(cm.FAST_COMPILE_SLOTS + 1, once=True) is None  # a large start: XLA's defaults
    mm.set_compile_mode("optimized")
    assert cm.compiler_options(10, once=True) is None


def test_a_solves_start_program_is_compiled_as_run_once(mode, monkeypatch):
    """The start state's program gets the run-once options, the loop's chunk does not; both compile,
    and the run reaches the optimized build's iterates to rounding."""
    from mmpgo_jax._core import compilation_cache
    from mmpgo_jax._mm import driver

    seen = []

    def recording(lowered, options):
        seen.append(options)
        return cm.compile_lowered(lowered, options)

    monkeypatch.setattr(driver, "compile_lowered", recording)
    monkeypatch.setattr(compilation_cache, "compile_lowered", recording)
    monkeypatch.setattr(driver, "_COMPILED", {})
    monkeypatch.setenv("MMPGO_COMPILATION_CACHE", "off")
    graph = mm.read_g2o(TINY).graph
    mm.set_compile_mode("fast")
    fast = mm.solve(graph, 2, iterations=20, stop_when_stalled=False)
    levels = [(o or {}).get("xla_backend_optimization_level") for o in seen]
    assert levels.count(0) == 1 and len(levels) == 2, seen  # the start (level 0) and the chunk
    mm.set_compile_mode("optimized")
    opt = mm.solve(graph, 2, iterations=20, stop_when_stalled=False)
    np.testing.assert_allclose(fast.history.f, opt.history.f, rtol=1e-9)


def test_modes_force_one_way(mode, monkeypatch):
    monkeypatch.setenv(cm.ENV, "optimized")
    assert cm.compiler_options(10) is None
    mm.set_compile_mode("fast")  # the call wins over the environment
    assert cm.compiler_options(10**9) == {"xla_cpu_use_fusion_emitters": False}


def test_bad_modes_are_refused(mode, monkeypatch):
    with pytest.raises(ValueError, match="compile mode must be one of auto, fast, optimized"):
        mm.set_compile_mode("quick")
    monkeypatch.setenv(cm.ENV, "quick")
    with pytest.raises(ValueError, match="MMPGO_COMPILE_MODE must be one of"):
        cm.compile_mode()


def test_program_slots_of_a_problem():
    """The padded pose slots of the first argument with a partition (a solver problem)."""
    graph = mm.read_g2o(TINY).graph
    part = partition(graph, mm.contiguous_robots(graph.num_poses, 3))
    problem = SimpleNamespace(partition=part)
    assert cm.program_slots((1, problem, "x")) == part.num_robots * part.max_poses >= graph.num_poses
    assert cm.program_slots((1, 2)) is None
    assert cm.program_slots((SimpleNamespace(pose_slots=7),)) == 7  # the distributed chordal start's stages


def test_an_unknown_option_falls_back_to_xla_defaults(monkeypatch):
    """A later XLA without the option: the program still compiles (with XLA's defaults) and computes
    the same values; any other compile error is raised."""
    lowered = jax.jit(lambda x: jnp.sin(x) * 2.0 + jnp.sum(x)).lower(jnp.arange(4.0))
    monkeypatch.setattr(cm, "_FAST", {"xla_cpu_use_fusion_emitters_gone": False})
    monkeypatch.setattr(cm, "_mode", "fast")
    compiled = cm.compile_lowered(lowered, cm.compiler_options(1))
    x = jnp.arange(4.0)
    np.testing.assert_allclose(compiled(x), jnp.sin(x) * 2.0 + jnp.sum(x), rtol=1e-6)
    monkeypatch.setattr(cm, "_FAST", {})
    monkeypatch.setattr(cm, "_ONCE", {"xla_backend_optimization_level_gone": 0})
    np.testing.assert_allclose(cm.compile_lowered(lowered, cm.compiler_options(1, once=True))(x),
                               jnp.sin(x) * 2.0 + jnp.sum(x), rtol=1e-6)
    monkeypatch.setattr(cm, "_FAST", {"no_such_xla_option": False})
    with pytest.raises(Exception, match="no_such_xla_option"):
        cm.compile_lowered(lowered, cm.compiler_options(1))


def test_both_modes_reach_the_same_solution(mode):
    """The fast and the optimized programs of one run: the same f to rounding (different code
    generators may round differently), every iteration."""
    graph = mm.read_g2o(TINY).graph
    runs = {}
    for m in ("fast", "optimized"):
        mm.set_compile_mode(m)
        runs[m] = mm.solve(graph, 2, iterations=30, stop_when_stalled=False)
    fast, opt = runs["fast"].history.f, runs["optimized"].history.f
    np.testing.assert_allclose(fast, opt, rtol=1e-9)
    assert {m: r.stats["compile_mode"] for m, r in runs.items()} == {"fast": "fast", "optimized": "optimized"}


def test_the_cli_names_the_mode_in_its_time_line(mode, monkeypatch, capsys):
    from mmpgo_jax.cli import main

    monkeypatch.delenv(cm.ENV, raising=False)
    assert main(["solve", str(TINY), "--robots", "2", "-n", "5", "--no-progress", "--no-compilation-cache"]) == 0
    assert re.search(r"compile [0-9.]+ s \(fast\),", capsys.readouterr().out)  # a tiny graph: auto -> fast
    assert main(["solve", str(TINY), "--robots", "2", "-n", "5", "--no-progress", "--no-compilation-cache",
                 "--compile-mode", "optimized"]) == 0
    assert re.search(r"compile [0-9.]+ s \(optimized\),", capsys.readouterr().out)
