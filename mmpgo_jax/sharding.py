"""Robots sharded over devices (one host or several): ``solve_sharded``, traffic reports, launchers.

The robot axis of :class:`~mmpgo_jax.MMProblem` and :class:`~mmpgo_jax.MMState` is split over a
1-D device mesh with axis name ``"robots"``: device k holds a contiguous block of A / D robots.
The outer loop (``lax.scan`` over :func:`mmpgo_jax.step`) runs inside ``jax.shard_map``, so every
device runs the ``vmap``-ped subproblems of its own robots only, and the only communication of an
iteration is in :class:`MeshCollectives`:

* ``gather_poses``: by default (``exchange="halo"``) one ``all_to_all`` in which every device
  sends each other device exactly the poses that device's robots read (the ends of their
  cross-device edges), padded to a common halo size H (:func:`halo_plan`); with
  ``exchange="all_gather"`` every device receives ALL poses, padded slots included (see
  :func:`communication_report` for both volumes);
* ``sum``: ``psum`` of the robots' objective shares and gradient norms (two scalars);
* the per-robot restart flags of a chunk are ``all_gather``-ed once at its end (booleans).

Restart decisions of AMM (and the ``lax.cond`` that skips the MM fallback when no robot needs it)
stay per device. Per-robot arithmetic is unchanged, so a sharded run is the same MM / AMM run as
:func:`solve`, up to rounding: sums across devices are ordered differently, and XLA rounds a robot's
reductions differently when a device vmaps over fewer robots. The default truncated-CG subproblem
solver amplifies such 1e-16 differences (to ~1e-5 relative in f on the Cube data); with a
well-conditioned subproblem (large ``xi``) runs agree to ~1e-15 (``tests/test_sharding.py``).

Robots are assigned to devices in contiguous blocks of the robot index. For contiguous blocks of
poses (``robots=<count>``) the natural order already keeps neighbours together; for a user
robot-of-pose array the robots are renumbered (reverse Cuthill-McKee on the robot adjacency graph,
kept only if it lowers the cross-device edge count) and the result is mapped back. The robot
count is padded with empty robots to a multiple of the device count.

Several processes (one host or several): call :func:`initialize_distributed` first in every
process, then :func:`solve_sharded` with the same arguments everywhere: the mesh spans all
processes' devices, each process materializes only its own robots' arrays, and every process gets
the gathered result (write files from process 0 only). :func:`run_multiprocess` launches P local
CPU processes on a loopback coordinator; ``python -m mmpgo_jax.sharding <mmpgo solve arguments>
--coordinator HOST:PORT --num-processes P --process-id I`` is one process of such a run on any host.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from typing import Callable, Literal, Sequence

import numpy as np

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from ._majorization import unstack
from ._mm import Collectives, IterationRecord, MMConfig, MMProblem, evaluate, init_state, step
from ._partition import Partition, contiguous_robots, partition, partition_stats
from ._progress import progress_bar
from ._pose_graph import PoseGraph, Poses
from ._gauge import FixedPoses
from ._solve import History, SolveResult, _stop_reason, check_finite, check_solve_options, output_frame
from ._subproblem import SubproblemConfig

AXIS = "robots"

try:  # JAX >= 0.6 exposes shard_map at the top level; older versions in jax.experimental.
    _shard_map = jax.shard_map
    _SHARD_MAP_NO_CHECK = {"check_vma": False}
except AttributeError:  # pragma: no cover - depends on the installed JAX
    from jax.experimental.shard_map import shard_map as _shard_map

    _SHARD_MAP_NO_CHECK = {"check_rep": False}


class MeshCollectives(Collectives):
    """Collectives over the mesh axis ``axis_name`` (use inside ``shard_map``)."""

    axis_name: str = eqx.field(static=True, default=AXIS)

    def gather_poses(self, X):
        return jax.lax.all_gather(X, self.axis_name, tiled=True)

    def sum(self, x):
        return jax.lax.psum(jnp.sum(x), self.axis_name)


class HaloCollectives(MeshCollectives):
    """Neighbour-only pose exchange: one ``all_to_all`` of fixed-size halo buffers per iteration.

    ``send_index[k, j, h]``: flat slot (robot-in-device * n_max + slot) of the h-th pose that
    device k sends to device j; ``recv_index[j, k, h]``: flat global slot (robot * n_max + slot) where
    device j puts it (``A * n_max`` for padding entries, which are dropped). Built by
    :func:`halo_plan`; both arrays are sharded on their first axis, so inside ``shard_map`` each
    device holds its own rows. The returned array has the device's own poses and the neighbour
    poses its robots' inter-robot edges read; all other slots are zero and never read.
    """

    send_index: jax.Array = None  # (D, D, H) int32
    recv_index: jax.Array = None  # (D, D, H) int32
    num_robots: int = eqx.field(static=True, default=0)

    def gather_poses(self, X):
        B, n_max = X.shape[0], X.shape[1]
        flat = X.reshape((B * n_max,) + X.shape[2:])
        send = flat[self.send_index[0]]  # (D, H, d, d+1): row j goes to device j
        recv = jax.lax.all_to_all(send, self.axis_name, 0, 0, tiled=True)  # row k came from device k
        full = jnp.zeros((self.num_robots * n_max,) + X.shape[2:], X.dtype)
        full = full.at[self.recv_index[0].reshape(-1)].set(recv.reshape((-1,) + X.shape[2:]), mode="drop")
        start = jax.lax.axis_index(self.axis_name) * (B * n_max)
        full = jax.lax.dynamic_update_slice_in_dim(full, flat, start, axis=0)
        return full.reshape((self.num_robots, n_max) + X.shape[2:])


def halo_plan(part: Partition, graph: PoseGraph, num_devices: int) -> tuple[np.ndarray, np.ndarray]:
    """(send_index, recv_index) of :class:`HaloCollectives` for a partition whose robots are split
    into ``num_devices`` contiguous blocks; H = the largest number of poses one device sends another
    (at least 1)."""
    A, n_max = part.num_robots, part.max_poses
    B = A // num_devices
    rop, sop = np.asarray(part.robot_of_pose), np.asarray(part.slot_of_pose)
    dev = rop // B
    I, J = np.asarray(graph.i), np.asarray(graph.j)
    cross = dev[I] != dev[J]
    # a pose is needed by the device holding the other end of one of its cross-device edges
    src_pose = np.concatenate([I[cross], J[cross]])
    dst_dev = np.concatenate([dev[J[cross]], dev[I[cross]]])
    pairs = np.unique(np.stack([dev[src_pose], dst_dev, src_pose], 1), axis=0).reshape(-1, 3)
    counts = np.zeros((num_devices, num_devices), int)
    np.add.at(counts, (pairs[:, 0], pairs[:, 1]), 1)
    H = max(int(counts.max(initial=0)), 1)
    # np.unique sorted the pairs by (k, j): a pose's halo slot h is its rank within its (k, j) group
    k, j, pose = pairs.T
    group = k * num_devices + j
    h = np.arange(len(pairs)) - np.searchsorted(group, group)
    send = np.zeros((num_devices, num_devices, H), np.int32)
    recv = np.full((num_devices, num_devices, H), A * n_max, np.int32)
    send[k, j, h] = (rop[pose] - k * B) * n_max + sop[pose]
    recv[j, k, h] = rop[pose] * n_max + sop[pose]
    return send, recv


# ------------------------------------------------------------------------------------------------
# Meshes and robot-to-device plans
# ------------------------------------------------------------------------------------------------


def make_mesh(devices: int | Sequence | None = None) -> Mesh:
    """1-D mesh with axis ``"robots"`` over ``devices``: a list of devices, a count (the first k of
    ``jax.devices()``, i.e. of all processes) or None (all devices)."""
    all_devices = jax.devices()
    if devices is None:
        devs = all_devices
    elif isinstance(devices, (int, np.integer)):
        if not 1 <= int(devices) <= len(all_devices):
            raise ValueError(f"devices must be between 1 and {len(all_devices)} (available), got {devices}")
        devs = all_devices[: int(devices)]
    else:
        devs = list(devices)
        if not devs:
            raise ValueError("empty device list")
    return Mesh(np.asarray(devs, dtype=object), (AXIS,))


def _robot_adjacency(graph: PoseGraph, robot_of_pose: np.ndarray, num_robots: int):
    """Symmetric (A, A) sparse matrix of inter-robot edge counts."""
    import scipy.sparse as sp

    ri = robot_of_pose[np.asarray(graph.i)]
    rj = robot_of_pose[np.asarray(graph.j)]
    inter = ri != rj
    a, b = ri[inter], rj[inter]
    W = sp.coo_matrix((np.ones(len(a)), (a, b)), shape=(num_robots, num_robots)).tocsr()
    return (W + W.T).tocsr()


def _cross_device_edges(graph: PoseGraph, device_of_pose: np.ndarray) -> int:
    return int(np.count_nonzero(device_of_pose[np.asarray(graph.i)] != device_of_pose[np.asarray(graph.j)]))


@dataclass(frozen=True)
class ShardPlan:
    """How robots are renumbered, padded and split over ``num_devices`` devices.

    ``order[p]`` is the user robot placed at sharded index p (p < num_robots); sharded indices
    num_robots .. padded_robots-1 are empty padding robots. Device k holds sharded robots
    k * per_device .. (k+1) * per_device - 1.
    """

    robot_of_pose: np.ndarray  # (n,) user robot of each pose
    order: np.ndarray  # (A,) user robot at each sharded index
    num_devices: int
    padded_robots: int
    reordered: bool

    @property
    def num_robots(self) -> int:
        return len(self.order)

    @property
    def per_device(self) -> int:
        return self.padded_robots // self.num_devices

    @property
    def sharded_of_user(self) -> np.ndarray:
        inv = np.empty_like(self.order)
        inv[self.order] = np.arange(len(self.order))
        return inv

    @property
    def sharded_robot_of_pose(self) -> np.ndarray:
        return self.sharded_of_user[self.robot_of_pose]

    @property
    def device_of_user_robot(self) -> np.ndarray:
        return self.sharded_of_user // self.per_device

    def device_of_pose(self) -> np.ndarray:
        return self.device_of_user_robot[self.robot_of_pose]


def _robot_of_pose(graph: PoseGraph, robots) -> np.ndarray:
    if isinstance(robots, Partition):
        return np.asarray(robots.robot_of_pose, np.int64)
    if np.ndim(robots) == 0:
        return contiguous_robots(graph.num_poses, int(robots))
    rop = np.asarray(robots, np.int64)
    if rop.shape != (graph.num_poses,):
        raise ValueError(f"robot-of-pose array must have shape ({graph.num_poses},), got {rop.shape}")
    return rop


def plan_shards(graph: PoseGraph, robots, num_devices: int, *, reorder: bool | None = None) -> ShardPlan:
    """Robot-to-device plan for ``robots`` (count, robot-of-pose array or Partition).

    ``reorder``: None (default) renumbers robots given as an array/Partition when that lowers the
    number of edges between devices, True always renumbers (reverse Cuthill-McKee), False never.
    """
    rop = _robot_of_pose(graph, robots)
    A = int(rop.max()) + 1
    if num_devices < 1:
        raise ValueError(f"num_devices must be >= 1, got {num_devices}")
    padded = -(-A // num_devices) * num_devices
    identity = np.arange(A)
    if reorder is None:
        reorder = (isinstance(robots, Partition) or np.ndim(robots) != 0) and num_devices > 1
    if not reorder or A == 1:
        return ShardPlan(rop, identity, num_devices, padded, False)
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    W = _robot_adjacency(graph, rop, A)
    order = np.asarray(reverse_cuthill_mckee(W, symmetric_mode=True), np.int64)
    natural = ShardPlan(rop, identity, num_devices, padded, False)
    rcm = ShardPlan(rop, order, num_devices, padded, True)
    if _cross_device_edges(graph, rcm.device_of_pose()) < _cross_device_edges(graph, natural.device_of_pose()):
        return rcm
    return natural


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


def _sharded_runner(mesh: Mesh, config: MMConfig, problem_specs, state_specs, comm_specs, length: int):
    def skipped(st):
        nan = jnp.full((), jnp.nan, st.share.dtype)
        return IterationRecord(f=nan, grad_norm=nan, restarted=jnp.zeros_like(st.s, dtype=bool))

    def chunk(problem, state, comm, limit):
        def body(st, _):
            skip = st.iteration >= limit
            return jax.lax.cond(skip, lambda s: (s, skipped(s)), lambda s: step(problem, config, s, comm), st)

        st, rec = jax.lax.scan(body, state, None, length=length)
        restarted = jax.lax.all_gather(rec.restarted, AXIS, axis=1, tiled=True)
        return st, IterationRecord(f=rec.f, grad_norm=rec.grad_norm, restarted=restarted)

    rec_specs = IterationRecord(f=P(), grad_norm=P(), restarted=P())
    mapped = _shard_map(
        chunk,
        mesh=mesh,
        in_specs=(problem_specs, state_specs, comm_specs, P()),
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
    reorder: bool | None = None,
    exchange: Literal["halo", "all_gather"] = "halo",
    fixed: FixedPoses | None = None,
    frame: FixedPoses | Literal["raw"] | None = None,
) -> SolveResult:
    """:func:`mmpgo_jax.solve` with the robots sharded over the devices of a 1-D mesh.

    Same arguments and result as :func:`~mmpgo_jax.solve`, plus ``mesh`` (a ``Mesh`` with one axis
    named ``"robots"``) or ``devices`` (a device list, a count, or None for all devices, of every
    process), ``reorder`` (see :func:`plan_shards`) and ``exchange``: "halo" (default) sends each
    device only the neighbour poses its robots read (one ``all_to_all`` per iteration), "all_gather"
    every pose. ``result.partition`` is the user's
    partition (robot indices as given); ``result.extra`` holds the mesh size, the shard plan and
    the sharded (renumbered, padded) partition. In a multi-process run every process must call
    this with the same arguments; the callback's stop decision is taken from process 0.
    """
    check_solve_options(iterations=iterations, xi=xi, chunk_size=chunk_size, grad_tol=grad_tol,
                        f_target=f_target, rel_decrease_tol=rel_decrease_tol)
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
    multiprocess = jax.process_count() > 1

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
        init_robots = user_part
        X0 = _initial_poses(graph, init, initial, init_robots, multiprocess, fixed)
        problem = MMProblem.build(part, xi, fixed=fixed)
        state0 = init_state(problem, part.scatter(X0), config)
        start = jax.device_get(evaluate(problem, state0))
    check_finite(np.atleast_1d(start.f), np.atleast_1d(start.grad_norm), 0)
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

    fs, gs = [np.atleast_1d(start.f)], [np.atleast_1d(start.grad_norm)]
    rs = [user_restarts(np.asarray(start.restarted)[None])]
    compile_seconds = solve_seconds = 0.0
    stop_reason = "iterations"
    if iterations > 0:
        length = min(chunk_size, iterations)
        limit = jnp.asarray(iterations)
        runner = _sharded_runner(mesh, config, problem_specs, state_specs, comm_specs, length)
        t = time.perf_counter()
        compiled = runner.lower(problem, state, comm, limit).compile()
        compile_seconds = time.perf_counter() - t
        done = 0
        while done < iterations:
            t = time.perf_counter()
            state, rec = compiled(problem, state, comm, limit)
            f_chunk, g_chunk, r_chunk = _to_host(rec.f), _to_host(rec.grad_norm), _to_host(rec.restarted)
            solve_seconds += time.perf_counter() - t
            take = min(length, iterations - done)
            fs.append(f_chunk[:take])
            gs.append(g_chunk[:take])
            rs.append(user_restarts(r_chunk[:take]))
            done += take
            reason = _stop_reason(fs, gs, grad_tol, f_target, rel_decrease_tol)
            if callback is not None and callback(done, f_chunk[:take]):
                reason = reason or "callback"
            if multiprocess:
                reason = _agree(reason)
            if reason:
                stop_reason = reason
                break
    X = _to_host(state.X)
    history = History(np.concatenate(fs), np.concatenate(gs), np.concatenate(rs))
    return SolveResult(
        poses=output_frame(part.gather(unstack(jnp.asarray(X))), fixed, frame),
        history=history,
        partition=user_part,
        config=config,
        init_seconds=init_seconds,
        compile_seconds=compile_seconds,
        solve_seconds=solve_seconds,
        stop_reason=stop_reason,
        extra={
            "devices": num_devices,
            "processes": jax.process_count(),
            "plan": plan,
            "sharded_partition": part,
            "exchange": exchange,
            "halo_size": int(comm.send_index.shape[-1]) if exchange == "halo" else None,
        },
    )


def _on_host():
    """Context: new arrays on this process's first CPU device (if the CPU backend is available)."""
    import contextlib

    try:
        return jax.default_device(jax.local_devices(backend="cpu")[0])
    except RuntimeError:
        return contextlib.nullcontext()


_REASONS = ("", "iterations", "grad_tol", "f_target", "rel_decrease_tol", "callback")


def _agree(reason: str | None) -> str | None:
    """Process 0's stop decision, on every process (keeps the chunk loops in lockstep)."""
    from jax.experimental import multihost_utils

    code = multihost_utils.broadcast_one_to_all(np.int32(_REASONS.index(reason or "")))
    return _REASONS[int(code)] or None


def _initial_poses(graph, init, initial, robots, multiprocess: bool, fixed=None) -> Poses:
    from ._initialization import initialize

    X0 = initialize(graph, init, initial=initial, robots=robots, fixed=fixed)
    if not multiprocess:
        return X0
    # Every process computes the same start; broadcast process 0's so that hosts with different
    # BLAS builds cannot start from slightly different poses.
    from jax.experimental import multihost_utils

    R, t = multihost_utils.broadcast_one_to_all((np.asarray(X0.R), np.asarray(X0.t)))
    return Poses(jnp.asarray(R, X0.R.dtype), jnp.asarray(t, X0.t.dtype))


# ------------------------------------------------------------------------------------------------
# Communication report
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CommunicationReport:
    """Per-iteration traffic of a partition split over devices (float64 poses, d + d^2 numbers each).

    Logical neighbour exchange (what the algorithm needs): robot a receives, from each neighbour b,
    the poses of b at the ends of their shared edges; ``recv_poses[a]`` (= partition_stats'
    ``received_poses``) and ``sent_poses[a]`` count distinct poses per (robot, neighbour) pair.
    Per device, ``device_recv_poses[k]`` counts the distinct poses of other devices that robots on k
    need, ``device_sent_poses[k]`` the distinct poses of k that other devices need.

    What :func:`solve_sharded` moves: with the default halo exchange, one ``all_to_all`` of
    ``halo_size`` poses per ordered device pair (the largest per-pair need, so ``halo_recv_bytes``
    = (D - 1) * halo_size poses per device); with ``exchange="all_gather"`` every robot's padded
    pose block, ``allgather_recv_bytes`` per device (the other devices' robots times n_max slots).
    Plus two scalar ``psum``s per iteration and one ``all_gather`` of A restart flags per chunk.
    """

    dim: int
    bytes_per_pose: int
    robot_device: np.ndarray  # (A,) device of each user robot
    recv_poses: np.ndarray  # (A,)
    sent_poses: np.ndarray  # (A,)
    neighbours: list
    device_recv_poses: np.ndarray  # (D,)
    device_sent_poses: np.ndarray  # (D,)
    device_robots: np.ndarray  # (D,) real robots per device
    padded_robots: int
    max_poses: int  # n_max of the sharded partition
    allgather_recv_bytes: np.ndarray  # (D,)
    psum_bytes: int  # per iteration, per device, payload of the scalar reductions
    halo_size: int = 0  # poses per ordered device pair in the halo all_to_all

    @property
    def halo_recv_bytes(self) -> np.ndarray:
        D = len(self.device_recv_poses)
        return np.full(D, (D - 1) * self.halo_size * self.bytes_per_pose, np.int64)

    @property
    def num_devices(self) -> int:
        return len(self.device_recv_poses)

    @property
    def recv_bytes(self) -> np.ndarray:
        return self.recv_poses * self.bytes_per_pose

    @property
    def sent_bytes(self) -> np.ndarray:
        return self.sent_poses * self.bytes_per_pose

    @property
    def device_recv_bytes(self) -> np.ndarray:
        return self.device_recv_poses * self.bytes_per_pose

    @property
    def device_sent_bytes(self) -> np.ndarray:
        return self.device_sent_poses * self.bytes_per_pose

    def to_text(self) -> str:
        b = self.bytes_per_pose
        lines = [
            f"per iteration, float64 poses of d + d^2 = {b // 8} numbers ({b} bytes)",
            "",
            f"{'robot':>5} {'device':>6} {'recv poses':>10} {'recv bytes':>11} {'sent poses':>10} {'sent bytes':>11}  neighbours",
        ]
        for a in range(len(self.recv_poses)):
            nb = " ".join(map(str, self.neighbours[a].tolist()))
            lines.append(
                f"{a:>5} {self.robot_device[a]:>6} {self.recv_poses[a]:>10} {self.recv_bytes[a]:>11} "
                f"{self.sent_poses[a]:>10} {self.sent_bytes[a]:>11}  {nb}"
            )
        lines.append(
            f"{'all':>5} {'':>6} {self.recv_poses.sum():>10} {self.recv_bytes.sum():>11} "
            f"{self.sent_poses.sum():>10} {self.sent_bytes.sum():>11}"
        )
        lines += [
            "",
            f"{'device':>6} {'robots':>6} {'cross-device recv poses':>23} {'bytes':>11} {'sent poses':>10} {'bytes':>11}"
            f" {'halo recv bytes':>15} {'all_gather recv bytes':>21}",
        ]
        for k in range(self.num_devices):
            lines.append(
                f"{k:>6} {self.device_robots[k]:>6} {self.device_recv_poses[k]:>23} {self.device_recv_bytes[k]:>11} "
                f"{self.device_sent_poses[k]:>10} {self.device_sent_bytes[k]:>11} {self.halo_recv_bytes[k]:>15} "
                f"{self.allgather_recv_bytes[k]:>21}"
            )
        lines += [
            "",
            f"note: solve_sharded's default halo exchange receives {int(self.halo_recv_bytes.sum())} bytes per "
            f"iteration over all devices (halo of {self.halo_size} poses per device pair, padding included) for "
            f"{int(self.device_recv_bytes.sum())} bytes of needed poses; exchange='all_gather' would receive "
            f"{int(self.allgather_recv_bytes.sum())} ({self.padded_robots} robots x {self.max_poses} slots). Plus "
            f"{self.psum_bytes} bytes of psum per device per iteration and one all_gather of the robots' restart "
            "flags per chunk.",
        ]
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.to_text()


def communication_report(
    graph: PoseGraph, robot_of_pose, devices: int | Sequence | Mesh | None = None, *, reorder: bool | None = None
) -> CommunicationReport:
    """Traffic per robot and per device of one outer iteration (see :class:`CommunicationReport`).

    ``robot_of_pose``: robot count (contiguous blocks), (n,) array or Partition; ``devices``: a
    count, a device list or a Mesh (None: 1 device). Devices are assigned as in
    :func:`solve_sharded` (same :func:`plan_shards`); robots keep the user's numbering.
    """
    if devices is None:
        D = 1
    elif isinstance(devices, Mesh):
        D = devices.devices.size
    elif isinstance(devices, (int, np.integer)):
        D = int(devices)
    else:
        D = len(list(devices))
    plan = plan_shards(graph, robot_of_pose, D, reorder=reorder)
    rop = plan.robot_of_pose
    A = plan.num_robots
    d = graph.dim
    bpp = 8 * (d + d * d)
    gi, gj = np.asarray(graph.i), np.asarray(graph.j)
    ri, rj = rop[gi], rop[gj]
    inter = ri != rj
    # (receiving robot, sending robot, pose) triples of the logical exchange, deduplicated.
    recv_robot = np.concatenate([ri[inter], rj[inter]])
    send_robot = np.concatenate([rj[inter], ri[inter]])
    pose = np.concatenate([gj[inter], gi[inter]])
    triples = np.unique(np.stack([recv_robot, send_robot, pose], 1), axis=0) if len(pose) else np.zeros((0, 3), np.int64)
    recv = np.bincount(triples[:, 0], minlength=A)
    sent = np.bincount(triples[:, 1], minlength=A)
    dev = plan.device_of_user_robot
    recv_dev, send_dev = dev[triples[:, 0]], dev[triples[:, 1]]
    cross = recv_dev != send_dev
    pairs = np.unique(np.stack([recv_dev[cross], triples[cross, 2]], 1), axis=0) if cross.any() else np.zeros((0, 2), np.int64)
    device_recv = np.bincount(pairs[:, 0], minlength=D)
    spairs = np.unique(np.stack([send_dev[cross], recv_dev[cross], triples[cross, 2]], 1), axis=0)
    # A pose sent to several devices counts once per destination device.
    device_sent = np.bincount(spairs[:, 0], minlength=D) if len(spairs) else np.zeros(D, np.int64)
    per_pair = np.zeros((D, D), np.int64)
    if len(spairs):
        np.add.at(per_pair, (spairs[:, 0], spairs[:, 1]), 1)
    n_max = int(np.bincount(rop, minlength=A).max())
    per_dev = plan.per_device
    allgather = np.full(D, (plan.padded_robots - per_dev) * n_max * bpp, np.int64)
    stats = partition_stats(graph, rop)
    return CommunicationReport(
        dim=d,
        bytes_per_pose=bpp,
        robot_device=dev,
        recv_poses=recv.astype(np.int64),
        sent_poses=sent.astype(np.int64),
        neighbours=stats.neighbours,
        device_recv_poses=device_recv.astype(np.int64),
        device_sent_poses=device_sent.astype(np.int64),
        device_robots=np.bincount(dev, minlength=D),
        padded_robots=plan.padded_robots,
        max_poses=n_max,
        allgather_recv_bytes=allgather,
        psum_bytes=2 * 8,
        halo_size=max(int(per_pair.max(initial=0)), 1),
    )


# ------------------------------------------------------------------------------------------------
# Multi-process runs (jax.distributed)
# ------------------------------------------------------------------------------------------------


def initialize_distributed(
    coordinator: str,
    num_processes: int,
    process_id: int,
    *,
    cpu: bool | None = None,
    local_devices: int | None = None,
    timeout_s: int = 120,
) -> None:
    """``jax.distributed.initialize`` with bounded timeouts; call before any other JAX work.

    ``cpu``: force the CPU backend (default: when ``JAX_PLATFORMS`` is ``cpu``), with the gloo
    CPU collectives and ``local_devices`` CPU devices per process.
    """
    if cpu is None:
        cpu = os.environ.get("JAX_PLATFORMS", "").strip().lower() == "cpu"
    if cpu:
        jax.config.update("jax_platforms", "cpu")
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        if local_devices:
            jax.config.update("jax_num_cpu_devices", int(local_devices))
    jax.distributed.initialize(
        coordinator_address=coordinator,
        num_processes=num_processes,
        process_id=process_id,
        initialization_timeout=timeout_s,
        heartbeat_timeout_seconds=max(10, timeout_s // 2),
        shutdown_timeout_seconds=max(10, timeout_s // 2),
    )


def free_port(host: str = "127.0.0.1") -> int:
    """An unused TCP port on ``host`` (for a local coordinator)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


@dataclass
class ProcessRun:
    returncodes: list
    outputs: list  # (stdout, stderr) per process
    seconds: float
    timed_out: bool = False

    @property
    def ok(self) -> bool:
        return not self.timed_out and all(rc == 0 for rc in self.returncodes)


def _strip_options(argv: Sequence[str], names: Sequence[str]) -> list[str]:
    """argv without the options ``names`` (each taking one value, as ``--x v`` or ``--x=v``)."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
            continue
        if a in names:
            skip = True
            continue
        if any(a.startswith(n + "=") for n in names):
            continue
        out.append(a)
    return out


_LAUNCH_OPTIONS = ("--processes", "--coordinator", "--num-processes", "--process-id")


def run_multiprocess(
    args_for_solve: Sequence[str],
    processes: int = 2,
    coordinator: str | None = None,
    *,
    local_devices: int = 1,
    timeout_s: float = 600.0,
    env: dict | None = None,
    capture: bool = True,
) -> ProcessRun:
    """Run ``mmpgo solve <args_for_solve>`` as ``processes`` local CPU processes.

    ``args_for_solve``: the arguments of ``mmpgo solve`` (file and options; a leading ``"solve"``
    is accepted). Every process runs ``python -m mmpgo_jax.sharding`` with ``--coordinator``,
    ``--num-processes`` and ``--process-id`` added, joins the coordinator (default a free port on
    127.0.0.1), owns ``local_devices`` CPU devices, i.e. a contiguous slice of the robots, and
    process 0 prints the summary and writes the output files. The processes are killed if they
    have not all exited after ``timeout_s`` seconds.
    """
    args = list(args_for_solve)
    if args and args[0] == "solve":
        args = args[1:]
    args = _strip_options(args, _LAUNCH_OPTIONS)
    if isinstance(processes, bool) or not isinstance(processes, (int, np.integer)) or processes < 1:
        raise ValueError(f"processes must be an integer >= 1, got {processes!r}")
    if isinstance(local_devices, bool) or not isinstance(local_devices, (int, np.integer)) or local_devices < 1:
        raise ValueError(f"local_devices must be an integer >= 1, got {local_devices!r}")
    if not (isinstance(timeout_s, (int, float, np.number)) and np.isfinite(timeout_s) and timeout_s > 0):
        raise ValueError(f"timeout_s must be a finite number > 0, got {timeout_s!r}")
    coordinator = coordinator or f"127.0.0.1:{free_port()}"
    child_env = dict(os.environ if env is None else env)
    child_env["JAX_PLATFORMS"] = "cpu"
    child_env["JAX_NUM_CPU_DEVICES"] = str(local_devices)
    if "xla_force_host_platform_device_count" in child_env.get("XLA_FLAGS", ""):
        del child_env["XLA_FLAGS"]  # the device count per process is JAX_NUM_CPU_DEVICES
    import tempfile

    procs, logs = [], []
    t0 = time.perf_counter()
    for i in range(processes):
        cmd = [
            sys.executable,
            "-m",
            "mmpgo_jax.sharding",
            "solve",
            *args,
            "--coordinator",
            coordinator,
            "--num-processes",
            str(processes),
            "--process-id",
            str(i),
            "--local-devices",
            str(local_devices),
        ]
        if capture:  # files, not pipes: a chatty process can never block on a full pipe
            out, err = tempfile.TemporaryFile("w+"), tempfile.TemporaryFile("w+")
            logs.append((out, err))
        else:
            out = err = None
        procs.append(subprocess.Popen(cmd, env=child_env, stdout=out, stderr=err, text=True))
    # Wait for all; if one fails (or time runs out) stop the others at once instead of letting
    # them wait in a collective for a peer that is gone.
    deadline = t0 + timeout_s
    timed_out = False
    while any(p.poll() is None for p in procs):
        failed = any(p.returncode not in (None, 0) for p in procs)
        if failed or time.perf_counter() > deadline:
            timed_out = not failed
            for p in procs:
                if p.poll() is None:
                    p.kill()
            for p in procs:
                p.wait()
            break
        time.sleep(0.1)
    codes = [p.returncode for p in procs]
    outputs = []
    for out, err in logs:
        out.seek(0), err.seek(0)
        outputs.append((out.read(), err.read()))
        out.close(), err.close()
    if not capture:
        outputs = [("", "")] * processes
    return ProcessRun(codes, outputs, time.perf_counter() - t0, timed_out)


# ------------------------------------------------------------------------------------------------
# Command line: options for `mmpgo solve` and the sharded solve command
# ------------------------------------------------------------------------------------------------


def add_cli_options(p) -> None:
    """Add the sharding / multi-process options to the ``mmpgo solve`` parser (every number is
    checked when it is parsed: see :func:`mmpgo_jax.cli.int_in`)."""
    from .cli import finite_float, host_port, int_in

    g = p.add_argument_group("sharding over devices and processes")
    g.add_argument("--devices", type=int_in(0), default=None,
                   help="shard the robots over this many devices of this process, >= 0 (0: all)")
    g.add_argument("--processes", type=int_in(1), default=None,
                   help="run as P >= 1 local CPU processes (jax.distributed on 127.0.0.1)")
    g.add_argument("--coordinator", type=host_port, default=None,
                   help="HOST:PORT of process 0, PORT 1..65535 (multi-host runs; with --num-processes, --process-id)")
    g.add_argument("--num-processes", type=int_in(1), default=None, help="number of processes of a multi-host run, >= 1")
    g.add_argument("--process-id", type=int_in(0), default=None,
                   help="this process's index 0..P-1 (process 0 writes the outputs)")
    g.add_argument("--local-devices", type=int_in(1), default=None, help="CPU devices per process, >= 1 (with JAX_PLATFORMS=cpu)")
    g.add_argument("--timeout", type=finite_float(0.0, strict=True), default=600.0,
                   help="seconds before launched processes are killed, > 0 (default 600)")
    g.add_argument("--exchange", choices=("halo", "all_gather"), default="halo",
                   help="per-iteration pose exchange between devices: neighbour poses only (default) or all poses")


def wants_sharding(args) -> bool:
    """True when the parsed ``solve`` arguments ask for a sharded / multi-process run."""
    return any(getattr(args, k, None) is not None for k in ("devices", "processes", "num_processes", "coordinator"))


def cli_solve(args, argv: Sequence[str] | None = None) -> int:
    """``mmpgo solve`` with sharding options (see :func:`add_cli_options`).

    ``--processes P`` (P > 1) relaunches this command as P local processes and returns their
    status; ``--coordinator/--num-processes/--process-id`` joins a multi-process run; ``--devices``
    alone shards over this process's devices. ``argv``: the full command line (default sys.argv).
    """
    from .cli import CLIError, _resolve_file, check_outputs

    if args.process_id in (None, 0):  # the process that writes (or launches the one that does)
        check_outputs(args)
    if args.processes is not None and args.num_processes is None:
        if args.processes < 1:
            raise CLIError(f"--processes must be >= 1, got {args.processes}")
        if args.processes > 1:
            _resolve_file(args.file, args.data, announce=False)  # fail before launching; process 0 announces
            argv = list(sys.argv[1:] if argv is None else argv)
            run = run_multiprocess(argv, args.processes, local_devices=args.local_devices or 1, timeout_s=args.timeout, capture=False)
            if run.timed_out:
                raise CLIError(f"the {args.processes} processes did not finish within {args.timeout:g} s and were stopped")
            return max((abs(rc) for rc in run.returncodes), default=0)
    if args.num_processes is not None or args.coordinator is not None:
        if args.num_processes is None or args.process_id is None or args.coordinator is None:
            raise CLIError("a multi-process run needs --coordinator HOST:PORT, --num-processes P and --process-id I")
        if not 0 <= args.process_id < args.num_processes:
            raise CLIError(f"--process-id must be between 0 and {args.num_processes - 1}, got {args.process_id}")
        initialize_distributed(args.coordinator, args.num_processes, args.process_id, local_devices=args.local_devices,
                               timeout_s=max(1, int(min(args.timeout, 600))))
        try:
            return _cli_solve_sharded(args)
        finally:
            jax.distributed.shutdown()
    return _cli_solve_sharded(args)


def _cli_solve_sharded(args) -> int:
    """Mirror of ``mmpgo solve`` (cli._cmd_solve) with :func:`solve_sharded`; process 0 writes."""
    from . import cli
    from ._datasets import benchmark_info

    writer = jax.process_index() == 0
    args.file = str(cli._resolve_file(args.file, args.data, announce=writer))
    data = cli._load_for_solve(args, announce=writer)
    if not 1 <= args.robots <= data.graph.num_poses:
        raise cli.CLIError(f"--robots must be between 1 and the number of poses ({data.graph.num_poses}), got {args.robots}")
    init = data.start(args.init, cli._SOLVE_STARTS)
    local = jax.local_devices()
    if args.devices:
        if args.devices > len(local):
            raise cli.CLIError(f"--devices {args.devices}: this process has only {len(local)} devices")
        local = local[: args.devices]
    # The mesh: this process's devices, or (multi-process) every process's, ordered by process.
    devices = local if jax.process_count() == 1 else sorted(jax.devices(), key=lambda d: (d.process_index, d.id))

    with progress_bar(f"{args.method.upper()}-PGO", args.iterations, disable=(not writer) or args.no_progress) as progress:
        result = solve_sharded(
            data.graph,
            args.robots,
            devices=devices,
            method=args.method,
            iterations=args.iterations,
            init=init,
            initial=data.initial,
            xi=args.xi,
            restart=args.restart,
            chunk_size=args.chunk,
            grad_tol=args.grad_tol,
            callback=progress,
            exchange=args.exchange,
            fixed=data.fixed,
            frame=data.frame,
        )
    if not writer:
        return 0
    info = benchmark_info(data.path.name)
    fstar = info.fstar if info is not None else None
    cli._print_summary(result, fstar)
    halo = f", halo of {result.extra['halo_size']} poses per device pair" if result.extra["halo_size"] else ""
    print(f"sharding    {result.extra['devices']} devices, {result.extra['processes']} processes, "
          f"{result.extra['exchange']} exchange{halo}")
    cli.finish_solve(args, data, result, fstar)
    return 0


def build_parser():
    """``mmpgo``'s parser with the sharding options on ``solve`` (used by ``python -m``)."""
    from .cli import build_parser as base

    parser = base()
    solve_parser = next(a for a in parser._subparsers._group_actions if hasattr(a, "choices")).choices["solve"]
    if not any(o in solve_parser._option_string_actions for o in ("--processes", "--coordinator")):
        add_cli_options(solve_parser)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m mmpgo_jax.sharding solve FILE [options]``: one process of a sharded solve."""
    from ._datasets import DatasetNotFoundError
    from ._g2o import G2OFormatError
    from .cli import CLIError, _exit_status, cli_warnings, print_error

    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] != "solve":
        argv = ["solve", *argv]
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # --help, or a bad option (reported in one line)
        return _exit_status(exc)
    if args.precision == "float64":
        jax.config.update("jax_enable_x64", True)
    with cli_warnings():
        try:
            return cli_solve(args, argv)
        except (G2OFormatError, DatasetNotFoundError, CLIError, ValueError, OSError) as err:
            print_error(err)
            return 2
        except KeyboardInterrupt:
            print("mmpgo: interrupted", file=sys.stderr)
            return 130


if __name__ == "__main__":
    sys.exit(main())
