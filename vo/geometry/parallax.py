"""Triangulation angle over image regions: a floor on the angle a pixel's neighbourhood sees.

A floor on each point's own ray angle keeps the points whose flow noise happened to widen
their angle, and so shortens their depth: a biased sample. The median angle of an image
cell is nearly free of that noise and depends on where the scene is (distance, position
against the epipole), so a floor on it drops whole regions the baseline cannot resolve
without selecting points by their own noise.
"""

from __future__ import annotations

import numpy as np


def cell_median(values: np.ndarray, pts: np.ndarray, cell_px: float) -> np.ndarray:
    """Median of ``values`` over the points in each square image cell, given back per point.

    Args:
        values: ``(N,)`` a value per point.
        pts: ``(N, 2)`` pixel coordinates ``(x, y)`` of the points.
        cell_px: side of a cell in pixels (> 0).

    Returns:
        ``(N,)`` the median of ``values`` over the points sharing each point's cell.
    """
    values = np.asarray(values, dtype=np.float64)
    pts = np.asarray(pts, dtype=np.float64)
    if values.ndim != 1 or pts.shape != (values.shape[0], 2):
        raise ValueError(f"values must be (N,) and pts (N, 2), got {values.shape} and {pts.shape}")
    if not cell_px > 0:
        raise ValueError(f"cell_px must be > 0, got {cell_px}")
    if values.size == 0:
        return values.copy()
    cx = np.floor(pts[:, 0] / cell_px).astype(np.int64)
    cy = np.floor(pts[:, 1] / cell_px).astype(np.int64)
    cx -= cx.min()
    cy -= cy.min()
    cell = cy * (int(cx.max()) + 1) + cx
    order = np.lexsort((values, cell))
    c_sorted, v_sorted = cell[order], values[order]
    starts = np.flatnonzero(np.r_[True, c_sorted[1:] != c_sorted[:-1]])
    counts = np.diff(np.r_[starts, c_sorted.size])
    lo = v_sorted[starts + (counts - 1) // 2]
    hi = v_sorted[starts + counts // 2]
    med = 0.5 * (lo + hi)
    out = np.empty_like(values)
    out[order] = np.repeat(med, counts)
    return out


def local_angle_floor(angle: np.ndarray, pts: np.ndarray, valid: np.ndarray, floor: float, keep: float,
                      cell_px: float) -> tuple[np.ndarray, float]:
    """Drop the valid points whose image cell sees the scene at a median ray angle under ``floor``.

    The floor is lowered where it would drop more than ``1 - keep`` of the valid points,
    so that a step whose whole scene is far (a highway) keeps enough points to carry its
    scale; the floor then still removes the worst-resolved cells.

    Args:
        angle: ``(N,)`` ray angles (radians) of the triangulated points.
        pts: ``(N, 2)`` their pixels in the keyframe.
        valid: ``(N,)`` bool, the points triangulated so far; only these enter the medians.
        floor: the floor (radians); 0 turns the rule off.
        keep: the smallest share of the valid points kept, in [0, 1].
        cell_px: side of an image cell in pixels.

    Returns:
        ``(valid (N,) bool, floor_used)``: ``valid`` with the dropped points cleared, and
        the floor applied after the ``keep`` guard.
    """
    valid = np.asarray(valid, dtype=bool)
    if not 0.0 <= keep <= 1.0:
        raise ValueError(f"keep must be in [0, 1], got {keep}")
    if floor <= 0 or not valid.any():
        return valid.copy(), 0.0
    med = np.full(valid.shape[0], np.inf)
    med[valid] = cell_median(np.asarray(angle)[valid], np.asarray(pts)[valid], cell_px)
    used = float(min(floor, np.quantile(med[valid], 1.0 - keep))) if keep > 0 else float(floor)
    return valid & (med >= used), used
