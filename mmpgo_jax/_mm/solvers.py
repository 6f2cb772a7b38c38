"""Solvers as objects: what a distributed method is to the one solve path.

A solver owns its settings (one owner per number: ξ lives here and nowhere else) and provides the
four things every layout runs (:mod:`mmpgo_jax._solve`): ``build`` (the constant data of a split
graph, on the host, once), ``init`` (the state at X^0 and its record), ``step`` (one outer iteration
of every robot: traced, ``vmap``-ed over robots inside, given the layout's :class:`Collectives`) and
``skipped`` (the record of an iteration past the budget). The generic chunk :func:`run_chunk` scans
``step``; one device, a sharded mesh and a sweep's batch all compile that same chunk, so a new
method plugs in by subclassing :class:`Solver`, without touching the driver or the layouts.

Every field of a solver is either static (it selects the compiled code) or a traced leaf (its
value does not): two runs that differ only in ξ or a tolerance share one compilation.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import equinox as eqx
import jax
import numpy as np

from .outer import (
    LOCAL,
    Collectives,
    IterationRecord,
    MMConfig,
    MMProblem,
    MMState,
    check_consistent,
    scan_with_budget,
    skipped_record,
    start_state,
    step,
)
from .robust import RobustLoss
from .subproblem import SubproblemConfig
from .weighting import NoWeights

__all__ = ["AMM", "MM", "Solver", "as_solver", "run_chunk", "start_run"]


class Solver(eqx.Module):
    """The protocol of the compiled loop (see the module docstring). ``name`` is the short name
    results and tables use ("mm", "amm", ...)."""

    @property
    def name(self) -> str:
        raise NotImplementedError

    def build(self, partition, *, poses, fixed=None, loss: RobustLoss | None = None, min_couplings: int = 0,
              aggregate: int | None = None, start_weights=None):
        """The constant data of a run (host, once): ``poses`` is the start X^0 scattered per robot;
        ``start_weights`` (A, e_max) the robust weights that came with the start (robust losses only)."""
        raise NotImplementedError

    def init(self, problem, X0):
        """(state at X^0, its record), traced."""
        raise NotImplementedError

    def step(self, problem, state, comm: Collectives = LOCAL):
        """One outer iteration of every robot: (state, record), traced."""
        raise NotImplementedError

    def skipped(self, state) -> IterationRecord:
        """The record of an iteration past the budget (the state does not change)."""
        raise NotImplementedError

    def start_structure(self, problem):
        """The output structure of ``init`` when known without tracing (a warm process then loads the
        start's program from the persistent cache without tracing it), else None."""
        return None

    def record_structure(self, problem) -> IterationRecord:
        """The structure of one iteration's record (leaves 0.0; None where the record has none)."""
        raise NotImplementedError

    def check(self, problem) -> None:
        """ValueError when this solver cannot run on ``problem`` (checked before tracing)."""

    def outcome(self, problem, graph, part, state, poses, to_host=np.asarray) -> tuple[dict, dict]:
        """What the final ``state`` adds to the result (e.g. a robust run's weights and inliers) and to
        its statistics; ``to_host`` brings a (possibly sharded) array to the host."""
        return {}, {}

    def final_poses(self, problem, part, X):
        """The stacked poses (A, n_max, d, d+1) a result reports, from the final iterate ``X`` (host
        array): ``X`` itself; a solver whose iterates are not poses (RBCD's lifted rank) maps them here."""
        return X

    def iteration(self, state):
        """The outer iterations ``state`` has done (traced)."""
        return state.iteration


class _Majorization(Solver):
    """MM-PGO and AMM-PGO (Algorithms 1 and 2): their settings are an :class:`MMConfig`."""

    config: MMConfig

    @property
    def name(self) -> str:
        return self.config.method

    @property
    def xi(self):
        return self.config.xi

    def build(self, partition, *, poses, fixed=None, loss=None, min_couplings=0, aggregate=None,
              start_weights=None) -> MMProblem:
        return MMProblem.build(partition, config=self.config, fixed=fixed, poses=poses, loss=loss,
                               start_weights=start_weights,
                               min_couplings=min_couplings, aggregate=aggregate)

    def init(self, problem: MMProblem, X0):
        return start_state.__wrapped__(problem, X0, self.config)

    def start_structure(self, problem: MMProblem):
        # known without tracing when the weighting has no state (robust states hold the weighted operators)
        if not problem.weighting.stateless:
            return None
        leaf = 0.0
        fields = {f.name: leaf for f in dataclasses.fields(MMState) if f.name != "weighting"}
        return MMState(**fields, weighting=NoWeights()), self.record_structure(problem)

    def record_structure(self, problem: MMProblem):
        return IterationRecord(f=0.0, grad_norm=0.0, restarted=0.0, settled=0.0)

    def outcome(self, problem: MMProblem, graph, part, state: MMState, poses, to_host=np.asarray):
        robust, stats = problem.weighting.outcome(graph, part, state.weighting, poses, to_host)
        if self.config.method == "amm":  # times the momentum guard (MMConfig.rise_limit) restarted every robot
            stats = {**stats, "momentum_resets": int(to_host(state.resets))}
        return robust, stats

    def step(self, problem: MMProblem, state: MMState, comm: Collectives = LOCAL):
        return step(problem, self.config, state, comm)

    def skipped(self, state: MMState) -> IterationRecord:
        return skipped_record(state)

    def check(self, problem: MMProblem) -> None:
        check_consistent(problem, self.config)


class MM(_Majorization):
    """MM-PGO (Algorithm 1): ``xi`` the proximal term of Eq. (13); ``subproblem`` the robots'
    Riemannian trust-region solve. No momentum, so no restart rule."""

    def __init__(self, xi: float | None = 1e-3, subproblem: SubproblemConfig | None = None):
        self.config = MMConfig(method="mm", xi=xi, subproblem=subproblem or SubproblemConfig())


class AMM(_Majorization):
    """AMM-PGO (Algorithm 2): MM with Nesterov momentum and a per-robot restart (``restart``:
    "adaptive" (default), "average" or "paper"; the constants as in :class:`MMConfig`)."""

    def __init__(self, xi: float | None = 1e-3, restart: Literal["paper", "adaptive", "average"] = "adaptive",
                 subproblem: SubproblemConfig | None = None, **constants):
        self.config = MMConfig(method="amm", restart=restart, xi=xi, subproblem=subproblem or SubproblemConfig(),
                               **constants)


def as_solver(solver=None, *, method: str | None = None, xi=None, restart=None, subproblem=None) -> Solver:
    """The solver of a call: ``solver`` (a :class:`Solver`, or an :class:`MMConfig`), or one made of
    the shortcut arguments (``method`` "mm" / "amm", default "amm"; ``restart`` applies to AMM); a
    shortcut given beside a solver is refused (its number would have two owners)."""
    shortcuts = dict(method=method, xi=xi, restart=restart, subproblem=subproblem)
    given = [k for k, v in shortcuts.items() if v is not None]
    if solver is not None:
        if given:
            raise ValueError(f"give {', '.join(given)} inside the solver, not beside solver=")
        if isinstance(solver, MMConfig):
            return MM(solver.xi, solver.subproblem) if solver.method == "mm" else AMM(
                solver.xi, solver.restart, solver.subproblem, slack_scale=solver.slack_scale,
                slack_decay=solver.slack_decay, average_rates=solver.average_rates,
                soft_restart_hits=solver.soft_restart_hits, rise_limit=solver.rise_limit)
        if not isinstance(solver, Solver):
            raise TypeError(f"solver must be a Solver (e.g. mmpgo_jax.AMM()), got {type(solver).__name__}")
        return solver
    method = "amm" if method is None else method
    xi = 1e-3 if xi is None else xi
    if method == "mm":
        return MM(xi, subproblem)  # (``restart`` is AMM's: MM has no momentum to restart)
    if method == "amm":
        return AMM(xi, restart or "adaptive", subproblem)
    raise ValueError(f"unknown method {method!r}: use 'mm' or 'amm'")


def _chunk(solver: Solver, problem, state, length: int, limit, comm: Collectives = LOCAL):
    return scan_with_budget(lambda s: solver.step(problem, s, comm), solver.skipped, solver.iteration, state,
                            length, limit)


_chunk.__name__ = _chunk.__qualname__ = "run_chunk"  # the name in compile logs
_jitted_chunk = jax.jit(_chunk, static_argnames=("length",))


def _start(solver: Solver, problem, X0):
    return solver.init(problem, X0)


_start.__name__ = _start.__qualname__ = "start_state"
start_run = jax.jit(_start)  # the solver's init in one compiled call (op by op: seconds of dispatch)


class _Chunk:
    """``run_chunk(solver, problem, state, length, limit=None)``: ``length`` outer iterations of
    ``solver`` in one ``lax.scan`` (jitted, ``length`` static); iterations at or past ``limit`` (a
    traced total) leave the state unchanged, so every chunk of a run is the same compiled program.
    The solver is checked against the problem (on concrete values) before tracing."""

    __name__ = __qualname__ = "run_chunk"
    __wrapped__ = staticmethod(_chunk)

    def __call__(self, solver: Solver, problem, state, length: int, limit=None):
        solver.check(problem)
        return _jitted_chunk(solver, problem, state, length, limit)

    def lower(self, solver: Solver, problem, state, length: int, limit=None):
        solver.check(problem)
        return _jitted_chunk.lower(solver, problem, state, length, limit)


run_chunk = _Chunk()
