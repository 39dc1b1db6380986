"""Top-down trajectory plot (``trajectory.png``) and the ground-truth alignment it shows.

The alignment is ``eval``'s, called here (one implementation): frames matched by index
(:func:`vo.eval.associate.match_frames`), both trajectories re-based to their first
common frame and the estimate 7-DoF (Sim(3)) aligned onto the ground truth
(:func:`vo.eval.align.align_paths`, evo's Umeyama). The paths are drawn by evo's
plotting (see :mod:`vo.eval.plot`), imported on first use; importing this module does
not import matplotlib.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from trianflow_vo.eval.align import align_paths, as_path
from trianflow_vo.eval.associate import match_frames


def _check_poses(T: np.ndarray, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"{name} must be (N, 4, 4), got {T.shape}")
    return T


def _frames_or_range(frames: np.ndarray | None, n: int, name: str) -> np.ndarray:
    if frames is None:
        return np.arange(n)
    frames = np.asarray(frames).astype(np.int64).reshape(-1)
    if frames.shape[0] != n:
        raise ValueError(f"{name} must have one entry per pose ({n}), got {frames.shape[0]}")
    return frames


def common_indices(est_frames: np.ndarray, gt_frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Row indices ``(i_est (K,), i_gt (K,))`` of the frame indices present in both
    ``est_frames (N,)`` and ``gt_frames (M,)``, in increasing frame order (eval's
    :func:`~vo.eval.associate.match_frames`)."""
    return match_frames(np.asarray(est_frames).reshape(-1), np.asarray(gt_frames).reshape(-1))


def align_estimate_to_gt(
    T_world_cam: np.ndarray,
    gt_T_world_cam: np.ndarray,
    frames: np.ndarray | None = None,
    gt_frames: np.ndarray | None = None,
) -> tuple[tuple[np.ndarray, np.ndarray, int], bool]:
    """Similarity putting the estimate beside the ground truth, as ``eval`` aligns.

    Args:
        T_world_cam: ``(N, 4, 4)`` estimated camera-to-world poses.
        gt_T_world_cam: ``(M, 4, 4)`` ground-truth camera-to-world poses.
        frames: ``(N,)`` source frame index of each estimated pose (default ``0..N-1``).
        gt_frames: ``(M,)`` source frame index of each ground-truth pose (default ``0..M-1``).

    Returns:
        ``((S_ref_est (4, 4), T_ref_gt (4, 4), n_common), valid)``: ``S_ref_est`` maps
        estimated world points into the reference frame (the ground truth re-based to
        the first common frame), ``T_ref_gt`` maps ground-truth world points into it.
        ``valid`` is False when fewer than 3 frames are common or either set of
        positions does not move (then ``S_ref_est`` may be singular: do not use it).
    """
    T = _check_poses(T_world_cam, "T_world_cam")
    G = _check_poses(gt_T_world_cam, "gt_T_world_cam")
    frames = _frames_or_range(frames, T.shape[0], "frames")
    gt_frames = _frames_or_range(gt_frames, G.shape[0], "gt_frames")
    i_est, i_gt = common_indices(frames, gt_frames)
    n = int(i_est.shape[0])
    if n == 0:
        return (np.eye(4), np.eye(4), 0), False
    est, ref = as_path(T[i_est]), as_path(G[i_gt])
    base_est = np.linalg.inv(T[i_est[0]])  # the re-basing eval applies (align_paths re-bases the same way)
    base_gt = np.linalg.inv(G[i_gt[0]])
    (s, R, t), valid = align_paths(est, ref, "7dof")  # eval's alignment, and its check of degenerate motion
    S = np.eye(4)
    S[:3, :3] = s * R
    S[:3, 3] = t
    return (S @ base_est, base_gt, n), valid


def _apply(M: np.ndarray, p: np.ndarray) -> np.ndarray:
    """``(4, 4)`` affine ``M`` applied to ``(N, 3)`` points."""
    return p @ M[:3, :3].T + M[:3, 3]


def plot_trajectory(
    T_world_cam: np.ndarray,
    out_png: str | Path,
    gt_T_world_cam: np.ndarray | None = None,
    frames: np.ndarray | None = None,
    gt_frames: np.ndarray | None = None,
    title: str | None = None,
) -> Path:
    """Write a top-down (x right, z forward) plot of a trajectory to ``out_png``.

    Without ground truth the estimate is drawn in its own world frame. With ground
    truth both are drawn in the ground truth's frame re-based to the first common
    frame, the estimate Sim(3)-aligned onto it (see ``align_estimate_to_gt``), and
    the legend gives the RMSE of the aligned positions over the common frames.
    The paths are drawn by evo's ``plot.traj`` on a headless Agg figure (matplotlib
    directly, with a :class:`vo.eval.plot.PlotFallbackWarning`, when evo's plotting
    cannot be imported); nothing is printed and no pyplot figure is left open.

    Args:
        T_world_cam: ``(N, 4, 4)`` estimated camera-to-world poses (N >= 1).
        out_png: output file (its folder must exist).
        gt_T_world_cam: ``(M, 4, 4)`` ground-truth camera-to-world poses, or None.
        frames: ``(N,)`` source frame indices of the estimate (default ``0..N-1``).
        gt_frames: ``(M,)`` source frame indices of the ground truth (default ``0..M-1``).
        title: figure title (default: "Trajectory (top-down)").

    Returns:
        The path written.
    """
    T = _check_poses(T_world_cam, "T_world_cam")
    if T.shape[0] == 0:
        raise ValueError("T_world_cam is empty: nothing to plot")
    frames = _frames_or_range(frames, T.shape[0], "frames")
    out_png = Path(out_png)

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from trianflow_vo.eval.plot import draw_top_view

    fig = Figure(figsize=(7, 7), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    est = T[:, :3, 3]
    note = None
    if gt_T_world_cam is not None:
        G = _check_poses(gt_T_world_cam, "gt_T_world_cam")
        gt_frames = _frames_or_range(gt_frames, G.shape[0], "gt_frames")
        (S, B, n_common), valid = align_estimate_to_gt(T, G, frames, gt_frames)
        gt = _apply(B, G[:, :3, 3])
        if valid:
            est = _apply(S, est)
            i_est, i_gt = common_indices(frames, gt_frames)
            rmse = float(np.sqrt(np.mean(np.sum((est[i_est] - gt[i_gt]) ** 2, axis=1))))
            est_label = f"estimate (Sim(3)-aligned, RMSE {rmse:.3g})"
        else:
            if n_common:  # re-base only: same start, no rotation/scale fit
                i_est, _ = common_indices(frames, gt_frames)
                est = _apply(np.linalg.inv(T[i_est[0]]), est)
            est_label = "estimate (not aligned)"
            note = f"ground truth not aligned: needs >= 3 common frames with motion ({n_common} common)"
        draw_top_view(ax, gt, "--", color="tab:orange", label="ground truth", linewidth=1.5,
                      zorder=3)  # dashed, on top: the estimate stays visible underneath
    else:
        est_label = "estimate"
    draw_top_view(ax, est, "-", color="tab:blue", label=est_label, linewidth=1.8)
    ax.plot(est[:1, 0], est[:1, 2], "o", color="tab:green", markersize=6, label="start")
    ax.plot(est[-1:, 0], est[-1:, 2], "s", color="black", markersize=5, label="end")
    ax.set_xlabel("x (right)")
    ax.set_ylabel("z (forward)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title if title is not None else "Trajectory (top-down)")
    if note:
        ax.text(0.01, 0.01, note, transform=ax.transAxes, fontsize=7, color="tab:red")
    fig.savefig(out_png, format="png")
    return out_png
