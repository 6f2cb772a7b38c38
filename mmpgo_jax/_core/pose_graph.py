"""The pose-graph model: measurements, poses, the PGO objective and its gradients.

Conventions (paper Eq. (3), NOTES §1-2):
  F(X) = 1/2 sum_e [ kappa_e ||R_i Rt_e - R_j||^2 + tau_e ||R_i tt_e + t_i - t_j||^2 ]
  f    = 2 F        (what the paper's Tables I/II and SE-Sync report)
All functions are pure and jittable; graphs and poses are pytrees.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from .geometry import sym


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

    def __add__(self, other: "Poses") -> "Poses":
        return Poses(self.R + other.R, self.t + other.t)

    def __sub__(self, other: "Poses") -> "Poses":
        return Poses(self.R - other.R, self.t - other.t)

    def scale(self, c) -> "Poses":
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

    @staticmethod
    def from_arrays(i, j, R, t, kappa, tau, num_poses: int | None = None, dtype=None) -> "PoseGraph":
        """Build a graph from array-likes; float dtype follows JAX's default unless given."""
        i = np.asarray(i, dtype=np.int64)
        j = np.asarray(j, dtype=np.int64)
        if num_poses is None:
            num_poses = int(max(i.max(initial=-1), j.max(initial=-1)) + 1)
        fdt = dtype or jnp.asarray(0.0).dtype
        return PoseGraph(
            i=jnp.asarray(i, jnp.int32),
            j=jnp.asarray(j, jnp.int32),
            R=jnp.asarray(R, fdt),
            t=jnp.asarray(t, fdt),
            kappa=jnp.asarray(kappa, fdt),
            tau=jnp.asarray(tau, fdt),
            num_poses=int(num_poses),
        )


def edge_residuals(graph: PoseGraph, poses: Poses):
    """Rotation residuals R_i Rt - R_j (m, d, d) and translation residuals R_i tt + t_i - t_j (m, d)."""
    Ri, Rj = poses.R[graph.i], poses.R[graph.j]
    rot = Ri @ graph.R - Rj
    trans = jnp.einsum("mab,mb->ma", Ri, graph.t) + poses.t[graph.i] - poses.t[graph.j]
    return rot, trans


def edge_costs(graph: PoseGraph, poses: Poses):
    """Per-edge cost kappa ||rot||^2 + tau ||trans||^2 (the f = 2F convention)."""
    rot, trans = edge_residuals(graph, poses)
    return graph.kappa * jnp.sum(rot**2, axis=(-1, -2)) + graph.tau * jnp.sum(trans**2, axis=-1)


def cost(graph: PoseGraph, poses: Poses):
    """f = 2F: the objective as reported in the paper's tables and by SE-Sync."""
    return jnp.sum(edge_costs(graph, poses))


def objective(graph: PoseGraph, poses: Poses):
    """F of Eq. (3) (with the 1/2)."""
    return 0.5 * cost(graph, poses)


def euclidean_gradient(graph: PoseGraph, poses: Poses) -> Poses:
    """Euclidean gradient of F with respect to (R, t), as a ``Poses`` of the same shapes."""
    rot, trans = edge_residuals(graph, poses)
    wr = graph.kappa[:, None, None] * rot
    wt = graph.tau[:, None] * trans
    n = graph.num_poses
    gRi = wr @ jnp.swapaxes(graph.R, -1, -2) + wt[:, :, None] * graph.t[:, None, :]
    gR = jax.ops.segment_sum(gRi, graph.i, n) - jax.ops.segment_sum(wr, graph.j, n)
    gt = jax.ops.segment_sum(wt, graph.i, n) - jax.ops.segment_sum(wt, graph.j, n)
    return Poses(gR, gt)


def riemannian_gradient_from_euclidean(poses: Poses, egrad: Poses) -> Poses:
    """Project a Euclidean gradient onto the tangent space of R^{d x n} x SO(d)^n (B.9-B.11)."""
    RtG = jnp.swapaxes(poses.R, -1, -2) @ egrad.R
    return Poses(egrad.R - poses.R @ sym(RtG), egrad.t)


def riemannian_gradient(graph: PoseGraph, poses: Poses) -> Poses:
    """grad F at ``poses`` (Eqs. B.9-B.11)."""
    return riemannian_gradient_from_euclidean(poses, euclidean_gradient(graph, poses))


def tangent_norm(v: Poses):
    """Frobenius norm of a tangent vector (or any Poses-shaped array pair)."""
    return jnp.sqrt(jnp.sum(v.R**2) + jnp.sum(v.t**2))


def riemannian_gradient_norm(graph: PoseGraph, poses: Poses):
    """||grad F|| (of F, the 1/2 convention)."""
    return tangent_norm(riemannian_gradient(graph, poses))


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


def data_matrix(graph: PoseGraph) -> sp.csr_matrix:
    """The data matrix M of Eq. (4), sparse ((d+1)n square), with F(X) = 1/2 tr(X M X^T).

    Column layout as :func:`poses_to_matrix`: translations first, then rotation blocks.
    Built on the host with scipy; meant for tests and small problems.
    """
    n, d = graph.num_poses, graph.dim
    I_ = np.asarray(graph.i)
    J_ = np.asarray(graph.j)
    Rm = np.asarray(graph.R, dtype=np.float64)
    tm = np.asarray(graph.t, dtype=np.float64)
    kap = np.asarray(graph.kappa, dtype=np.float64)
    tau = np.asarray(graph.tau, dtype=np.float64)
    rows, cols, vals = [], [], []

    def add(r, c, v):
        rows.append(np.broadcast_to(r, v.shape).ravel())
        cols.append(np.broadcast_to(c, v.shape).ravel())
        vals.append(v.ravel())

    # Translation residual r = X a with a[i] = 1, a[j] = -1, a[rot block of i] = tt.
    # Rotation residual   Q = X B with B[rot block of i] = Rt, B[rot block of j] = -I.
    ar = np.arange(d)
    ri = n + d * I_[:, None] + ar  # (m, d) rotation columns of pose i
    rj = n + d * J_[:, None] + ar
    ti, tj = I_[:, None], J_[:, None]
    # tau * a a^T
    idx = np.concatenate([ti, tj, ri], 1)  # (m, d+2)
    coef = np.concatenate([np.ones((len(I_), 1)), -np.ones((len(I_), 1)), tm], 1)
    add(idx[:, :, None], idx[:, None, :], tau[:, None, None] * coef[:, :, None] * coef[:, None, :])
    # kappa * B B^T : blocks (i,i) = Rt Rt^T = I, (j,j) = I, (i,j) = -Rt, (j,i) = -Rt^T
    eye = np.broadcast_to(np.eye(d), Rm.shape)
    add(ri[:, :, None], ri[:, None, :], kap[:, None, None] * (Rm @ np.swapaxes(Rm, 1, 2)))
    add(rj[:, :, None], rj[:, None, :], kap[:, None, None] * eye)
    add(ri[:, :, None], rj[:, None, :], -kap[:, None, None] * Rm)
    add(rj[:, :, None], ri[:, None, :], -kap[:, None, None] * np.swapaxes(Rm, 1, 2))
    size = (d + 1) * n
    M = sp.coo_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(size, size)
    )
    return M.tocsr()


def connected_components(num_poses: int, i, j) -> list[np.ndarray]:
    """Connected components of the measurement graph, largest first (host-side)."""
    from scipy.sparse.csgraph import connected_components as _cc

    i = np.asarray(i)
    j = np.asarray(j)
    A = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(num_poses, num_poses))
    k, labels = _cc(A, directed=False)
    comps = [np.flatnonzero(labels == c) for c in range(k)]
    comps.sort(key=lambda c: (-len(c), c[0]))
    return comps
