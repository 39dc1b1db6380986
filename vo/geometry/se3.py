"""Rigid transforms as ``(4, 4)`` matrices.

Convention: ``T_a_b`` maps points in frame b to frame a (``X_a = T_a_b @ X_b``).
``T_world_cam`` is a camera-to-world pose. A relative pose ``(R, t)`` between two
views is ``T_cam2_cam1``: ``X2 = R @ X1 + t``.
"""

from __future__ import annotations

import numpy as np


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(4, 4)`` transform from ``R`` ``(3, 3)`` and ``t`` ``(3,)``."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def invert_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid ``(4, 4)`` transform."""
    R = T[:3, :3]
    t = T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def rotation_angle(R: np.ndarray) -> float:
    """Rotation angle (radians) of a ``(3, 3)`` rotation."""
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


def skew(v: np.ndarray) -> np.ndarray:
    """``(3, 3)`` cross-product matrix of ``v`` ``(3,)``."""
    x, y, z = np.asarray(v, dtype=np.float64).reshape(3)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def rodrigues(rvec: np.ndarray) -> np.ndarray:
    """``(3, 3)`` rotation of an axis-angle vector ``(3,)``."""
    rvec = np.asarray(rvec, dtype=np.float64).reshape(3)
    theta = np.linalg.norm(rvec)
    if theta < 1e-12:
        return np.eye(3) + skew(rvec)
    k = rvec / theta
    K = skew(k)
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * (K @ K)


def rotation_log(R: np.ndarray) -> np.ndarray:
    """Axis-angle vector ``(3,)`` of a ``(3, 3)`` rotation."""
    theta = rotation_angle(R)
    if theta < 1e-9:
        return np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    if np.pi - theta < 1e-6:
        # axis from the symmetric part
        A = (R + np.eye(3)) / 2.0
        axis = np.sqrt(np.clip(np.diag(A), 0, None))
        i = int(np.argmax(axis))
        axis = A[:, i] / np.sqrt(max(A[i, i], 1e-12))
        return axis / np.linalg.norm(axis) * theta
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return w * theta / (2.0 * np.sin(theta))
