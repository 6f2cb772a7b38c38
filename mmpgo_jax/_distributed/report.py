"""Per-iteration communication of a partition split over devices (:func:`communication_report`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from jax.sharding import Mesh

from .._core.partition import partition_stats
from .._core.pose_graph import PoseGraph
from .plan import plan_shards

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
            f"{'robot':>5} {'device':>6} {'recv poses':>10} {'recv bytes':>11} {'sent poses':>10} {'sent bytes':>11}"
            "  neighbours",
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
            f"{'device':>6} {'robots':>6} {'cross-device recv poses':>23} {'bytes':>11} {'sent poses':>10} "
            f"{'bytes':>11} {'halo recv bytes':>15} {'all_gather recv bytes':>21}",
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
    if len(pose):
        triples = np.unique(np.stack([recv_robot, send_robot, pose], 1), axis=0)
    else:
        triples = np.zeros((0, 3), np.int64)
    recv = np.bincount(triples[:, 0], minlength=A)
    sent = np.bincount(triples[:, 1], minlength=A)
    dev = plan.device_of_user_robot
    recv_dev, send_dev = dev[triples[:, 0]], dev[triples[:, 1]]
    cross = recv_dev != send_dev
    if cross.any():
        pairs = np.unique(np.stack([recv_dev[cross], triples[cross, 2]], 1), axis=0)
    else:
        pairs = np.zeros((0, 2), np.int64)
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
