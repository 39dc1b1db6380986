"""Working resolution and intrinsics scaling."""

from __future__ import annotations

import numpy as np

KITTI_SIZE = (256, 832)  # (H, W): the paper's working size for KITTI-like frames


def working_size(height: int, width: int, override: tuple[int, int] | None = None) -> tuple[int, int]:
    """Working resolution ``(h, w)`` for an ``(height, width)`` source image.

    KITTI-like frames (aspect ratio near 3.3) use 256x832. Others are scaled so the
    long side is at most 832, both sides rounded to multiples of 64 (at least 64).
    ``override`` (``(h, w)``) wins when given.
    """
    if override is not None:
        return int(override[0]), int(override[1])
    aspect = width / height
    if 2.8 <= aspect <= 3.8 and width >= 832:
        return KITTI_SIZE
    s = min(1.0, 832.0 / max(height, width))
    h = max(64, int(round(height * s / 64.0)) * 64)
    w = max(64, int(round(width * s / 64.0)) * 64)
    return h, w


def scale_intrinsics(K: np.ndarray, src_hw: tuple[int, int], dst_hw: tuple[int, int]) -> np.ndarray:
    """Intrinsics ``(3, 3)`` of an image resized from ``src_hw`` to ``dst_hw``.

    Uses the pixel-corner convention of ``cv2.resize``: a pixel centre ``u`` maps
    to ``(u + 0.5) * sx - 0.5``.
    """
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must be (3, 3), got {K.shape}")
    sy = dst_hw[0] / src_hw[0]
    sx = dst_hw[1] / src_hw[1]
    out = K.copy()
    out[0, 0] *= sx
    out[0, 1] *= sx
    out[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    out[1, 1] *= sy
    out[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return out
