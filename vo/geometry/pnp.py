"""Pose from 3-D points of a reference frame and their pixels in another frame."""

from __future__ import annotations

import cv2
import numpy as np


def solve_pnp(
    X_ref: np.ndarray, pts_cur: np.ndarray, K: np.ndarray, reproj_px: float = 1.0, min_inliers: int = 20,
    rng_seed: int = 0,
) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], bool]:
    """``(R, t)`` with ``x_cur ~ K (R X_ref + t)`` by PnP in RANSAC, refined on inliers.

    Args:
        X_ref: ``(N, 3)`` points in reference-camera coordinates.
        pts_cur: ``(N, 2)`` their pixels in the current frame.
        K: ``(3, 3)`` intrinsics.
        reproj_px: RANSAC reprojection threshold (pixels).
        min_inliers: fewer inliers gives ``valid = False``.

    Returns:
        ``((R (3, 3), t (3,), inliers (N,) bool), valid)``.
    """
    X_ref = np.ascontiguousarray(X_ref, dtype=np.float64)
    pts_cur = np.ascontiguousarray(pts_cur, dtype=np.float64)
    if X_ref.ndim != 2 or X_ref.shape[1] != 3 or pts_cur.shape != (X_ref.shape[0], 2):
        raise ValueError(f"X_ref must be (N, 3) and pts_cur (N, 2), got {X_ref.shape}, {pts_cur.shape}")
    n = X_ref.shape[0]
    empty = (np.eye(3), np.zeros(3), np.zeros(n, dtype=bool))
    if n < max(6, min_inliers):
        return empty, False
    cv2.setRNGSeed(rng_seed)
    try:
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            X_ref, pts_cur, K, None, iterationsCount=200, reprojectionError=reproj_px, confidence=0.999,
            flags=cv2.SOLVEPNP_EPNP,
        )
    except cv2.error:  # degenerate point sets can trip OpenCV's own assertions: no pose
        return empty, False
    if not ok or inl is None or len(inl) < min_inliers:
        return empty, False
    idx = inl.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(X_ref[idx], pts_cur[idx], K, None, rvec, tvec)
    R, _ = cv2.Rodrigues(rvec)
    t = tvec.ravel()
    proj = X_ref @ R.T + t
    z = proj[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (proj @ K.T)[:, :2] / z[:, None]
    err = np.linalg.norm(uv - pts_cur, axis=1)
    inliers = (z > 0) & (err < reproj_px)
    return (R, t, inliers), bool(inliers.sum() >= min_inliers)
