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


def fit_scale_ransac(
    depth_tri: np.ndarray, depth_ref: np.ndarray, threshold: float = 1.0, trials: int = 100,
    min_points: int = 100, sample_size: int = 3, rng: np.random.Generator | None = None,
) -> tuple[float, bool]:
    """Scale ``s`` with ``depth_ref ~ s * depth_tri`` by RANSAC on a line through the origin.

    The fit of TrianFlow's inference (reference §5): each trial fits ``s`` by least
    squares on ``sample_size`` random pairs, counts the pairs with
    ``|depth_ref - s * depth_tri| < threshold`` (depth units of ``depth_ref``), and
    the best trial's inliers give the final least-squares ``s``.

    Args:
        depth_tri: ``(N,)`` up-to-scale depths (triangulated).
        depth_ref: ``(N,)`` reference depths of the same pixels (0/NaN = unknown).
        threshold: inlier residual. trials: RANSAC trials. sample_size: pairs per trial.
        min_points: fewer than this many usable pairs (more than, as in the
            reference: ``> min_points``) gives ``valid = False``.
        rng: random generator (default: seeded 0).

    Returns:
        ``(s, valid)``; invalid also when no trial yields a positive scale.
    """
    z = np.asarray(depth_tri, dtype=np.float64)
    d = np.asarray(depth_ref, dtype=np.float64)
    if z.shape != d.shape or z.ndim != 1:
        raise ValueError(f"depth_tri and depth_ref must both be (N,), got {z.shape}, {d.shape}")
    ok = np.isfinite(z) & np.isfinite(d) & (z > 0) & (d > 0)
    z, d = z[ok], d[ok]
    if z.size <= min_points:
        return 1.0, False
    rng = np.random.default_rng(0) if rng is None else rng
    best_n, best = 0, None
    for _ in range(trials):
        i = rng.choice(z.size, sample_size, replace=False)
        s = float(z[i] @ d[i] / (z[i] @ z[i]))
        if not s > 0:
            continue
        inl = np.abs(d - s * z) < threshold
        n = int(inl.sum())
        if n > best_n:
            best_n, best = n, inl
    if best is None or best_n < sample_size:
        return 1.0, False
    s = float(z[best] @ d[best] / (z[best] @ z[best]))
    return s, s > 0
