"""How XLA:CPU compiles the solver's programs: quickly, or for the fastest iterations.

XLA:CPU turns a program's fused kernels into machine code through its MLIR fusion emitters (XLA's
default) or through its older LLVM IR emitters (``xla_cpu_use_fusion_emitters=False``). Measured on
the benchmark files (``benchmarks/compile_mode.md``, AMM, 10 robots, 2-core AMD EPYC): with the older
emitters the CLI's whole compile phase takes 1.4-2.0 s instead of 2.1-3.0 s (0.55-0.94 s less on
every file, 0.74-1.01 s on the held-out ones, 1.1 s less for a TLS run), and the iterations run 0-5 %
slower in warm interleaved runs (XLA then executes the loop closures' scatter-adds and some layout
changes as small loops instead of fused kernels). The saving is a fixed amount per compiled
program; the cost grows with the iterations' work. So ``"auto"``
(the default) compiles programs of at most :data:`FAST_COMPILE_SLOTS` padded pose slots (all the
benchmark files at 10 robots) the fast way, where 1000 iterations at the measured 5 % lose less
than the compile saves, and larger programs for the fastest iterations; ``"fast"`` and
``"optimized"`` force one or the other. A per-program compiler option: no global XLA flag is set.
Only the CPU backend has the choice; on a GPU the setting has no effect.

A program a run calls once (a solver's start state: f, the gradient and the weights at X^0, one
iteration's work) compiled the fast way is also compiled at LLVM's optimization level 0: its code
runs slower (about 5x, measured on the loop) but once, and it compiles in about a third of the time
(MIT, 10 robots, 2-core Intel Xeon: 0.07-0.08 s against 0.20 s, `benchmarks/compile_mode.md`).
"""

from __future__ import annotations

import os

import jax
import numpy as np

ENV = "MMPGO_COMPILE_MODE"
MODES = ("auto", "fast", "optimized")
#: Programs with at most this many padded pose slots (robots x poses per robot, times the
#: configurations of a sweep) compile the fast way under "auto": about 1.5 ms per iteration at
#: 10^4 slots on the measured CPU, so 5 % of 1000 iterations is ~0.1 s at 2 * 10^4 against the
#: 0.6-0.8 s the fast compile saves.
FAST_COMPILE_SLOTS = 20_000
_FAST = {"xla_cpu_use_fusion_emitters": False}
_ONCE = {"xla_backend_optimization_level": 0}  # added for a program run once (module docstring)
_mode: str | None = None


def set_compile_mode(mode: str) -> None:
    """``"auto"`` (default), ``"fast"`` or ``"optimized"`` for the programs compiled from now on in
    this process (see the module docstring). Programs already compiled are kept."""
    if mode not in MODES:
        raise ValueError(f"compile mode must be one of {', '.join(MODES)}, got {mode!r}")
    global _mode
    _mode = mode


def compile_mode() -> str:
    """The mode in use: :func:`set_compile_mode`'s, else ``MMPGO_COMPILE_MODE``, else ``"auto"``."""
    if _mode is not None:
        return _mode
    value = os.environ.get(ENV, "auto").strip().lower() or "auto"
    if value not in MODES:
        raise ValueError(f"{ENV} must be one of {', '.join(MODES)}, got {value!r}")
    return value


def program_slots(args) -> int | None:
    """The padded pose slots of a program's arguments: those of the first argument with a
    ``partition`` (every solver problem has one) or a ``pose_slots`` count (the distributed chordal
    start's stages), or None."""
    for a in args:
        part = getattr(a, "partition", None)
        if part is not None and hasattr(part, "pose_mask"):
            return int(np.size(part.pose_mask))
        slots = getattr(a, "pose_slots", None)
        if isinstance(slots, int):
            return slots
    return None


def compiler_options(slots: int | None, once: bool = False) -> dict | None:
    """XLA compiler options for a program of ``slots`` padded pose slots, or None (XLA's defaults).
    ``once``: the program runs once per run (its fast way is then LLVM's level 0 too)."""
    if jax.default_backend() != "cpu":
        return None
    mode = compile_mode()
    if mode == "fast" or (mode == "auto" and slots is not None and slots <= FAST_COMPILE_SLOTS):
        return {**_FAST, **_ONCE} if once else dict(_FAST)
    return None


def code_generation(slots: int | None) -> str:
    """How a program of ``slots`` padded pose slots is compiled now: ``"fast"``, ``"optimized"``
    (XLA:CPU's default), or ``"default"`` off the CPU backend (a run's ``stats["compile_mode"]``)."""
    if jax.default_backend() != "cpu":
        return "default"
    return "fast" if compiler_options(slots) else "optimized"


def compile_lowered(lowered, options: dict | None):
    """``lowered.compile()`` with the XLA ``options`` of :func:`compiler_options`; an XLA that no
    longer knows the option compiles with its defaults (the choice moves compile and run time and
    rounding only)."""
    if options is None:
        return lowered.compile()
    try:
        return lowered.compile(compiler_options=options)
    except Exception as err:  # an unknown option: XLA's message names it
        if not any(name in str(err) for name in ("fusion_emitters", "backend_optimization_level")):
            raise
        return lowered.compile()
