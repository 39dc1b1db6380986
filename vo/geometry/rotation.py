"""Rotation-only fit of matches and the parallax left after removing it."""

from __future__ import annotations

import numpy as np

from trianflow_vo.camera import focal_px
from trianflow_vo.geometry.triangulation import bearings


def fit_rotation(pts1: np.ndarray, pts2: np.ndarray, K: np.ndarray, iters: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Rotation ``R`` ``(3, 3)`` best explaining ``pts2 ~ K R K^-1 pts1`` (robust Wahba/Kabsch).

    Args:
        pts1, pts2: ``(N, 2)`` matching pixels.
        K: ``(3, 3)`` intrinsics.
        iters: re-weighting passes (matches far from the fit get less weight).

    Returns:
        ``(R, parallax (N,))``: the residual of each match after rotating its ray,
        in pixels (angle times focal length).
    """
    b1 = bearings(pts1, K)
    b2 = bearings(pts2, K)
    b1 /= np.linalg.norm(b1, axis=1, keepdims=True)
    b2 /= np.linalg.norm(b2, axis=1, keepdims=True)
    f = focal_px(K)
    w = np.ones(len(b1))
    R = np.eye(3)
    res = np.zeros(len(b1))
    for _ in range(iters):
        H = (b2 * w[:, None]).T @ b1
        U, _, Vt = np.linalg.svd(H)
        S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
        R = U @ S @ Vt
        res = np.linalg.norm(b1 @ R.T - b2, axis=1) * f
        scale = max(np.median(res), 1e-3)
        w = 1.0 / (1.0 + (res / (2.0 * scale)) ** 2)
    return R, res
