"""The methods by name: one registry behind ``solve(method=...)``, ``sweep(methods=...)`` and the
command line's ``--method`` / ``--methods``.

=====================  ==========================================================================
name                   solver
=====================  ==========================================================================
``mm``                 :class:`~mmpgo_jax.MM` (MM-PGO, Algorithm 1)
``amm``                :class:`~mmpgo_jax.AMM` (AMM-PGO, Algorithm 2, adaptive restart)
``rbcd``               ``RBCD()`` (greedy selection: the block with the largest gradient)
``rbcd++``             ``RBCD(accelerated=True)`` (Nesterov momentum, adaptive restart)
``rbcd[++]-SEL``       ``RBCD(selection=SEL[, accelerated=True])``, SEL one of ``uniform``,
                       ``round-robin``, ``parallel`` (colour classes of the robot graph at once)
``dgs``                ``DGS()`` (distributed Gauss-Seidel), once the baseline is a solver
=====================  ==========================================================================

The proximal term ``xi``, AMM's ``restart`` rule and the ``subproblem`` settings are shortcuts of
MM and AMM only (their solvers own them); every other method takes its settings from its solver
object (e.g. ``solve(graph, robots, solver=RBCD(selection="uniform", seed=3))``). This module
imports no solver until one is asked for, so the command line can read :data:`METHOD_NAMES` cheaply.
"""

from __future__ import annotations

import importlib

__all__ = ["MAJORIZATION", "METHOD_NAMES", "check_loss", "method_label", "method_name", "solver_for"]

#: the methods that the ``xi`` / ``restart`` / ``subproblem`` shortcuts apply to
MAJORIZATION = ("mm", "amm")
_SELECTIONS = ("greedy", "uniform", "round-robin", "parallel")  # RBCD's, greedy the default
#: name -> RBCD's (selection, accelerated)
_RBCD = {f"rbcd{'++' if acc else ''}{'' if sel == 'greedy' else '-' + sel}": (sel, acc)
         for sel in _SELECTIONS for acc in (False, True)}
#: every method name, in the order help texts list them
METHOD_NAMES = (*MAJORIZATION, *_RBCD, "dgs")
#: the methods that minimise the least-squares F only (a robust ``loss`` is refused)
_LEAST_SQUARES_ONLY = ("rbcd", "rbcd++", "dgs")
_LABELS = {"mm": "MM-PGO", "amm": "AMM-PGO", "dgs": "DGS"}


def solver_for(method, *, xi=None, restart=None, subproblem=None):
    """The :class:`~mmpgo_jax.Solver` of ``method``: a name of :data:`METHOD_NAMES`, or a Solver
    (returned as it is). ``xi`` / ``restart`` / ``subproblem`` apply to "mm" and "amm" (as
    :func:`~mmpgo_jax._mm.solvers.as_solver` makes them; ``restart`` is AMM's, ignored by MM); given
    with any other method they are refused (ValueError naming them)."""
    from .._mm.solvers import Solver, as_solver

    if isinstance(method, Solver):
        _refuse_shortcuts(method.name, xi=xi, restart=restart, subproblem=subproblem)
        return method
    if not isinstance(method, str):
        raise TypeError(f"method must be a method name ({', '.join(METHOD_NAMES)}) or a Solver, "
                        f"got {type(method).__name__}")
    if method in MAJORIZATION:
        return as_solver(method=method, xi=xi, restart=restart, subproblem=subproblem)
    if method not in METHOD_NAMES:
        raise ValueError(f"unknown method {method!r}: use one of {', '.join(METHOD_NAMES)}")
    _refuse_shortcuts(method, xi=xi, restart=restart, subproblem=subproblem)
    if method == "dgs":
        return _dgs()
    from .._baselines.rbcd import RBCD

    selection, accelerated = _RBCD[method]
    return RBCD(selection=selection, accelerated=accelerated)


def _refuse_shortcuts(method: str, **shortcuts) -> None:
    given = [k for k, v in shortcuts.items() if v is not None]
    if given:
        raise ValueError(f"{', '.join(given)} {'applies' if len(given) == 1 else 'apply'} to the methods "
                         f"'mm' and 'amm' only, not to {method!r} (give its settings in its solver object)")


def _dgs():
    """``DGS()`` when the baseline is a solver of the one solve path, else a clear error."""
    cls = getattr(importlib.import_module("mmpgo_jax._baselines.dgs"), "DGS", None)
    if cls is None:
        raise ValueError("DGS is not available as a solver yet (mmpgo_jax.dgs runs it on its own)")
    return cls()


def method_name(solver) -> str:
    """The registry name of ``solver`` ("rbcd-parallel" for ``RBCD(selection="parallel")``), else its
    ``name``: the label results and tables key it by."""
    name = solver.name
    selection = getattr(solver, "selection", None)
    if name in ("rbcd", "rbcd++") and selection in _SELECTIONS and selection != "greedy":
        return f"{name}-{selection}"
    return name


def method_label(name: str) -> str:
    """How progress bars and tables write a method: "MM-PGO", "AMM-PGO", "RBCD++", "RBCD (parallel)", "DGS"."""
    if name in _LABELS:
        return _LABELS[name]
    base, _, selection = name.partition("-")
    return f"{base.upper()} ({selection})" if selection else base.upper()


def check_loss(solver, loss) -> None:
    """ValueError naming the method when ``loss`` (a :class:`~mmpgo_jax.RobustLoss`, None: least
    squares) is given to a method that minimises the least-squares F only."""
    if loss is not None and solver.name in _LEAST_SQUARES_ONLY:
        raise ValueError(f"loss {loss.name!r}: the method {method_name(solver)!r} minimises the least-squares F "
                         "only (robust losses run with 'mm' or 'amm')")
