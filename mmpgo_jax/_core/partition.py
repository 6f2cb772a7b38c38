"""Splitting a pose graph among robots, in a padded layout (robot axis first).

Every robot alpha owns a set of poses, stored in ``n_max`` local slots (``pose_mask`` marks the
real ones). Each robot also holds the list of edges *incident* to its poses, padded to ``e_max``:
its own edges (both ends local) and the inter-robot edges with one end local. An edge endpoint is
addressed globally by (robot, slot); ``is_local`` says which endpoints belong to the robot.
Padding edges have zero weights and padding slots have no edges, so padding never changes a
result. Everything a robot computes per iteration (its gradient block, its majorizer) only
touches these incident edges, and only reads the poses of neighbours at their remote endpoints.
"""

from __future__ import annotations

from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .pose_graph import PoseGraph, Poses


def contiguous_robots(num_poses: int, num_robots: int) -> np.ndarray:
    """Robot of each pose for contiguous blocks in file order (docs/conventions.md §4).

    With n poses and A robots the first n mod A robots get floor(n/A)+1 poses, the rest floor(n/A).
    """
    if not 1 <= num_robots <= num_poses:
        raise ValueError(f"number of robots must be between 1 and the number of poses ({num_poses}), got {num_robots}")
    base, extra = divmod(num_poses, num_robots)
    sizes = np.full(num_robots, base)
    sizes[:extra] += 1
    return np.repeat(np.arange(num_robots), sizes)


class RobotEdges(eqx.Module):
    """Per-robot padded incident edges, arrays of shape (A, e_max, ...)."""

    robot_i: jax.Array  # robot owning the tail pose
    slot_i: jax.Array  # local slot of the tail pose in its robot
    robot_j: jax.Array
    slot_j: jax.Array
    local_i: jax.Array  # bool: tail belongs to this robot
    local_j: jax.Array  # bool: head belongs to this robot
    R: jax.Array  # (A, e_max, d, d)
    t: jax.Array  # (A, e_max, d)
    kappa: jax.Array  # 0 on padding
    tau: jax.Array

    @property
    def is_inter(self):
        return jnp.logical_xor(self.local_i, self.local_j)


class Partition(eqx.Module):
    """A pose graph split among ``num_robots`` robots, padded (see module docstring)."""

    pose_index: jax.Array  # (A, n_max) global pose index of each slot (0 on padding)
    pose_mask: jax.Array  # (A, n_max) bool
    edges: RobotEdges
    robot_of_pose: jax.Array  # (n,)
    slot_of_pose: jax.Array  # (n,)
    num_poses: int = eqx.field(static=True)

    @property
    def num_robots(self) -> int:
        return self.pose_mask.shape[0]

    @property
    def max_poses(self) -> int:
        return self.pose_mask.shape[1]

    @property
    def max_edges(self) -> int:
        return self.edges.kappa.shape[1]

    def scatter(self, poses: Poses, *, host: bool = False) -> Poses:
        """Global poses (n, ...) -> padded per-robot poses (A, n_max, ...); padding gets R = I, t = 0.

        Outside a trace this is numpy on the host and one transfer (no JAX dispatch); ``host=True``
        returns the host arrays without the transfer."""
        xp, (index, mask, R, t) = _namespace(self.pose_index, self.pose_mask, poses.R, poses.t)
        eye = xp.eye(R.shape[-1], dtype=R.dtype)
        R = xp.where(mask[..., None, None], R[index], eye)
        t = xp.where(mask[..., None], t[index], xp.zeros((), t.dtype))
        return Poses(R, t) if host and xp is np else _device(xp, Poses(R, t))

    def gather(self, padded: Poses) -> Poses:
        """Padded per-robot poses (A, n_max, ...) -> global poses (n, ...) (numpy on the host
        outside a trace)."""
        xp, (robot, slot, R, t) = _namespace(self.robot_of_pose, self.slot_of_pose, padded.R, padded.t)
        return _device(xp, Poses(R[robot, slot], t[robot, slot]))

    def padding(self) -> PaddingWaste:
        """How much of the padded layout is padding (:class:`PaddingWaste`), at this partition's
        float precision."""
        mask = np.asarray(self.pose_mask)
        real_edges = np.asarray(self.edges.local_i) | np.asarray(self.edges.local_j)
        return PaddingWaste.of(mask.sum(1), real_edges.sum(1), mask.shape[1], real_edges.shape[1],
                               self.edges.R.shape[-1], self.edges.kappa.dtype)


def _namespace(*arrays):
    """(numpy, host arrays) when no array is traced, else (jax.numpy, the arrays)."""
    if any(isinstance(a, jax.core.Tracer) for a in arrays):
        return jnp, arrays
    return np, tuple(np.asarray(a) for a in arrays)


def _device(xp, poses: Poses) -> Poses:
    """Host results moved to the default device (a transfer, no compilation)."""
    return poses if xp is jnp else Poses(jax.device_put(poses.R), jax.device_put(poses.t))


@dataclass(frozen=True)
class PaddingWaste:
    """The padded layout's waste: every robot holds ``n_max`` pose slots and ``e_max`` incident-edge
    slots; the slots beyond its own poses and edges are padding.

    Bytes count the partition's arrays per slot (pose: its index and mask; edge: two (robot, slot)
    ends, two locality flags, R~, t~, kappa, tau) at the float precision ``dtype``; the solver's
    per-slot arrays (poses, Gamma's blocks, preconditioner) follow the same slot counts, so
    ``ratio`` (bytes of padding / bytes used) describes them too.
    """

    pose_slots: int  # A n_max
    poses: int  # n
    edge_slots: int  # A e_max
    edges: int  # incident edges summed over robots (inter-robot edges count twice)
    bytes_padding: int
    bytes_used: int

    @property
    def ratio(self) -> float:
        """Bytes of padding / bytes used (0: no padding)."""
        return self.bytes_padding / max(self.bytes_used, 1)

    @staticmethod
    def of(poses_per_robot, edges_per_robot, n_max: int, e_max: int, dim: int, dtype=np.float64) -> PaddingWaste:
        """From the per-robot counts of poses and incident edges and the padded sizes."""
        fsize = np.dtype(dtype).itemsize
        pose_bytes = 4 + 1  # pose_index (int32), pose_mask
        edge_bytes = 4 * 4 + 2 + (dim * dim + dim + 2) * fsize
        A = len(poses_per_robot)
        n, e = int(np.sum(poses_per_robot)), int(np.sum(edges_per_robot))
        slots_n, slots_e = A * int(n_max), A * int(e_max)
        return PaddingWaste(slots_n, n, slots_e, e, (slots_n - n) * pose_bytes + (slots_e - e) * edge_bytes,
                            n * pose_bytes + e * edge_bytes)

    def summary(self) -> str:
        return (f"{self.ratio:.1%} of the bytes used ({self.pose_slots - self.poses} of {self.pose_slots} pose "
                f"slots, {self.edge_slots - self.edges} of {self.edge_slots} edge slots are padding)")


@dataclass(frozen=True)
class PartitionStats:
    """Host-side description of a partition (for reports and the CLI).

    Per iteration, robot a receives from each neighbour b the poses of b at the ends of their
    shared edges (``received_poses[a]``: distinct poses, summed over neighbours) and sends its own
    such poses to each neighbour (``sent_poses[a]``: a pose needed by two neighbours is sent twice).
    """

    poses: np.ndarray  # (A,) poses per robot
    own_edges: np.ndarray  # (A,) edges with both ends in the robot
    inter_edges: np.ndarray  # (A,) inter-robot edges incident to the robot
    neighbours: list[np.ndarray]  # robots sharing an edge with each robot
    received_poses: np.ndarray  # (A,) distinct remote poses each robot must receive per iteration
    sent_poses: np.ndarray  # (A,) poses each robot sends per iteration (once per neighbour that needs it)
    dim: int = 0  # d of the graph (bytes per pose: d + d^2 numbers)

    @property
    def total_inter_edges(self) -> int:
        return int(self.inter_edges.sum() // 2)

    def bytes_per_pose(self, dtype=np.float64) -> int:
        """Bytes of one pose (R and t: d^2 + d numbers) at the precision ``dtype``."""
        return (self.dim * self.dim + self.dim) * np.dtype(dtype).itemsize

    def received_bytes(self, dtype=np.float64) -> np.ndarray:
        return self.received_poses * self.bytes_per_pose(dtype)

    def sent_bytes(self, dtype=np.float64) -> np.ndarray:
        return self.sent_poses * self.bytes_per_pose(dtype)

    def padding(self, dtype=np.float64) -> PaddingWaste:
        """The padding of :func:`partition`'s layout of these robots (no extra padding)."""
        edges = self.own_edges + self.inter_edges
        return PaddingWaste.of(self.poses, edges, max(int(self.poses.max()), 1), max(int(edges.max(initial=0)), 1),
                               self.dim, dtype)


SPLITS = ("blocks", "metis", "random")


def metis_robots(graph: PoseGraph, parts: int, *, seed: int = 0, ufactor: int = 30) -> np.ndarray:
    """Robot of each pose from METIS's k-way partitioning (through ``pymetis``): balanced parts
    with a small edge cut, as MESA splits single-robot datasets.

    The METIS graph has one vertex per pose and one edge per pair of poses joined by a
    measurement, weighted by the number of measurements between them (so the weighted cut is the
    number of inter-robot edges). ``ufactor``: METIS's load-imbalance tolerance in thousandths
    (its k-way default 30: no part holds more than 1.03 n / parts poses, up to METIS's rounding
    on small graphs). ``seed``: METIS's random seed (the result is deterministic for a seed).
    Parts are numbered in the order of their smallest pose index. Raises ValueError when METIS
    leaves a part empty (possible when ``parts`` is close to the number of poses).
    """
    import pymetis

    n = graph.num_poses
    _check_parts(n, parts)
    if parts == 1:
        return np.zeros(n, dtype=np.int64)
    gi, gj = np.asarray(graph.i, np.int64), np.asarray(graph.j, np.int64)
    lo, hi = np.minimum(gi, gj), np.maximum(gi, gj)
    pairs, mult = np.unique(np.stack([lo, hi], 1), axis=0, return_counts=True)
    # symmetric CSR adjacency: both directions of every pair, sorted by source
    src = np.concatenate([pairs[:, 0], pairs[:, 1]])
    dst = np.concatenate([pairs[:, 1], pairs[:, 0]])
    w = np.concatenate([mult, mult])
    order = np.argsort(src, kind="stable")
    xadj = np.concatenate([[0], np.cumsum(np.bincount(src, minlength=n))])
    options = pymetis.Options()
    options.seed = int(seed)
    options.ufactor = int(ufactor)
    adjacency = pymetis.CSRAdjacency(xadj.astype(np.int64), dst[order].astype(np.int64))
    _, membership = pymetis.part_graph(int(parts), adjacency, eweights=w[order].astype(np.int64), options=options,
                                       recursive=False)
    part = np.asarray(membership, dtype=np.int64)
    counts = np.bincount(part, minlength=parts)
    if np.any(counts == 0):
        raise ValueError(f"METIS left {int(np.sum(counts == 0))} of {parts} parts empty on a graph of {n} poses; "
                         "use fewer robots")
    return _number_by_first_pose(part, parts)


def random_robots(num_poses: int, parts: int, *, seed: int = 0) -> np.ndarray:
    """Robot of each pose for random balanced parts: the sizes of :func:`contiguous_robots`, the
    poses shuffled (``numpy.random.default_rng(seed)``), parts numbered by their smallest pose."""
    rop = contiguous_robots(num_poses, parts)
    rop = rop[np.random.default_rng(seed).permutation(num_poses)]
    return _number_by_first_pose(rop, parts)


def _check_parts(num_poses: int, parts) -> None:
    if isinstance(parts, (bool, np.bool_)) or not isinstance(parts, (int, np.integer)):
        raise ValueError(f"number of robots must be an integer, got {parts!r}")
    if not 1 <= parts <= num_poses:
        raise ValueError(f"number of robots must be between 1 and the number of poses ({num_poses}), got {parts}")


def _number_by_first_pose(rop: np.ndarray, parts: int) -> np.ndarray:
    """Renumber parts in the order of their smallest pose index (vectorised)."""
    first = np.full(parts, rop.shape[0], dtype=np.int64)
    np.minimum.at(first, rop, np.arange(rop.shape[0]))
    rank = np.empty(parts, dtype=np.int64)
    rank[np.argsort(first, kind="stable")] = np.arange(parts)
    return rank[rop]


def split_robots(graph: PoseGraph, robots, parts: int | None = None, *, seed: int = 0) -> np.ndarray:
    """Robot of each pose, (n,) int64.

    ``robots``: a count (contiguous blocks, docs/conventions.md §4); ``"blocks"``, ``"metis"``
    (:func:`metis_robots`) or ``"random"`` (:func:`random_robots`, ``seed``) with ``parts``
    robots; or an (n,) robot-of-pose array (robots 0..A-1, each owning a pose), returned checked.
    Robots read from the data (GTSAM symbol keys, a label file, one file per robot) arrive as such
    an array: :attr:`~mmpgo_jax.G2OFile.robot_of_pose`.
    """
    n = graph.num_poses
    if isinstance(robots, str):
        if robots not in SPLITS:
            raise ValueError(f"unknown split {robots!r}: use one of {', '.join(SPLITS)} (or a robot-of-pose array)")
        if parts is None:
            raise ValueError(f"split {robots!r} needs parts= (the number of robots)")
        _check_parts(n, parts)
        if robots == "blocks":
            return contiguous_robots(n, int(parts))
        if robots == "metis":
            return metis_robots(graph, int(parts), seed=seed)
        return random_robots(n, int(parts), seed=seed)
    if parts is not None:
        raise ValueError("parts= applies to the splits 'blocks', 'metis' and 'random' only")
    if np.ndim(robots) == 0:
        _check_parts(n, robots)
        return contiguous_robots(n, int(robots))
    rop = np.asarray(robots)
    if not np.issubdtype(rop.dtype, np.integer):
        raise ValueError(f"robot-of-pose array must hold integers, got dtype {rop.dtype}")
    rop = rop.astype(np.int64)
    if rop.shape != (n,):
        raise ValueError(f"robot-of-pose array must have shape ({n},), got {rop.shape}")
    if rop.min() < 0:
        raise ValueError("robot indices must be non-negative")
    counts = np.bincount(rop)
    if np.any(counts == 0):
        empty = np.flatnonzero(counts == 0)
        raise ValueError(f"robots {empty.tolist()} own no pose; robot indices must be 0..A-1 without gaps")
    return rop


def partition(
    graph: PoseGraph,
    robots: int | str | np.ndarray,
    parts: int | None = None,
    *,
    seed: int = 0,
    min_max_poses: int = 0,
    min_max_edges: int = 0,
    num_robots: int | None = None,
) -> Partition:
    """Split ``graph`` among robots.

    ``robots``: a robot count (contiguous blocks, docs/conventions.md §4), ``"blocks"`` /
    ``"metis"`` / ``"random"`` with ``parts`` robots (``seed`` for METIS and random parts), or an
    (n,) array giving the robot of each pose (see :func:`split_robots`; e.g. the robots of a
    multi-robot file, :attr:`~mmpgo_jax.G2OFile.robot_of_pose`). ``min_max_poses`` /
    ``min_max_edges`` / ``num_robots`` pad to larger common
    shapes (e.g. to batch several partitions); padding changes a result only through rounding:
    the padded arrays hold the same numbers, but reductions over longer axes may round
    differently, and an inexact inner solve can then stop one CG iteration earlier or later
    (measured: up to 2e-5 relative in f after 8 MM iterations on a Cube graph).
    """
    n = graph.num_poses
    robot_of_pose = split_robots(graph, robots, parts, seed=seed)
    A = int(robot_of_pose.max()) + 1
    if num_robots is not None:
        if num_robots < A:
            raise ValueError(f"num_robots={num_robots} is smaller than the {A} robots used")
        A = num_robots
    counts = np.bincount(robot_of_pose, minlength=A)
    n_max = max(int(counts.max()), min_max_poses, 1)
    # Local slot = rank of the pose among its robot's poses (in global index order).
    order = np.argsort(robot_of_pose, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot_of_pose = np.empty(n, dtype=np.int64)
    slot_of_pose[order] = np.arange(n) - np.repeat(starts, counts)
    pose_index = np.zeros((A, n_max), dtype=np.int64)
    pose_mask = np.zeros((A, n_max), dtype=bool)
    pose_index[robot_of_pose, slot_of_pose] = np.arange(n)
    pose_mask[robot_of_pose, slot_of_pose] = True

    gi, gj = np.asarray(graph.i), np.asarray(graph.j)
    ri, rj = robot_of_pose[gi], robot_of_pose[gj]
    # Incident edge list: each edge appears for the tail's robot, and again for the head's robot
    # when that is a different robot.
    inter = ri != rj
    owner = np.concatenate([ri, rj[inter]])
    edge_id = np.concatenate([np.arange(len(gi)), np.flatnonzero(inter)])
    e_counts = np.bincount(owner, minlength=A)
    e_max = max(int(e_counts.max(initial=0)), min_max_edges, 1)
    order_e = np.argsort(owner, kind="stable")
    owner, edge_id = owner[order_e], edge_id[order_e]
    e_starts = np.concatenate([[0], np.cumsum(e_counts)[:-1]])
    e_slot = np.arange(len(owner)) - np.repeat(e_starts, e_counts)

    def padded(values, fill, dtype):
        out = np.full((A, e_max, *values.shape[1:]), fill, dtype=dtype)
        out[owner, e_slot] = values
        return out

    d = graph.dim
    fdt = np.asarray(graph.kappa).dtype
    Rm = np.asarray(graph.R)[edge_id]
    tm = np.asarray(graph.t)[edge_id]
    eye_pad = np.full((A, e_max, d, d), 0.0, dtype=fdt)
    eye_pad[...] = np.eye(d)
    Rpad = eye_pad
    Rpad[owner, e_slot] = Rm
    put = jax.device_put  # host arrays to the device: a transfer, no JAX dispatch
    edges = RobotEdges(
        robot_i=put(padded(ri[edge_id], 0, np.int32)),
        slot_i=put(padded(slot_of_pose[gi[edge_id]], 0, np.int32)),
        robot_j=put(padded(rj[edge_id], 0, np.int32)),
        slot_j=put(padded(slot_of_pose[gj[edge_id]], 0, np.int32)),
        local_i=put(padded(ri[edge_id] == owner, False, bool)),
        local_j=put(padded(rj[edge_id] == owner, False, bool)),
        R=put(Rpad),
        t=put(padded(tm, 0.0, fdt)),
        kappa=put(padded(np.asarray(graph.kappa)[edge_id], 0.0, fdt)),
        tau=put(padded(np.asarray(graph.tau)[edge_id], 0.0, fdt)),
    )
    return Partition(
        pose_index=put(pose_index.astype(np.int32)),
        pose_mask=put(pose_mask),
        edges=edges,
        robot_of_pose=put(robot_of_pose.astype(np.int32)),
        slot_of_pose=put(slot_of_pose.astype(np.int32)),
        num_poses=n,
    )


def partition_stats(graph: PoseGraph, robot_of_pose: np.ndarray) -> PartitionStats:
    """Poses, own/inter edges, neighbours and poses received and sent per iteration, per robot
    (host-side, vectorised)."""
    robot_of_pose = np.asarray(robot_of_pose)
    A = int(robot_of_pose.max()) + 1
    gi, gj = np.asarray(graph.i), np.asarray(graph.j)
    ri, rj = robot_of_pose[gi], robot_of_pose[gj]
    inter = ri != rj
    own = np.bincount(ri[~inter], minlength=A)
    inter_count = np.bincount(ri[inter], minlength=A) + np.bincount(rj[inter], minlength=A)
    # (receiving robot, sending robot, pose) of the exchange, each once
    recv = np.concatenate([ri[inter], rj[inter]])
    send = np.concatenate([rj[inter], ri[inter]])
    pose = np.concatenate([gj[inter], gi[inter]])
    triples = np.unique(np.stack([recv, send, pose], 1), axis=0) if recv.size else np.zeros((0, 3), np.int64)
    pairs = np.unique(triples[:, :2], axis=0)  # (robot, neighbour), sorted by robot
    neighbours = np.split(pairs[:, 1].astype(np.int64), np.cumsum(np.bincount(pairs[:, 0], minlength=A))[:-1])
    return PartitionStats(
        poses=np.bincount(robot_of_pose, minlength=A),
        own_edges=own,
        inter_edges=inter_count,
        neighbours=neighbours,
        received_poses=np.bincount(triples[:, 0], minlength=A).astype(np.int64),
        sent_poses=np.bincount(triples[:, 1], minlength=A).astype(np.int64),
        dim=graph.dim,
    )


def pad_partition(p: Partition, n_max: int, e_max: int, num_robots: int) -> Partition:
    """``partition(graph, robots, min_max_poses=n_max, min_max_edges=e_max, num_robots=...)`` from the
    unpadded partition ``p`` (host arrays): the same arrays, without partitioning the graph again
    (a sweep pads every configuration of a batch to one shape)."""
    A0, n0 = np.shape(p.pose_mask)
    e0 = np.shape(p.edges.kappa)[1]
    A, n_max, e_max = max(num_robots, A0), max(n_max, n0), max(e_max, e0)

    def pad(x, lead, fill=0):
        x = np.asarray(x)
        out = np.full(lead + x.shape[2:], fill, dtype=x.dtype)
        out[: x.shape[0], : x.shape[1]] = x
        return jnp.asarray(out)

    e = p.edges
    d = np.shape(e.t)[-1]
    R = np.broadcast_to(np.eye(d, dtype=np.asarray(e.R).dtype), (A, e_max, d, d)).copy()
    R[:A0, :e0] = np.asarray(e.R)
    E = (A, e_max)
    edges = RobotEdges(
        robot_i=pad(e.robot_i, E), slot_i=pad(e.slot_i, E), robot_j=pad(e.robot_j, E), slot_j=pad(e.slot_j, E),
        local_i=pad(e.local_i, E, False), local_j=pad(e.local_j, E, False), R=jnp.asarray(R), t=pad(e.t, E),
        kappa=pad(e.kappa, E), tau=pad(e.tau, E),
    )
    return Partition(pose_index=pad(p.pose_index, (A, n_max)), pose_mask=pad(p.pose_mask, (A, n_max), False),
                     edges=edges, robot_of_pose=jnp.asarray(p.robot_of_pose), slot_of_pose=jnp.asarray(p.slot_of_pose),
                     num_poses=p.num_poses)
