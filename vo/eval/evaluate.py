"""The eval protocol end to end: associate, re-base, align, segment metric, ATE, RPE.

evo does the trajectory types, the timestamp association, the Umeyama fit and its
application, and ATE (APE); see :mod:`vo.eval.align`, :mod:`vo.eval.associate`,
:mod:`vo.eval.ate_rpe` and :mod:`vo.eval.segments` for what stays ours and why.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from evo.core import metrics as _evo_metrics
from evo.core.trajectory import PosePath3D

from trianflow_vo.errors import InputError
from trianflow_vo.eval.align import ALIGN_MODES, align_paths, as_path, degenerate_message, path_poses
from trianflow_vo.eval.associate import DEFAULT_MAX_TIME_DIFF, match_frames
from trianflow_vo.eval.ate_rpe import rmse, rpe_errors
from trianflow_vo.eval.loader import MIN_COMMON_FRAMES, Association, associate, load_ground_truth, load_prediction
from trianflow_vo.eval.segments import (
    DEFAULT_LENGTHS,
    DEFAULT_STEP,
    PROTOCOLS,
    SegmentErrors,
    path_distances,
    segment_errors,
    segment_errors_all_gt,
    summarize_segments,
)


@dataclass(frozen=True)
class EvalResult:
    """Metrics plus the arrays behind them (for plots and viewers).

    Attributes:
        metrics: the JSON-ready dict (see :func:`evaluate`).
        pred_aligned: ``(K, 4, 4)`` prediction re-based and aligned onto ``gt_rebased``.
        gt_rebased: ``(K, 4, 4)`` ground truth re-based to its first common frame.
        frames: ``(K,)`` frame indices, or None (matched by timestamp).
        segments: the per-segment errors.
        ate: ``(K,)`` position error per frame (m).
    """

    metrics: dict
    pred_aligned: np.ndarray
    gt_rebased: np.ndarray
    frames: np.ndarray | None
    segments: SegmentErrors
    ate: np.ndarray

    def paths(self) -> tuple[PosePath3D, PosePath3D]:
        """``(gt_rebased, pred_aligned)`` as new evo paths (e.g. for ``evo.tools.plot``)."""
        return as_path(self.gt_rebased), as_path(self.pred_aligned)


def suggest_lengths(path_length: float) -> list[float]:
    """Eight round segment lengths (1, 2 or 5 x 10^k steps) that fit in ``path_length`` m."""
    if not path_length > 0:
        return []
    target = path_length / 8.0
    k = math.floor(math.log10(target))
    step = max(m * 10.0**k for m in (1, 2, 5) if m * 10.0**k <= target)
    return [step * i for i in range(1, 9)]


def _fmt_len(x: float) -> str:
    return f"{x:g}"


def evaluate_associated(
    pred_poses: np.ndarray,
    gt_poses: np.ndarray,
    align: str = "7dof",
    lengths=DEFAULT_LENGTHS,
    step: int = DEFAULT_STEP,
    frames: np.ndarray | None = None,
    protocol: str = "kept-frames",
    gt_all: np.ndarray | None = None,
    gt_all_frames: np.ndarray | None = None,
) -> EvalResult:
    """Protocol steps 2-5 on poses already associated one-to-one (same frames, in order).

    Args:
        pred_poses: ``(K, 4, 4)`` predicted camera-to-world poses (or an evo path).
        gt_poses: ``(K, 4, 4)`` ground-truth camera-to-world poses (or an evo path).
        align: ``"7dof"``, ``"6dof"``, ``"scale"`` or ``"none"``.
        lengths: segment lengths (m).
        step: first frames every ``step`` kept frames (``"kept-frames"``), or every
            ``step`` ground-truth frames (``"kitti-odom-eval"``).
        frames: ``(K,)`` frame indices (needed by ``"kitti-odom-eval"``, else only recorded).
        protocol: ``"kept-frames"`` (default) or ``"kitti-odom-eval"``: which segments
            the KITTI metric uses (see :mod:`vo.eval.segments`).
        gt_all: ``(M, 4, 4)`` the whole ground truth, and ``gt_all_frames`` ``(M,)`` its
            frame indices: needed by ``"kitti-odom-eval"`` only.

    Raises:
        InputError: fewer than 3 frames, a degenerate alignment, or
            ``"kitti-odom-eval"`` without frame indices.
    """
    pred = path_poses(pred_poses) if isinstance(pred_poses, PosePath3D) else np.asarray(pred_poses, dtype=np.float64)
    gt = path_poses(gt_poses) if isinstance(gt_poses, PosePath3D) else np.asarray(gt_poses, dtype=np.float64)
    if pred.ndim != 3 or pred.shape[1:] != (4, 4) or pred.shape != gt.shape:
        raise ValueError(f"pred_poses and gt_poses must both be (K, 4, 4), got {pred.shape} and {gt.shape}")
    if align not in ALIGN_MODES:
        raise InputError(f"unknown alignment {align!r}; expected one of {', '.join(ALIGN_MODES)}")
    lengths = [float(x) for x in lengths]
    if not lengths or any(not (math.isfinite(x) and x > 0) for x in lengths):
        raise InputError(f"segment lengths must be positive numbers, got {lengths}")
    if pred.shape[0] < MIN_COMMON_FRAMES:
        raise InputError(f"only {pred.shape[0]} common frame(s); need at least {MIN_COMMON_FRAMES}")
    if protocol not in PROTOCOLS:
        raise InputError(f"unknown protocol {protocol!r}; expected one of {', '.join(PROTOCOLS)}")
    pred_gt_pos = None
    if protocol == "kitti-odom-eval":
        if frames is None or gt_all is None or gt_all_frames is None:
            raise InputError("--protocol kitti-odom-eval needs frame indices (it starts segments at ground-truth "
                             "frames 0, 10, 20, ...): not available when matched by timestamp")
        gt_all = np.asarray(gt_all, dtype=np.float64)
        gaf = np.asarray(gt_all_frames, dtype=np.int64)
        fr = np.asarray(frames, dtype=np.int64)
        pred_gt_pos = np.searchsorted(gaf, fr)
        found = pred_gt_pos < gaf.size
        if np.any(np.diff(gaf) <= 0) or not found.all() or np.any(gaf[pred_gt_pos] != fr):
            raise ValueError("gt_all_frames must be increasing and hold every one of frames")
    est, ref = as_path(pred), as_path(gt)
    (s, R, t), valid = align_paths(est, ref, align)
    if not valid:
        raise InputError(degenerate_message(align))
    pred_aligned, gt_r = path_poses(est), path_poses(ref)
    if protocol == "kitti-odom-eval":
        seg = segment_errors_all_gt(gt_all, pred_aligned, pred_gt_pos, lengths, step)
    else:
        seg = segment_errors(gt_r, pred_aligned, lengths, step)
    seg_summary = summarize_segments(seg, lengths)
    ape = _evo_metrics.APE(_evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    ate = np.asarray(ape.error, dtype=np.float64)
    rpe_t, rpe_r = rpe_errors(gt_r, pred_aligned, 1)
    path_length = float(path_distances(ref.positions_xyz)[-1])
    note = ""
    if seg_summary["num_segments"] == 0:
        sugg = ",".join(_fmt_len(x) for x in suggest_lengths(path_length))
        note = (
            f"no segment: the ground-truth path of the common frames is {path_length:.1f} m, "
            f"shorter than the shortest segment length ({_fmt_len(min(lengths))} m)"
            + (f"; try --lengths {sugg}" if sugg else "")
        )
    metrics = {
        "t_err": seg_summary["t_err"],
        "r_err": seg_summary["r_err"],
        "ate_rmse": float(ape.get_statistic(_evo_metrics.StatisticsType.rmse)),
        "ate_mean": float(ape.get_statistic(_evo_metrics.StatisticsType.mean)),
        "ate_max": float(ape.get_statistic(_evo_metrics.StatisticsType.max)),
        "rpe_trans": rmse(rpe_t),
        "rpe_rot": float(np.degrees(rmse(rpe_r))),
        "rpe_trans_mean": float(rpe_t.mean()),
        "rpe_rot_mean": float(np.degrees(rpe_r.mean())),
        "num_frames": int(pred.shape[0]),
        "num_segments": seg_summary["num_segments"],
        "align": align,
        "protocol": protocol,
        "scale": float(s),
        "lengths": lengths,
        "step": int(step),
        "path_length": path_length,
        "per_length": seg_summary["per_length"],
        "units": {
            "t_err": "%",
            "r_err": "deg/100m",
            "ate": "m",
            "rpe_trans": "m",
            "rpe_rot": "deg",
            "path_length": "m",
        },
    }
    if note:
        metrics["note"] = note
    frames_arr = None if frames is None else np.asarray(frames, dtype=np.int64)
    return EvalResult(metrics, pred_aligned, gt_r, frames_arr, seg, ate)


def evaluate(
    pred_poses: np.ndarray,
    pred_frames: np.ndarray | None,
    gt_poses: np.ndarray,
    gt_frames: np.ndarray | None = None,
    align: str = "7dof",
    lengths=DEFAULT_LENGTHS,
    step: int = DEFAULT_STEP,
    protocol: str = "kept-frames",
) -> dict:
    """Evaluate a predicted trajectory against ground truth (the ``trianflow-vo eval`` protocol).

    1. Keep the frames present in both, in frame order.
    2. Re-base both to their first common frame (it becomes identity).
    3. Align: ``"7dof"`` Umeyama with scale on positions, applied to whole poses
       (rotation ``R @ R_i``, position ``s R p_i + t``); ``"6dof"`` without scale;
       ``"scale"`` least-squares scale only; ``"none"``.
    4. KITTI segment metric: cumulative ground-truth path length over the kept frames,
       first frames every ``step`` kept frames, for each length L whose end frame (first
       one more than L further along the path) exists the relative-pose error; ``t_err``
       = mean translation error / L (%), ``r_err`` = mean rotation angle / L (deg/100 m).
       With ``protocol="kitti-odom-eval"`` the segments follow that script instead:
       distances along every ground-truth frame, first frames the ground-truth frames
       0, ``step``, 2 ``step``, ..., a segment dropped when its first or end frame is not
       predicted (the same as the default when every ground-truth frame is predicted).
    5. ATE (position error after alignment) and RPE between consecutive kept frames
       (rotations replaced by the nearest rotation first, see :mod:`vo.eval.ate_rpe`).

    Args:
        pred_poses: ``(N, 4, 4)`` predicted camera-to-world poses.
        pred_frames: ``(N,)`` unique frame indices of ``pred_poses``, or None for
            ``0..N-1``.
        gt_poses: ``(M, 4, 4)`` ground-truth camera-to-world poses.
        gt_frames: ``(M,)`` unique frame indices, or None for ``0..M-1``.
        align: ``"7dof"`` (default), ``"6dof"``, ``"scale"``, ``"none"``.
        lengths: segment lengths in metres (default 100, 200, ..., 800).
        step: first-frame spacing in kept frames (default 10).
        protocol: ``"kept-frames"`` (default) or ``"kitti-odom-eval"`` (see step 4).

    Returns:
        A dict: ``t_err`` (%), ``r_err`` (deg/100 m) -- None when no segment fits, with
        a ``note`` saying so --, ``ate_rmse``/``ate_mean``/``ate_max`` (m), ``rpe_trans``
        (RMSE, m), ``rpe_rot`` (RMSE, deg), ``rpe_trans_mean``, ``rpe_rot_mean``,
        ``num_frames`` (common frames), ``num_segments``, ``align``, ``scale`` (the
        alignment's), ``lengths``, ``step``, ``path_length`` (m), ``per_length``
        (list of ``{"length", "t_err", "r_err", "num_segments"}``), ``units``.

    Raises:
        vo.errors.InputError: fewer than 3 common frames, degenerate alignment.
    """
    pred = np.asarray(pred_poses, dtype=np.float64)
    gt = np.asarray(gt_poses, dtype=np.float64)
    for name, T in (("pred_poses", pred), ("gt_poses", gt)):
        if T.ndim != 3 or T.shape[1:] != (4, 4):
            raise ValueError(f"{name} must be (N, 4, 4), got {T.shape}")
    pf = np.arange(pred.shape[0]) if pred_frames is None else np.asarray(pred_frames, dtype=np.int64)
    gf = np.arange(gt.shape[0]) if gt_frames is None else np.asarray(gt_frames, dtype=np.int64)
    if pf.shape != (pred.shape[0],) or gf.shape != (gt.shape[0],):
        raise ValueError("frame arrays must have one entry per pose")
    for name, f in (("pred_frames", pf), ("gt_frames", gf)):
        if np.unique(f).size != f.size:
            raise InputError(f"{name} has repeated frame indices")
    pi, gi = match_frames(pf, gf)
    if pi.size < MIN_COMMON_FRAMES:
        raise InputError(f"only {pi.size} frame(s) in common with the ground truth; need at least {MIN_COMMON_FRAMES}")
    order = np.argsort(gf, kind="stable")
    return evaluate_associated(pred[pi], gt[gi], align, lengths, step, pf[pi], protocol, gt[order],
                               gf[order]).metrics


def coverage_check(num_pred: int, num_common: int, allow_partial: bool, where=None) -> list[str]:
    """Warnings (or the refusal) about predicted frames that have no ground truth.

    Returns one warning line when some predicted frames have no ground-truth pose.

    Raises:
        InputError: fewer than half of the predicted frames have a ground-truth pose and
            ``allow_partial`` is False (a ``frames.txt`` shifted or of another sequence).
    """
    missing = num_pred - num_common
    if missing <= 0:
        return []
    if 2 * num_common < num_pred and not allow_partial:
        raise InputError(
            f"only {num_common} of the {num_pred} predicted frames have a ground-truth pose: this prediction (or its "
            "frames.txt) does not seem to belong to this ground truth (shifted indices or another sequence); "
            f"pass --allow-partial to evaluate the {num_common} common frames anyway",
            where,
        )
    return [f"{missing} of the {num_pred} predicted frames have no ground-truth pose and are not evaluated "
            f"({num_common} evaluated)"]


def evaluate_files(
    pred_path: str | Path,
    gt_path: str | Path,
    align: str = "7dof",
    lengths=DEFAULT_LENGTHS,
    step: int = DEFAULT_STEP,
    max_time_diff: float = DEFAULT_MAX_TIME_DIFF,
    protocol: str = "kept-frames",
    allow_partial: bool = False,
) -> EvalResult:
    """Load, associate (see :func:`vo.eval.loader.associate`) and evaluate.

    ``pred_path`` is a run folder or a trajectory file. The metrics dict also gets
    ``pred``, ``gt`` (files read), ``matched_by``, ``num_pred_frames``,
    ``num_gt_frames``, ``num_pred_unmatched`` (predicted frames without ground truth)
    and ``warnings`` (lines; ``trianflow-vo eval`` prints them on stderr). Degenerate
    alignments are reported against ``pred_path``.

    Raises:
        InputError: as :func:`vo.eval.loader.associate`; fewer than half of the predicted
            frames have a ground-truth pose (unless ``allow_partial``).
    """
    gt = load_ground_truth(gt_path)
    pred, desc = load_prediction(pred_path, gt.kind)
    assoc: Association = associate(pred, gt, max_time_diff, desc)
    num_common = len(assoc.pred_poses)
    warnings = coverage_check(assoc.num_pred, num_common, allow_partial, pred.path)
    try:
        gt_all = gt_frames = None
        if protocol == "kitti-odom-eval" and assoc.frames is not None:
            gt_all, gt_frames = gt.poses, gt.frames
        result = evaluate_associated(assoc.pred, assoc.gt, align, lengths, step, assoc.frames, protocol, gt_all,
                                     gt_frames)
    except InputError as exc:
        if exc.path is None:
            raise InputError(exc.message, pred.path) from None
        raise
    result.metrics.update(
        {
            "pred": desc,
            "gt": str(gt_path),
            "matched_by": assoc.matched_by,
            "num_pred_frames": assoc.num_pred,
            "num_gt_frames": assoc.num_gt,
            "num_pred_unmatched": assoc.num_pred - num_common,
            "warnings": warnings,
        }
    )
    return result
