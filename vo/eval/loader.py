"""Files to associated pose arrays: run folders, KITTI/indexed-KITTI/TUM trajectories.

A run folder (written by ``trianflow-vo run``) holds ``poses.txt`` (KITTI, one line per
processed frame), ``frames.txt`` (the source frame index of each line),
``trajectory.tum`` and ``run.json``.

The trajectories travel as evo's types (``TrajectoryFile.traj``, ``Association.pred`` /
``.gt``); the frame-index bookkeeping (``frames.txt``, 13 columns, line numbers) is ours.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
from evo.core.trajectory import PosePath3D

from trianflow_vo.errors import InputError
from trianflow_vo.eval.associate import DEFAULT_MAX_TIME_DIFF, match_frames, match_timestamps
from trianflow_vo.io.trajectory import TrajectoryFile, read_frame_indices, read_trajectory

RUN_POSES = "poses.txt"
RUN_FRAMES = "frames.txt"
RUN_TUM = "trajectory.tum"
MIN_COMMON_FRAMES = 3


@dataclass(frozen=True)
class Association:
    """Predicted and ground-truth poses of the common frames, in frame (or time) order.

    Attributes:
        pred: evo path (``PoseTrajectory3D`` for TUM) of the K predicted poses kept.
        gt: evo path of the K ground-truth poses they are paired with.
        frames: ``(K,)`` int frame indices, or None when matched by timestamp.
        timestamps: ``(K,)`` ground-truth seconds when matched by timestamp, else None.
        matched_by: ``"frame index"``, ``"line number"`` or ``"timestamp"``.
        num_pred: number of predicted poses read.
        num_gt: number of ground-truth poses read.
        pred_source: what was read for the prediction (for the report).

    Properties:
        pred_poses: ``(K, 4, 4)`` predicted camera-to-world poses.
        gt_poses: ``(K, 4, 4)`` ground-truth camera-to-world poses.
    """

    pred: PosePath3D
    gt: PosePath3D
    frames: np.ndarray | None
    timestamps: np.ndarray | None
    matched_by: str
    num_pred: int
    num_gt: int
    pred_source: str

    @cached_property
    def pred_poses(self) -> np.ndarray:
        return np.array(self.pred.poses_se3, dtype=np.float64).reshape(-1, 4, 4)

    @cached_property
    def gt_poses(self) -> np.ndarray:
        return np.array(self.gt.poses_se3, dtype=np.float64).reshape(-1, 4, 4)


def _subset(traj: PosePath3D, ids: np.ndarray) -> PosePath3D:
    """A copy of an evo path (or trajectory, with its timestamps) reduced to ``ids``."""
    out = copy.deepcopy(traj)
    out.reduce_to_ids(np.asarray(ids, dtype=np.int64))
    return out


def find_latest_run(runs_dir: str | Path) -> Path:
    """The folder under ``runs_dir`` whose ``poses.txt`` was modified last.

    Raises:
        InputError: no such folder (or no run with a ``poses.txt`` in it).
    """
    runs_dir = Path(runs_dir)
    if not runs_dir.is_dir():
        raise InputError(
            "no --pred given and no runs folder here; run `trianflow-vo run` first or pass --pred", runs_dir
        )
    candidates = [d for d in runs_dir.iterdir() if d.is_dir() and (d / RUN_POSES).is_file()]
    if not candidates:
        raise InputError(
            f"no --pred given and no run folder with a {RUN_POSES} in it; pass --pred RUN_DIR_OR_FILE", runs_dir
        )
    return max(candidates, key=lambda d: ((d / RUN_POSES).stat().st_mtime_ns, d.name))


def load_ground_truth(path: str | Path) -> TrajectoryFile:
    """The one ground-truth reader (``eval`` and ``run --gt``): KITTI, indexed KITTI or TUM.

    Args:
        path: a KITTI file (12 numbers per line, line i = frame i), an indexed KITTI file
            (13 numbers, frame index first) or a TUM file.

    Returns:
        A :class:`~vo.io.trajectory.TrajectoryFile`: ``.poses`` ``(N, 4, 4)`` float64
        camera-to-world, ``.frames`` ``(N,)`` int64 frame indices (``0..N-1`` for
        KITTI, the first column for indexed KITTI, rows sorted by it; None for TUM,
        whose rows are identified by ``.timestamps``), ``.traj`` the evo type
        (``PosePath3D``, ``PoseTrajectory3D`` for TUM), ``.kind``, ``.lines``.

    Raises:
        vo.errors.InputError: any bad line, naming the file and line.
    """
    gt = read_trajectory(path)
    if gt.kind == "kitti":
        gt = dataclasses.replace(gt, frames=np.arange(len(gt), dtype=np.int64))
    return gt


def _with_frames_file(traj: TrajectoryFile, frames_path: Path) -> TrajectoryFile:
    idx, lines = read_frame_indices(frames_path)
    n = len(traj)
    if idx.size != n:
        raise InputError(
            f"{idx.size} frame indices for {n} poses in {traj.path}: the two files must have one line per pose",
            frames_path,
        )
    if traj.kind == "tum":
        # TUM rows were sorted by time; frames.txt follows the file's line order.
        order = np.argsort(traj.lines, kind="stable")
        frames = np.empty(n, dtype=np.int64)
        frames[order] = idx
    else:
        frames = idx
    order = np.argsort(frames, kind="stable")
    if traj.kind != "tum":
        return dataclasses.replace(traj, traj=_subset(traj.traj, order), frames=frames[order], lines=traj.lines[order])
    return dataclasses.replace(traj, frames=frames)


def load_prediction(path: str | Path, gt_kind: str = "kitti") -> tuple[TrajectoryFile, str]:
    """Read a prediction: a run folder or a trajectory file.

    A run folder gives ``poses.txt`` with ``frames.txt`` (or ``trajectory.tum`` when the
    ground truth is TUM, ``gt_kind == "tum"``). A 12-column or TUM file picks up a
    ``frames.txt`` beside it, if there is one, as its frame indices.

    Returns:
        ``(trajectory, description)``; the description names the files used.
    """
    path = Path(path)
    if path.is_dir():
        if gt_kind == "tum" and (path / RUN_TUM).is_file():
            traj_path = path / RUN_TUM
        elif (path / RUN_POSES).is_file():
            traj_path = path / RUN_POSES
        else:
            raise InputError(f"not a run folder: no {RUN_POSES} in it", path)
    elif path.is_file():
        traj_path = path
    else:
        raise InputError("no such file or folder", path)
    traj = read_trajectory(traj_path)
    desc = str(traj_path)
    frames_path = traj_path.parent / RUN_FRAMES
    if traj.kind in ("kitti", "tum") and frames_path.is_file() and frames_path.resolve() != traj_path.resolve():
        traj = _with_frames_file(traj, frames_path)
        desc += f" + {frames_path}"
    return traj, desc


def associate(
    pred: TrajectoryFile,
    gt: TrajectoryFile,
    max_time_diff: float = DEFAULT_MAX_TIME_DIFF,
    pred_source: str | None = None,
) -> Association:
    """Keep the frames present in both trajectories (protocol step 1).

    Rules: a TUM ground truth is matched by timestamp (``|dt| <= max_time_diff``) with a
    prediction that has timestamps; otherwise frames are matched by index. A 12-column
    prediction without frame indices is matched line by line, and only when it has as
    many lines as the ground truth. A TUM prediction without frame indices is matched
    to a frame-indexed ground truth only when its timestamps are integers (taken as
    frame indices).

    Raises:
        InputError: the frames cannot be matched, or fewer than 3 are common.
    """
    pred_source = pred_source or pred.path
    matched_by = "frame index"
    if gt.kind == "tum":
        if pred.timestamps is None:
            raise InputError(
                "the ground truth is TUM (timestamps) but this prediction has none; give a TUM prediction "
                f"(a run folder's {RUN_TUM}) or a frame-indexed ground truth",
                pred.path,
            )
        pi, gi = match_timestamps(pred.timestamps, gt.timestamps, max_time_diff)
        matched_by = "timestamp"
    else:
        pred_frames = pred.frames
        if pred_frames is None and pred.kind == "kitti":
            if len(pred) != len(gt):
                raise InputError(
                    f"{len(pred)} poses but the ground truth {gt.path} has {len(gt)}: "
                    "cannot tell which frames they are. Put a frames.txt beside it (one source frame index "
                    "per line), or use 13 columns (frame index first)",
                    pred.path,
                )
            pred_frames = np.arange(len(pred), dtype=np.int64)
            matched_by = "line number"
        elif pred_frames is None:  # TUM without frames.txt
            ts = pred.timestamps
            if not np.all(ts == np.round(ts)):
                raise InputError(
                    f"TUM timestamps cannot be matched to the frame-indexed ground truth {gt.path}: give a TUM "
                    "ground truth, a frames.txt beside the prediction, or integer timestamps (frame indices)",
                    pred.path,
                )
            pred_frames = ts.astype(np.int64)
        pred = dataclasses.replace(pred, frames=pred_frames)
        pi, gi = match_frames(pred_frames, gt.frames)
    if pi.size < MIN_COMMON_FRAMES:
        if matched_by == "timestamp":
            detail = f"timestamps matched within {max_time_diff} s"
        else:
            detail = (
                f"prediction frames {_span(pred.frames)}, ground-truth frames {_span(gt.frames)}"
            )
        raise InputError(
            f"only {pi.size} frame(s) in common with the ground truth {gt.path} ({detail}); need at least "
            f"{MIN_COMMON_FRAMES}",
            pred.path,
        )
    return Association(
        pred=_subset(pred.traj, pi),
        gt=_subset(gt.traj, gi),
        frames=None if matched_by == "timestamp" else pred.frames[pi],
        timestamps=gt.timestamps[gi] if matched_by == "timestamp" else None,
        matched_by=matched_by,
        num_pred=len(pred),
        num_gt=len(gt),
        pred_source=pred_source,
    )


def _span(frames: np.ndarray | None) -> str:
    if frames is None or frames.size == 0:
        return "none"
    return f"{int(frames.min())}..{int(frames.max())} ({frames.size})"
