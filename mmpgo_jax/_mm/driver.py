"""The one driver of the compiled outer loop: init, chunks of steps, terminate.

Every way of laying a run out — one device (:func:`~mmpgo_jax.solve`), robots sharded over a mesh
(:func:`~mmpgo_jax.sharding.solve_sharded`) — builds its start state and one compiled chunk of
``length`` outer iterations (``lax.scan`` over :func:`~mmpgo_jax.step`), then hands both to
:func:`drive`, which runs chunks until the budget or a stopping rule ends the run, and records
the history. Stopping rules, the history, the non-finite guard and the result enum live here once,
in the spirit of optimistix's ``init / step / terminate`` and ``Solution(value, result, stats)``.

:func:`compile_once` keeps compiled chunks per (function, static arguments, argument shapes), so a
second run of the same shapes and configuration structure does not compile again; the numbers
of a configuration (ξ, tolerances, restart constants) are traced arguments.
"""

from __future__ import annotations

import enum
import time
from collections.abc import Callable
from dataclasses import dataclass

import jax
import numpy as np

from .._core.compilation_cache import compile_exported
from .._core.compile_mode import compile_lowered, compiler_options, program_slots
from .._core.validate import check_count, check_flag, check_real

__all__ = ["RESULTS", "STALL_EPS", "History", "Monitor", "NonFiniteError", "Termination", "compile_once", "drive"]


class RESULTS(enum.Enum):
    """Why a run stopped (``SolveResult.result``; ``.value`` is the short name, ``describe`` says it in words)."""

    iterations = "iterations"
    grad_tol = "grad_tol"
    f_target = "f_target"
    rel_decrease_tol = "rel_decrease_tol"
    rel_change_tol = "rel_change_tol"
    stalled = "stalled"
    callback = "callback"
    converged = "converged"

    def describe(self, termination: Termination) -> str:
        t = termination
        if self is RESULTS.iterations:
            return f"budget of {t.iterations} iterations reached"
        if self is RESULTS.grad_tol:
            return f"||grad F|| <= {t.grad_tol:g}"
        if self is RESULTS.f_target:
            return f"f <= {t.f_target:g}"
        if self is RESULTS.rel_decrease_tol:
            return f"f fell by less than a relative {t.rel_decrease_tol:g} over the last chunk"
        if self is RESULTS.rel_change_tol:
            return f"f changed by at most a relative {t.rel_change_tol:g} over the last chunk"
        if self is RESULTS.stalled:
            return (f"stationary: f moved by at most {STALL_EPS} x machine epsilon (relative) over the last "
                    f"{t.length} iterations, i.e. only by rounding")
        if self is RESULTS.converged:
            return "the solver's own stopping rule held"
        return "stopped by the callback"


class Monitor:
    """Hooks to watch a run from outside (e.g. the CLI's progress bar); each does nothing here.

    ``phase(name)``: a phase begins: "initializing" (partition, start poses), "building" (the
    majorization data, the state at the start), "compiling", "iterating" (the compiled chunks;
    their time alone is ``solve_seconds``), "finishing" (the iterations are over; the result is
    being put together). ``chunk(done, f, grad_norm)``: after each chunk, with
    the iterations so far and the chunk's f = 2F and ||grad F||. Unlike ``callback`` it cannot stop
    the run, and it needs no fetch beyond the one the driver does anyway. ``note(text)``: how the
    phase under way is getting on, for phases that take long on their own (the GNC start's stages).
    """

    def phase(self, name: str) -> None:
        """Called when phase ``name`` begins."""

    def chunk(self, done: int, f: np.ndarray, grad_norm: np.ndarray) -> None:
        """Called after each chunk of iterations."""

    def note(self, text: str) -> None:
        """Called with a line of text on the phase under way."""


class NonFiniteError(ValueError):
    """f or its gradient became NaN or infinite during a solve (no result is returned)."""


@dataclass(frozen=True)
class History:
    """Per-iteration history; index k is the state after k outer iterations (k = 0: the start)."""

    f: np.ndarray  # (K+1,) f = 2F (the paper's tables)
    grad_norm: np.ndarray  # (K+1,) ||grad F|| (Riemannian)
    restarts: np.ndarray  # (K+1, A) bool: robot fell back to the MM step in iteration k

    @property
    def iterations(self) -> int:
        return len(self.f) - 1

    def first_below(self, target: float) -> int | None:
        """First iteration k with f[k] <= target, or None."""
        hit = np.flatnonzero(self.f <= target)
        return int(hit[0]) if len(hit) else None


@dataclass(frozen=True)
class Termination:
    """When a driven run stops: after ``iterations`` (an upper bound), or — checked after each chunk
    of ``chunk_size`` iterations — when ||grad F|| <= ``grad_tol``, f <= ``f_target``, f fell by less
    than a relative ``rel_decrease_tol`` over the last chunk, f changed by at most a relative
    ``rel_change_tol`` (up or down) over it, or (``stop_when_stalled``, on by
    default) f stayed within ``STALL_EPS`` machine epsilons (relative) of its value before the chunk
    at every iteration of it: the iterations change f only by rounding, so more of them would be
    work that does nothing (e.g. a robust run whose start is already a critical point). Checked when
    constructed."""

    iterations: int
    chunk_size: int = 50
    grad_tol: float | None = None
    f_target: float | None = None
    rel_decrease_tol: float | None = None
    stop_when_stalled: bool = True
    rel_change_tol: float | None = None

    def __post_init__(self):
        check_count(None, "iterations", self.iterations, 0, scalar=True)
        check_count(None, "chunk_size", self.chunk_size, 1, scalar=True)
        check_real(None, "grad_tol", self.grad_tol, 0.0, low_open=True, optional=True, scalar=True)
        check_real(None, "f_target", self.f_target, optional=True, scalar=True)
        check_real(None, "rel_decrease_tol", self.rel_decrease_tol, 0.0, optional=True, scalar=True)
        check_flag(None, "stop_when_stalled", self.stop_when_stalled)
        check_real(None, "rel_change_tol", self.rel_change_tol, 0.0, optional=True, scalar=True)

    @property
    def length(self) -> int:
        """Iterations per compiled chunk."""
        return max(1, min(self.chunk_size, self.iterations))

    def __call__(self, fs: list[np.ndarray], gs: list[np.ndarray]) -> RESULTS | None:
        """The rule that stops the run after the last chunk (``fs[-1]``, ``gs[-1]``), or None."""
        check_finite(fs[-1], gs[-1], sum(len(f) for f in fs[:-1]))
        if self.grad_tol is not None and gs[-1][-1] <= self.grad_tol:
            return RESULTS.grad_tol
        if self.f_target is not None and fs[-1][-1] <= self.f_target:
            return RESULTS.f_target
        if self.rel_decrease_tol is not None and len(fs) > 1:
            before = fs[-2][-1]
            if before - fs[-1][-1] <= self.rel_decrease_tol * abs(before):
                return RESULTS.rel_decrease_tol
        # |f before the chunk - f| <= tol |f|: for methods whose f is not monotone (momentum without
        # a monotone restart), where an increase must not read as convergence
        if self.rel_change_tol is not None and len(fs) > 1 and \
                abs(fs[-2][-1] - fs[-1][-1]) <= self.rel_change_tol * abs(fs[-1][-1]):
            return RESULTS.rel_change_tol
        if self.stop_when_stalled and len(fs) > 1 and stalled(fs[-2][..., -1], fs[-1]):
            return RESULTS.stalled
        return None


# f is a sum of m terms: its own rounding is ~sqrt(m) eps relative (Higham's probabilistic bound), so
# a chunk whose every f lies within 100 eps of the f before it has not moved f beyond rounding on
# any graph of up to ~10^4 edges, and by less than 1e-13 relative (float64) on any graph.
STALL_EPS = 100


def stalled(before: np.ndarray, chunk: np.ndarray) -> bool:
    """Whether every f of ``chunk`` (iterations on the last axis) lies within STALL_EPS machine
    epsilons (relative) of ``before``, the f before the chunk."""
    before, chunk = np.asarray(before), np.asarray(chunk)
    tol = STALL_EPS * np.finfo(chunk.dtype).eps * np.abs(before)
    return bool(np.all(np.abs(chunk - before[..., None]) <= tol[..., None]))


def check_finite(f: np.ndarray, grad_norm: np.ndarray, first_iteration: int) -> None:
    """Raise :class:`NonFiniteError` at the first non-finite f or ||grad F|| of a chunk (iterations
    on the last axis; leading axes, e.g. a sweep's configurations, are checked together)."""
    f, grad_norm = np.asarray(f), np.asarray(grad_norm)
    bad = ~(np.isfinite(f) & np.isfinite(grad_norm))
    if bad.any():
        k = int(np.flatnonzero(bad.reshape(-1, bad.shape[-1]).any(axis=0))[0]) if bad.ndim else 0
        fk, gk = f[..., k], grad_norm[..., k]
        what = "f" if not np.all(np.isfinite(fk)) else "||grad F||"
        value = (fk if what == "f" else gk)
        value = value.reshape(-1)[~np.isfinite(value.reshape(-1))][0] if np.ndim(value) else value
        at = "at the start" if first_iteration + k == 0 else f"after iteration {first_iteration + k}"
        raise NonFiniteError(
            f"{what} = {value} {at}: the data's weights or measurements are too large or too small "
            "for the floating-point precision in use; nothing was written"
        )


_COMPILED: dict = {}


def _signature(tree):
    leaves, treedef = jax.tree.flatten(tree)
    return treedef, tuple(
        (np.shape(x), getattr(x, "dtype", type(x)), getattr(x, "weak_type", None), getattr(x, "sharding", None))
        for x in leaves
    )


def compile_once(fn, *args, static=(), exported=None, once: bool = False):
    """``fn.lower(*args).compile()`` (``fn`` jitted; ``static`` its hashable static values, also
    part of the key) with the compile mode's options, cached per argument structure, shapes, dtypes,
    shardings and those options. ``once``: a program a run calls once, e.g. a solver's start
    (:func:`~mmpgo_jax._core.compile_mode.compiler_options`). ``exported``:
    ``(python function, static argument positions, output structure)`` to keep the traced program
    in the persistent cache when it is on (:func:`~mmpgo_jax._core.compilation_cache.compile_exported`:
    a warm process does not trace again)."""
    options = compiler_options(program_slots(args), once=once)
    key = (fn, static, _signature(args), tuple(sorted((options or {}).items())))
    compiled = _COMPILED.get(key)
    if compiled is None:
        if len(_COMPILED) > 64:  # bounded: long sessions with many shapes
            _COMPILED.pop(next(iter(_COMPILED)))
        compiled = compile_exported(*exported[:1], args, *exported[1:], options) if exported is not None else None
        if compiled is None:
            compiled = compile_lowered(fn.lower(*args), options)
        _COMPILED[key] = compiled
    return compiled


@dataclass(frozen=True)
class Driven:
    """What :func:`drive` returns: the final state, the history, why it stopped, and timings."""

    state: object
    history: History
    result: RESULTS
    compile_seconds: float
    solve_seconds: float


def converged_at(state) -> int | None:
    """The iteration after which the solver's own stopping rule held, read from a state with a
    ``converged_at`` field (-1 while it has not; a sweep's configurations: once all have, the last
    of them), or None. Such a solver leaves its state unchanged after that iteration."""
    at = getattr(state, "converged_at", None)
    if at is None:
        return None
    at = np.asarray(jax.device_get(at))
    return int(at.max()) if np.all(at >= 0) else None


def _chunks_of(history: History, length: int) -> tuple[list, list, list]:
    """The driver's lists of a history: the start, then chunks of ``length`` iterations."""
    K = history.iterations
    bounds = [(0, 1)] + [(1 + a, 1 + min(a + length, K)) for a in range(0, K, length)]
    f, g, r = (np.asarray(x) for x in (history.f, history.grad_norm, history.restarts))
    return [f[..., a:b] for a, b in bounds], [g[..., a:b] for a, b in bounds], [r[..., a:b, :] for a, b in bounds]


def drive(
    compile_chunk: Callable,
    state,
    start,
    termination: Termination,
    *,
    fetch: Callable | None,
    callback: Callable[[int, np.ndarray], bool | None] | None = None,
    agree: Callable[[RESULTS | None], RESULTS | None] | None = None,
    monitor: Monitor | None = None,
    checkpoint: Callable | None = None,
    history: History | None = None,
) -> Driven:
    """Run compiled chunks of the outer loop from ``state`` until ``termination`` says stop.

    ``compile_chunk(state, length, limit)`` returns ``chunk(state, limit) -> (state, record)``
    (compiled once: every chunk reuses it; ``limit`` is the traced iteration budget, iterations
    past it leave the state unchanged). ``start``: (f, grad_norm, restarted) at X^0. ``fetch(record)``:
    the chunk's (f, grad_norm, restarted[, settled]) as numpy arrays (``settled``: per iteration,
    whether the stopping rules may apply yet, e.g. GNC has ended), iterations on the last axis of f and
    grad_norm (restarted: (..., length, A)); leading axes (a sweep's configurations) are kept.
    ``fetch=None``: the run cannot stop early (no tolerance, no callback), so the records stay on
    the device and are fetched once at the end. ``callback(k, f)`` after each chunk (k iterations
    so far; True stops the run). A solver with its own stopping rule reports it in its state
    (:func:`converged_at`): the run stops after that chunk with ``RESULTS.converged`` and its history
    ends at that iteration. ``agree``: the stop decision every process takes (multi-process).
    ``monitor``: told of the "compiling" and "iterating" phases and of each chunk (:class:`Monitor`).
    ``checkpoint(done, length, state, fs, gs, rs)``: after every chunk the run goes on from (the
    iterations done, the chunk length, the state, the history so far as lists of chunks), e.g. a
    :class:`~mmpgo_jax._mm.checkpoint.Checkpointer`. ``history``: a resumed run: the history of the
    iterations already done (a multiple of the chunk length), ``state`` the state after them;
    ``start`` is then ignored and the run continues as the uninterrupted one would.
    """
    if history is not None:
        fs, gs, rs = _chunks_of(history, termination.length)
    else:
        f0, g0, r0 = jax.device_get(start)
        fs, gs, rs = [np.asarray(f0)[..., None]], [np.asarray(g0)[..., None]], [np.expand_dims(np.asarray(r0), -2)]
    check_finite(fs[0], gs[0], 0)
    lazy = fetch is None
    t = termination
    rules = (t.grad_tol, t.f_target, t.rel_decrease_tol, t.rel_change_tol)
    if lazy and any(v is not None for v in (callback, agree, monitor, checkpoint, *rules)):
        raise ValueError("fetch=None needs a run without stopping rules, callback, monitor or checkpoint")
    compile_seconds = solve_seconds = 0.0
    result = RESULTS.iterations
    iterations = termination.iterations
    pending = []
    monitor = monitor or Monitor()
    done = 0 if history is None else history.iterations
    if iterations > done:
        length = termination.length
        limit = np.asarray(iterations)
        monitor.phase("compiling")
        t = time.perf_counter()
        chunk = compile_chunk(state, length, limit)
        compile_seconds = time.perf_counter() - t
        monitor.phase("iterating")
        t = time.perf_counter()
        while done < iterations:
            state, rec = chunk(state, limit)
            take = min(length, iterations - done)
            done += take
            if lazy:
                pending.append((rec, take))
                continue
            fetched = fetch(rec)  # waits for the chunk: the time of the compiled iterations
            f, g, r = fetched[:3]
            solve_seconds += time.perf_counter() - t
            fs.append(f[..., :take])
            gs.append(g[..., :take])
            rs.append(r[..., :take, :])
            reason = termination(fs, gs)
            if len(fetched) > 3 and not np.all(np.asarray(fetched[3])[..., take - 1]):
                reason = None  # GNC still running: the stopping rules wait for its end
            monitor.chunk(done, fs[-1], gs[-1])
            if callback is not None and callback(done, f[..., :take]):
                reason = reason or RESULTS.callback
            if converged_at(state) is not None:
                reason = RESULTS.converged
            if agree is not None:
                reason = agree(reason)
            if reason is not None:
                result = reason
                break
            if checkpoint is not None and done < iterations:
                checkpoint(done, length, state, fs, gs, rs)
            t = time.perf_counter()
        monitor.phase("finishing")
        if lazy:
            for rec, take in pending:
                f, g, r = jax.device_get((rec.f, rec.grad_norm, rec.restarted))
                fs.append(np.asarray(f)[..., :take])
                gs.append(np.asarray(g)[..., :take])
                rs.append(np.asarray(r)[..., :take, :])
            solve_seconds = time.perf_counter() - t
            termination(fs, gs)  # the non-finite guard
    history = History(np.concatenate(fs, -1), np.concatenate(gs, -1), np.concatenate(rs, -2))
    at = converged_at(state)
    if at is not None:  # the history ends at the iteration where the solver's rule held
        keep = at + 1
        history = History(history.f[..., :keep], history.grad_norm[..., :keep], history.restarts[..., :keep, :])
        result = RESULTS.converged
    return Driven(state, history, result, compile_seconds, solve_seconds)
