"""The shared argument checks: messages name the parameter and its range; traced values pass."""

import argparse

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mmpgo_jax._core.validate import (
    check_choice,
    check_count,
    check_flag,
    check_real,
    finite_float,
    int_in,
)


@pytest.mark.parametrize("call, message", [
    (lambda: check_count("Cfg", "n", 0, 1), r"^Cfg\.n must be an integer >= 1, got 0$"),
    (lambda: check_count("Cfg", "n", 2.0, 1), r"Cfg\.n must be an integer >= 1, got 2\.0"),
    (lambda: check_count("Cfg", "n", True, 1), r"Cfg\.n must be an integer >= 1, got True"),
    (lambda: check_count(None, "iterations", -1, 0), r"^iterations must be a non-negative integer, got -1$"),
    (lambda: check_count(None, "k", 11, 0, 10), r"k must be an integer between 0 and 10, got 11"),
    (lambda: check_count(None, "k", "3", 0, optional=True), r"k must be a non-negative integer or None, got '3'"),
    (lambda: check_real("Cfg", "x", -1.0, 0.0), r"^Cfg\.x must be a finite number >= 0, got -1\.0$"),
    (lambda: check_real("Cfg", "x", 0.0, 0.0, 1.0, low_open=True), r"Cfg\.x must be a finite number in \(0, 1\]"),
    (lambda: check_real("Cfg", "x", 1.0, 0.0, 1.0, high_open=True), r"Cfg\.x must be a finite number in \[0, 1\)"),
    (lambda: check_real("Cfg", "x", np.array([0.5, 2.0]), 0.0, 1.0), r"Cfg\.x must be a finite number in \[0, 1\]"),
    (lambda: check_real(None, "tol", float("inf"), 0.0, low_open=True, optional=True),
     r"^tol must be a finite number > 0 or None, got inf$"),
    (lambda: check_real(None, "f", float("nan"), optional=True), r"^f must be a finite number or None, got nan$"),
    (lambda: check_real(None, "tol", np.array([1.0]), 0.0, scalar=True), r"tol must be a finite number >= 0"),
    (lambda: check_choice("Cfg", "mode", "fast", ("a", "b")), r"^Cfg\.mode: unknown mode 'fast': use 'a' or 'b'$"),
    (lambda: check_flag(None, "stop", 1), r"^stop must be True or False, got 1$"),
])
def test_messages(call, message):
    with pytest.raises(ValueError, match=message):
        call()


def test_accepted():
    check_count("Cfg", "n", np.int64(3), 1)
    check_count("Cfg", "n", np.array([1, 2]), 1)
    check_count(None, "n", None, 0, optional=True)
    check_real("Cfg", "x", 1, 0.0, 1.0)
    check_real(None, "tol", np.float32(0.5), 0.0, scalar=True)
    check_real(None, "tol", None, 0.0, optional=True, scalar=True)
    check_choice(None, "mode", "a", ("a", "b"))
    check_flag(None, "stop", False)


def test_traced_values_pass_unless_scalar():
    @jax.jit
    def f(x):
        check_real("Cfg", "x", x, 0.0, 1.0)  # not checkable under jit: accepted
        check_count("Cfg", "n", x.astype(jnp.int32), 1)
        with pytest.raises(ValueError, match="tol must be a finite number >= 0"):
            check_real(None, "tol", x, 0.0, scalar=True)
        return x

    f(jnp.asarray(-3.0))


def test_argparse_types():
    assert int_in(0, 9)("7") == 7 and finite_float(0.0, strict=True)("1e-3") == 1e-3
    for parse, text, message in [
        (int_in(1), "0", "must be an integer >= 1, got '0'"),
        (int_in(0, 2147483647), "1.5", "must be an integer between 0 and 2147483647, got '1.5'"),
        (finite_float(0.0), "-1", "must be a finite number >= 0, got '-1'"),
        (finite_float(0.0, strict=True), "0", "must be a finite number > 0, got '0'"),
        (finite_float(0.0), "nan", "must be a finite number >= 0, got 'nan'"),
    ]:
        with pytest.raises(argparse.ArgumentTypeError) as err:
            parse(text)
        assert str(err.value) == message
