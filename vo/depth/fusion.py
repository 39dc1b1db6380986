"""A small depth filter: carried and new depth fused along each ray, in log depth."""

from __future__ import annotations

import numpy as np


def fuse_log_depth(d_ref: np.ndarray, w_ref: np.ndarray, d_new: np.ndarray, w_new: np.ndarray,
                   max_log_gap: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Inverse-variance fusion of carried and new depth along each ray, in log depth.

    The depth filter of the weight-free path (dense and sparse): where a carried
    depth exists (``d_ref > 0``, finite weight) and agrees with the new one within
    ``max_log_gap`` in log depth, the two are averaged with their weights and the
    weights add; elsewhere the new depth and weight are kept.

    Args:
        d_ref, w_ref: ``(N,)`` carried depth (0 = unknown) and its weight.
        d_new, w_new: ``(N,)`` new (already scaled) depth, > 0, and its weight.

    Returns:
        ``(depth (N,), weight (N,))``.
    """
    d_ref = np.asarray(d_ref, dtype=np.float64)
    d_new = np.asarray(d_new, dtype=np.float64)
    if d_ref.shape != d_new.shape or d_ref.ndim != 1:
        raise ValueError(f"d_ref and d_new must both be (N,), got {d_ref.shape}, {d_new.shape}")
    has = (d_ref > 0) & np.isfinite(w_ref) & (w_ref > 0)
    has[has] &= np.abs(np.log(d_ref[has] / d_new[has])) < max_log_gap
    log_f = np.log(d_new)
    log_f[has] = (w_ref[has] * np.log(d_ref[has]) + w_new[has] * np.log(d_new[has])) / (w_ref[has] + w_new[has])
    w_out = np.asarray(w_new, dtype=np.float64).copy()
    w_out[has] = w_ref[has] + w_new[has]
    return np.exp(log_f), w_out
