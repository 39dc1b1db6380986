"""Pairing predicted and ground-truth poses: by frame index or by timestamp."""

from __future__ import annotations

import numpy as np

DEFAULT_MAX_TIME_DIFF = 0.02  # s, as usual for TUM-format association


def match_frames(pred_frames: np.ndarray, gt_frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions of the frames present in both, in increasing frame order.

    Args:
        pred_frames: ``(N,)`` unique integer frame indices of the prediction.
        gt_frames: ``(M,)`` unique integer frame indices of the ground truth.

    Returns:
        ``(pred_pos (K,), gt_pos (K,))`` with ``pred_frames[pred_pos] ==
        gt_frames[gt_pos]``, increasing.
    """
    pf = np.asarray(pred_frames)
    gf = np.asarray(gt_frames)
    if pf.ndim != 1 or gf.ndim != 1:
        raise ValueError(f"frame arrays must be (N,), got {pf.shape} and {gf.shape}")
    _, pi, gi = np.intersect1d(pf, gf, assume_unique=True, return_indices=True)
    return pi.astype(np.int64), gi.astype(np.int64)


def match_timestamps(
    pred_times: np.ndarray, gt_times: np.ndarray, max_diff: float = DEFAULT_MAX_TIME_DIFF
) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one pairs of nearest timestamps within ``max_diff`` seconds.

    Each predicted time proposes its nearest ground-truth time; proposals are
    accepted closest first, each ground-truth time used at most once.

    Args:
        pred_times: ``(N,)`` increasing seconds.
        gt_times: ``(M,)`` increasing seconds.
        max_diff: largest accepted ``|t_pred - t_gt|``.

    Returns:
        ``(pred_pos (K,), gt_pos (K,))`` ordered by predicted time.
    """
    pt = np.asarray(pred_times, dtype=np.float64)
    gt = np.asarray(gt_times, dtype=np.float64)
    if pt.ndim != 1 or gt.ndim != 1:
        raise ValueError(f"timestamp arrays must be (N,), got {pt.shape} and {gt.shape}")
    if pt.size == 0 or gt.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    right = np.clip(np.searchsorted(gt, pt), 0, gt.size - 1)
    left = np.clip(right - 1, 0, gt.size - 1)
    use_left = np.abs(gt[left] - pt) <= np.abs(gt[right] - pt)
    nearest = np.where(use_left, left, right)
    diff = np.abs(gt[nearest] - pt)
    used: set[int] = set()
    pairs = []
    for i in np.argsort(diff, kind="stable"):
        j = int(nearest[i])
        if diff[i] > max_diff or j in used:
            continue
        used.add(j)
        pairs.append((int(i), j))
    pairs.sort()
    if not pairs:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    arr = np.asarray(pairs, dtype=np.int64)
    return arr[:, 0], arr[:, 1]
