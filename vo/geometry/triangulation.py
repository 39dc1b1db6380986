"""Mid-point triangulation in closed form (vectorised)."""

from __future__ import annotations

import numpy as np


def bearings(pts: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Rays ``(N, 3)`` with z = 1 of pixels ``pts`` ``(N, 2)`` under intrinsics ``K`` ``(3, 3)``."""
    pts = np.asarray(pts, dtype=np.float64)
    Kinv = np.linalg.inv(K)
    return np.concatenate([pts, np.ones((pts.shape[0], 1))], axis=1) @ Kinv.T


def triangulate_midpoint(
    pts1: np.ndarray,
    pts2: np.ndarray,
    K: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    min_angle: float = 1e-3,
    max_depth: float = 1e4,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mid-point of the closest approach of the two rays of each match.

    Camera 1 is at the origin; camera 2 has ``X2 = R @ X1 + t``.

    Args:
        pts1: ``(N, 2)`` pixels in image 1.
        pts2: ``(N, 2)`` pixels in image 2.
        K: ``(3, 3)`` intrinsics (both images).
        R: ``(3, 3)`` rotation; t: ``(3,)`` translation.
        min_angle: rays meeting at less than this angle (radians) are dropped as
            near-parallel (the paper's tiny-angle filter); 1e-3 rad is about half a
            pixel of parallax at f = 500 px.
        max_depth: points farther than this (in units of ``|t|``) are dropped.

    Returns:
        ``(X1 (N, 3) points in camera-1 coordinates, valid (N,) bool, angle (N,)
        ray angle in radians)``. ``valid`` is False for near-parallel rays and
        for points behind either camera or beyond ``max_depth``.
    """
    pts1 = np.asarray(pts1, dtype=np.float64)
    pts2 = np.asarray(pts2, dtype=np.float64)
    if pts1.ndim != 2 or pts1.shape[1] != 2 or pts1.shape != pts2.shape:
        raise ValueError(f"pts1 and pts2 must both be (N, 2), got {pts1.shape} and {pts2.shape}")
    t = np.asarray(t, dtype=np.float64).reshape(3)
    d1 = bearings(pts1, K)  # camera 1 frame
    d2 = bearings(pts2, K) @ R  # R^T d2: camera 2 rays in camera 1 frame
    c2 = -R.T @ t
    a = (d1 * d1).sum(1)
    b = (d1 * d2).sum(1)
    c = (d2 * d2).sum(1)
    w0 = -c2  # c1 - c2 with c1 = 0
    d = (d1 * w0).sum(1)
    e = (d2 * w0).sum(1)
    denom = a * c - b * b
    cos_angle = b / np.sqrt(a * c)
    angle = np.arccos(np.clip(cos_angle, -1.0, 1.0))
    ok = angle > min_angle
    safe = np.where(np.abs(denom) > 1e-18, denom, 1.0)
    lam1 = (b * e - c * d) / safe
    lam2 = (a * e - b * d) / safe
    P1 = d1 * lam1[:, None]
    P2 = c2[None, :] + d2 * lam2[:, None]
    X = 0.5 * (P1 + P2)
    z2 = X @ R[2] + t[2]
    base = max(np.linalg.norm(t), 1e-12)
    valid = ok & (lam1 > 0) & (lam2 > 0) & (X[:, 2] > 0) & (z2 > 0) & (X[:, 2] < max_depth * base)
    return X, valid, angle
