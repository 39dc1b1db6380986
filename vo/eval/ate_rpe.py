"""Absolute trajectory error and relative pose error on associated, aligned poses.

ATE is evo's APE on the translation part (:class:`evo.core.metrics.APE`). RPE stays
here: evo's RPE inverts poses by transposing their rotation and measures angles with
``so3_log``, which refuses rotations more than 1e-6 off orthonormal, while rotations read
from files (KITTI, 7-Scenes) are orthonormal to ~1e-7 only: evo's numbers differ from the
devkit-style ones (exact inverse, ``acos`` of the trace, as the segment metric) by up to
1e-2 relative on rotation, and evo raises on 7-Scenes ground truth.

Before the relative rotations of RPE, both trajectories' rotations are replaced by the
nearest rotation (SVD, :func:`vo.eval.segments.nearest_rotation`): with the rotations
as read, the ~1e-7 non-orthonormality of KITTI ground truth biases the
``acos((trace - 1) / 2)`` of the small frame-to-frame rotations (RPE rotation RMSE of
KITTI 09 +0.18 %, its mean -1.2 %). The segment metric keeps the rotations as read, to
reproduce the published numbers (there the angles are large and the change is ~1e-5
relative).
"""

from __future__ import annotations

import numpy as np
from evo.core import metrics as _evo_metrics
from evo.core.trajectory import PosePath3D

from trianflow_vo.eval.segments import nearest_rotation, rotation_angle


def _pair(gt_poses, pred_poses) -> tuple[PosePath3D, PosePath3D]:
    """Both as evo paths (arrays are checked to be ``(N, 4, 4)`` of the same N)."""
    if isinstance(gt_poses, PosePath3D) and isinstance(pred_poses, PosePath3D):
        if gt_poses.num_poses != pred_poses.num_poses:
            raise ValueError(f"the paths must have the same number of poses, got {gt_poses.num_poses} and "
                             f"{pred_poses.num_poses}")
        return gt_poses, pred_poses
    G = np.asarray(gt_poses, dtype=np.float64)
    P = np.asarray(pred_poses, dtype=np.float64)
    if G.ndim != 3 or G.shape[1:] != (4, 4) or P.shape != G.shape or G.shape[0] == 0:
        raise ValueError(f"gt_poses and pred_poses must both be (N, 4, 4), got {G.shape} and {P.shape}")
    return PosePath3D(poses_se3=list(G)), PosePath3D(poses_se3=list(P))


def ate_errors(gt_poses, pred_poses) -> np.ndarray:
    """``(N,)`` position error (m) per frame: ``|p_pred - p_gt|`` (evo's APE, translation part).

    Args:
        gt_poses: ``(N, 4, 4)`` ground-truth camera-to-world poses (or an evo path).
        pred_poses: ``(N, 4, 4)`` predicted poses of the same frames, already aligned
            (or an evo path).
    """
    if not isinstance(gt_poses, PosePath3D) and np.asarray(gt_poses).shape == (0, 4, 4) == np.asarray(pred_poses).shape:
        return np.zeros(0)
    ref, est = _pair(gt_poses, pred_poses)
    ape = _evo_metrics.APE(_evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    return np.asarray(ape.error, dtype=np.float64)


def rpe_errors(gt_poses: np.ndarray, pred_poses: np.ndarray, delta: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Relative pose error between frames ``i`` and ``i + delta``.

    ``E_i = inv(inv(G_i) G_{i+d}) @ inv(P_i) P_{i+d}``: its translation norm (m) and
    rotation angle (rad), after replacing every rotation of both trajectories by its
    nearest rotation (SVD). Exact inverses and the devkit's ``acos`` angle (see the
    module docstring for why this is not evo's RPE).

    Args:
        gt_poses: ``(N, 4, 4)`` ground-truth camera-to-world poses.
        pred_poses: ``(N, 4, 4)`` predicted poses of the same frames, already aligned
            (the scale matters, the rigid part of the alignment does not).
        delta: frame gap (>= 1).

    Returns:
        ``(trans (N - delta,), rot_rad (N - delta,))``; empty when ``N <= delta``.
    """
    G = np.asarray(gt_poses, dtype=np.float64)
    P = np.asarray(pred_poses, dtype=np.float64)
    if G.ndim != 3 or G.shape[1:] != (4, 4) or P.shape != G.shape:
        raise ValueError(f"gt_poses and pred_poses must both be (N, 4, 4), got {G.shape} and {P.shape}")
    if delta < 1:
        raise ValueError(f"delta must be >= 1, got {delta}")
    if G.shape[0] <= delta:
        return np.zeros(0), np.zeros(0)
    G, P = nearest_rotation(G), nearest_rotation(P)
    rel_gt = np.linalg.inv(G[:-delta]) @ G[delta:]
    rel_pred = np.linalg.inv(P[:-delta]) @ P[delta:]
    E = np.linalg.inv(rel_gt) @ rel_pred
    return np.linalg.norm(E[:, :3, 3], axis=1), rotation_angle(E[:, :3, :3])


def rmse(x: np.ndarray) -> float:
    """Root mean square of a non-empty ``(N,)`` array."""
    x = np.asarray(x, dtype=np.float64)
    return float(np.sqrt(np.mean(x * x)))
