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
