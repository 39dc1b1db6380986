"""Umeyama alignment of point sets (Sim(3), SE(3) or scale only)."""

from __future__ import annotations

import numpy as np


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> tuple[tuple[float, np.ndarray, np.ndarray], bool]:
    """Least-squares ``s, R, t`` with ``dst ~ s * R @ src + t`` (Umeyama 1991).

    Args:
        src: ``(N, 3)`` points.
        dst: ``(N, 3)`` points.
        with_scale: estimate ``s`` (Sim(3)); otherwise ``s = 1`` (SE(3)).

    Returns:
        ``((s, R (3, 3), t (3,)), valid)``; ``valid`` is False when the source
        points are degenerate (all equal) or fewer than 3.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"src and dst must both be (N, 3), got {src.shape} and {dst.shape}")
    n = src.shape[0]
    if n < 3:
        return (1.0, np.eye(3), np.zeros(3)), False
    mu_s = src.mean(0)
    mu_d = dst.mean(0)
    xs = src - mu_s
    xd = dst - mu_d
    var_s = (xs ** 2).sum() / n
    if var_s < 1e-12:
        return (1.0, np.eye(3), np.zeros(3)), False
    cov = xd.T @ xs / n
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / var_s) if with_scale else 1.0
    t = mu_d - s * R @ mu_s
    return (s, R, t), True


# --------------------------------------------------------------------------- trajectories

ALIGN_MODES = ("7dof", "6dof", "scale", "none")

_DEGENERATE_SPREAD = 1e-12  # mean squared distance to the centroid (m^2) below which points are "all equal"


def estimate_alignment(
    src: np.ndarray, dst: np.ndarray, mode: str = "7dof"
) -> tuple[tuple[float, np.ndarray, np.ndarray], bool]:
    """Similarity ``dst ~ s * R @ src + t`` of one of the eval alignment modes.

    Args:
        src: ``(N, 3)`` predicted positions (already re-based to the first common frame).
        dst: ``(N, 3)`` ground-truth positions (idem).
        mode: ``"7dof"`` Umeyama with scale, ``"6dof"`` Umeyama without scale,
            ``"scale"`` least-squares scale about the origin (the first frame,
            ``s = sum(dst . src) / sum(src . src)``, ``R = I``, ``t = 0``), ``"none"``.

    Returns:
        ``((s, R (3, 3), t (3,)), valid)``; ``valid`` is False when either point set is
        degenerate (fewer than 3 points, or all positions equal) for a mode that
        estimates something. ``"none"`` is always valid.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"src and dst must both be (N, 3), got {src.shape} and {dst.shape}")
    if mode not in ALIGN_MODES:
        raise ValueError(f"unknown alignment mode {mode!r}; expected one of {ALIGN_MODES}")
    identity = (1.0, np.eye(3), np.zeros(3))
    if mode == "none":
        return identity, True
    n = src.shape[0]
    if n < 3 or _spread(src) < _DEGENERATE_SPREAD or _spread(dst) < _DEGENERATE_SPREAD:
        return identity, False
    if mode == "scale":
        den = float((src * src).sum())
        if den < _DEGENERATE_SPREAD:
            return identity, False
        return (float((dst * src).sum()) / den, np.eye(3), np.zeros(3)), True
    return umeyama(src, dst, with_scale=(mode == "7dof"))


def _spread(p: np.ndarray) -> float:
    """Mean squared distance of ``(N, 3)`` points to their centroid."""
    return float(((p - p.mean(0)) ** 2).sum() / len(p))


def apply_alignment(T_world_cam: np.ndarray, s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Apply a similarity to whole poses: rotation ``R @ R_i``, position ``s * R @ p_i + t``.

    Args:
        T_world_cam: ``(N, 4, 4)`` camera-to-world poses.
        s, R, t: scale, ``(3, 3)`` rotation, ``(3,)`` translation.

    Returns:
        ``(N, 4, 4)`` poses that stay rigid (the scale only acts on positions).
    """
    T = np.asarray(T_world_cam, dtype=np.float64)
    out = T.copy()
    out[:, :3, :3] = np.asarray(R) @ T[:, :3, :3]
    out[:, :3, 3] = s * T[:, :3, 3] @ np.asarray(R).T + np.asarray(t)
    return out


def rebase(T_world_cam: np.ndarray) -> np.ndarray:
    """``(N, 4, 4)`` poses expressed relative to the first one (which becomes identity)."""
    T = np.asarray(T_world_cam, dtype=np.float64)
    return np.linalg.inv(T[0]) @ T


def align_rebased(
    pred_poses: np.ndarray, gt_poses: np.ndarray, mode: str = "7dof"
) -> tuple[np.ndarray, np.ndarray, tuple[float, np.ndarray, np.ndarray], bool]:
    """Steps 2-3 of the eval protocol on associated poses.

    Args:
        pred_poses: ``(N, 4, 4)`` predicted camera-to-world poses, associated
            one-to-one with ``gt_poses`` (same frames, same order).
        gt_poses: ``(N, 4, 4)`` ground-truth camera-to-world poses.
        mode: one of :data:`ALIGN_MODES`.

    Returns:
        ``(pred_aligned (N, 4, 4), gt_rebased (N, 4, 4), (s, R, t), valid)``: both
        trajectories re-based to their first pose, then the prediction aligned onto
        the ground truth with :func:`estimate_alignment` on positions and
        :func:`apply_alignment` on whole poses. ``valid`` as in
        :func:`estimate_alignment` (when False, ``pred_aligned`` is only re-based).
    """
    pred = _check_poses(pred_poses, "pred_poses")
    gt = _check_poses(gt_poses, "gt_poses")
    if pred.shape != gt.shape:
        raise ValueError(f"pred_poses and gt_poses must have the same shape, got {pred.shape} and {gt.shape}")
    pred_r = rebase(pred)
    gt_r = rebase(gt)
    sim, valid = estimate_alignment(pred_r[:, :3, 3], gt_r[:, :3, 3], mode)
    return apply_alignment(pred_r, *sim), gt_r, sim, valid


def align_trajectory(pred_poses: np.ndarray, gt_poses: np.ndarray, mode: str = "7dof") -> np.ndarray:
    """The prediction aligned onto the ground truth exactly as ``trianflow-vo eval`` does,
    expressed in the ground truth's own world frame (for drawing both together).

    Re-bases both trajectories to their first pose, estimates the alignment of
    ``mode`` on positions (see :func:`estimate_alignment`), applies it to whole poses,
    then maps the result back with the first ground-truth pose, so the output can be
    drawn next to ``gt_poses`` unchanged. Errors measured against ``gt_poses`` are the
    same as eval's (that last step is rigid).

    Args:
        pred_poses: ``(N, 4, 4)`` predicted camera-to-world poses, associated
            one-to-one with ``gt_poses`` (use :func:`vo.eval.associate` first when the
            frames differ).
        gt_poses: ``(N, 4, 4)`` ground-truth camera-to-world poses.
        mode: ``"7dof"`` (default), ``"6dof"``, ``"scale"`` or ``"none"``.

    Returns:
        ``(N, 4, 4)`` aligned predicted poses.

    Raises:
        vo.errors.InputError: degenerate alignment (fewer than 3 poses or all
            positions equal) for a mode other than ``"none"``.
    """
    from trianflow_vo.errors import InputError

    aligned, _, sim, valid = align_rebased(pred_poses, gt_poses, mode)
    if not valid:
        raise InputError(degenerate_message(mode))
    gt0 = np.asarray(gt_poses, dtype=np.float64)[0]
    return gt0 @ aligned


def degenerate_message(mode: str) -> str:
    """The user-facing explanation of an invalid alignment."""
    return (
        f"cannot estimate the {mode} alignment: fewer than 3 common frames, or all predicted "
        "(or ground-truth) positions are equal (the camera never moved); use --align none "
        "to evaluate without alignment"
    )


def _check_poses(T: np.ndarray, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or T.shape[0] < 1:
        raise ValueError(f"{name} must be (N, 4, 4) with N >= 1, got {T.shape}")
    return T
