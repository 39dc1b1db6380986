"""The pinhole camera: intrinsics, the working resolution, projection and back-projection.

One type for every part of the tool (odometry, viewers, readers). Pixel
coordinates are ``(u, v)`` with the centre of the top-left pixel at ``(0, 0)``;
camera coordinates are x right, y down, z forward (OpenCV).
"""

from __future__ import annotations

from dataclasses import dataclass

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


MIN_FOCAL_PX = 1.0  # below one pixel the field of view is ~180 degrees even for a tiny image


def intrinsics_problem(K: np.ndarray, size_hw: tuple[int, int]) -> str | None:
    """Why ``K`` ``(3, 3)`` cannot be the pinhole intrinsics of ``size_hw`` ``(H, W)`` images, or None.

    Refused: non-finite entries; a focal length below :data:`MIN_FOCAL_PX` (zero or
    negative included); a principal point more than one image size outside the image,
    i.e. ``cx`` outside ``[-W, 2W]`` or ``cy`` outside ``[-H, 2H]``.
    """
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        return "the matrix is not a finite 3x3 K"
    H, W = (int(v) for v in size_hw)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if fx < MIN_FOCAL_PX or fy < MIN_FOCAL_PX:
        return f"focal lengths must be at least {MIN_FOCAL_PX:g} pixel, got fx={fx:g}, fy={fy:g}"
    if not (-W <= cx <= 2 * W) or not (-H <= cy <= 2 * H):
        return (f"principal point (cx, cy) = ({cx:g}, {cy:g}) is more than one image size outside the "
                f"{W}x{H} image (allowed: cx in [{-W}, {2 * W}], cy in [{-H}, {2 * H}])")
    return None


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


def focal_px(K: np.ndarray) -> float:
    """One focal length for angles of any direction: ``sqrt(fx * fy)`` of ``K`` ``(3, 3)``.

    A small angle ``a`` (radians) near the principal point spans ``a * fx`` pixels
    horizontally and ``a * fy`` vertically; the geometric mean is the scale that turns
    pixel distances into angles (and back) without favouring either axis.
    """
    return float(np.sqrt(K[0, 0] * K[1, 1]))


def project(X_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixels ``(N, 2)`` of camera-frame points ``(N, 3)`` (z > 0 assumed; see :meth:`PinholeCamera.project`)."""
    X_cam = np.asarray(X_cam, dtype=np.float64)
    return (X_cam @ K.T)[:, :2] / X_cam[:, 2:3]


def unproject(pts: np.ndarray, depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame points ``(N, 3)`` of pixels ``(N, 2)`` with depths (z) ``(N,)``."""
    pts = np.asarray(pts, dtype=np.float64)
    x = (pts[:, 0] - K[0, 2]) / K[0, 0]
    y = (pts[:, 1] - K[1, 2]) / K[1, 1]
    d = np.asarray(depth, dtype=np.float64)
    return np.stack([x * d, y * d, d], axis=1)


@dataclass(frozen=True)
class PinholeCamera:
    """A pinhole camera at one resolution.

    Attributes:
        K: ``(3, 3)`` intrinsics.
        size_hw: image size ``(h, w)`` in pixels.
    """

    K: np.ndarray
    size_hw: tuple[int, int]

    def __post_init__(self):
        K = np.array(self.K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"K must be (3, 3), got {K.shape}")
        h, w = (int(v) for v in self.size_hw)
        if h <= 0 or w <= 0:
            raise ValueError(f"size_hw must be positive, got {self.size_hw}")
        K.flags.writeable = False
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "size_hw", (h, w))

    @property
    def h(self) -> int:
        return self.size_hw[0]

    @property
    def w(self) -> int:
        return self.size_hw[1]

    def resized(self, size_hw: tuple[int, int]) -> PinholeCamera:
        """The same camera for the image resized (``cv2.resize``) to ``size_hw``."""
        return PinholeCamera(scale_intrinsics(self.K, self.size_hw, size_hw), size_hw)

    def project(self, X_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(pixels (N, 2), valid (N,))``: valid = in front of the camera and inside the image."""
        X_cam = np.asarray(X_cam, dtype=np.float64)
        front = X_cam[:, 2] > 0
        uv = np.full((X_cam.shape[0], 2), np.nan)
        uv[front] = project(X_cam[front], self.K)
        inside = front & (uv[:, 0] > -0.5) & (uv[:, 0] < self.w - 0.5) & (uv[:, 1] > -0.5) & (uv[:, 1] < self.h - 0.5)
        return uv, inside

    def unproject(self, pts: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Camera-frame points ``(N, 3)`` of pixels ``(N, 2)`` with depths ``(N,)``."""
        return unproject(pts, depth, self.K)
