"""One robust scale factor aligning triangulated depth to a reference depth."""

from __future__ import annotations

import numpy as np


def weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """Weighted median of ``values`` ``(N,)`` with non-negative ``weights`` ``(N,)``."""
    order = np.argsort(values)
    v = values[order]
    c = np.cumsum(weights[order])
    return float(v[np.searchsorted(c, 0.5 * c[-1])])


def align_scale(
    depth_tri: np.ndarray, depth_ref: np.ndarray, weights: np.ndarray | None = None, min_points: int = 10
) -> tuple[float, bool]:
    """Scale ``s`` with ``depth_ref ~ s * depth_tri``: weighted median of log ratios.

    Args:
        depth_tri: ``(N,)`` up-to-scale depths (triangulated).
        depth_ref: ``(N,)`` reference depths of the same pixels (0/NaN = unknown).
        weights: ``(N,)`` confidence of each pair (e.g. ray parallax); default 1.
        min_points: fewer usable pairs than this gives ``valid = False``.

    Returns:
        ``(s, valid)``.
    """
    depth_tri = np.asarray(depth_tri, dtype=np.float64)
    depth_ref = np.asarray(depth_ref, dtype=np.float64)
    if depth_tri.shape != depth_ref.shape or depth_tri.ndim != 1:
        raise ValueError(f"depth_tri and depth_ref must both be (N,), got {depth_tri.shape}, {depth_ref.shape}")
    w = np.ones_like(depth_tri) if weights is None else np.asarray(weights, dtype=np.float64)
    ok = np.isfinite(depth_tri) & np.isfinite(depth_ref) & (depth_tri > 0) & (depth_ref > 0) & (w > 0)
    if ok.sum() < min_points:
        return 1.0, False
    log_r = np.log(depth_ref[ok]) - np.log(depth_tri[ok])
    return float(np.exp(weighted_median(log_r, w[ok]))), True
