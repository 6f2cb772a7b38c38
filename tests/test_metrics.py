"""Trajectory accuracy against ground truth: ATE, RPE, rigid alignment, and their use in ``solve``."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest
from lie_cases import each_dim

import mmpgo_jax as mm
from mmpgo_jax._core.geometry import rotation_2d
from mmpgo_jax._core.metrics import (
    absolute_trajectory_error,
    relative_pose_error,
    rigid_alignment,
)


def _random_rotations(rng, n, d):
    M = rng.standard_normal((n, d, d))
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    R[np.linalg.det(R) < 0, :, 0] *= -1
    return R


def _rigidly_moved(gt: mm.Poses, Q, c) -> mm.Poses:
    R = np.asarray(gt.R)
    t = np.asarray(gt.t)
    return mm.Poses(jnp.asarray(Q @ R), jnp.asarray(t @ Q.T + c))


@each_dim
def test_metrics_vanish_for_rigidly_transformed_ground_truth(d):
    rng = np.random.default_rng(d)
    n = 40
    gt = mm.Poses(jnp.asarray(_random_rotations(rng, n, d)), jnp.asarray(5.0 * rng.standard_normal((n, d))))
    Q = _random_rotations(rng, 1, d)[0]
    c = 10.0 * rng.standard_normal(d)
    est = _rigidly_moved(gt, Q, c)
    assert absolute_trajectory_error(est, gt) < 1e-12
    rpe = relative_pose_error(est, gt)
    assert rpe.translation < 1e-12 and rpe.rotation_deg < 1e-6
    rpe5 = relative_pose_error(est, gt, delta=5)
    assert rpe5.translation < 1e-12 and rpe5.rotation_deg < 1e-6
    # the alignment recovers the transform that maps est onto gt
    Qa, ca = rigid_alignment(np.asarray(est.t), np.asarray(gt.t))
    np.testing.assert_allclose(Qa, Q.T, atol=1e-12)
    np.testing.assert_allclose(ca, -Q.T @ c, atol=1e-10)


def test_ate_hand_computation():
    """Square of radius 1; estimate = 1.1 x ground truth, then rotated by 30 deg and shifted.

    By symmetry the best rigid alignment undoes the rotation and the shift but no scale remains
    (no scale in the alignment), so every point is off by 0.1 * |p| = 0.1: ATE = 0.1 exactly.
    """
    pts = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
    R = np.broadcast_to(np.eye(2), (4, 2, 2))
    gt = mm.Poses(jnp.asarray(R), jnp.asarray(pts))
    Q = np.asarray(rotation_2d(math.radians(30.0)))
    est_t = 1.1 * pts @ Q.T + np.array([3.0, -2.0])
    est = mm.Poses(jnp.asarray(Q @ R), jnp.asarray(est_t))
    assert absolute_trajectory_error(est, gt) == pytest.approx(0.1, abs=1e-12)
    # one point moved by (0.4, 0): compare with a brute-force search over the rotation angle (the
    # best translation for a given rotation matches the centroids)
    est2 = mm.Poses(gt.R, jnp.asarray(pts + np.array([[0.4, 0.0], [0, 0], [0, 0], [0, 0]])))

    theta = np.linspace(-0.5, 0.5, 200001)
    c, s = np.cos(theta)[:, None], np.sin(theta)[:, None]
    P = np.asarray(est2.t)
    Px, Py = c * P[:, 0] - s * P[:, 1], s * P[:, 0] + c * P[:, 1]  # (angles, points)
    Px = Px - Px.mean(axis=1, keepdims=True) + pts[:, 0].mean()
    Py = Py - Py.mean(axis=1, keepdims=True) + pts[:, 1].mean()
    brute = np.sqrt(np.mean((Px - pts[:, 0]) ** 2 + (Py - pts[:, 1]) ** 2, axis=1)).min()
    assert absolute_trajectory_error(est2, gt) == pytest.approx(brute, abs=1e-9)


def test_rpe_hand_computation():
    """Straight line: gt steps 1 m along x, estimate steps 1.1 m and turns 1 deg per step."""
    n = 6
    gt = mm.Poses(jnp.asarray(np.broadcast_to(np.eye(2), (n, 2, 2))),
                  jnp.asarray(np.stack([np.arange(n, dtype=float), np.zeros(n)], 1)))
    rpe = relative_pose_error(mm.Poses(gt.R, 1.1 * gt.t), gt)
    assert rpe.translation == pytest.approx(0.1, abs=1e-12) and rpe.rotation_deg == pytest.approx(0.0, abs=1e-12)
    # heading turns 1 deg per step, body-frame step length 1 m: the relative motions differ from
    # the ground truth's by a pure 1-degree rotation
    ang = np.radians(np.arange(n, dtype=float))
    R = np.stack([np.asarray(rotation_2d(a)) for a in ang])
    t = np.zeros((n, 2))
    for k in range(1, n):
        t[k] = t[k - 1] + R[k - 1] @ np.array([1.0, 0.0])
    rpe = relative_pose_error(mm.Poses(jnp.asarray(R), jnp.asarray(t)), gt)
    assert rpe.translation == pytest.approx(0.0, abs=1e-12)
    assert rpe.rotation_deg == pytest.approx(1.0, abs=1e-9)
    with pytest.raises(ValueError):
        relative_pose_error(gt, gt, delta=n)


@each_dim
def test_trajectory_accuracy_matches_definitions(d):
    """Per-pose perturbation of a rigidly moved ground truth: every field against a direct formula."""
    rng = np.random.default_rng(10 + d)
    n = 30
    gt = mm.Poses(jnp.asarray(_random_rotations(rng, n, d)), jnp.asarray(3.0 * rng.standard_normal((n, d))))
    moved = _rigidly_moved(gt, _random_rotations(rng, 1, d)[0], rng.standard_normal(d))
    noisy = mm.Poses(moved.R, moved.t + 0.05 * rng.standard_normal((n, d)))
    acc = mm.trajectory_accuracy(noisy, gt)
    assert acc.ate == pytest.approx(absolute_trajectory_error(noisy, gt), rel=1e-12)
    rpe = relative_pose_error(noisy, gt)
    assert (acc.rpe_translation, acc.rpe_rotation_deg) == pytest.approx((rpe.translation, rpe.rotation_deg), rel=1e-12)
    aligned = mm.align_poses(noisy, gt)
    err = np.linalg.norm(np.asarray(aligned.t) - np.asarray(gt.t), axis=1)
    assert acc.ate_max == pytest.approx(err.max(), rel=1e-12) and acc.ate_max >= acc.ate
    # rotation error: geodesic angle of R_gt^T R_aligned (arccos of the trace), RMS in degrees
    rel = np.swapaxes(np.asarray(gt.R), 1, 2) @ np.asarray(aligned.R)
    cos = (np.trace(rel, axis1=1, axis2=2) - (d - 2)) / 2  # d=2: tr/2, d=3: (tr-1)/2
    angles = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    assert acc.rotation_deg == pytest.approx(np.sqrt(np.mean(angles**2)), rel=1e-6, abs=1e-9)
    # the rotations were not perturbed, so every pose is off by the alignment's residual rotation alone
    np.testing.assert_allclose(angles, angles[0], atol=1e-6)


def test_solve_reports_accuracy_against_ground_truth():
    data = mm.cube_dataset(1, num_poses=200, grid=4)
    start = mm.solve(data.graph, 4, iterations=0, ground_truth=data.ground_truth)
    res = mm.solve(data.graph, 4, iterations=30, ground_truth=data.ground_truth)
    plain = mm.solve(data.graph, 4, iterations=30)
    assert plain.accuracy is None
    assert res.accuracy == mm.trajectory_accuracy(res.poses, data.ground_truth)
    # the optimum of the noisy problem is not the ground truth, but it is close (sigma_t = 2 cm)
    assert 0 < res.accuracy.ate < 0.5 and res.accuracy.ate <= start.accuracy.ate * 1.5
