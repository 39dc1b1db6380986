"""Alignment of a prediction onto the ground truth: re-base, then Sim(3), SE(3) or scale only.

The Umeyama fit is evo's (:func:`evo.core.geometry.umeyama_alignment`) and it is applied
to evo's :class:`~evo.core.trajectory.PosePath3D` the way ``PosePath3D.align`` applies it
(``scale(s)`` then ``transform(se3(R, t))``: rotation ``R @ R_i``, position
``s R p_i + t``). What stays here is what evo does not do the way the eval protocol
needs:

- re-basing both trajectories to their first common frame with the exact inverse of
  that pose (the KITTI devkit's ``inv``; evo's ``se3_inverse`` transposes the rotation,
  and rotations read from files are orthonormal only to ~1e-7);
- the ``"scale"`` mode: least-squares scale about the first frame,
  ``s = sum(dst . src) / sum(src . src)`` (evo's ``correct_only_scale`` keeps the scale
  of the full Sim(3) fit instead, which is another number);
- point sets on a line (a straight drive): evo refuses them (covariance of rank 1), the
  fit is solved here in closed form (the rotation about the line is free and changes no
  metric);
- the checks of degenerate input, with the user-facing message.
"""

from __future__ import annotations

import numpy as np
from evo.core import geometry as _evo_geometry
from evo.core import lie_algebra as _lie
from evo.core.trajectory import PosePath3D


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> tuple[tuple[float, np.ndarray, np.ndarray], bool]:
    """Least-squares ``s, R, t`` with ``dst ~ s * R @ src + t`` (Umeyama 1991, through evo).

    Args:
        src: ``(N, 3)`` points.
        dst: ``(N, 3)`` points.
        with_scale: estimate ``s`` (Sim(3)); otherwise ``s = 1`` (SE(3)).

    Returns:
        ``((s, R (3, 3), t (3,)), valid)``; ``valid`` is False when the source
        points are degenerate (all equal) or fewer than 3. ``R`` is always a proper
        rotation (no reflection).
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"src and dst must both be (N, 3), got {src.shape} and {dst.shape}")
    n = src.shape[0]
    if n < 3 or _spread(src) < _DEGENERATE_SPREAD:
        return (1.0, np.eye(3), np.zeros(3)), False
    try:
        R, t, s = _evo_geometry.umeyama_alignment(src.T, dst.T, with_scale)
    except _evo_geometry.GeometryException:  # rank-deficient covariance: one of the sets is on a line
        s, R, t = _umeyama_rank_one(src, dst, with_scale)
    return (float(s), np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64)), True


def _umeyama_rank_one(src: np.ndarray, dst: np.ndarray, with_scale: bool) -> tuple[float, np.ndarray, np.ndarray]:
    """Umeyama's solution when the covariance ``C = sum (y - my)(x - mx)^T / n`` has rank <= 1.

    Then ``C = d u v^T`` and every rotation with ``R v = u`` is optimal; the one of least
    angle is taken. ``s = d / var(src)``, ``t = my - s R mx``. The aligned points, hence
    every metric, do not depend on which optimal rotation is used.
    """
    n = src.shape[0]
    mu_s, mu_d = src.mean(0), dst.mean(0)
    cov = (dst - mu_d).T @ (src - mu_s) / n
    U, D, Vt = np.linalg.svd(cov)
    u, v, d = U[:, 0], Vt[0], float(D[0])
    R = _rotation_between(v, u)
    s = d / _spread(src) if with_scale else 1.0
    return s, R, mu_d - s * R @ mu_s


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The rotation of least angle taking unit vector ``a`` to unit vector ``b``."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    axis = np.cross(a, b)
    sin, cos = float(np.linalg.norm(axis)), float(a @ b)
    if sin < 1e-12:
        if cos > 0:
            return np.eye(3)
        # opposite: half turn about any axis orthogonal to a
        e = np.eye(3)[int(np.argmin(np.abs(a)))]
        k = np.cross(a, e)
        k /= np.linalg.norm(k)
        return 2.0 * np.outer(k, k) - np.eye(3)
    k = axis / sin
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    angle = np.arctan2(sin, cos)
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K


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
        mode: ``"7dof"`` Umeyama with scale, ``"6dof"`` Umeyama without scale (both
            evo's), ``"scale"`` least-squares scale about the origin (the first frame,
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


# --------------------------------------------------------------------------- evo paths


def as_path(T_world_cam) -> PosePath3D:
    """A new evo :class:`~evo.core.trajectory.PosePath3D` of ``(N, 4, 4)`` poses (or a copy
    of an evo path), safe to transform in place."""
    if isinstance(T_world_cam, PosePath3D):
        return PosePath3D(poses_se3=[np.array(p, dtype=np.float64) for p in T_world_cam.poses_se3])
    T = _check_poses(T_world_cam, "T_world_cam")
    return PosePath3D(poses_se3=list(T.copy()))


def path_poses(path: PosePath3D) -> np.ndarray:
    """``(N, 4, 4)`` float64 array of an evo path's poses."""
    return np.array(path.poses_se3, dtype=np.float64).reshape(-1, 4, 4)


def rebase_path(path: PosePath3D) -> np.ndarray:
    """Re-base an evo path in place to its first pose (which becomes identity); returns
    the ``(4, 4)`` transform applied, ``inv(T_0)`` (the exact inverse, as the devkit)."""
    base = np.linalg.inv(np.asarray(path.poses_se3[0], dtype=np.float64))
    path.transform(base)
    return base


def apply_sim3_path(path: PosePath3D, s: float, R: np.ndarray, t: np.ndarray) -> None:
    """Apply a similarity to an evo path in place, as ``PosePath3D.align`` does:
    ``scale(s)`` then ``transform(se3(R, t))``."""
    path.scale(float(s))
    path.transform(_lie.se3(np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64)))


def apply_alignment(T_world_cam: np.ndarray, s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Apply a similarity to whole poses: rotation ``R @ R_i``, position ``s * R @ p_i + t``.

    Args:
        T_world_cam: ``(N, 4, 4)`` camera-to-world poses.
        s, R, t: scale, ``(3, 3)`` rotation, ``(3,)`` translation.

    Returns:
        ``(N, 4, 4)`` poses that stay rigid (the scale only acts on positions).
    """
    path = as_path(T_world_cam)
    apply_sim3_path(path, s, R, t)
    return path_poses(path)


def rebase(T_world_cam: np.ndarray) -> np.ndarray:
    """``(N, 4, 4)`` poses expressed relative to the first one (which becomes identity)."""
    path = as_path(T_world_cam)
    rebase_path(path)
    return path_poses(path)


def align_paths(
    est: PosePath3D, ref: PosePath3D, mode: str = "7dof"
) -> tuple[tuple[float, np.ndarray, np.ndarray], bool]:
    """Steps 2-3 of the eval protocol on associated evo paths, in place.

    Both paths are re-based to their first pose (:func:`rebase_path`), then ``est`` is
    aligned onto ``ref`` with :func:`estimate_alignment` on positions and
    :func:`apply_sim3_path` on whole poses (when the alignment is not valid ``est`` is
    only re-based).

    Returns:
        ``((s, R, t), valid)`` as :func:`estimate_alignment`.
    """
    if est.num_poses != ref.num_poses:
        raise ValueError(f"the paths must have the same number of poses, got {est.num_poses} and {ref.num_poses}")
    rebase_path(est)
    rebase_path(ref)
    sim, valid = estimate_alignment(est.positions_xyz, ref.positions_xyz, mode)
    apply_sim3_path(est, *sim)
    return sim, valid


def align_rebased(
    pred_poses: np.ndarray, gt_poses: np.ndarray, mode: str = "7dof"
) -> tuple[np.ndarray, np.ndarray, tuple[float, np.ndarray, np.ndarray], bool]:
    """Steps 2-3 of the eval protocol on associated poses (arrays in, arrays out).

    Args:
        pred_poses: ``(N, 4, 4)`` predicted camera-to-world poses, associated
            one-to-one with ``gt_poses`` (same frames, same order).
        gt_poses: ``(N, 4, 4)`` ground-truth camera-to-world poses.
        mode: one of :data:`ALIGN_MODES`.

    Returns:
        ``(pred_aligned (N, 4, 4), gt_rebased (N, 4, 4), (s, R, t), valid)``: see
        :func:`align_paths`. ``valid`` as in :func:`estimate_alignment` (when False,
        ``pred_aligned`` is only re-based).
    """
    pred = _check_poses(pred_poses, "pred_poses")
    gt = _check_poses(gt_poses, "gt_poses")
    if pred.shape != gt.shape:
        raise ValueError(f"pred_poses and gt_poses must have the same shape, got {pred.shape} and {gt.shape}")
    est, ref = as_path(pred), as_path(gt)
    sim, valid = align_paths(est, ref, mode)
    return path_poses(est), path_poses(ref), sim, valid


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

    est, ref = as_path(pred_poses), as_path(gt_poses)
    gt0 = np.array(ref.poses_se3[0], dtype=np.float64)
    _, valid = align_paths(est, ref, mode)
    if not valid:
        raise InputError(degenerate_message(mode))
    est.transform(gt0)
    return path_poses(est)


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
