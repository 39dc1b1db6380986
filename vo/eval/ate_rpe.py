"""Absolute trajectory error and relative pose error on associated, aligned poses."""

from __future__ import annotations

import numpy as np

from trianflow_vo.eval.segments import rotation_angle


def ate_errors(gt_poses: np.ndarray, pred_poses: np.ndarray) -> np.ndarray:
    """``(N,)`` position error (m) per frame: ``|p_pred - p_gt|``.

    Args:
        gt_poses: ``(N, 4, 4)`` ground-truth camera-to-world poses.
        pred_poses: ``(N, 4, 4)`` predicted poses of the same frames, already aligned.
    """
    G = np.asarray(gt_poses, dtype=np.float64)
    P = np.asarray(pred_poses, dtype=np.float64)
    if G.ndim != 3 or G.shape[1:] != (4, 4) or P.shape != G.shape:
        raise ValueError(f"gt_poses and pred_poses must both be (N, 4, 4), got {G.shape} and {P.shape}")
    return np.linalg.norm(P[:, :3, 3] - G[:, :3, 3], axis=1)


def rpe_errors(gt_poses: np.ndarray, pred_poses: np.ndarray, delta: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Relative pose error between frames ``i`` and ``i + delta``.

    ``E_i = inv(inv(G_i) G_{i+d}) @ inv(P_i) P_{i+d}``: its translation norm (m) and
    rotation angle (rad).

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
    rel_gt = np.linalg.inv(G[:-delta]) @ G[delta:]
    rel_pred = np.linalg.inv(P[:-delta]) @ P[delta:]
    E = np.linalg.inv(rel_gt) @ rel_pred
    return np.linalg.norm(E[:, :3, 3], axis=1), rotation_angle(E[:, :3, :3])


def rmse(x: np.ndarray) -> float:
    """Root mean square of a non-empty ``(N,)`` array."""
    x = np.asarray(x, dtype=np.float64)
    return float(np.sqrt(np.mean(x * x)))
