"""Device meshes and robot-to-device plans (:func:`make_mesh`, :func:`plan_shards`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import jax
import numpy as np
from jax.sharding import Mesh

from .._core.partition import Partition, contiguous_robots
from .._core.pose_graph import PoseGraph
from .collectives import AXIS

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
