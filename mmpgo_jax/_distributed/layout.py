"""The sharded layout: robots split over the devices of a 1-D mesh (``shard_map``), one host or several.

:class:`Sharded` is a layout of the one solve path (:func:`mmpgo_jax.solve`; ``solve_sharded`` is its
front-end): the partition, start, problem and state are built whole on this process's CPU (one
gradient evaluation), then split over the mesh, so each device receives only its own robots' blocks
and no accelerator ever holds the whole problem. The compiled chunk is
:func:`~mmpgo_jax._mm.solvers.run_chunk`'s scan of ``solver.step`` under ``shard_map``, with
collectives that exchange only the neighbour poses a device's robots read ("halo") or all poses.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from .._core.partition import Partition, partition
from .._core.pose_graph import Poses
from .._mm.driver import RESULTS, compile_once
from .._mm.layouts import Placement
from .._mm.outer import IterationRecord, MMProblem
from .._mm.solvers import Solver, run_chunk
from .collectives import (
    _SHARD_MAP_NO_CHECK,
    AXIS,
    HaloCollectives,
    MeshCollectives,
    _shard_map,
    halo_plan,
)
from .plan import make_mesh, plan_shards

__all__ = ["TRACE_COUNT", "Sharded"]

# ------------------------------------------------------------------------------------------------
# Sharded arrays
# ------------------------------------------------------------------------------------------------


def _specs(tree, num_robots: int):
    """PartitionSpec per leaf: the robot axis (leading, of length num_robots) is sharded."""

    def spec(x):
        return P(AXIS) if getattr(x, "ndim", 0) >= 1 and x.shape[0] == num_robots else P()

    return jax.tree.map(spec, tree)


def _problem_specs(problem: MMProblem):
    specs = _specs(problem, problem.partition.num_robots)
    # Global (n,) pose arrays of the partition are not per robot: replicate them.
    return eqx.tree_at(lambda p: (p.partition.robot_of_pose, p.partition.slot_of_pose), specs, (P(), P()))


def _shard(tree, specs, mesh: Mesh):
    """Global arrays from host values; each process materializes only its addressable shards."""

    def put(x, spec):
        host = np.asarray(x)
        sharding = NamedSharding(mesh, spec)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    return jax.tree.map(put, tree, specs)


def _to_host(x) -> np.ndarray:
    """A (possibly multi-process) global array as a numpy array on every process."""
    if getattr(x, "is_fully_addressable", True) or x.is_fully_replicated:
        return np.asarray(x)
    from jax.experimental import multihost_utils

    return np.asarray(multihost_utils.process_allgather(x, tiled=True))


TRACE_COUNT = [0]  # traces of the sharded chunk (tests assert one per shape and configuration structure)


class _Specs:
    """Partition specs of the chunk's arguments, hashable (a static key of the cached runner)."""

    def __init__(self, *trees):
        self.trees = trees
        flat = [jax.tree.flatten(t) for t in trees]
        self._key = tuple((treedef, tuple(leaves)) for leaves, treedef in flat)

    def __hash__(self):
        return hash(self._key)

    def __eq__(self, other):
        return isinstance(other, _Specs) and self._key == other._key


@functools.lru_cache(maxsize=16)
def _sharded_runner(mesh: Mesh, specs: _Specs, length: int):
    """The jitted ``shard_map`` of one chunk; one per (mesh, argument specs, length), so repeated
    solves with the same shapes reuse it (the solver is an argument: its numbers are traced)."""
    problem_specs, solver_specs, state_specs, comm_specs = specs.trees

    def chunk(solver, problem, state, comm, limit):
        TRACE_COUNT[0] += 1
        st, rec = run_chunk.__wrapped__(solver, problem, state, length, limit, comm)
        restarted = jax.lax.all_gather(rec.restarted, AXIS, axis=1, tiled=True)
        return st, IterationRecord(f=rec.f, grad_norm=rec.grad_norm, restarted=restarted, settled=rec.settled)

    rec_specs = IterationRecord(f=P(), grad_norm=P(), restarted=P(), settled=P())
    mapped = _shard_map(
        chunk,
        mesh=mesh,
        in_specs=(solver_specs, problem_specs, state_specs, comm_specs, P()),
        out_specs=(state_specs, rec_specs),
        **_SHARD_MAP_NO_CHECK,
    )
    return jax.jit(mapped)


# ------------------------------------------------------------------------------------------------
# The layout
# ------------------------------------------------------------------------------------------------

EXCHANGES = ("halo", "all_gather")


@dataclass(frozen=True)
class Sharded:
    """Robots sharded over the devices of a 1-D mesh: ``mesh`` (one axis named ``"robots"``) or
    ``devices`` (a device list, a count, or None for all devices of every process); ``reorder``
    (see :func:`~mmpgo_jax.sharding.plan_shards`); ``exchange``: "halo" (default) sends each device
    only the neighbour poses its robots read (one ``all_to_all`` per iteration), "all_gather" every
    pose. In a multi-process run every process runs the same call; process 0 takes the stop
    decisions and writes checkpoints. Checked when constructed."""

    mesh: Mesh | None = None
    devices: int | Sequence | None = None
    exchange: Literal["halo", "all_gather"] = "halo"
    reorder: bool | None = None

    def __post_init__(self):
        if self.mesh is not None and self.devices is not None:
            raise ValueError("give either mesh or devices, not both")
        if self.exchange not in EXCHANGES:
            raise ValueError(f"exchange must be 'halo' or 'all_gather', got {self.exchange!r}")
        if self.mesh is not None and self.mesh.axis_names != (AXIS,):
            raise ValueError(f"the mesh must have exactly one axis named {AXIS!r}, got {self.mesh.axis_names}")

    def setup(self, graph, robots) -> ShardedPlacement:
        mesh = self.mesh if self.mesh is not None else make_mesh(self.devices)
        return ShardedPlacement(self, mesh, graph, robots)


class ShardedPlacement(Placement):
    """One sharded run: the shard plan (robots renumbered so that neighbours share a device, padded
    to a multiple of the device count), the mesh, the exchange and its collectives."""

    def __init__(self, layout: Sharded, mesh: Mesh, graph, robots):
        self.layout, self.mesh, self.graph = layout, mesh, graph
        self.num_devices = mesh.devices.size
        self.plan = plan_shards(graph, robots, self.num_devices, reorder=layout.reorder)
        self.multiprocess = jax.process_count() > 1
        self.agree = _agree if self.multiprocess else None
        with self.building():
            user = robots if isinstance(robots, Partition) else partition(graph, robots)
            plan = self.plan
            same = not plan.reordered and plan.padded_robots == plan.num_robots
            part = user if same else partition(graph, plan.sharded_robot_of_pose, num_robots=plan.padded_robots)
        super().__init__(user, part)
        self.comm = None

    def building(self):
        return _on_host()

    def share_start(self, X0):
        if not self.multiprocess:
            return X0
        # Every process computes the same start; broadcast process 0's so that hosts with different
        # BLAS builds cannot start from slightly different poses.
        from jax.experimental import multihost_utils

        R, t = multihost_utils.broadcast_one_to_all((np.asarray(X0.R), np.asarray(X0.t)))
        return Poses(jnp.asarray(R, X0.R.dtype), jnp.asarray(t, X0.t.dtype))

    def identity(self):
        p = self.plan
        return ("sharded", self.num_devices, self.layout.exchange, p.padded_robots, np.asarray(p.sharded_robot_of_pose))

    def checkpoint_options(self) -> dict:
        return dict(to_host=lambda st: [_to_host(x) for x in jax.tree.leaves(st)], write=jax.process_index() == 0)

    def place(self, problem: MMProblem, state):
        self.problem_specs = _problem_specs(problem)
        self.state_specs = _specs(state, self.part.num_robots)
        problem = _shard(problem, self.problem_specs, self.mesh)
        state = _shard(state, self.state_specs, self.mesh)
        if self.layout.exchange == "halo":
            send, recv = halo_plan(self.part, self.graph, self.num_devices)
            num = self.part.num_robots
            self.comm_specs = HaloCollectives(send_index=P(AXIS), recv_index=P(AXIS), num_robots=num)
            self.comm = _shard(HaloCollectives(send_index=send, recv_index=recv, num_robots=num), self.comm_specs,
                               self.mesh)
        else:
            self.comm = self.comm_specs = MeshCollectives()
        return problem, state

    def compile_chunk(self, solver: Solver, problem):
        comm, mesh = self.comm, self.mesh
        specs = _Specs(self.problem_specs, jax.tree.map(lambda _: P(), solver), self.state_specs, self.comm_specs)

        def compile_chunk(state, length, limit):
            runner = _sharded_runner(mesh, specs, length)

            def sharded_chunk(solver, problem, state, comm, limit):
                return runner(solver, problem, state, comm, limit)

            # the program kept in the persistent cache (a warm process does not trace it again); its key
            # holds the argument shapes and shardings, and the chunk length through the name
            sharded_chunk.__name__ = f"sharded_chunk_{length}"
            out = (state, solver.record_structure(problem))
            compiled = compile_once(runner, solver, problem, state, comm, limit, exported=(sharded_chunk, (), out))
            return lambda st, lim: compiled(solver, problem, st, comm, lim)

        return compile_chunk

    def _user_restarts(self, flags):
        """(k, padded robots) flags in sharded order -> (k, user robots) in the user's order."""
        out = np.zeros((flags.shape[0], self.user_part.num_robots), dtype=bool)
        out[:, : self.plan.num_robots] = flags[:, self.plan.sharded_of_user]
        return out

    def fetch(self, rec):
        return (_to_host(rec.f), _to_host(rec.grad_norm), self._user_restarts(_to_host(rec.restarted)),
                _to_host(rec.settled))

    def start_record(self, rec) -> tuple:
        return rec.f, rec.grad_norm, self._user_restarts(np.asarray(rec.restarted)[None])[0]

    def to_host(self, x) -> np.ndarray:
        return _to_host(x)

    def stats(self) -> dict:
        halo = self.layout.exchange == "halo"
        return dict(devices=self.num_devices, processes=jax.process_count(), plan=self.plan,
                    sharded_partition=self.part, exchange=self.layout.exchange,
                    halo_size=int(self.comm.send_index.shape[-1]) if halo else None)


def _on_host():
    """Context: new arrays on this process's first CPU device (if the CPU backend is available)."""
    try:
        return jax.default_device(jax.local_devices(backend="cpu")[0])
    except RuntimeError:
        return contextlib.nullcontext()


_REASONS = (None, *RESULTS)


def _agree(reason: RESULTS | None) -> RESULTS | None:
    """Process 0's stop decision, on every process (keeps the chunk loops in lockstep)."""
    from jax.experimental import multihost_utils

    code = multihost_utils.broadcast_one_to_all(np.int32(_REASONS.index(reason)))
    return _REASONS[int(code)]
