"""How sharded robots exchange poses: :class:`MeshCollectives` (all poses, ``all_gather``) and
:class:`HaloCollectives` (each device's neighbour poses only, one ``all_to_all``), with the halo plan."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._core.partition import Partition
from .._core.pose_graph import PoseGraph
from .._mm.outer import (
    Collectives,
)

AXIS = "robots"

try:  # JAX >= 0.6 exposes shard_map at the top level; older versions in jax.experimental.
    _shard_map = jax.shard_map
    _SHARD_MAP_NO_CHECK = {"check_vma": False}
except AttributeError:  # pragma: no cover - depends on the installed JAX

    _SHARD_MAP_NO_CHECK = {"check_rep": False}


class MeshCollectives(Collectives):
    """Collectives over the mesh axis ``axis_name`` (use inside ``shard_map``)."""

    axis_name: str = eqx.field(static=True, default=AXIS)

    def gather_poses(self, X):
        return jax.lax.all_gather(X, self.axis_name, tiled=True)

    def sum(self, x):
        return jax.lax.psum(jnp.sum(x), self.axis_name)

    def max(self, x):
        return jax.lax.pmax(jnp.max(x), self.axis_name)


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
        flat = X.reshape((B * n_max, *X.shape[2:]))
        send = flat[self.send_index[0]]  # (D, H, d, d+1): row j goes to device j
        recv = jax.lax.all_to_all(send, self.axis_name, 0, 0, tiled=True)  # row k came from device k
        full = jnp.zeros((self.num_robots * n_max, *X.shape[2:]), X.dtype)
        full = full.at[self.recv_index[0].reshape(-1)].set(recv.reshape((-1, *X.shape[2:])), mode="drop")
        start = jax.lax.axis_index(self.axis_name) * (B * n_max)
        full = jax.lax.dynamic_update_slice_in_dim(full, flat, start, axis=0)
        return full.reshape((self.num_robots, n_max, *X.shape[2:]))


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
