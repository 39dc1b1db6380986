"""Pairing predicted and ground-truth poses: by frame index or by timestamp.

Timestamps go through evo's nearest-neighbour search
(:func:`evo.core.sync.matching_time_indices`); on top of it each ground-truth pose is
used at most once (evo's association may give one ground-truth pose to several
predictions), closest pair first. Frame indices (strided runs, ``frames.txt``, 13-column
files) are matched exactly, which evo has no notion of.
"""

from __future__ import annotations

import numpy as np
from evo.core.sync import matching_time_indices

DEFAULT_MAX_TIME_DIFF = 0.02  # s, as usual for TUM-format association


def match_frames(pred_frames: np.ndarray, gt_frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions of the frames present in both, in increasing frame order.

    Args:
        pred_frames: ``(N,)`` integer frame indices of the prediction (unique; for a
            repeated index its first position is used).
        gt_frames: ``(M,)`` integer frame indices of the ground truth (idem).

    Returns:
        ``(pred_pos (K,), gt_pos (K,))`` with ``pred_frames[pred_pos] ==
        gt_frames[gt_pos]``, increasing.
    """
    pf = np.asarray(pred_frames)
    gf = np.asarray(gt_frames)
    if pf.ndim != 1 or gf.ndim != 1:
        raise ValueError(f"frame arrays must be (N,), got {pf.shape} and {gf.shape}")
    _, pi, gi = np.intersect1d(pf, gf, assume_unique=False, return_indices=True)
    return pi.astype(np.int64), gi.astype(np.int64)


def match_timestamps(
    pred_times: np.ndarray, gt_times: np.ndarray, max_diff: float = DEFAULT_MAX_TIME_DIFF
) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one pairs of nearest timestamps within ``max_diff`` seconds.

    Each predicted time proposes its nearest ground-truth time (evo's
    ``matching_time_indices``); proposals are accepted closest first, each ground-truth
    time used at most once.

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
    empty = np.zeros(0, np.int64), np.zeros(0, np.int64)
    if pt.size == 0 or gt.size == 0:
        return empty
    pi, gi = (np.asarray(x, dtype=np.int64) for x in matching_time_indices(pt, gt, max_diff))
    if pi.size == 0:
        return empty
    diff = np.abs(gt[gi] - pt[pi])
    used: set[int] = set()
    keep = []
    for k in np.argsort(diff, kind="stable"):
        j = int(gi[k])
        if j in used:
            continue
        used.add(j)
        keep.append(int(k))
    keep = np.sort(np.asarray(keep, dtype=np.int64))
    return pi[keep], gi[keep]
