"""Fundamental matrix by the normalised eight-point algorithm (Hartley 1997)."""

from __future__ import annotations

import numpy as np


def _check_pts(pts1: np.ndarray, pts2: np.ndarray) -> None:
    if pts1.ndim != 2 or pts1.shape[1] != 2 or pts1.shape != pts2.shape:
        raise ValueError(f"pts1 and pts2 must both be (N, 2), got {pts1.shape} and {pts2.shape}")


def normalize_points(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hartley normalisation: centroid at 0, mean distance sqrt(2).

    Args:
        pts: ``(N, 2)`` points.

    Returns:
        ``(pts_n (N, 2), T (3, 3))`` with ``pts_n ~ T @ pts`` in homogeneous coordinates.
    """
    c = pts.mean(0)
    d = np.sqrt(((pts - c) ** 2).sum(1)).mean()
    s = np.sqrt(2.0) / max(d, 1e-12)
    T = np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])
    return (pts - c) * s, T


def eight_point(pts1: np.ndarray, pts2: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, bool]:
    """Fundamental matrix with ``x2^T F x1 = 0`` from ``N >= 8`` matches.

    Args:
        pts1: ``(N, 2)`` pixels in image 1.
        pts2: ``(N, 2)`` pixels in image 2.
        weights: optional ``(N,)`` non-negative weights (for IRLS).

    Returns:
        ``(F (3, 3), valid)``: rank-2, unit Frobenius norm. ``valid`` is False for
        fewer than 8 matches or a degenerate configuration.
    """
    pts1 = np.asarray(pts1, dtype=np.float64)
    pts2 = np.asarray(pts2, dtype=np.float64)
    _check_pts(pts1, pts2)
    if pts1.shape[0] < 8:
        return np.zeros((3, 3)), False
    p1, T1 = normalize_points(pts1)
    p2, T2 = normalize_points(pts2)
    x1, y1 = p1[:, 0], p1[:, 1]
    x2, y2 = p2[:, 0], p2[:, 1]
    A = np.stack([x2 * x1, x2 * y1, x2, y2 * x1, y2 * y1, y2, x1, y1, np.ones_like(x1)], axis=1)
    if weights is not None:
        A = A * np.asarray(weights, dtype=np.float64)[:, None]
    _, S, Vt = np.linalg.svd(A, full_matrices=False)
    if S[-2] < 1e-10 * S[0]:
        return np.zeros((3, 3)), False
    F = Vt[-1].reshape(3, 3)
    U, s, Vt2 = np.linalg.svd(F)
    F = U @ np.diag([s[0], s[1], 0.0]) @ Vt2
    F = T2.T @ F @ T1
    n = np.linalg.norm(F)
    if not np.isfinite(n) or n < 1e-15:
        return np.zeros((3, 3)), False
    return F / n, True


def essential_from_fundamental(F: np.ndarray, K1: np.ndarray, K2: np.ndarray | None = None) -> np.ndarray:
    """``E = K2^T F K1`` projected to the essential manifold (singular values 1, 1, 0)."""
    K2 = K1 if K2 is None else K2
    E = K2.T @ F @ K1
    U, _, Vt = np.linalg.svd(E)
    return U @ np.diag([1.0, 1.0, 0.0]) @ Vt


def fundamental_from_pose(R: np.ndarray, t: np.ndarray, K1: np.ndarray, K2: np.ndarray | None = None) -> np.ndarray:
    """``F = K2^-T [t]_x R K1^-1`` for ``X2 = R X1 + t``; unit Frobenius norm."""
    from trianflow_vo.geometry.se3 import skew

    K2 = K1 if K2 is None else K2
    F = np.linalg.inv(K2).T @ skew(t) @ R @ np.linalg.inv(K1)
    return F / np.linalg.norm(F)
