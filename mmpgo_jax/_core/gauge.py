"""Fixed poses and the frame of a result.

PGO is invariant to one rigid motion applied to all poses (the gauge). Two things pin it:

* **Fixed poses** (g2o ``FIX`` lines, :class:`FixedPoses`): constraints. Every initialization
  puts them at their values, and every solver keeps them there (their tangent space is {0}: the
  inner solver never moves them). One fixed pose only fixes the gauge, so the optimum is the
  unconstrained one; two or more constrain the problem itself.
* **The frame of the result** (:func:`express_in_frame`): without fixed poses, the solvers'
  iterates live in an arbitrary gauge (the start's). Results are moved rigidly so that one
  reference pose takes a given value: for g2o files, the first pose at its VERTEX value (the
  identity when it has none), so a solved trajectory overlays its input. The cost is unchanged.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import jax
import numpy as np

from .pose_graph import HostPoses, PoseGraph, Poses, component_labels
from .precision import to_device

__all__ = ["FixedPoses", "anchor_poses", "anchor_set", "express_in_frame"]


@dataclass(frozen=True, eq=False)
class FixedPoses:
    """Poses held at given values: internal indices ``index`` (k,) ascending, ``R`` (k, d, d), ``t`` (k, d)."""

    index: np.ndarray
    R: np.ndarray
    t: np.ndarray

    def __post_init__(self):
        index = np.asarray(self.index, dtype=np.int64).reshape(-1)
        R = np.asarray(self.R, dtype=np.float64)
        t = np.asarray(self.t, dtype=np.float64)
        k = index.shape[0]
        if R.ndim != 3 or R.shape[0] != k or R.shape[1] != R.shape[2] or t.shape != (k, R.shape[-1]):
            raise ValueError(
                f"FixedPoses: need R (k, d, d) and t (k, d) for k = {k} indices, got {R.shape} and {t.shape}"
            )
        if k == 0:
            raise ValueError("FixedPoses: at least one pose index is needed")
        if np.unique(index).shape[0] != k or np.any(index < 0):
            raise ValueError("FixedPoses: indices must be distinct and non-negative")
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
            raise ValueError("FixedPoses: values must be finite")
        order = np.argsort(index)
        object.__setattr__(self, "index", index[order])
        object.__setattr__(self, "R", R[order])
        object.__setattr__(self, "t", t[order])

    @staticmethod
    def identity(index, dim: int) -> FixedPoses:
        """``index`` held at R = I, t = 0 (pose 0 alone, the usual gauge: one shared read-only instance)."""
        index = np.atleast_1d(np.asarray(index, dtype=np.int64))
        k = index.shape[0]
        if k == 1 and index[0] == 0:
            return _origin(dim)
        return FixedPoses(index, np.broadcast_to(np.eye(dim), (k, dim, dim)).copy(), np.zeros((k, dim)))

    @staticmethod
    def from_poses(index, poses: Poses) -> FixedPoses:
        """``index`` held at their values in ``poses`` (n poses)."""
        index = np.atleast_1d(np.asarray(index, dtype=np.int64))
        return FixedPoses(index, np.asarray(poses.R, np.float64)[index], np.asarray(poses.t, np.float64)[index])

    @property
    def dim(self) -> int:
        return self.R.shape[-1]

    def __len__(self) -> int:
        return self.index.shape[0]

    def check(self, num_poses: int, dim: int) -> FixedPoses:
        """Validate against a graph of ``num_poses`` poses in dimension ``dim``; returns self."""
        if self.dim != dim:
            raise ValueError(f"fixed poses are {self.dim}D, the graph is {dim}D")
        if self.index[-1] >= num_poses:
            raise ValueError(f"fixed pose index {int(self.index[-1])} is out of range for {num_poses} poses")
        return self

    def mask(self, num_poses: int) -> np.ndarray:
        """(n,) bool, True at the fixed poses."""
        out = np.zeros(num_poses, dtype=bool)
        out[self.index] = True
        return out

    def restrict(self, keep: np.ndarray) -> FixedPoses | None:
        """Re-indexed to the poses ``keep`` (ascending old indices) of a sub-graph; None if none is kept."""
        keep = np.asarray(keep, dtype=np.int64)
        new_index = np.full(int(max(keep.max(initial=-1), self.index.max())) + 1, -1)
        new_index[keep] = np.arange(keep.shape[0])
        mapped = new_index[self.index]
        sel = mapped >= 0
        if not sel.any():
            return None
        return FixedPoses(mapped[sel], self.R[sel], self.t[sel])

    def apply(self, poses: Poses) -> Poses:
        """``poses`` with the fixed poses set to their values (same dtype; set on the host; a
        :class:`HostPoses` stays on the host)."""
        R = np.array(poses.R)
        t = np.array(poses.t)
        R[self.index] = self.R
        t[self.index] = self.t
        return HostPoses(R, t) if isinstance(poses, HostPoses) else Poses(jax.device_put(R), jax.device_put(t))


@functools.cache
def _origin(dim: int) -> FixedPoses:
    """Pose 0 at R = I, t = 0, built once per dimension (its checks cost more than a tiny graph's
    iteration); its arrays are read-only, as it is shared."""
    origin = FixedPoses(np.zeros(1, dtype=np.int64), np.eye(dim)[None], np.zeros((1, dim)))
    for array in (origin.index, origin.R, origin.t):
        array.setflags(write=False)
    return origin


def express_in_frame(poses: Poses, frame: FixedPoses) -> Poses:
    """``poses`` moved rigidly (g -> T g) so that pose ``frame.index[0]`` equals its value in ``frame``.

    T = g_ref_target g_ref^-1; the PGO cost is invariant to it. Computed in float64 on the host
    (a :class:`HostPoses` is returned as one, else the result is put on the device).
    """
    R = np.asarray(poses.R, dtype=np.float64)
    t = np.asarray(poses.t, dtype=np.float64)
    k = int(frame.index[0])
    if np.array_equal(R[k], frame.R[0]) and np.array_equal(t[k], frame.t[0]):
        return poses  # already in the frame (e.g. pose 0 held at the identity): T is exactly the identity
    # T = (Ra, ta) with Ra R_k = R_target, Ra t_k + ta = t_target
    Ra = frame.R[0] @ R[k].T
    ta = frame.t[0] - Ra @ t[k]
    R_new = np.einsum("ab,nbc->nac", Ra, R)
    t_new = t @ Ra.T + ta
    dt = np.dtype(poses.R.dtype)
    if isinstance(poses, HostPoses):
        return HostPoses(R_new.astype(dt, copy=False), t_new.astype(dt, copy=False))
    return Poses(to_device(R_new, dt), to_device(t_new, dt))


def anchor_set(graph: PoseGraph, fixed: FixedPoses | None = None) -> FixedPoses:
    """The poses the initializations hold: the ``fixed`` poses at their values, plus the first pose
    of every connected component without a fixed pose, at R = I, t = 0 (pose 0 alone for a connected
    graph without fixed poses). ``graph`` may be a :class:`~mmpgo_jax._core.pose_graph.HostGraph`."""
    d = graph.dim
    labels, _, firsts = component_labels(graph.num_poses, np.asarray(graph.i), np.asarray(graph.j))
    if fixed is None:
        return FixedPoses.identity(firsts, d)
    fixed.check(graph.num_poses, d)
    held = np.zeros(firsts.size, dtype=bool)
    held[labels[fixed.index]] = True
    free_comps = firsts[~held]
    if free_comps.size == 0:
        return fixed
    ident = FixedPoses.identity(free_comps, d)
    return FixedPoses(
        np.concatenate([fixed.index, ident.index]),
        np.concatenate([fixed.R, ident.R]),
        np.concatenate([fixed.t, ident.t]),
    )


def anchor_poses(graph: PoseGraph, fixed: FixedPoses | None = None) -> np.ndarray:
    """Indices of :func:`anchor_set` (sorted ascending; ``[0]`` for a connected graph without fixed poses)."""
    return anchor_set(graph, fixed).index
