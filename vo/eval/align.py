"""Umeyama alignment of point sets (Sim(3), SE(3) or scale only)."""

from __future__ import annotations

import numpy as np


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> tuple[tuple[float, np.ndarray, np.ndarray], bool]:
    """Least-squares ``s, R, t`` with ``dst ~ s * R @ src + t`` (Umeyama 1991).

    Args:
        src: ``(N, 3)`` points.
        dst: ``(N, 3)`` points.
        with_scale: estimate ``s`` (Sim(3)); otherwise ``s = 1`` (SE(3)).

    Returns:
        ``((s, R (3, 3), t (3,)), valid)``; ``valid`` is False when the source
        points are degenerate (all equal) or fewer than 3.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"src and dst must both be (N, 3), got {src.shape} and {dst.shape}")
    n = src.shape[0]
    if n < 3:
        return (1.0, np.eye(3), np.zeros(3)), False
    mu_s = src.mean(0)
    mu_d = dst.mean(0)
    xs = src - mu_s
    xd = dst - mu_d
    var_s = (xs ** 2).sum() / n
    if var_s < 1e-12:
        return (1.0, np.eye(3), np.zeros(3)), False
    cov = xd.T @ xs / n
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / var_s) if with_scale else 1.0
    t = mu_d - s * R @ mu_s
    return (s, R, t), True
