"""Initial estimates for pose-graph optimization.

* :func:`chordal_initialization` -- the centralized chordal initialization used for the paper's
  Tables I/II (docs/conventions.md §5): relax SO(d)^n to R^{d x dn}, minimise the relaxed rotation objective
  (Eq. (22)) with R_0 = I by one sparse linear solve, project each block to SO(d) (SVD, det
  fixed), then solve the translation least-squares problem (Eq. (25)) with t_0 = 0.
* :func:`odometry_initialization` -- compose the measurements along a spanning tree (the
  odometry chain (i, i+1) when it exists).

Everything here except the distributed variant runs on the host (numpy / scipy.sparse) in
float64; the returned :class:`Poses` use the graph's float dtype.

Anchoring. The relaxed problems are invariant to a common left-multiplication of all
rotations (and a common translation offset), so one pose per connected component of the
measurement graph is fixed: the first pose (smallest index) of each component, at R = I,
t = 0. For a connected graph that is pose 0 exactly as in the paper. Poses in different
components are unrelated; this just makes the linear systems non-singular.

Cost conventions follow :mod:`mmpgo_jax._core.pose_graph`: "cost" is the sum without the 1/2 (the f = 2F
convention of the paper's tables); ``relaxed_rotation_cost`` = 2 F_R of Eq. (23).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from .._core.gauge import FixedPoses, anchor_poses, anchor_set
from .._core.geometry import project_to_so
from .._core.pose_graph import HostPoses, PoseGraph, Poses, assemble_edge_blocks, edge_blocks
from .._core.precision import to_device
from .._core.sparse import block_order, pose_order, solve_spd

__all__ = [
    "anchor_poses",
    "anchor_set",
    "chordal_initialization",
    "chordal_relaxed_rotations",
    "load_poses",
    "odometry_initialization",
    "poses_from_arrays",
    "relaxed_rotation_cost",
    "relaxed_translation_cost",
    "rotation_connection_laplacian",
    "translation_laplacian",
    "translation_rhs",
    "translations_given_rotations",
]

# --------------------------------------------------------------------------------------------
# host-side helpers
# --------------------------------------------------------------------------------------------


def _edges_np(graph: PoseGraph):
    """Edge arrays of ``graph`` as float64/int64 numpy arrays."""
    return (
        np.asarray(graph.i, dtype=np.int64),
        np.asarray(graph.j, dtype=np.int64),
        np.asarray(graph.R, dtype=np.float64),
        np.asarray(graph.t, dtype=np.float64),
        np.asarray(graph.kappa, dtype=np.float64),
        np.asarray(graph.tau, dtype=np.float64),
    )


def _float_dtype(graph: PoseGraph):
    return np.dtype(graph.R.dtype)


def rotation_connection_laplacian(graph: PoseGraph) -> sp.csr_matrix:
    """The (dn x dn) matrix L with 2 F_R(R) = tr(R L R^T), R = [R_1 .. R_n] in R^{d x dn}.

    Row/column ``d*i + a`` belongs to pose i. Blocks per edge e = (i, j) (the rotation blocks of
    :func:`~mmpgo_jax._core.pose_graph.edge_blocks` without the tau terms):
    (i, i) += kappa Rt Rt^T, (j, j) += kappa I, (i, j) -= kappa Rt, (j, i) -= kappa Rt^T.
    """
    n, d = graph.num_poses, graph.dim
    Hii, Hjj, Hij = (H[:, 1:, 1:] for H in edge_blocks(graph, translation=False))
    index = d * np.arange(n)[:, None] + np.arange(d)
    return assemble_edge_blocks(graph.i, graph.j, Hii, Hjj, Hij, index, d * n)


def translation_laplacian(graph: PoseGraph) -> sp.csr_matrix:
    """The (n x n) tau-weighted graph Laplacian of the measurement graph (the translation entries
    of :func:`~mmpgo_jax._core.pose_graph.edge_blocks` without the kappa terms)."""
    n = graph.num_poses
    Hii, Hjj, Hij = (H[:, :1, :1] for H in edge_blocks(graph, rotation=False))
    return assemble_edge_blocks(graph.i, graph.j, Hii, Hjj, Hij, np.arange(n)[:, None], n)


def translation_rhs(graph: PoseGraph, R) -> np.ndarray:
    """b (n, d) such that the translation problem (25) is  min 1/2 t^T L_tau t - <b, t> + const.

    With v_e = R_i tt_e: b_i = -sum_{e: tail i} tau_e v_e + sum_{e: head i} tau_e v_e.
    """
    I_, J_, _, tm, _, tau = _edges_np(graph)
    R = np.asarray(R, dtype=np.float64)
    n, d = graph.num_poses, graph.dim
    v = tau[:, None] * np.einsum("mab,mb->ma", R[I_], tm)
    b = np.zeros((n, d))
    np.add.at(b, I_, -v)
    np.add.at(b, J_, v)
    return b


def pose_order_of(graph: PoseGraph) -> np.ndarray:
    """The fill-reducing order of ``graph``'s poses used by every sparse solve here
    (:func:`~mmpgo_jax._core.sparse.pose_order`: METIS nested dissection)."""
    return pose_order(graph.num_poses, np.asarray(graph.i), np.asarray(graph.j))


def _order_getter(graph: PoseGraph, order) -> Callable[[], np.ndarray]:
    """``order`` (an array, a callable returning one, or None for :func:`pose_order_of`) as a
    callable computed at most once: only SuperLU needs it (PARDISO orders the matrix itself)."""
    if callable(order):
        return order
    if order is not None:
        return lambda: order
    return functools.cache(lambda: pose_order_of(graph))


def _free_mask(n: int, anchors: np.ndarray) -> np.ndarray:
    free = np.ones(n, dtype=bool)
    free[anchors] = False
    return free


# --------------------------------------------------------------------------------------------
# centralized chordal initialization
# --------------------------------------------------------------------------------------------


def chordal_relaxed_rotations(graph: PoseGraph, fixed: FixedPoses | None = None, *,
                              order=None, backend: str = "auto") -> np.ndarray:
    """Minimiser of the relaxed rotation problem (22) with the anchor poses held (:func:`anchor_set`:
    the ``fixed`` poses at their rotations, else I): (n, d, d).

    The blocks are general d x d matrices (not yet projected to SO(d)). float64 numpy. One sparse
    symmetric factorization (:func:`~mmpgo_jax._core.sparse.solve_spd`; for SuperLU in the pose
    order ``order``, an array or a callable returning one, default :func:`pose_order_of`).
    """
    n, d = graph.num_poses, graph.dim
    anchor = anchor_set(graph, fixed)
    free = _free_mask(n, anchor.index)
    # V = R^T stacked pose-major ((dn) x d): 2 F_R = tr(V^T L V). Fix V_a = I for anchors:
    # L_ff V_f = -L_fa V_a.
    L = rotation_connection_laplacian(graph).tocsr()
    fdof = np.repeat(free, d)
    L_f = L[fdof]
    Va = np.swapaxes(anchor.R, 1, 2).reshape(-1, d)  # (d*|anchors|, d): V_a = R_a^T
    order = _order_getter(graph, order)
    Vf = solve_spd(L_f[:, fdof], -(L_f[:, ~fdof] @ Va), lambda: block_order(order(), d, fdof),
                   backend=backend)
    V = np.zeros((d * n, d))
    V[fdof] = Vf
    V[~fdof] = Va
    return np.swapaxes(V.reshape(n, d, d), 1, 2)


def relaxed_rotation_cost(graph: PoseGraph, R) -> float:
    """2 F_R(R) = sum_e kappa_e ||R_i Rt_e - R_j||^2 for arbitrary d x d blocks ``R`` (n, d, d)."""
    I_, J_, Rm, _, kap, _ = _edges_np(graph)
    R = np.asarray(R, dtype=np.float64)
    res = R[I_] @ Rm - R[J_]
    return float(np.sum(kap * np.sum(res**2, axis=(1, 2))))


def relaxed_translation_cost(graph: PoseGraph, R, t) -> float:
    """2 F_t(t) = sum_e tau_e ||R_i tt_e + t_i - t_j||^2 for given rotations ``R`` (Eq. (26))."""
    I_, J_, _, tm, _, tau = _edges_np(graph)
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    res = np.einsum("mab,mb->ma", R[I_], tm) + t[I_] - t[J_]
    return float(np.sum(tau * np.sum(res**2, axis=1)))


def translations_given_rotations(graph: PoseGraph, R, fixed: FixedPoses | None = None, *,
                                 order=None, backend: str = "auto") -> np.ndarray:
    """Minimiser of the translation problem (25) for rotations ``R`` with the anchor translations
    held (:func:`anchor_set`: the ``fixed`` poses' translations, else 0); a sparse factorization as
    in :func:`chordal_relaxed_rotations`.

    Returns (n, d) float64.
    """
    n, d = graph.num_poses, graph.dim
    anchor = anchor_set(graph, fixed)
    free = _free_mask(n, anchor.index)
    L = translation_laplacian(graph).tocsr()
    b = translation_rhs(graph, R)
    t = np.zeros((n, d))
    t[anchor.index] = anchor.t
    # L_ff t_f = b_f - L_fa t_a
    L_f = L[free]
    order = _order_getter(graph, order)
    t[free] = solve_spd(L_f[:, free], b[free] - L_f[:, ~free] @ t[~free],
                        lambda: block_order(order(), 1, free), backend=backend)
    return t


def _project_np(R: np.ndarray) -> np.ndarray:
    """SO(d) projection on the host (numpy's SVD), float64."""
    return project_to_so(np.asarray(R, dtype=np.float64))


def _poses(graph: PoseGraph, R: np.ndarray, t: np.ndarray) -> Poses:
    """Host arrays as the graph's dtype, on the device (a transfer, no JAX dispatch)."""
    dt = _float_dtype(graph)
    return Poses(to_device(R, dt), to_device(t, dt))


def chordal_initialization(graph: PoseGraph, fixed: FixedPoses | None = None, *,
                           backend: str = "auto") -> Poses:
    """Centralized chordal initialization (the paper's start for Tables I/II, Section VII):
    relaxed rotations, SO(d) projection, translations by linear least squares. The anchor poses
    (:func:`anchor_set`: the ``fixed`` poses at their values, else pose 0 when connected, at
    identity) are held. ``backend``: the sparse solver
    (:func:`~mmpgo_jax._core.sparse.solve_spd`; ``"auto"`` uses MKL PARDISO for large systems when
    installed)."""
    order = _order_getter(graph, None)  # shared by both solves, computed only for SuperLU
    R = _project_np(chordal_relaxed_rotations(graph, fixed, order=order, backend=backend))
    if fixed is not None:
        R[fixed.index] = fixed.R  # exactly, not their projection
    t = translations_given_rotations(graph, R, fixed, order=order, backend=backend)
    return _poses(graph, R, t)


# --------------------------------------------------------------------------------------------
# odometry initialization
# --------------------------------------------------------------------------------------------


def _bfs_predecessors(num_nodes: int, a: np.ndarray, b: np.ndarray, source: int) -> np.ndarray:
    """Predecessor of every node in a breadth-first tree from ``source`` over the undirected edges
    (a, b) (scipy.sparse.csgraph; -9999 for the source and unreachable nodes)."""
    from scipy.sparse.csgraph import breadth_first_order

    A = sp.coo_matrix((np.ones(a.shape[0]), (a, b)), shape=(num_nodes, num_nodes)).tocsr()
    return breadth_first_order(A, source, directed=False, return_predecessors=True)[1]


def _spanning_tree(graph: PoseGraph, roots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Parent pose and parent edge of every pose in a spanning forest rooted at ``roots`` (the anchor
    poses); -1 for the roots.

    Odometry edges (|i - j| = 1) are preferred and loop closures used as few times as possible:
    the odometry edges split the poses into chains (components); a breadth-first search over the
    components, linked by loop closures and started from the components holding a root, gives each
    component the fewest loop closures to a root, and it is entered through the lowest-index loop
    closure from its predecessor component. Inside the components a second breadth-first search over
    the odometry edges, started from all roots and entry poses at once, hangs every pose from the
    nearest of them (so poses reachable from a root along the odometry chain are reached through it).
    Two scipy.sparse.csgraph searches and array operations; no Python loop over poses or edges.
    """
    from scipy.sparse.csgraph import connected_components as _components

    I_ = np.asarray(graph.i, dtype=np.int64)
    J_ = np.asarray(graph.j, dtype=np.int64)
    n = graph.num_poses
    roots = np.asarray(roots, dtype=np.int64)
    odo = np.abs(I_ - J_) == 1
    oi, oj = I_[odo], J_[odo]
    A = sp.coo_matrix((np.ones(oi.shape[0]), (oi, oj)), shape=(n, n))
    nc, lab = _components(A, directed=False)

    # components: BFS from a virtual node (nc) linked to every component that holds a root
    loop = ~odo & (lab[I_] != lab[J_])
    li, lj = lab[I_[loop]], lab[J_[loop]]
    pred_c = _bfs_predecessors(nc + 1, np.concatenate([li, np.full(roots.shape[0], nc)]),
                               np.concatenate([lj, lab[roots]]), nc)
    # the entering loop closure of every other component: the lowest-index one from its predecessor
    e_loop = np.flatnonzero(loop)
    into_j = pred_c[lj] == li  # enters lab[j] from lab[i]
    into_i = pred_c[li] == lj  # enters lab[i] from lab[j]
    comp = np.concatenate([lj[into_j], li[into_i]])
    edge = np.concatenate([e_loop[into_j], e_loop[into_i]])
    entry = np.concatenate([J_[e_loop[into_j]], I_[e_loop[into_i]]])
    source = np.concatenate([I_[e_loop[into_j]], J_[e_loop[into_i]]])
    order = np.lexsort((edge, comp))
    _, first = np.unique(comp[order], return_index=True)
    pick = order[first]
    entry, edge, source = entry[pick], edge[pick], source[pick]

    # poses: BFS over the odometry edges from a virtual node (n) linked to the roots and entry poses
    starts = np.concatenate([roots, entry])
    pred = _bfs_predecessors(n + 1, np.concatenate([oi, np.full(starts.shape[0], n)]),
                             np.concatenate([oj, starts]), n)[:n]
    parent = pred.copy()
    parent_edge = np.full(n, -1, dtype=np.int64)
    parent[roots] = -1
    parent[entry] = source
    parent_edge[entry] = edge
    inner = np.flatnonzero((pred >= 0) & (pred < n))  # reached along an odometry edge
    # that edge: the lowest-index odometry edge joining the pair
    e_odo = np.flatnonzero(odo)
    key = np.minimum(oi, oj) * n + np.maximum(oi, oj)
    korder = np.lexsort((e_odo, key))
    q = pred[inner]
    pos = np.searchsorted(key[korder], np.minimum(inner, q) * n + np.maximum(inner, q))
    parent_edge[inner] = e_odo[korder[pos]]
    if np.any(parent[np.setdiff1d(np.arange(n), roots)] < 0):  # anchor_set gives every component a root
        raise AssertionError("spanning tree does not reach every pose")
    return parent, parent_edge


def odometry_initialization(graph: PoseGraph, fixed: FixedPoses | None = None) -> Poses:
    """Compose the measurements from the anchors along a spanning tree.

    The anchors (:func:`anchor_set`) are the ``fixed`` poses at their values, else pose 0 at
    identity; each component of a disconnected graph without a fixed pose starts from its first
    pose at identity. When every consecutive pair (i, i+1) is measured the tree is the odometry
    chain; otherwise it prefers odometry edges and uses as few loop closures as possible
    (:func:`_spanning_tree`). The relative poses are composed by pointer doubling: each pose holds
    its transform from an ancestor, and every pass composes it with its ancestor's and jumps to that
    ancestor's ancestor, so ceil(log2(depth)) vectorised passes reach the roots (no Python loop over
    poses; the products are associated differently from a pose-by-pose fold, so values agree with it
    to round-off).
    """
    _, J_, Rm, tm, _, _ = _edges_np(graph)
    n, d = graph.num_poses, graph.dim
    anchor = anchor_set(graph, fixed)
    parent, parent_edge = _spanning_tree(graph, anchor.index)
    # transform (A, b) from the ancestor anc[p] to p: g_p = g_anc * (A, b)
    A = np.broadcast_to(np.eye(d), (n, d, d)).copy()
    b = np.zeros((n, d))
    anc = np.arange(n)
    child = np.flatnonzero(parent >= 0)
    e = parent_edge[child]
    fwd = J_[e] == child  # parent is the tail: g_j = g_i * (Rm, tm)
    A[child] = np.where(fwd[:, None, None], Rm[e], np.swapaxes(Rm[e], 1, 2))
    b[child] = np.where(fwd[:, None], tm[e], -np.einsum("kba,kb->ka", Rm[e], tm[e]))  # (Rm, tm)^-1
    anc[child] = parent[child]
    active = child
    while active.size:  # one pass per doubling of the depth reached
        q = anc[active]
        b[active] = b[q] + np.einsum("kab,kb->ka", A[q], b[active])
        A[active] = A[q] @ A[active]
        anc[active] = anc[q]
        active = active[anc[active] != anc[anc[active]]]
    R = np.zeros((n, d, d))
    t = np.zeros((n, d))
    R[anchor.index] = anchor.R
    t[anchor.index] = anchor.t
    R0, t0 = R[anc], t[anc]
    R = R0 @ A
    t = t0 + np.einsum("kab,kb->ka", R0, b)
    R = _project_np(R)  # remove round-off drift along long chains
    if fixed is not None:
        R[fixed.index] = fixed.R  # exactly, not their projection
    return _poses(graph, R, t)


# --------------------------------------------------------------------------------------------
# dispatcher
# --------------------------------------------------------------------------------------------


def poses_from_arrays(graph: PoseGraph, R, t, *, what: str = "initial poses", host: bool = False) -> Poses:
    """Validate (n, d, d) rotations / (n, d) translations for ``graph``, project to SO(d)
    (``host``: returned as NumPy arrays in a :class:`HostPoses`, for host-side solvers)."""
    n, d = graph.num_poses, graph.dim
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if R.shape != (n, d, d):
        raise ValueError(f"{what}: rotations must have shape ({n}, {d}, {d}), got {R.shape}")
    if t.shape != (n, d):
        raise ValueError(f"{what}: translations must have shape ({n}, {d}), got {t.shape}")
    if not (np.isfinite(R).all() and np.isfinite(t).all()):
        raise ValueError(f"{what}: contain non-finite values")
    R = _project_np(R)
    if host:
        dt = _float_dtype(graph)
        return HostPoses(R.astype(dt, copy=False), t.astype(dt, copy=False))
    return _poses(graph, R, t)


def _id_list(ids: np.ndarray, limit: int = 5) -> str:
    shown = ", ".join(map(str, ids[:limit].tolist()))
    return shown + (f", ... ({ids.size} in all)" if ids.size > limit else "")


def match_vertex_ids(file_ids, graph_ids, *, where: str) -> np.ndarray:
    """Row of ``file_ids`` holding each of ``graph_ids``; ValueError naming missing / extra ids.

    ``file_ids`` need not be sorted but must be distinct; ``where`` starts the error message.
    """
    file_ids = np.asarray(file_ids, dtype=np.int64).reshape(-1)
    graph_ids = np.asarray(graph_ids, dtype=np.int64).reshape(-1)
    if np.unique(file_ids).size != file_ids.size:
        raise ValueError(f"{where}: vertex ids are not distinct")
    order = np.argsort(file_ids, kind="stable")
    sorted_ids = file_ids[order]
    if sorted_ids.size == 0:
        raise ValueError(f"{where}: no poses")
    pos = np.minimum(np.searchsorted(sorted_ids, graph_ids), sorted_ids.size - 1)
    found = sorted_ids[pos] == graph_ids
    extra = np.setdiff1d(file_ids, graph_ids)
    if not found.all() or extra.size:
        parts = []
        if not found.all():
            parts.append(f"missing vertex ids {_id_list(np.sort(graph_ids[~found]))}")
        if extra.size:
            parts.append(f"vertex ids not in the graph {_id_list(extra)}")
        raise ValueError(f"{where}: poses do not match the graph's vertex ids ({'; '.join(parts)})")
    return order[pos]


def load_poses(graph: PoseGraph, path, *, vertex_ids=None, what: str = "initial-pose file") -> Poses:
    """Poses for ``graph`` from a ``.g2o`` file (its VERTEX lines) or an ``.npz`` with ``R``, ``t``.

    Poses are matched by vertex id: ``vertex_ids`` (n,) are the original ids of the graph's poses
    (e.g. :attr:`G2OFile.vertex_ids`; default 0..n-1). A g2o file's VERTEX lines must name exactly
    these ids (edges are optional: a poses-only file is fine); an ``.npz`` may carry them as
    ``vertex_ids`` (else its rows are taken in the graph's pose order). Missing or extra ids,
    another dimension, non-finite values: ValueError. ``what`` names the file's role in messages.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    n, d = graph.num_poses, graph.dim
    graph_ids = np.arange(n, dtype=np.int64) if vertex_ids is None else np.asarray(vertex_ids, dtype=np.int64)
    if graph_ids.shape != (n,):
        raise ValueError(f"vertex_ids must have shape ({n},), got {graph_ids.shape}")
    where = f"{what} {path}"
    if not path.exists():
        raise ValueError(f"{where}: file does not exist")
    if not path.is_file():
        raise ValueError(f"{where}: is not a file")
    if suffix == ".npz":
        with np.load(path) as z:
            missing = [k for k in ("R", "t") if k not in z.files]
            if missing:
                raise ValueError(f"{where}: .npz poses need arrays 'R' (n,d,d) and 't' (n,d); missing {missing}")
            R, t = z["R"], z["t"]
            if "vertex_ids" in z.files:
                ids = z["vertex_ids"]
                if ids.shape != (R.shape[0],) or not np.issubdtype(ids.dtype, np.integer):
                    raise ValueError(
                        f"{where}: 'vertex_ids' must be ({R.shape[0]},) integers, got {ids.dtype} {ids.shape}"
                    )
                rows = match_vertex_ids(ids, graph_ids, where=where)
                R, t = R[rows], t[rows]
            return poses_from_arrays(graph, R, t, what=where)
    if suffix == ".g2o":
        from .._io.g2o import read_g2o_poses

        f = read_g2o_poses(path)
        if f.dim != d:
            raise ValueError(f"{where}: poses are {f.dim}D, the graph is {d}D")
        rows = match_vertex_ids(f.vertex_ids, graph_ids, where=where)
        return poses_from_arrays(graph, f.R[rows], f.t[rows], what=where)
    raise ValueError(f"{where}: expected a .g2o or .npz file")
