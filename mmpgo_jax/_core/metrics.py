"""Accuracy of an estimate against ground truth: ATE and RPE (host-side, float64 numpy).

* :func:`absolute_trajectory_error` (ATE): the estimate is first aligned to the ground truth by
  the best rigid transform (rotation + translation, **no scale**; Horn 1987 / Umeyama 1991 closed
  form on the positions), then the RMSE of the translation differences is reported. PGO fixes
  poses only up to one global rigid transform, so the alignment is needed.
* :func:`relative_pose_error` (RPE, Sturm et al. 2012): for every pair (k, k + delta) the relative
  motions P_k^{-1} P_{k+delta} (estimate) and Q_k^{-1} Q_{k+delta} (ground truth) are compared
  through E_k = (Q_k^{-1} Q_{k+delta})^{-1} (P_k^{-1} P_{k+delta}); the RMSE over k of the
  translation of E_k (metres) and of its rotation angle (degrees) are reported. RPE needs no
  alignment (it is invariant to a global rigid transform of either trajectory).

Poses follow the package convention: ``R`` (n, d, d) rotations, ``t`` (n, d) positions, with
g_i = (R_i, t_i) mapping body to world coordinates.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .lie import GROUPS
from .pose_graph import Poses

__all__ = [
    "RelativePoseError",
    "TrajectoryAccuracy",
    "absolute_trajectory_error",
    "align_poses",
    "relative_pose_error",
    "rigid_alignment",
    "trajectory_accuracy",
]


def _as_np(poses: Poses) -> tuple[np.ndarray, np.ndarray]:
    R = np.asarray(poses.R, dtype=np.float64)
    t = np.asarray(poses.t, dtype=np.float64)
    if R.ndim != 3 or t.ndim != 2 or R.shape[0] != t.shape[0] or R.shape[1:] != (t.shape[1],) * 2:
        raise ValueError(f"poses must have R (n, d, d) and t (n, d), got {R.shape} and {t.shape}")
    return R, t


def _check_pair(est: Poses, gt: Poses):
    Re, te = _as_np(est)
    Rg, tg = _as_np(gt)
    if te.shape != tg.shape:
        raise ValueError(f"estimate and ground truth differ in shape: {te.shape} vs {tg.shape}")
    return Re, te, Rg, tg


def rigid_alignment(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Q, c) minimising sum_k ||Q source_k + c - target_k||^2 over rotations Q and vectors c.

    Umeyama's closed form without scale: with centred point sets, Q = U diag(1, .., 1, s) V^T from
    the SVD U S V^T of the cross-covariance sum_k target_k source_k^T, s = sign(det(U V^T)).
    """
    P = np.asarray(source, dtype=np.float64)
    Q_ = np.asarray(target, dtype=np.float64)
    mp, mq = P.mean(axis=0), Q_.mean(axis=0)
    H = (Q_ - mq).T @ (P - mp)
    U, _, Vt = np.linalg.svd(H)
    S = np.eye(P.shape[1])
    S[-1, -1] = np.sign(np.linalg.det(U @ Vt)) or 1.0
    Q = U @ S @ Vt
    return Q, mq - Q @ mp


def absolute_trajectory_error(est: Poses, gt: Poses) -> float:
    """RMSE (same unit as the translations) of the positions after the best rigid alignment."""
    _, te, _, tg = _check_pair(est, gt)
    Q, c = rigid_alignment(te, tg)
    diff = te @ Q.T + c - tg
    return float(np.sqrt(np.mean(np.sum(diff**2, axis=-1))))


class RelativePoseError(NamedTuple):
    translation: float  # RMSE of the translational error of the relative motions (length unit)
    rotation_deg: float  # RMSE of the rotation angle of the relative-motion error, in degrees


def _rotation_angle(R: np.ndarray) -> np.ndarray:
    """Geodesic angle (radians) of rotations (k, d, d): the group's :meth:`~mmpgo_jax._core.lie.SO3.angle`
    for d = 2 or 3 (accurate near 0 and near pi, unlike arccos), else via the eigenvalues."""
    group = GROUPS.get(R.shape[-1])
    if group is not None:
        return group.angle(R)
    # general d: root-sum-square of the principal angles
    ev = np.linalg.eigvals(R)
    return np.sqrt(0.5 * np.sum(np.angle(ev) ** 2, axis=-1))


def relative_pose_error(est: Poses, gt: Poses, delta: int = 1) -> RelativePoseError:
    """RMSE of the errors of the relative motions between poses k and k + ``delta``."""
    Re, te, Rg, tg = _check_pair(est, gt)
    n = te.shape[0]
    delta = int(delta)
    if not 1 <= delta < n:
        raise ValueError(f"delta must satisfy 1 <= delta < n = {n}, got {delta}")
    a, b = slice(0, n - delta), slice(delta, n)
    # relative motions (R_k^T R_{k+delta}, R_k^T (t_{k+delta} - t_k))
    Rre = np.swapaxes(Re[a], 1, 2) @ Re[b]
    tre = np.einsum("kji,kj->ki", Re[a], te[b] - te[a])
    Rrg = np.swapaxes(Rg[a], 1, 2) @ Rg[b]
    trg = np.einsum("kji,kj->ki", Rg[a], tg[b] - tg[a])
    # E = rel_gt^{-1} rel_est = (Rrg^T Rre, Rrg^T (tre - trg))
    RE = np.swapaxes(Rrg, 1, 2) @ Rre
    tE = np.einsum("kji,kj->ki", Rrg, tre - trg)
    trans = float(np.sqrt(np.mean(np.sum(tE**2, axis=-1))))
    rot = float(np.degrees(np.sqrt(np.mean(_rotation_angle(RE) ** 2))))
    return RelativePoseError(trans, rot)


def align_poses(est: Poses, gt: Poses) -> Poses:
    """``est`` moved by the rigid transform that best aligns its positions with ``gt``'s.

    PGO determines the poses only up to one global rigid motion; this expresses the estimate in
    the ground truth's frame (for plots and per-pose comparisons).
    """
    Re, te, _, tg = _check_pair(est, gt)
    Q, c = rigid_alignment(te, tg)
    return Poses(np.einsum("ab,nbc->nac", Q, Re), te @ Q.T + c)


class TrajectoryAccuracy(NamedTuple):
    """Errors of an estimate against the ground truth, after the best rigid alignment."""

    ate: float  # RMSE of the positions (length unit)
    ate_max: float  # largest position error
    rotation_deg: float  # RMSE of the absolute rotation errors, degrees
    rpe_translation: float  # RPE (consecutive poses), translation RMSE
    rpe_rotation_deg: float  # RPE (consecutive poses), rotation RMSE in degrees


def trajectory_accuracy(est: Poses, gt: Poses) -> TrajectoryAccuracy:
    """ATE (mean and max), absolute rotation error and RPE of ``est`` against ``gt``."""
    aligned = align_poses(est, gt)
    Rg, tg = _as_np(gt)
    err = np.linalg.norm(aligned.t - tg, axis=1)
    rot = _rotation_angle(np.swapaxes(Rg, 1, 2) @ aligned.R)
    rpe = relative_pose_error(est, gt) if len(tg) > 1 else RelativePoseError(0.0, 0.0)
    return TrajectoryAccuracy(
        ate=float(np.sqrt(np.mean(err**2))),
        ate_max=float(err.max()),
        rotation_deg=float(np.degrees(np.sqrt(np.mean(rot**2)))),
        rpe_translation=rpe.translation,
        rpe_rotation_deg=rpe.rotation_deg,
    )
