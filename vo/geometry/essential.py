"""Essential matrix: decomposition into the four [R|t] and the cheirality check."""

from __future__ import annotations

import numpy as np

from trianflow_vo.geometry.triangulation import triangulate_midpoint


def decompose_essential(E: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The four ``(R (3, 3), t (3,))`` candidates of an essential matrix ``(3, 3)``, ``|t| = 1``."""
    if E.shape != (3, 3):
        raise ValueError(f"E must be (3, 3), got {E.shape}")
    U, _, Vt = np.linalg.svd(E)
    if np.linalg.det(U) < 0:
        U = -U
    if np.linalg.det(Vt) < 0:
        Vt = -Vt
    W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    R1 = U @ W @ Vt
    R2 = U @ W.T @ Vt
    t = U[:, 2]
    return [(R1, t), (R1, -t), (R2, t), (R2, -t)]


def choose_pose_cheirality(
    E: np.ndarray, pts1: np.ndarray, pts2: np.ndarray, K: np.ndarray
) -> tuple[tuple[np.ndarray, np.ndarray], int, bool]:
    """Pick the candidate of ``E`` that puts most points in front of both cameras.

    Args:
        E: ``(3, 3)`` essential matrix with ``x2n^T E x1n = 0``.
        pts1, pts2: ``(N, 2)`` matching pixels.
        K: ``(3, 3)`` intrinsics.

    Returns:
        ``((R, t), n_front, valid)``; ``valid`` is False when no candidate has any
        point in front, or the best is not clearly better than the second
        (ambiguous, e.g. no translation).
    """
    counts = []
    cands = decompose_essential(E)
    for R, t in cands:
        _, ok, _ = triangulate_midpoint(pts1, pts2, K, R, t, min_angle=0.0, max_depth=np.inf)
        counts.append(int(ok.sum()))
    order = np.argsort(counts)[::-1]
    best, second = counts[order[0]], counts[order[1]]
    valid = best > 0 and best > 1.5 * second
    return cands[order[0]], best, valid
