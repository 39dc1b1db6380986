"""Trajectory files: KITTI (12 numbers per line), TUM (t tx ty tz qx qy qz qw).

Writers here are used by the run writer; readers are used by ``eval``.
"""

from __future__ import annotations

import numpy as np


def format_kitti_line(T_world_cam: np.ndarray) -> str:
    """One KITTI line: the top 3x4 of a ``(4, 4)`` camera-to-world pose, row-major."""
    T = np.asarray(T_world_cam, dtype=np.float64)
    return " ".join(f"{v:.9e}" for v in T[:3, :4].reshape(-1))


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(4,)`` as ``(qx, qy, qz, qw)`` with ``qw >= 0`` of a ``(3, 3)`` rotation."""
    R = np.asarray(R, dtype=np.float64)
    m = R
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        q = np.array([(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s])
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = np.array([0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s])
    elif m[1, 1] > m[2, 2]:
        s = np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = np.array([(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s])
    else:
        s = np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = np.array([(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s])
    q /= np.linalg.norm(q)
    if q[3] < 0:
        q = -q
    return q


def format_tum_line(timestamp: float, T_world_cam: np.ndarray) -> str:
    """One TUM line ``timestamp tx ty tz qx qy qz qw`` of a ``(4, 4)`` camera-to-world pose."""
    T = np.asarray(T_world_cam, dtype=np.float64)
    q = rotation_to_quaternion(T[:3, :3])
    vals = [*T[:3, 3], *q]
    return f"{timestamp:.6f} " + " ".join(f"{v:.9f}" for v in vals)
