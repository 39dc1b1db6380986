"""Epipolar distances of matches under a fundamental matrix."""

from __future__ import annotations

import numpy as np


def _homog(pts: np.ndarray) -> np.ndarray:
    return np.concatenate([pts, np.ones((pts.shape[0], 1))], axis=1)


def epipolar_distance(F: np.ndarray, pts1: np.ndarray, pts2: np.ndarray) -> np.ndarray:
    """Distance (pixels) of each ``pts2`` to the epipolar line ``F @ pts1`` in image 2.

    Args:
        F: ``(3, 3)`` with ``x2^T F x1 = 0``.
        pts1: ``(N, 2)`` pixels in image 1.
        pts2: ``(N, 2)`` pixels in image 2.

    Returns:
        ``(N,)`` distances; this is the paper's D_epi.
    """
    if F.shape != (3, 3):
        raise ValueError(f"F must be (3, 3), got {F.shape}")
    x1 = _homog(np.asarray(pts1, dtype=np.float64))
    x2 = _homog(np.asarray(pts2, dtype=np.float64))
    lines = x1 @ F.T  # (N, 3): l2 = F x1
    num = np.abs((lines * x2).sum(1))
    den = np.sqrt(lines[:, 0] ** 2 + lines[:, 1] ** 2) + 1e-12
    return num / den


def sampson_distance(F: np.ndarray, pts1: np.ndarray, pts2: np.ndarray) -> np.ndarray:
    """Sampson distance ``(N,)`` (first-order geometric error, pixels) of matches under ``F`` ``(3, 3)``."""
    x1 = _homog(np.asarray(pts1, dtype=np.float64))
    x2 = _homog(np.asarray(pts2, dtype=np.float64))
    Fx1 = x1 @ F.T
    Ftx2 = x2 @ F
    num = (x2 * Fx1).sum(1)
    den = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2 + 1e-18
    return np.abs(num) / np.sqrt(den)


def inlier_score(d_epi: np.ndarray, threshold: float = 0.5) -> np.ndarray:
    """The paper's inlier score ``M_r = (D_epi < threshold) / (1 + D_epi)``, same shape as ``d_epi``."""
    return (d_epi < threshold).astype(np.float32) / (1.0 + d_epi.astype(np.float32))


def epipolar_distance_map(F: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """``D_epi`` ``(h, w)`` float32 of every pixel under a dense flow.

    The distance of ``x + flow(x)`` to the epipolar line ``F x`` in the second
    image, for each pixel ``x`` of the first.

    Args:
        F: ``(3, 3)`` fundamental matrix with ``x2^T F x1 = 0``.
        flow: ``(h, w, 2)`` float32 flow from image 1 to image 2, ``flow[y, x] = (dx, dy)``.
    """
    if F.shape != (3, 3) or flow.ndim != 3 or flow.shape[2] != 2:
        raise ValueError(f"F must be (3, 3) and flow (h, w, 2), got {F.shape} and {flow.shape}")
    h, w = flow.shape[:2]
    F = F.astype(np.float32)
    gx = np.arange(w, dtype=np.float32)[None, :]
    gy = np.arange(h, dtype=np.float32)[:, None]
    a = F[0, 0] * gx + F[0, 1] * gy + F[0, 2]
    b = F[1, 0] * gx + F[1, 1] * gy + F[1, 2]
    c = F[2, 0] * gx + F[2, 1] * gy + F[2, 2]
    num = np.abs(a * (gx + flow[..., 0]) + b * (gy + flow[..., 1]) + c)
    return num / (np.sqrt(a * a + b * b) + 1e-12)


def project_to_epipolar_line(F: np.ndarray, pts1: np.ndarray, pts2: np.ndarray) -> np.ndarray:
    """``pts2`` ``(N, 2)`` moved to the nearest point of their epipolar lines ``F @ pts1``.

    For matches whose first point is exact (a dense flow sampled at the keyframe's own
    pixels), all measurement noise is in ``pts2``; the noise across the line is not
    parallax, and removing it keeps it out of the triangulated ray angle.

    Args:
        F: ``(3, 3)`` with ``x2^T F x1 = 0``.
        pts1: ``(N, 2)`` pixels in image 1.
        pts2: ``(N, 2)`` pixels in image 2.

    Returns:
        ``(N, 2)`` float64 points on the lines; a point whose line is degenerate
        (the epipole itself) is returned unchanged.
    """
    if F.shape != (3, 3):
        raise ValueError(f"F must be (3, 3), got {F.shape}")
    x1 = _homog(np.asarray(pts1, dtype=np.float64))
    p2 = np.asarray(pts2, dtype=np.float64)
    lines = x1 @ F.T
    n2 = lines[:, 0] ** 2 + lines[:, 1] ** 2
    ok = n2 > 1e-24
    r = (lines[:, 0] * p2[:, 0] + lines[:, 1] * p2[:, 1] + lines[:, 2]) / np.where(ok, n2, 1.0)
    r = np.where(ok, r, 0.0)
    return p2 - r[:, None] * lines[:, :2]
