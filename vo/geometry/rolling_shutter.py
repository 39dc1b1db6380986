"""Rolling shutter: pixels seen row by row, moved to the view of one instant.

A rolling-shutter camera exposes row ``y`` of an ``H``-row image at time
``tau(y) = readout * (y - (H - 1) / 2) / H`` (in frame intervals) from the moment of
its middle row, which is the moment the frame's pose stands for. While the rows
are read the camera moves with a twist ``(omega, v)`` per frame interval, both in
the camera's own frame at that moment (``T_cam(0)_cam(tau) ~ exp(tau [omega, v])``).

To first order in ``tau`` a point ``X_tau`` seen at time ``tau`` is, in the camera at
the middle row's moment, ``X_0 = X_tau + tau (omega x X_tau + v)``: rotation moves
pixels independently of depth, translation by ``v / depth``. The functions here turn
the observed pixels into the pixels a global shutter at that moment would have seen,
so that two-view geometry, triangulation and PnP can be used unchanged.
"""

from __future__ import annotations

import cv2
import numpy as np

from trianflow_vo.geometry.se3 import rotation_log


def row_time(v: np.ndarray, height: int, readout: float) -> np.ndarray:
    """``(N,)`` capture time of pixel rows ``v`` ``(N,)`` relative to the middle row, in frame
    intervals, for an image of ``height`` rows read out in ``readout`` frame intervals."""
    return readout * (np.asarray(v, dtype=np.float64) - 0.5 * (height - 1)) / float(height)


def to_global_shutter(pts: np.ndarray, K: np.ndarray, height: int, readout: float, omega: np.ndarray,
                      v: np.ndarray | None = None, inv_depth: np.ndarray | float | None = None) -> np.ndarray:
    """Pixels ``pts`` ``(N, 2)`` of a rolling-shutter image moved to the middle row's instant.

    Args:
        pts: ``(N, 2)`` observed pixels ``(u, v)``.
        K: ``(3, 3)`` intrinsics of the image (no skew).
        height: image rows ``H`` (row ``v`` is read at :func:`row_time`).
        readout: top-to-bottom readout time in frame intervals (0 = global shutter).
        omega: ``(3,)`` angular velocity, radians per frame interval, camera frame.
        v: ``(3,)`` linear velocity per frame interval in the camera frame (the units of
            the depth), or None to correct rotation only.
        inv_depth: ``(N,)`` or scalar inverse depth of the points (needed with ``v``).

    Returns:
        ``(N, 2)`` float64 pixels; points that the correction would put behind the
        camera are returned unchanged.
    """
    pts = np.asarray(pts, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"pts must be (N, 2), got {pts.shape}")
    if readout == 0 or pts.shape[0] == 0:
        return pts.copy()
    tau = row_time(pts[:, 1], height, readout)
    K = np.asarray(K, dtype=np.float64)
    x = (pts[:, 0] - K[0, 2]) / K[0, 0]
    y = (pts[:, 1] - K[1, 2]) / K[1, 1]
    wx, wy, wz = (float(c) for c in np.asarray(omega, dtype=np.float64))
    # X0 = X + tau (omega x X (+ v)) with X = (x, y, 1) depth; dividing by depth keeps the rays
    X0 = np.empty((len(pts), 3))
    X0[:, 0] = x + tau * (wy - wz * y)
    X0[:, 1] = y + tau * (wz * x - wx)
    X0[:, 2] = 1.0 + tau * (wx * y - wy * x)
    if v is not None and inv_depth is not None:
        X0 += (tau * np.asarray(inv_depth, dtype=np.float64))[:, None] * np.asarray(v, dtype=np.float64)[None, :]
    z = X0[:, 2]
    ok = z > 1e-9
    out = pts.copy()
    out[ok, 0] = K[0, 0] * X0[ok, 0] / z[ok] + K[0, 2]
    out[ok, 1] = K[1, 1] * X0[ok, 1] / z[ok] + K[1, 2]
    return out


def twist_per_frame(T_prev_cur: np.ndarray, frames: float) -> tuple[np.ndarray, np.ndarray]:
    """``(omega (3,), v (3,))``: the constant twist (first order) that moves a camera by
    ``T_prev_cur`` ``(4, 4)`` (the later camera in the earlier one) over ``frames`` frame intervals."""
    omega = rotation_log(T_prev_cur[:3, :3])
    return omega / frames, T_prev_cur[:3, 3] / frames


def dense_inverse_depth(depth: np.ndarray, cell_px: int = 16) -> np.ndarray:
    """``(h, w)`` float64 inverse depth everywhere from a sparse ``depth`` ``(h, w)`` (0 = none).

    The translation part of :func:`to_global_shutter` needs a depth at every match. Pixels
    with depth keep theirs; the others take the mean inverse depth of their ``cell_px`` cell,
    cells without depth are filled from their neighbours (normalised convolution on the cell
    grid, at growing scales) and the grid is interpolated back to pixels. At least one pixel must have depth.
    """
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2:
        raise ValueError(f"depth must be (h, w), got {depth.shape}")
    h, w = depth.shape
    valid = depth > 0
    if not valid.any():
        raise ValueError("depth has no pixel with depth")
    inv = np.where(valid, 1.0 / np.where(valid, depth, 1.0), 0.0)
    gh, gw = max(1, -(-h // cell_px)), max(1, -(-w // cell_px))
    ph, pw = gh * cell_px - h, gw * cell_px - w
    s = np.pad(inv, ((0, ph), (0, pw))).reshape(gh, cell_px, gw, cell_px).sum((1, 3))
    n = np.pad(valid, ((0, ph), (0, pw))).reshape(gh, cell_px, gw, cell_px).sum((1, 3))
    has = (n > 0).astype(np.float32)
    grid = np.where(n > 0, s / np.maximum(n, 1), 0.0).astype(np.float32)
    sigma = 1.0
    while not has.all():
        # normalised convolution: empty cells take the Gaussian-weighted mean of the cells
        # around them, at the smallest scale that reaches cells with depth
        num = cv2.GaussianBlur(grid * has, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)
        den = cv2.GaussianBlur(has, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)
        fill = (has == 0) & (den > 1e-3)
        grid[fill] = num[fill] / den[fill]
        has[fill] = 1.0
        sigma *= 2.0
    full = cv2.resize(grid, (gw * cell_px, gh * cell_px), interpolation=cv2.INTER_LINEAR)[:h, :w]
    return np.where(valid, inv, np.maximum(full.astype(np.float64), 1e-9))
