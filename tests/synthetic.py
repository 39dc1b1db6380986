"""Synthetic two-view scenes with known K, R, t and 3-D points."""

from __future__ import annotations

import numpy as np

from trianflow_vo.geometry.se3 import rodrigues

K_TEST = np.array([[480.0, 0.0, 416.0], [0.0, 480.0, 128.0], [0.0, 0.0, 1.0]])
SIZE = (256, 832)


def project(K, X):
    x = X @ K.T
    return x[:, :2] / x[:, 2:3]


def two_view_scene(n=500, R=None, t=None, seed=0, depth=(4.0, 40.0), K=K_TEST, size=SIZE):
    """Points in front of camera 1, visible in both views. Returns pts1, pts2, X1, R, t."""
    rng = np.random.default_rng(seed)
    R = rodrigues(np.array([0.01, 0.05, -0.02])) if R is None else R
    t = np.array([0.1, -0.05, 1.0]) if t is None else np.asarray(t, dtype=float)
    pts1_all, pts2_all, X_all = [], [], []
    h, w = size
    while sum(len(p) for p in pts1_all) < n:
        u = rng.uniform(0, w, 4 * n)
        v = rng.uniform(0, h, 4 * n)
        z = rng.uniform(*depth, 4 * n)
        X = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], 1)
        X2 = X @ R.T + t
        ok = X2[:, 2] > 0.1
        p2 = project(K, X2[ok])
        inside = (p2[:, 0] >= 0) & (p2[:, 0] < w) & (p2[:, 1] >= 0) & (p2[:, 1] < h)
        X = X[ok][inside]
        pts1_all.append(project(K, X))
        pts2_all.append(p2[inside])
        X_all.append(X)
    pts1 = np.concatenate(pts1_all)[:n]
    pts2 = np.concatenate(pts2_all)[:n]
    X1 = np.concatenate(X_all)[:n]
    return pts1, pts2, X1, R, t


def angle_between(a, b):
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    return float(np.degrees(np.arccos(np.clip(a @ b, -1, 1))))


def winding(n: int, seed: int = 0) -> np.ndarray:
    """``(n, 4, 4)`` camera-to-world poses of a smooth drive, ~1 m forward per frame."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    out = [np.eye(4)]
    for _ in range(n - 1):
        S = np.eye(4)
        S[:3, :3] = Rotation.from_rotvec(rng.normal(0.0, [0.01, 0.04, 0.01])).as_matrix()
        S[:3, 3] = (rng.normal(0, 0.05), rng.normal(0, 0.02), 1.0)
        out.append(out[-1] @ S)
    return np.stack(out)


def noise_texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    """``(h, w)`` uint8 blurred uniform noise stretched to 0-255: texture SIFT and flow can match."""
    import cv2

    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (h, w)).astype(np.float32), (0, 0), 2.0)
    return ((img - img.min()) / (img.max() - img.min()) * 255).astype(np.uint8)


def plane_point(u, v):
    """World points ``(N, 3)`` of texture pixels ``(u, v)`` of an 800 x 600 texture laid on the slanted
    plane ``z = 12 + 4 (x + 6) / 12``, ``-6 <= x <= 6``, ``-4.5 <= y <= 4.5``."""
    u, v = np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64)
    return np.c_[-6 + 12 * u / 800, -4.5 + 9 * v / 600, 12 + 4 * u / 800]


def render_plane(tex: np.ndarray, T_world_cam: np.ndarray, K: np.ndarray, size_wh=(640, 480)) -> np.ndarray:
    """The 800 x 600 texture ``tex`` on the plane of :func:`plane_point` seen from ``T_world_cam``
    ``(4, 4)`` with intrinsics ``K``, rendered through the plane's homography."""
    import cv2

    corners = np.array([[0, 0], [800, 0], [800, 600], [0, 600]], dtype=np.float64)
    Xc = (plane_point(corners[:, 0], corners[:, 1]) - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]
    uv = project(K, Xc)
    H = cv2.getPerspectiveTransform(corners.astype(np.float32), uv.astype(np.float32))
    return cv2.warpPerspective(tex, H, tuple(size_wh))


def pose(rvec, t) -> np.ndarray:
    """``(4, 4)`` T_world_cam of a camera rotated by ``rvec`` (axis-angle) at world position ``t``."""
    T = np.eye(4)
    T[:3, :3] = rodrigues(np.asarray(rvec, dtype=np.float64))
    T[:3, 3] = np.asarray(t, dtype=np.float64)
    return T


def project_world(K, T_world_cam, X) -> np.ndarray:
    """``(N, 2)`` pixels of world points ``X`` ``(N, 3)`` seen from ``T_world_cam`` ``(4, 4)``."""
    return project(K, (X - T_world_cam[:3, 3]) @ T_world_cam[:3, :3])
