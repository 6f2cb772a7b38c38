"""The shared driver: stopping rules, results, and compile-once across calls (solve and solve_sharded)."""

import jax
import numpy as np
import pytest

import mmpgo_jax as mm
from mmpgo_jax._distributed import layout as sharded_module
from mmpgo_jax._mm.driver import RESULTS, Termination
from mmpgo_jax.sharding import solve_sharded


@pytest.fixture(scope="module")
def cube():
    return mm.cube_dataset(0, num_poses=120, grid=4).graph


def test_termination_validates_and_decides():
    with pytest.raises(ValueError, match="chunk_size"):
        Termination(10, 0)
    with pytest.raises(ValueError, match="grad_tol"):
        Termination(10, grad_tol=float("nan"))
    t = Termination(100, 10, grad_tol=1e-3, rel_decrease_tol=1e-6)
    assert t([np.array([5.0]), np.array([4.0])], [np.array([1.0]), np.array([2e-3])]) is None
    assert t([np.array([5.0]), np.array([4.0])], [np.array([1.0]), np.array([5e-4])]) is RESULTS.grad_tol
    assert t([np.array([5.0]), np.array([5.0])], [np.array([1.0]), np.array([1.0])]) is RESULTS.rel_decrease_tol
    assert RESULTS.iterations.describe(t) == "budget of 100 iterations reached"
    assert RESULTS.grad_tol.describe(t) == "||grad F|| <= 0.001"


def test_relative_change_rule_does_not_take_an_increase_for_convergence():
    """rel_change_tol (the distributed chordal start's rule: momentum, f not monotone): |change| <= tol
    |f| stops, a rise beyond it does not (rel_decrease_tol, for monotone methods, stops on a rise)."""
    t = Termination(100, 10, rel_change_tol=1e-6)
    rise = ([np.array([5.0]), np.array([6.0])], [np.array([1.0]), np.array([1.0])])
    assert t(*rise) is None
    assert Termination(100, 10, rel_decrease_tol=1e-6)(*rise) is RESULTS.rel_decrease_tol
    assert t([np.array([5.0]), np.array([5.0 - 1e-7])], [np.array([1.0]), np.array([1.0])]) is RESULTS.rel_change_tol
    assert RESULTS.rel_change_tol.describe(t) == "f changed by at most a relative 1e-06 over the last chunk"


def test_solve_result_is_a_solution(cube):
    res = mm.solve(cube, 4, iterations=30, chunk_size=10, grad_tol=1e9)
    assert res.result is RESULTS.grad_tol and res.stop_reason == "grad_tol" and res.iterations == 10
    assert res.stop_description == "||grad F|| <= 1e+09"
    assert set(res.stats) >= {"init_seconds", "compile_seconds", "solve_seconds"}
    assert res.extra is res.stats and res.solve_seconds == res.stats["solve_seconds"]


def _compiles(fn):
    """Number of XLA compilations logged while ``fn()`` runs."""
    import logging

    from jax._src import dispatch  # noqa: F401  (the logger below lives there)

    seen = []

    class Catch(logging.Handler):
        def emit(self, record):
            if "Finished XLA compilation" in record.getMessage() or "Compiling" in record.getMessage():
                seen.append(record.getMessage())

    logger = logging.getLogger("jax._src.dispatch")
    handler = Catch()
    logger.addHandler(handler)
    try:
        with jax.log_compiles(True):
            fn()
    finally:
        logger.removeHandler(handler)
    return seen


def test_second_solve_with_same_shapes_compiles_nothing_new(cube):
    mm.solve(cube, 4, iterations=20, chunk_size=10)
    again = _compiles(lambda: mm.solve(cube, 4, iterations=20, chunk_size=10, grad_tol=1e-12))
    assert not [m for m in again if "run" in m], again


def test_solve_sharded_twice_compiles_once(cube):
    before = sharded_module.TRACE_COUNT[0]
    a = solve_sharded(cube, 4, devices=1, iterations=20, chunk_size=10)
    b = solve_sharded(cube, 4, devices=1, iterations=20, chunk_size=10)
    assert sharded_module.TRACE_COUNT[0] - before <= 1
    assert b.compile_seconds < 0.5 * max(a.compile_seconds, 1e-3) or b.compile_seconds < 0.05
    np.testing.assert_array_equal(a.history.f, b.history.f)
    # other numbers, same structure: still no new trace (the config is a traced argument)
    solve_sharded(cube, 4, devices=1, iterations=20, chunk_size=10, xi=2e-3)
    assert sharded_module.TRACE_COUNT[0] - before <= 1
