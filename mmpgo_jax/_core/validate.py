"""Argument checks shared by every layer: one wording for every "bad value" error.

A check raises ValueError naming the owner and parameter (``MMConfig.xi``, or a bare ``tol``) and the
allowed range, so a user learns what to change without reading code. Configs that are equinox
modules are also built under ``jit`` / ``vmap``, where their fields are tracers: those values cannot
be inspected and are accepted unchecked (``scalar=True`` rejects them instead, for host-side
arguments that must be one concrete number). The argparse types (:func:`int_in`,
:func:`finite_float`) word their ranges the same way, so the command line and the Python API agree.
"""

from __future__ import annotations

import argparse
import math

import jax
import numpy as np

__all__ = [
    "check_choice",
    "check_count",
    "check_flag",
    "check_real",
    "concrete_value",
    "count_text",
    "finite_float",
    "int_in",
    "param_name",
    "real_text",
]


def concrete_value(x):
    """``x`` as a numpy array, or None when it is traced (under jit / vmap: not checkable)."""
    try:
        return np.asarray(x)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return None


def param_name(owner: str | None, name: str) -> str:
    """How an error names a parameter: ``owner.name``, or ``name`` alone for a function's argument."""
    return f"{owner}.{name}" if owner else name


def count_text(low: int, high: int | None = None, *, symbols: bool = False) -> str:
    """The allowed range of an integer, e.g. "an integer >= 1" or "an integer between 0 and 9";
    ``low`` 0 reads "a non-negative integer" in the library's messages and "an integer >= 0" with
    ``symbols`` (the command line's options, which state every range as a comparison)."""
    if high is not None:
        return f"an integer between {low} and {high}"
    return "a non-negative integer" if low == 0 and not symbols else f"an integer >= {low}"


def real_text(low: float | None = None, high: float | None = None, *,
              low_open: bool = False, high_open: bool = False) -> str:
    """The allowed range of a real number, e.g. "a finite number in (0, 1]" or "... >= 0"."""
    if low is not None and high is not None:
        lo, hi = "(" if low_open else "[", ")" if high_open else "]"
        return f"a finite number in {lo}{low:g}, {high:g}{hi}"
    if low is not None:
        return f"a finite number {'>' if low_open else '>='} {low:g}"
    if high is not None:
        return f"a finite number {'<' if high_open else '<='} {high:g}"
    return "a finite number"


def _numbers(value, kinds: str, scalar: bool):
    """``value`` as a numpy array of numbers of dtype ``kinds``; None if it is not one (wrong type,
    empty, or -- with ``scalar`` -- not one concrete number); ``...`` when traced (not checkable)."""
    if isinstance(value, bool):  # True is an int to Python, never a count or a tolerance
        return None
    v = concrete_value(value)
    if v is None:
        return None if scalar else ...
    if v.dtype.kind not in kinds or v.size == 0 or (scalar and v.ndim != 0):
        return None
    return v


def _fail(owner, name, text: str, value, optional: bool):
    raise ValueError(f"{param_name(owner, name)} must be {text}{' or None' if optional else ''}, got {value!r}")


def check_choice(owner: str | None, name: str, value, allowed) -> None:
    """``value`` is one of the strings ``allowed``."""
    if not isinstance(value, str) or value not in allowed:
        options = " or ".join(repr(a) for a in allowed)
        raise ValueError(f"{param_name(owner, name)}: unknown {name} {value!r}: use {options}")


def check_count(owner: str | None, name: str, value, low: int, high: int | None = None, *,
                optional: bool = False, scalar: bool = False) -> None:
    """A Python or numpy integer (arrays: every element) with ``low <= value (<= high)``; None too
    with ``optional``. Traced values are accepted unchecked unless ``scalar`` (one concrete number)."""
    if optional and value is None:
        return
    v = _numbers(value, "iu", scalar)
    if v is ...:
        return
    if v is None or np.any(v < low) or (high is not None and np.any(v > high)):
        _fail(owner, name, count_text(low, high), value, optional)


def check_real(owner: str | None, name: str, value, low: float | None = None, high: float | None = None, *,
               low_open: bool = False, high_open: bool = False, optional: bool = False,
               scalar: bool = False) -> None:
    """A finite real number in [low, high] (open at an end with ``low_open`` / ``high_open``; None:
    unbounded there); arrays are checked elementwise; None too with ``optional``. Traced values (under
    jit / vmap) are accepted unchecked unless ``scalar`` (one concrete number)."""
    if optional and value is None:
        return
    v = _numbers(value, "iuf", scalar)
    if v is ...:
        return
    ok = v is not None
    if ok:
        v = v.astype(np.float64)
        ok = bool(np.all(np.isfinite(v)))
        ok = ok and (low is None or bool(np.all(v > low if low_open else v >= low)))
        ok = ok and (high is None or bool(np.all(v < high if high_open else v <= high)))
    if not ok:
        _fail(owner, name, real_text(low, high, low_open=low_open, high_open=high_open), value, optional)


def check_flag(owner: str | None, name: str, value) -> None:
    """``value`` is True or False (not merely truthy: a misplaced positional argument would be)."""
    if not isinstance(value, bool):
        raise ValueError(f"{param_name(owner, name)} must be True or False, got {value!r}")


# --- argparse types: the same ranges, worded for a command line ------------------------------


def int_in(low: int, high: int | None = None):
    """argparse ``type``: an integer with ``low <= value (<= high)``."""

    def parse(text: str) -> int:
        try:
            value = int(text, 10)
        except (TypeError, ValueError):
            value = None
        if value is None or value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"must be {count_text(low, high, symbols=True)}, got {text!r}")
        return value

    parse.__name__ = "integer"
    return parse


def finite_float(low: float, *, strict: bool = False, below: float | None = None):
    """argparse ``type``: a finite number ``>= low`` (``> low`` with ``strict``) and, with ``below``,
    ``< below``."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except (TypeError, ValueError):
            value = math.nan
        if not math.isfinite(value) or value < low or (strict and value == low) or \
                (below is not None and value >= below):
            allowed = real_text(low, below, low_open=strict, high_open=below is not None)
            raise argparse.ArgumentTypeError(f"must be {allowed}, got {text!r}")
        return value

    parse.__name__ = "number"
    return parse
