"""Layouts: where a run's robots live. The layout is an argument of the one solve path
(:func:`mmpgo_jax.solve`), not a pipeline of its own.

A layout's ``setup(graph, robots)`` returns a :class:`Placement`, the per-run part: the partition
the solver runs on (a sharded run may renumber and pad robots), how the host-built problem and
state are placed on devices, the compiled chunk of :func:`~mmpgo_jax._mm.solvers.run_chunk` and
how its records come back. Everything else — partition, start, ``solver.build``, ``solver.init``,
the driver, the result — is the same code for every layout (:mod:`mmpgo_jax._solve.build`).
:class:`OneDevice` is the default; ``mmpgo_jax.sharding.Sharded`` splits the robots over a mesh.
"""

from __future__ import annotations

import contextlib

import jax
import numpy as np

from .._core.partition import Partition, pad_partition, partition
from .driver import compile_once
from .solvers import Solver, run_chunk

__all__ = ["OneDevice", "Padded", "Placement"]


class Placement:
    """One run's layout on one device (the base every layout's placement refines)."""

    agree = None  # multi-process runs: the stop decision every process takes

    def __init__(self, user_part: Partition, part: Partition | None = None):
        self.user_part = user_part  # the user's robots
        self.part = part if part is not None else user_part  # the robots the solver runs

    def building(self):
        """Context in which the problem and state are built (a sharded run: the host CPU)."""
        return contextlib.nullcontext()

    def share_start(self, X0):
        """The start every process uses (one process: X0 itself)."""
        return X0

    def identity(self):
        """What a checkpoint of this layout must match to resume."""
        return "one device"

    def checkpoint_options(self) -> dict:
        """``Checkpointer`` options (how the state reaches the host, which process writes)."""
        return {}

    def build_options(self, graph, fixed) -> dict:
        """``solver.build``'s keyword arguments this layout sets (shape padding, the fixed poses)."""
        return dict(fixed=fixed)

    def place(self, problem, state):
        """(problem, state) on the layout's devices."""
        return problem, state

    def compile_chunk(self, solver: Solver, problem):
        """The driver's ``compile_chunk(state, length, limit)`` for ``solver`` on ``problem``."""

        def compile_chunk(state, length, limit):
            out = (state, solver.record_structure(problem))  # the chunk's result structure
            # a problem with host callbacks (``exportable`` False) cannot be serialized: compiled as usual
            exported = (run_chunk.__wrapped__, (3,), out) if getattr(problem, "exportable", True) else None
            compiled = compile_once(run_chunk, solver, problem, state, length, limit, static=(length,),
                                    exported=exported)
            return lambda st, lim: compiled(solver, problem, st, lim)

        return compile_chunk

    def fetch(self, rec):
        """A chunk's records on the host: (f, grad_norm, restarted, settled)."""
        return jax.device_get((rec.f, rec.grad_norm, rec.restarted, rec.settled))

    def start_record(self, rec) -> tuple:
        """The driver's start: (f, grad_norm, restarted) at X^0, host values."""
        return rec.f, rec.grad_norm, rec.restarted

    def to_host(self, x) -> np.ndarray:
        return np.asarray(x)

    def stats(self) -> dict:
        """What this layout adds to ``SolveResult.stats``."""
        return {}


class OneDevice:
    """Every robot on one device (the default layout)."""

    def setup(self, graph, robots) -> Placement:
        return Placement(robots if isinstance(robots, Partition) else partition(graph, robots))

    def __repr__(self) -> str:
        return "OneDevice()"


class Padded:
    """One device, the partition padded to a common shape: ``n_max`` slots per robot, ``e_max``
    incident edges, ``robots`` robots, Γ^α's loop-closure list padded to ``couplings`` and one
    coarse ``aggregate`` size, an all-free fixed-pose mask where a graph has no fixed poses
    (``mask_fixed``), so that the configurations of a sweep's batch stack into one array each.
    ``robots`` given to ``setup`` is the configuration's unpadded :class:`Partition` (host arrays)."""

    def __init__(self, n_max: int, e_max: int, robots: int, *, couplings: int = 0, aggregate: int | None = None,
                 mask_fixed: bool = False):
        self.shape = (int(n_max), int(e_max), int(robots))
        self.couplings, self.aggregate, self.mask_fixed = int(couplings), aggregate, bool(mask_fixed)

    def setup(self, graph, robots: Partition) -> Placement:
        return _PaddedPlacement(self, robots, pad_partition(robots, *self.shape))

    def __repr__(self) -> str:
        return f"Padded(n_max={self.shape[0]}, e_max={self.shape[1]}, robots={self.shape[2]})"


class _PaddedPlacement(Placement):
    def __init__(self, layout: Padded, user_part: Partition, part: Partition):
        super().__init__(user_part, part)
        self.layout = layout

    def identity(self):
        return ("padded", self.layout.shape)

    def build_options(self, graph, fixed) -> dict:
        if fixed is None and self.layout.mask_fixed:  # one pytree structure per batch: an all-free mask
            fixed = np.zeros(graph.num_poses, dtype=bool)
        return dict(fixed=fixed, min_couplings=self.layout.couplings, aggregate=self.layout.aggregate)
