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


def _inverse_depth_pairs(depth_est: np.ndarray, depth_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(u, v)``: the inverse depths ``(M,)`` of the pairs of ``(N,)`` depths that are both finite and > 0."""
    z = np.asarray(depth_est, dtype=np.float64)
    d = np.asarray(depth_ref, dtype=np.float64)
    if z.shape != d.shape or z.ndim != 1:
        raise ValueError(f"depth_est and depth_ref must both be (N,), got {z.shape}, {d.shape}")
    ok = np.isfinite(z) & np.isfinite(d) & (z > 0) & (d > 0)
    return 1.0 / z[ok], 1.0 / d[ok]


def _huber_weights(abs_residuals: np.ndarray, huber_k: float) -> tuple[float, np.ndarray | None]:
    """``(s, w)``: the residuals' scaled median absolute deviation and the Huber weights ``(M,)`` at
    the threshold ``huber_k * s``; ``w`` is None when ``s`` is 0 (an exact fit)."""
    s = 1.4826 * float(np.median(abs_residuals))
    if s <= 0:
        return s, None
    return s, np.minimum(1.0, huber_k * s / np.maximum(abs_residuals, 1e-300))


def fit_inverse_depth_affine(
    depth_est: np.ndarray, depth_ref: np.ndarray, min_points: int = 10, min_spread: float = 0.1,
    iters: int = 10, huber_k: float = 1.5,
) -> tuple[tuple[float, float], bool]:
    """``(a, b)`` with ``1 / depth_ref ~ a / depth_est + b``: an affine map of inverse depth.

    A two-view step whose rotation or translation direction is slightly wrong
    triangulates every point with the same error of its ray angle, i.e. an error of
    inverse depth that is the same for near and far points: such a depth is not off
    by one scale, and a rescale fitted on some of its points is wrong for the others.
    The fit is a Huber-weighted least squares line in inverse depth (residuals in
    inverse depth have about the same noise near and far), ``iters`` reweightings
    with the threshold ``huber_k`` x the residuals' scaled median absolute deviation.
    When the inverse depths span less than ``min_spread`` (10th to 90th percentile,
    relative to their median) the offset is not separable from the scale, and only
    the scale is fitted (``b = 0``, ``a`` the median ratio of inverse depths).

    Args:
        depth_est: ``(N,)`` depths to be corrected (> 0; others are ignored).
        depth_ref: ``(N,)`` better depths of the same points (> 0; others are ignored).
        min_points: fewer usable pairs than this gives ``valid = False``.

    Returns:
        ``((a, b), valid)``; not valid also when the fitted ``a`` is not positive.
    """
    u, v = _inverse_depth_pairs(depth_est, depth_ref)
    if u.size < min_points:
        return (1.0, 0.0), False
    p10, p50, p90 = np.percentile(u, [10, 50, 90])
    scale_only = (float(np.median(v / u)), 0.0)
    if (p90 - p10) < min_spread * p50:
        return scale_only, True
    w = np.ones_like(u)
    a = b = 0.0
    for _ in range(max(1, iters)):
        sw = np.sqrt(w)
        (a, b), *_ = np.linalg.lstsq(np.stack([u * sw, sw], axis=1), v * sw, rcond=None)
        _, w = _huber_weights(np.abs(v - a * u - b), huber_k)
        if w is None:
            break
    a, b = float(a), float(b)
    return (a, b), bool(np.isfinite(a) and np.isfinite(b) and a > 0)


def inverse_depth_offset_t(
    depth_est: np.ndarray, depth_ref: np.ndarray, a: float, b: float, huber_k: float = 1.5,
) -> tuple[float, bool]:
    """How many standard errors the offset of a fitted map ``1 / depth_ref ~ a / depth_est + b``
    (:func:`fit_inverse_depth_affine`) lies from zero: ``(b / a) / se(b / a)``.

    The standard error comes from the Huber-weighted normal equations of the fit (threshold
    ``huber_k`` x the residuals' scaled median absolute deviation, as in the fit), the
    residuals taken as independent. A large ``|t|`` says the points hold an offset of inverse
    depth; a small one that the offset is the fit's noise.

    Args:
        depth_est, depth_ref: ``(N,)`` the depths the map was fitted to (> 0; others are ignored).
        a, b: the fitted map (``a > 0``).

    Returns:
        ``(t, valid)``; not valid with fewer than 3 usable pairs, a degenerate system or ``a <= 0``.
    """
    u, v = _inverse_depth_pairs(depth_est, depth_ref)
    if u.size < 3 or not (np.isfinite(a) and np.isfinite(b) and a > 0):
        return 0.0, False
    s, w = _huber_weights(np.abs(v - a * u - b), huber_k)
    if w is None:  # an exact fit: any offset is certain
        return (float("inf") if b != 0 else 0.0), True
    X = np.stack([u, np.ones_like(u)], axis=1)
    N = X.T @ (w[:, None] * X)
    if not np.linalg.cond(N) < 1e12:
        return 0.0, False
    cov = s * s * np.linalg.inv(N)
    g = np.array([-b / a**2, 1.0 / a])  # d(b/a) / d(a, b)
    se = float(np.sqrt(max(g @ cov @ g, 0.0)))
    if se <= 0:
        return 0.0, False
    return float((b / a) / se), True
