"""Optical flow to a colour image (hue = direction, saturation = magnitude)."""

from __future__ import annotations

import cv2
import numpy as np


def flow_to_rgb(flow: np.ndarray, max_magnitude: float | None = None) -> tuple[np.ndarray, float]:
    """Colour-code a dense flow field.

    Hue encodes the direction of motion in image coordinates (x right, y down):
    0 deg (red) = +x, 90 deg (yellow-green) = +y, 180 deg (cyan) = -x,
    270 deg (blue-violet) = -y. Saturation grows linearly with magnitude and
    reaches 1 at ``max_magnitude``; value is always 1, so zero flow is white.
    Non-finite vectors are drawn black.

    Args:
        flow: ``(h, w, 2)`` flow in pixels, ``flow[..., 0]`` = dx, ``flow[..., 1]`` = dy.
        max_magnitude: magnitude drawn fully saturated; None = the largest finite
            magnitude in ``flow`` (1 if the flow is all zero or non-finite).

    Returns:
        ``(rgb (h, w, 3) uint8, max_magnitude used)``.
    """
    flow = np.asarray(flow)
    if flow.ndim != 3 or flow.shape[2] != 2:
        raise ValueError(f"flow must be (h, w, 2), got {flow.shape}")
    fx = flow[..., 0].astype(np.float32)
    fy = flow[..., 1].astype(np.float32)
    finite = np.isfinite(fx) & np.isfinite(fy)
    fx = np.where(finite, fx, 0.0).astype(np.float32)
    fy = np.where(finite, fy, 0.0).astype(np.float32)
    mag = np.sqrt(fx * fx + fy * fy)
    if max_magnitude is None:
        max_magnitude = float(mag.max()) if mag.size else 0.0
    if not np.isfinite(max_magnitude) or max_magnitude <= 0:
        max_magnitude = 1.0
    angle = np.degrees(np.arctan2(fy, fx)) % 360.0  # [0, 360)
    hsv = np.empty(fx.shape + (3,), dtype=np.float32)
    hsv[..., 0] = angle
    hsv[..., 1] = np.clip(mag / max_magnitude, 0.0, 1.0)
    hsv[..., 2] = 1.0
    rgb = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)  # float32 HSV: H in [0, 360), S, V in [0, 1]
    rgb = np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8)
    rgb[~finite] = 0
    return rgb, float(max_magnitude)
