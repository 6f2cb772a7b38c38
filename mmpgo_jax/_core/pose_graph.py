"""The pose-graph model: measurements, poses, the PGO objective and its gradients.

Conventions (paper Eq. (3); weights and f = 2F as in docs/conventions.md §1-2):
  F(X) = 1/2 sum_e [ kappa_e ||R_i Rt_e - R_j||^2 + tau_e ||R_i tt_e + t_i - t_j||^2 ]
  f    = 2 F        (what the paper's Tables I/II and SE-Sync report)
All functions are pure and jittable; graphs and poses are pytrees.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from .geometry import sym
from .precision import array_module, default_float_dtype, to_device


class Poses(eqx.Module):
    """A set of n poses in SE(d): rotations ``R`` (n, d, d) and translations ``t`` (n, d)."""

    R: jax.Array
    t: jax.Array

    @property
    def num_poses(self) -> int:
        return self.R.shape[-3]

    @property
    def dim(self) -> int:
        return self.R.shape[-1]

    def __add__(self, other: Poses) -> Poses:
        return Poses(self.R + other.R, self.t + other.t)

    def __sub__(self, other: Poses) -> Poses:
        return Poses(self.R - other.R, self.t - other.t)

    def scale(self, c) -> Poses:
        return Poses(c * self.R, c * self.t)


class PoseGraph(eqx.Module):
    """Relative pose measurements between ``num_poses`` poses.

    Edge e measures g_i^{-1} g_j = (Rt_e, tt_e) with weights kappa_e (rotation) and tau_e
    (translation), following SE-Sync's conversion from g2o information matrices.
    """

    i: jax.Array  # (m,) int32, tail pose of each edge
    j: jax.Array  # (m,) int32, head pose of each edge
    R: jax.Array  # (m, d, d) measured relative rotations
    t: jax.Array  # (m, d) measured relative translations
    kappa: jax.Array  # (m,) rotation weights
    tau: jax.Array  # (m,) translation weights
    num_poses: int = eqx.field(static=True)

    @property
    def dim(self) -> int:
        return self.R.shape[-1]

    @property
    def num_edges(self) -> int:
        return self.i.shape[0]

    def select_edges(self, keep) -> PoseGraph:
        """The graph with only the edges where ``keep`` (m,) is True (the poses unchanged). Device
        arrays are selected on the host and put back where they were: a boolean mask on a JAX array
        compiles a gather for every new shape (tens of ms each, a robust solve selects edges often)."""
        keep = np.asarray(keep, bool)

        def select(x):
            if isinstance(x, jax.Array) and not isinstance(x, jax.core.Tracer) and len(x.sharding.device_set) == 1:
                return jax.device_put(np.asarray(x)[keep], x.sharding)
            return x[keep]

        return PoseGraph(*map(select, (self.i, self.j, self.R, self.t, self.kappa, self.tau)), num_poses=self.num_poses)

    @staticmethod
    def from_arrays(i, j, R, t, kappa, tau, num_poses: int | None = None, dtype=None) -> PoseGraph:
        """Build a graph from array-likes; float dtype follows JAX's default unless given."""
        i = np.asarray(i, dtype=np.int64)
        j = np.asarray(j, dtype=np.int64)
        if num_poses is None:
            num_poses = int(max(i.max(initial=-1), j.max(initial=-1)) + 1)
        fdt = np.dtype(dtype or default_float_dtype())
        return PoseGraph(
            i=to_device(i, np.int32),
            j=to_device(j, np.int32),
            R=to_device(R, fdt),
            t=to_device(t, fdt),
            kappa=to_device(kappa, fdt),
            tau=to_device(tau, fdt),
            num_poses=int(num_poses),
        )


def _segment_sum(xp, values, index, n: int):
    """Sum of ``values`` rows into ``n`` segments (jax.ops.segment_sum, or a bincount on the host)."""
    if xp is jnp:
        return jax.ops.segment_sum(values, index, n)
    # one bincount over (segment, component) pairs: the same sums, in input order, as np.add.at
    k = math.prod(values.shape[1:])
    flat = (np.asarray(index, np.int64)[:, None] * k + np.arange(k)).reshape(-1)
    sums = np.bincount(flat, values.reshape(-1), minlength=n * k).reshape(n, *values.shape[1:])
    return sums if sums.dtype == values.dtype else sums.astype(values.dtype)


def edge_residuals(graph: PoseGraph, poses: Poses):
    """Rotation residuals R_i Rt - R_j (m, d, d) and translation residuals R_i tt + t_i - t_j (m, d).

    Like every function of this group, it runs in NumPy when the graph and poses hold NumPy arrays
    (:func:`host_graph`) and is jittable otherwise; a host graph with concrete device poses runs in
    NumPy too (op-by-op JAX would compile every operation for every new shape)."""
    if isinstance(graph.R, np.ndarray) and not isinstance(poses.R, jax.core.Tracer):
        poses = HostPoses(np.asarray(poses.R), np.asarray(poses.t))
    xp = array_module(graph.R, poses.R)
    Ri, Rj = poses.R[graph.i], poses.R[graph.j]
    rot = Ri @ graph.R - Rj
    trans = xp.einsum("mab,mb->ma", Ri, graph.t) + poses.t[graph.i] - poses.t[graph.j]
    return rot, trans


def edge_costs(graph: PoseGraph, poses: Poses):
    """Per-edge cost kappa ||rot||^2 + tau ||trans||^2 (the f = 2F convention)."""
    rot, trans = edge_residuals(graph, poses)
    xp = array_module(rot)
    return graph.kappa * xp.sum(rot**2, axis=(-1, -2)) + graph.tau * xp.sum(trans**2, axis=-1)


def host_edge_costs(graph: PoseGraph, poses: Poses) -> np.ndarray:
    """:func:`edge_costs` computed on the host in NumPy (float64) whatever arrays ``graph`` and
    ``poses`` hold: for host-side decisions between runs, where op-by-op JAX would compile every
    operation for every new shape."""
    return edge_costs(host_graph(graph), poses)


def cost(graph: PoseGraph, poses: Poses):
    """f = 2F: the objective as reported in the paper's tables and by SE-Sync."""
    costs = edge_costs(graph, poses)
    return array_module(costs).sum(costs)


def objective(graph: PoseGraph, poses: Poses):
    """F of Eq. (3) (with the 1/2)."""
    return 0.5 * cost(graph, poses)


def euclidean_gradient(graph: PoseGraph, poses: Poses) -> Poses:
    """Euclidean gradient of F with respect to (R, t), as a ``Poses`` of the same shapes."""
    rot, trans = edge_residuals(graph, poses)
    xp = array_module(rot)
    wr = graph.kappa[:, None, None] * rot
    wt = graph.tau[:, None] * trans
    n, d = graph.num_poses, wt.shape[-1]
    gRi = wr @ graph.R.swapaxes(-1, -2) + wt[:, :, None] * graph.t[:, None, :]
    # one sum per end of the edges, rotation and translation parts side by side (same sums per entry)
    tails = _segment_sum(xp, xp.concatenate([gRi.reshape(-1, d * d), wt], 1), graph.i, n)
    heads = _segment_sum(xp, xp.concatenate([wr.reshape(-1, d * d), wt], 1), graph.j, n)
    g = tails - heads
    return Poses(g[:, : d * d].reshape(n, d, d), g[:, d * d :])


def riemannian_gradient_from_euclidean(poses: Poses, egrad: Poses) -> Poses:
    """Project a Euclidean gradient onto the tangent space of R^{d x n} x SO(d)^n (B.9-B.11)."""
    RtG = poses.R.swapaxes(-1, -2) @ egrad.R
    return Poses(egrad.R - poses.R @ sym(RtG), egrad.t)


def riemannian_gradient(graph: PoseGraph, poses: Poses) -> Poses:
    """grad F at ``poses`` (Eqs. B.9-B.11)."""
    return riemannian_gradient_from_euclidean(poses, euclidean_gradient(graph, poses))


def tangent_norm(v: Poses):
    """Frobenius norm of a tangent vector (or any Poses-shaped array pair)."""
    xp = array_module(v.R, v.t)
    return xp.sqrt(xp.sum(v.R**2) + xp.sum(v.t**2))


def riemannian_gradient_norm(graph: PoseGraph, poses: Poses):
    """||grad F|| (of F, the 1/2 convention)."""
    return tangent_norm(riemannian_gradient(graph, poses))


def host_graph(graph: PoseGraph) -> PoseGraph:
    """``graph`` with NumPy leaves (int64 indices, float64 values): the functions above then run on
    the host in float64, without JAX dispatch."""
    return PoseGraph(**host_view(graph)._asdict())


class HostGraph(NamedTuple):
    """A graph's fields as NumPy arrays in a tuple (:func:`host_view`): the functions above read
    only these fields, and a tuple's fields are read without the lookup an equinox module's
    attributes cost (about a microsecond each, which host-side solvers of tiny graphs pay hundreds
    of times per solve)."""

    i: np.ndarray
    j: np.ndarray
    R: np.ndarray
    t: np.ndarray
    kappa: np.ndarray
    tau: np.ndarray
    num_poses: int

    @property
    def dim(self) -> int:
        return self.R.shape[-1]


class HostPoses(NamedTuple):
    """Poses as a tuple of NumPy arrays (R (n, d, d), t (n, d)), for the same reason as :class:`HostGraph`."""

    R: np.ndarray
    t: np.ndarray


def host_view(graph: PoseGraph) -> HostGraph:
    """``graph``'s arrays on the host (int64 indices, float64 values) as a :class:`HostGraph`."""
    return HostGraph(np.asarray(graph.i, np.int64), np.asarray(graph.j, np.int64), np.asarray(graph.R, np.float64),
                     np.asarray(graph.t, np.float64), np.asarray(graph.kappa, np.float64),
                     np.asarray(graph.tau, np.float64), graph.num_poses)


def poses_to_matrix(poses: Poses) -> np.ndarray:
    """X = [t_1 .. t_n R_1 .. R_n] in R^{d x (d+1)n}, the paper's layout of Eq. (1)."""
    R = np.asarray(poses.R)
    t = np.asarray(poses.t)
    n, d = t.shape
    return np.concatenate([t.T, np.transpose(R, (1, 0, 2)).reshape(d, d * n)], axis=1)


def matrix_to_poses(X) -> Poses:
    """Inverse of :func:`poses_to_matrix`."""
    X = np.asarray(X)
    d = X.shape[0]
    n = X.shape[1] // (d + 1)
    t = X[:, :n].T
    R = np.transpose(X[:, n:].reshape(d, n, d), (1, 0, 2))
    return Poses(jnp.asarray(R), jnp.asarray(t))


def edge_hessian_blocks(R, t, kappa, tau, *, unit_rotations: bool = False, xp=np):
    """Per-edge blocks (H_ii, H_jj, H_ij) of the PGO objective, each (m, d+1, d+1).

    Layout per pose: Y_p = [t_p | R_p] (d x (d+1)), index 0 the translation, 1..d the rotation
    columns. For an edge e = (i, j) with measurement (R~, t~) and a = (1, t~):

        kappa ||R_i R~ - R_j||^2 + tau ||R_i t~ + t_i - t_j||^2
            = tr(Y_i H_ii Y_i^T) + tr(Y_j H_jj Y_j^T) + 2 tr(Y_i H_ij Y_j^T),
        H_ii = tau a a^T + kappa diag(0, R~ R~^T),  H_jj = tau e0 e0^T + kappa diag(0, I),
        H_ij = -tau a e0^T - kappa diag(0, R~)

    (the edge's blocks of the connection Laplacian M of Eq. (4); H_ji = H_ij^T). The blocks are
    linear in (kappa, tau): ``tau = 0`` gives the rotation connection Laplacian's blocks (in
    [1:, 1:]), ``kappa = 0`` the translation Laplacian's (in [0, 0]). ``unit_rotations=True``
    writes I for R~ R~^T (equal up to rounding for measurements in SO(d)). Inputs: ``R`` (m, d, d),
    ``t`` (m, d), ``kappa`` and ``tau`` (m,) or scalars. ``xp=np`` (default): float64 NumPy on the
    host (set-up, tests, initializations); ``xp=jax.numpy``: in the arrays' own dtype, jittable (the
    weighted Gamma assembled inside the compiled step). One formula for both, so that the host's
    Gamma and the compiled step's are the same blocks.
    """
    if xp is np:
        R, t = np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64)
        kappa, tau = np.asarray(kappa, dtype=np.float64), np.asarray(tau, dtype=np.float64)
    m, d = t.shape
    dt = t.dtype
    kappa = xp.broadcast_to(kappa, (m,))[:, None, None]
    tau = xp.broadcast_to(tau, (m,))[:, None, None]
    a = xp.concatenate([xp.ones((m, 1), dt), t], 1)
    e0 = xp.concatenate([xp.ones(1, dt), xp.zeros(d, dt)])
    S = xp.diag(xp.concatenate([xp.zeros(1, dt), xp.ones(d, dt)]))  # diag(0, I)

    def pad(B):  # diag(0, B) of (m, d, d) blocks
        return xp.pad(B, ((0, 0), (1, 0), (1, 0)))

    gram = S if unit_rotations else pad(R @ xp.swapaxes(R, 1, 2))
    Hii = tau * a[:, :, None] * a[:, None, :] + kappa * gram
    Hjj = tau * xp.outer(e0, e0) + kappa * S
    Hij = -tau * a[:, :, None] * e0[None, None, :] - kappa * pad(R)
    return Hii, Hjj, Hij


def edge_blocks(graph: PoseGraph, *, rotation: bool = True, translation: bool = True):
    """:func:`edge_hessian_blocks` of ``graph``'s edges: (H_ii, H_jj, H_ij), each (m, d+1, d+1).

    ``rotation=False`` drops the kappa terms, ``translation=False`` the tau terms (so the rotation
    connection Laplacian and the tau-weighted graph Laplacian come from the same blocks).
    """
    kappa = np.asarray(graph.kappa, dtype=np.float64) if rotation else 0.0
    tau = np.asarray(graph.tau, dtype=np.float64) if translation else 0.0
    return edge_hessian_blocks(graph.R, graph.t, kappa, tau)


def full_layout_index(num_poses: int, dim: int) -> np.ndarray:
    """(n, d+1) columns of pose p's [t_p | R_p] in the layout of :func:`poses_to_matrix`:
    p (its translation), then n + d p + a (its rotation columns)."""
    p = np.arange(num_poses)[:, None]
    return np.concatenate([p, num_poses + dim * p + np.arange(dim)], 1)


def assemble_blocks(rows, cols, blocks, size: int) -> sp.csr_matrix:
    """Sparse (size x size) sum of the blocks: ``blocks[e]`` (k, l) is added at rows ``rows[e]`` (k,)
    and columns ``cols[e]`` (l,). Exact zeros of the blocks are not stored; duplicates add up."""
    blocks = np.asarray(blocks, dtype=np.float64)
    r = np.broadcast_to(np.asarray(rows)[:, :, None], blocks.shape).ravel()
    c = np.broadcast_to(np.asarray(cols)[:, None, :], blocks.shape).ravel()
    v = blocks.ravel()
    keep = v != 0.0
    return sp.csr_matrix((v[keep], (r[keep], c[keep])), shape=(size, size))


def assemble_edge_blocks(i, j, Hii, Hjj, Hij, index, size: int) -> sp.csr_matrix:
    """Symmetric sparse matrix of per-edge blocks: H_ii at (i, i), H_jj at (j, j), H_ij at (i, j)
    and H_ij^T at (j, i), where pose p's block rows/columns are ``index[p]`` (e.g.
    :func:`full_layout_index`, or ``d p + a`` for rotation blocks alone)."""
    index = np.asarray(index)
    ri, rj = index[np.asarray(i)], index[np.asarray(j)]
    rows = np.concatenate([ri, rj, ri, rj])
    cols = np.concatenate([ri, rj, rj, ri])
    blocks = np.concatenate([Hii, Hjj, Hij, np.swapaxes(Hij, 1, 2)])
    return assemble_blocks(rows, cols, blocks, size)


def data_matrix(graph: PoseGraph) -> sp.csr_matrix:
    """The data matrix M of Eq. (4), sparse ((d+1)n square), with F(X) = 1/2 tr(X M X^T).

    Column layout as :func:`poses_to_matrix`: translations first, then rotation blocks; the
    per-edge blocks are :func:`edge_blocks`. Built on the host with scipy; meant for tests,
    certificates and small problems.
    """
    n, d = graph.num_poses, graph.dim
    return assemble_edge_blocks(graph.i, graph.j, *edge_blocks(graph), full_layout_index(n, d), (d + 1) * n)


def component_labels(num_poses: int, i, j) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Connected components of the measurement graph as arrays (host-side): ``labels`` (n,), the
    component of each pose, numbered largest first (ties: by smallest pose), ``sizes`` and
    ``firsts`` (the smallest pose of each component), both in that numbering."""
    from scipy.sparse.csgraph import connected_components as _cc

    i = np.asarray(i)
    j = np.asarray(j)
    if _odometry_connects(num_poses, i, j):  # the usual pose graph: one component, no graph search
        return np.zeros(num_poses, dtype=np.int64), np.array([num_poses]), np.zeros(1, dtype=np.int64)
    A = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(num_poses, num_poses))
    k, labels = _cc(A, directed=False)
    sizes = np.bincount(labels, minlength=k)
    firsts = np.full(k, num_poses, dtype=np.int64)
    np.minimum.at(firsts, labels, np.arange(num_poses))
    order = np.lexsort((firsts, -sizes))  # new number -> old label
    renumber = np.empty(k, dtype=np.int64)
    renumber[order] = np.arange(k)
    return renumber[labels], sizes[order], firsts[order]


def _odometry_connects(num_poses: int, i: np.ndarray, j: np.ndarray) -> bool:
    """Whether edges between consecutive poses (k, k + 1) join all poses into one chain: then the
    graph is connected whatever its other edges (a test of a few microseconds, where the general
    search costs ~0.1 ms of fixed overhead, a noticeable share of a tiny graph's centralized solve)."""
    if num_poses <= 1:
        return True
    step = i - j
    low = np.minimum(i, j)[(step == 1) | (step == -1)]
    return low.size >= num_poses - 1 and bool(np.bincount(low, minlength=num_poses).astype(bool)[:-1].all())


def connected_subgraph(graph: PoseGraph, keep) -> PoseGraph | None:
    """``graph.select_edges(keep)``, or None when the kept edges leave the poses in more than one
    connected component (no relative placement of the parts to optimize)."""
    keep = np.asarray(keep, bool)
    if len(connected_components(graph.num_poses, np.asarray(graph.i)[keep], np.asarray(graph.j)[keep])) > 1:
        return None
    return graph.select_edges(keep)


def connected_components(num_poses: int, i, j) -> list[np.ndarray]:
    """Connected components of the measurement graph, largest first (host-side): each the
    ascending array of its poses."""
    labels, sizes, _ = component_labels(num_poses, i, j)
    members = np.argsort(labels, kind="stable")  # poses grouped by component, ascending within each
    return np.split(members, np.cumsum(sizes)[:-1])  # O(n), not one scan of the labels per component
