"""The friendly entry point: ``solve(graph, robots=10, method="amm", ...)``.

Builds the partition and the constant majorization data once, compiles one chunk of the outer
loop, and runs it as many times as needed (progress callbacks and stopping tolerances are checked
between chunks on the host; the compiled code is the same for every chunk).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Literal

import jax
import jax.numpy as jnp
import numpy as np

from ._gauge import FixedPoses, express_in_frame
from ._initialization import initialize
from ._majorization import unstack
from ._metrics import TrajectoryAccuracy, trajectory_accuracy
from ._mm import MMConfig, MMProblem, evaluate, init_state, run
from ._partition import Partition, partition
from ._pose_graph import PoseGraph, Poses
from ._precision import float64_enabled
from ._subproblem import SubproblemConfig


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
class SolveResult:
    poses: Poses  # final estimate, global order
    history: History
    partition: Partition
    config: MMConfig
    init_seconds: float
    compile_seconds: float
    solve_seconds: float  # outer iterations only (compiled), excluding compilation
    stop_reason: str
    accuracy: TrajectoryAccuracy | None = None  # against ``ground_truth`` when one was given
    extra: dict = field(default_factory=dict)

    @property
    def f(self) -> float:
        return float(self.history.f[-1])

    @property
    def iterations(self) -> int:
        return self.history.iterations

    @property
    def ms_per_iteration(self) -> float:
        return 1e3 * self.solve_seconds / max(self.iterations, 1)


def solve(
    graph: PoseGraph,
    robots: int | np.ndarray | Partition = 10,
    *,
    method: Literal["mm", "amm"] = "amm",
    iterations: int = 1000,
    init="chordal",
    initial: Poses | None = None,
    xi: float = 1e-3,
    restart: Literal["paper", "adaptive", "average"] = "adaptive",
    subproblem: SubproblemConfig | None = None,
    chunk_size: int = 50,
    grad_tol: float | None = None,
    f_target: float | None = None,
    rel_decrease_tol: float | None = None,
    callback: Callable[[int, np.ndarray], bool | None] | None = None,
    ground_truth: Poses | None = None,
    fixed: FixedPoses | None = None,
    frame: FixedPoses | Literal["raw"] | None = None,
) -> SolveResult:
    """Run MM-PGO (``method="mm"``) or AMM-PGO (``"amm"``) on ``graph`` split among ``robots``.

    ``robots``: a count (contiguous blocks, as in the paper), an (n,) robot-of-pose array, or a
    prepared :class:`Partition`. ``init``: see :func:`mmpgo_jax.initialize` (``"chordal"`` is the
    paper's start); ``initial`` holds the file's VERTEX estimates for ``init="vertices"``.
    ``restart``: AMM's restart rule, ``"adaptive"`` (default), ``"average"`` or ``"paper"`` (see
    :class:`MMConfig`; measured in benchmarks/restart_rules.md). Stops after ``iterations`` or, checked after each chunk of ``chunk_size`` iterations, when
    ||grad F|| <= ``grad_tol``, f <= ``f_target``, or the relative decrease of f over the last chunk
    is below ``rel_decrease_tol``. ``callback(k, f_chunk)`` is called after each chunk (k = total
    iterations so far); returning True stops the run. With ``ground_truth`` (synthetic data), the
    result's ``accuracy`` holds ATE / RPE of the final estimate after rigid alignment.

    ``fixed`` (e.g. :attr:`G2OFile.fixed_poses`): poses held at their values by the start and by
    every iteration. ``frame``: the frame of ``result.poses`` (see :func:`output_frame`): by
    default the fixed poses' frame when there are fixed poses, else pose 0 at the identity; a
    :class:`FixedPoses` (e.g. :attr:`G2OFile.frame`: the file's first pose at its VERTEX value)
    moves the result rigidly so that its first pose takes that value; ``"raw"`` keeps the solver's
    own gauge. f and the history do not depend on it.

    Raises :class:`NonFiniteError` when f or its gradient stops being finite (data whose weights or
    residuals float arithmetic cannot represent).
    """
    check_solve_options(iterations=iterations, xi=xi, chunk_size=chunk_size, grad_tol=grad_tol,
                        f_target=f_target, rel_decrease_tol=rel_decrease_tol)
    config = MMConfig(method=method, restart=restart, xi=xi, subproblem=subproblem or SubproblemConfig())
    t0 = time.perf_counter()
    part = robots if isinstance(robots, Partition) else partition(graph, robots)
    X0 = initialize(graph, init, initial=initial, robots=part, fixed=fixed)
    problem = MMProblem.build(part, xi, fixed=fixed)
    state = init_state(problem, part.scatter(X0), config)
    start = jax.device_get(evaluate(problem, state))
    check_finite(np.atleast_1d(start.f), np.atleast_1d(start.grad_norm), 0)
    init_seconds = time.perf_counter() - t0

    fs, gs, rs = [np.atleast_1d(start.f)], [np.atleast_1d(start.grad_norm)], [start.restarted[None]]
    compile_seconds = solve_seconds = 0.0
    stop_reason = "iterations"
    if iterations > 0:
        length = min(chunk_size, iterations)
        limit = jnp.asarray(iterations)
        t = time.perf_counter()
        compiled = run.lower(problem, config, state, length, limit).compile()
        compile_seconds = time.perf_counter() - t
        done = 0
        while done < iterations:
            t = time.perf_counter()
            state, rec = compiled(problem, config, state, limit)
            rec = jax.device_get(rec)
            solve_seconds += time.perf_counter() - t
            take = min(length, iterations - done)
            fs.append(rec.f[:take])
            gs.append(rec.grad_norm[:take])
            rs.append(rec.restarted[:take])
            done += take
            reason = _stop_reason(fs, gs, grad_tol, f_target, rel_decrease_tol)
            if callback is not None and callback(done, rec.f[:take]):
                reason = reason or "callback"
            if reason:
                stop_reason = reason
                break
    history = History(np.concatenate(fs), np.concatenate(gs), np.concatenate(rs))
    poses = output_frame(part.gather(unstack(state.X)), fixed, frame)
    return SolveResult(
        poses=poses,
        history=history,
        partition=part,
        config=config,
        init_seconds=init_seconds,
        compile_seconds=compile_seconds,
        solve_seconds=solve_seconds,
        stop_reason=stop_reason,
        accuracy=None if ground_truth is None else trajectory_accuracy(poses, ground_truth),
    )


class NonFiniteError(ValueError):
    """f or its gradient became NaN or infinite during a solve (no result is returned)."""


def check_finite(f: np.ndarray, grad_norm: np.ndarray, first_iteration: int) -> None:
    """Raise :class:`NonFiniteError` at the first non-finite f or ||grad F|| of a chunk."""
    bad = ~(np.isfinite(f) & np.isfinite(grad_norm))
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        what = "f" if not np.isfinite(f[k]) else "||grad F||"
        value = f[k] if what == "f" else grad_norm[k]
        at = "at the start" if first_iteration + k == 0 else f"after iteration {first_iteration + k}"
        raise NonFiniteError(
            f"{what} = {value} {at}: the data's weights or measurements are too large or too small "
            "for the floating-point precision in use; nothing was written"
        )


def _finite_number(name: str, value, *, low: float, inclusive: bool = True, optional: bool = False) -> None:
    if value is None and optional:
        return
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
    ok = ok and np.isfinite(value) and (value >= low if inclusive else value > low)
    if not ok:
        bound = f">= {low:g}" if inclusive else f"> {low:g}"
        raise ValueError(f"{name} must be a finite number {bound}{' or None' if optional else ''}, got {value!r}")


def check_solve_options(*, iterations, xi, chunk_size, grad_tol=None, f_target=None, rel_decrease_tol=None) -> None:
    """ValueError naming the parameter and its allowed range (shared by solve and solve_sharded)."""
    if isinstance(iterations, bool) or not isinstance(iterations, (int, np.integer)) or iterations < 0:
        raise ValueError(f"iterations must be an integer >= 0, got {iterations!r}")
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, (int, np.integer)) or chunk_size < 1:
        raise ValueError(f"chunk_size must be an integer >= 1, got {chunk_size!r}")
    _finite_number("xi", xi, low=0.0)
    _finite_number("grad_tol", grad_tol, low=0.0, inclusive=False, optional=True)
    if f_target is not None and not (isinstance(f_target, (int, float, np.number)) and np.isfinite(f_target)):
        raise ValueError(f"f_target must be a finite number or None, got {f_target!r}")
    _finite_number("rel_decrease_tol", rel_decrease_tol, low=0.0, optional=True)


def output_frame(poses: Poses, fixed: FixedPoses | None, frame) -> Poses:
    """The frame a result is reported in (see :func:`solve`)."""
    if isinstance(frame, str):
        if frame != "raw":
            raise ValueError(f"frame must be a FixedPoses, 'raw' or None, got {frame!r}")
        return poses
    if frame is None:
        if fixed is not None:
            return poses  # the fixed poses hold the gauge
        frame = FixedPoses.identity([0], poses.dim)
    return express_in_frame(poses, frame)


def _stop_reason(fs, gs, grad_tol, f_target, rel_decrease_tol) -> str | None:
    check_finite(fs[-1], gs[-1], sum(len(f) for f in fs[:-1]))
    if grad_tol is not None and gs[-1][-1] <= grad_tol:
        return "grad_tol"
    if f_target is not None and fs[-1][-1] <= f_target:
        return "f_target"
    if rel_decrease_tol is not None and len(fs) > 1:
        before = fs[-2][-1]
        if before - fs[-1][-1] <= rel_decrease_tol * abs(before):
            return "rel_decrease_tol"
    return None


def centralized_optimum(
    graph: PoseGraph,
    *,
    init="chordal",
    initial: Poses | None = None,
    grad_tol: float = 1e-6,
    max_iterations: int = 5000,
    xi: float = 1e-6,
    subproblem: SubproblemConfig | None = None,
    fixed: FixedPoses | None = None,
    frame: FixedPoses | Literal["raw"] | None = None,
) -> SolveResult:
    """Centralized mode: one robot (A = 1) and MM run to a tight gradient tolerance.

    With A = 1 the majorizer is F plus the proximal term xi/2 ||X - X^k||^2, so each outer iteration
    is a damped Riemannian Newton step on F itself. The default inner solve is near exact (CG to a
    relative residual 1e-8 in float64, 1e-4 in float32, at most 1000 iterations) with a tiny xi: then the outer iteration is
    Newton's method and converges in tens of iterations. A cheap inner solve (the distributed
    default, 20 CG iterations) needs thousands on ill-conditioned files (parking-garage: its
    rotation weights span 9 decades). In float32, which stalls far above ``grad_tol``, it also stops
    once 25 iterations lower f by less than a relative 1e-7. Used by the benchmarks as f*; check a
    result with :func:`~mmpgo_jax.certify`. ``init`` / ``initial`` / ``fixed`` / ``frame``: as for
    :func:`solve` (with two or more fixed poses the optimum is a constrained one, which the
    certificate does not cover).
    """
    # float32 cannot resolve a 1e-8 residual: CG would always run to its cap
    tol = 1e-8 if float64_enabled() else 1e-4
    sub = subproblem or SubproblemConfig(newton_steps=1, cg_iterations=1000, cg_tolerance=tol)
    return solve(
        graph,
        1,
        method="mm",
        iterations=max_iterations,
        init=init,
        initial=initial,
        xi=xi,
        subproblem=sub,
        chunk_size=25,
        grad_tol=grad_tol,
        # float32 stalls far above grad_tol: stop once a chunk no longer lowers f
        rel_decrease_tol=None if float64_enabled() else 1e-7,
        fixed=fixed,
        frame=frame,
    )
