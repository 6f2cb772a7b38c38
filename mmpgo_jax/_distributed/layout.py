"""``solve_sharded``: :func:`mmpgo_jax.solve` with the robot axis split over a device mesh (``shard_map``)."""

from __future__ import annotations

import functools
import os
import time
from collections.abc import Callable, Sequence
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from .._core.gauge import FixedPoses
from .._core.partition import Partition, partition
from .._core.pose_graph import PoseGraph, Poses
from .._core.metrics import trajectory_accuracy
from .._mm.checkpoint import DEFAULT_EVERY, Checkpointer, restore_state
from .._mm.checkpoint import load as load_checkpoint
from .._mm.driver import RESULTS, Monitor, Termination, compile_once, drive
from .._mm.majorization import unstack
from .._mm.outer import (
    IterationRecord,
    MMConfig,
    MMProblem,
    start_state,
    step,
)
from .._mm.robust import GNCConfig, RobustLoss, as_loss
from .._mm.solve import SolveResult, output_frame, robust_fields, run_identity, start_for
from .._mm.subproblem import SubproblemConfig
from .collectives import (
    _SHARD_MAP_NO_CHECK,
    AXIS,
    HaloCollectives,
    MeshCollectives,
    _shard_map,
    halo_plan,
)
from .plan import make_mesh, plan_shards

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
    solves with the same shapes reuse it (the config is an argument: its numbers are traced)."""
    problem_specs, config_specs, state_specs, comm_specs = specs.trees

    def skipped(st):
        nan = jnp.full((), jnp.nan, st.share.dtype)
        settled = None if st.schedule is None else jnp.ones((), bool)
        return IterationRecord(f=nan, grad_norm=nan, restarted=jnp.zeros_like(st.s, dtype=bool), settled=settled)

    def chunk(problem, config, state, comm, limit):
        TRACE_COUNT[0] += 1

        def body(st, _):
            skip = st.iteration >= limit
            return jax.lax.cond(skip, lambda s: (s, skipped(s)), lambda s: step(problem, config, s, comm), st)

        st, rec = jax.lax.scan(body, state, None, length=length)
        restarted = jax.lax.all_gather(rec.restarted, AXIS, axis=1, tiled=True)
        return st, IterationRecord(f=rec.f, grad_norm=rec.grad_norm, restarted=restarted, settled=rec.settled)

    robust = problem_specs.robust is not None
    rec_specs = IterationRecord(f=P(), grad_norm=P(), restarted=P(), settled=P() if robust else None)
    mapped = _shard_map(
        chunk,
        mesh=mesh,
        in_specs=(problem_specs, config_specs, state_specs, comm_specs, P()),
        out_specs=(state_specs, rec_specs),
        **_SHARD_MAP_NO_CHECK,
    )
    return jax.jit(mapped)


# ------------------------------------------------------------------------------------------------
# solve_sharded
# ------------------------------------------------------------------------------------------------


def solve_sharded(
    graph: PoseGraph,
    robots: int | np.ndarray | Partition = 10,
    *,
    mesh: Mesh | None = None,
    devices: int | Sequence | None = None,
    method: Literal["mm", "amm"] = "amm",
    iterations: int = 1000,
    init=None,
    initial: Poses | None = None,
    xi: float = 1e-3,
    restart: Literal["paper", "adaptive", "average"] = "adaptive",
    subproblem: SubproblemConfig | None = None,
    chunk_size: int = 50,
    grad_tol: float | None = None,
    f_target: float | None = None,
    rel_decrease_tol: float | None = None,
    stop_when_stalled: bool = True,
    callback: Callable[[int, np.ndarray], bool | None] | None = None,
    reorder: bool | None = None,
    exchange: Literal["halo", "all_gather"] = "halo",
    fixed: FixedPoses | None = None,
    frame: FixedPoses | Literal["raw"] | None = None,
    monitor: Monitor | None = None,
    ground_truth: Poses | None = None,
    loss: str | RobustLoss = "l2",
    loss_scale: float | None = None,
    gnc: GNCConfig | None = None,
    checkpoint: str | os.PathLike | None = None,
    checkpoint_every: int = DEFAULT_EVERY,
    resume: str | os.PathLike | None = None,
) -> SolveResult:
    """:func:`mmpgo_jax.solve` with the robots sharded over the devices of a 1-D mesh.

    Same arguments and result as :func:`~mmpgo_jax.solve`, plus ``mesh`` (a ``Mesh`` with one axis
    named ``"robots"``) or ``devices`` (a device list, a count, or None for all devices, of every
    process), ``reorder`` (see :func:`plan_shards`) and ``exchange``: "halo" (default) sends each
    device only the neighbour poses its robots read (one ``all_to_all`` per iteration), "all_gather"
    every pose. ``result.partition`` is the user's
    partition (robot indices as given); ``result.stats`` also holds the mesh size, the shard plan and
    the sharded (renumbered, padded) partition. A second call with the same shapes and
    configuration structure does not compile again. In a multi-process run every process must call
    this with the same arguments; the callback's stop decision is taken from process 0.

    ``checkpoint`` / ``checkpoint_every`` / ``resume``: as for :func:`~mmpgo_jax.solve`; the state is
    saved in the sharded layout, so a checkpoint resumes only on the same number of devices with the
    same ``exchange`` (and is refused otherwise). In a multi-process run every process gathers
    the state for a checkpoint and process 0 writes it; to resume, every process reads the file (on
    several hosts it must be readable on each, e.g. a shared file system).
    """
    termination = Termination(iterations, chunk_size, grad_tol, f_target, rel_decrease_tol, stop_when_stalled)
    if mesh is None:
        mesh = make_mesh(devices)
    elif devices is not None:
        raise ValueError("give either mesh or devices, not both")
    if exchange not in ("halo", "all_gather"):
        raise ValueError(f"exchange must be 'halo' or 'all_gather', got {exchange!r}")
    if mesh.axis_names != (AXIS,):
        raise ValueError(f"the mesh must have exactly one axis named {AXIS!r}, got {mesh.axis_names}")
    num_devices = mesh.devices.size
    config = MMConfig(method=method, restart=restart, xi=xi, subproblem=subproblem or SubproblemConfig())
    robust = as_loss(loss, loss_scale, gnc)
    multiprocess = jax.process_count() > 1

    monitor = monitor or Monitor()
    monitor.phase("initializing")
    t0 = time.perf_counter()
    plan = plan_shards(graph, robots, num_devices, reorder=reorder)
    # The partition, the constant data and the state at X^0 are built whole on this process's CPU
    # (one gradient evaluation), then split over the mesh: each device receives only its own
    # robots' blocks, so no accelerator ever holds the whole problem.
    with _on_host():
        user_part = robots if isinstance(robots, Partition) else partition(graph, robots)
        if not plan.reordered and plan.padded_robots == plan.num_robots:
            part = user_part
        else:
            part = partition(graph, plan.sharded_robot_of_pose, num_robots=plan.padded_robots)
        start_method, start_options = start_for(init, robust)
        key = snapshot = saver = None
        if checkpoint is not None or resume is not None:
            layout = ("sharded", num_devices, exchange, plan.padded_robots, np.asarray(plan.sharded_robot_of_pose))
            key = run_identity(graph, user_part, (start_method, start_options, initial), config, robust, fixed,
                               chunk_size, layout)
        if resume is not None:  # every process reads the file: the same start everywhere
            snapshot = load_checkpoint(resume)
            snapshot.check(key, iterations)
            X0 = Poses(*(jnp.asarray(x) for x in snapshot.X0))
        else:
            X0 = _initial_poses(graph, start_method, start_options, initial, user_part, multiprocess, fixed)
        if checkpoint is not None:
            saver = Checkpointer(checkpoint, checkpoint_every, key, jax.device_get(X0), chunk_size=chunk_size,
                                 to_host=lambda st: [_to_host(x) for x in jax.tree.leaves(st)],
                                 write=jax.process_index() == 0)
        start_poses = X0
        X0 = part.scatter(X0)
        monitor.phase("building")
        problem = MMProblem.build(part, xi, config=config, fixed=fixed, poses=X0, loss=robust)
        state0, start = start_state(problem, X0, config)
        start = jax.device_get(start)
        if snapshot is not None:  # the checkpoint's state, sharded as the fresh one
            state0 = restore_state(snapshot, state0)
    problem_specs = _problem_specs(problem)
    state_specs = _specs(state0, part.num_robots)
    problem = _shard(problem, problem_specs, mesh)
    state = _shard(state0, state_specs, mesh)
    if exchange == "halo":
        send, recv = halo_plan(part, graph, num_devices)
        comm_specs = HaloCollectives(send_index=P(AXIS), recv_index=P(AXIS), num_robots=part.num_robots)
        comm = _shard(HaloCollectives(send_index=send, recv_index=recv, num_robots=part.num_robots), comm_specs, mesh)
    else:
        comm = comm_specs = MeshCollectives()
    del state0
    init_seconds = time.perf_counter() - t0

    def user_restarts(flags):
        """(k, padded robots) flags in sharded order -> (k, user robots) in the user's order."""
        out = np.zeros((flags.shape[0], user_part.num_robots), dtype=bool)
        out[:, : plan.num_robots] = flags[:, plan.sharded_of_user]
        return out

    config_specs = jax.tree.map(lambda _: P(), config)
    specs = _Specs(problem_specs, config_specs, state_specs, comm_specs)

    def compile_chunk(state, length, limit):
        runner = _sharded_runner(mesh, specs, length)

        def sharded_chunk(problem, config, state, comm, limit):
            return runner(problem, config, state, comm, limit)

        # the program kept in the persistent cache (a warm process does not trace it again); its key
        # holds the argument shapes and shardings, and the chunk length through the name
        sharded_chunk.__name__ = f"sharded_chunk_{length}"
        settled = None if problem.robust is None else 0.0
        out = (state, IterationRecord(f=0.0, grad_norm=0.0, restarted=0.0, settled=settled))
        compiled = compile_once(runner, problem, config, state, comm, limit, exported=(sharded_chunk, (), out))
        return lambda st, lim: compiled(problem, config, st, comm, lim)

    def fetch(rec):
        extra = () if rec.settled is None else (_to_host(rec.settled),)
        return _to_host(rec.f), _to_host(rec.grad_norm), user_restarts(_to_host(rec.restarted)), *extra

    start_record = (start.f, start.grad_norm, user_restarts(np.asarray(start.restarted)[None])[0])
    out = drive(compile_chunk, state, start_record, termination, fetch=fetch, callback=callback,
                agree=_agree if multiprocess else None, monitor=monitor, checkpoint=saver,
                history=None if snapshot is None else snapshot.history)
    X = _to_host(out.state.X)
    poses = output_frame(part.gather(unstack(X)), fixed, frame)  # sliced on the host
    final = out.state if problem.robust is None else eqx.tree_at(lambda st: st.weights, out.state,
                                                                 _to_host(out.state.weights))
    outcome, robust_stats = robust_fields(problem, graph, part, final, poses)
    return SolveResult(
        poses=poses,
        accuracy=None if ground_truth is None else trajectory_accuracy(poses, ground_truth),
        history=out.history,
        _partition=user_part,
        config=config,
        result=out.result,
        stats={
            "init_seconds": init_seconds,
            "compile_seconds": out.compile_seconds,
            "solve_seconds": out.solve_seconds,
            "devices": num_devices,
            "processes": jax.process_count(),
            "plan": plan,
            "sharded_partition": part,
            "exchange": exchange,
            "halo_size": int(comm.send_index.shape[-1]) if exchange == "halo" else None,
            **robust_stats,
        },
        termination=termination,
        start=output_frame(Poses(*jax.device_get((start_poses.R, start_poses.t))), fixed, frame),
        **outcome,
    )


def _on_host():
    """Context: new arrays on this process's first CPU device (if the CPU backend is available)."""
    import contextlib

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


def _initial_poses(graph, init, options, initial, robots, multiprocess: bool, fixed=None) -> Poses:
    from .._init.start import initialize

    X0 = initialize(graph, init, initial=initial, robots=robots, fixed=fixed, **options)
    if not multiprocess:
        return X0
    # Every process computes the same start; broadcast process 0's so that hosts with different
    # BLAS builds cannot start from slightly different poses.
    from jax.experimental import multihost_utils

    R, t = multihost_utils.broadcast_one_to_all((np.asarray(X0.R), np.asarray(X0.t)))
    return Poses(jnp.asarray(R, X0.R.dtype), jnp.asarray(t, X0.t.dtype))
