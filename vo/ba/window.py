"""One bundle adjustment of a window of keyframes, on GTSAM.

Variables: the camera-to-world poses of the window's keyframes and one 3-D point
per track seen in at least two of them. Factors: the reprojection of each point
into every keyframe of the window that observed it, with an isotropic pixel noise
and a Huber kernel (``huber_px``, in pixels), and a tight prior on each *fixed*
keyframe (the oldest ones): they hold the gauge of the monocular problem, its
scale included, at the trajectory the earlier windows made. Solved with
Levenberg-Marquardt.

Poses are ``T_world_cam`` ``(4, 4)`` (GTSAM's ``Pose3`` of a camera, z forward);
points are world coordinates; pixels ``(u, v)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from trianflow_vo.ba.graph import add_reprojection_factors, levenberg_marquardt, project

# prior on the fixed keyframes: effectively a constant (radians and trajectory units)
FIXED_SIGMA = 1e-6


@dataclass(frozen=True)
class WindowSolution:
    """The optimised window.

    Attributes:
        poses: keyframe index -> ``(4, 4)`` revised ``T_world_cam`` (fixed ones included, unchanged).
        landmarks: track id -> ``(3,)`` revised world point (the tracks that took part).
        residual_px: track id -> largest reprojection error (pixels) of its observations after the solve.
        error_before, error_after: the graph's total (robust) error at the start and the end.
        iterations: Levenberg-Marquardt iterations run.
        n_factors: reprojection factors; n_points: points optimised.
    """

    poses: dict[int, np.ndarray]
    landmarks: dict[int, np.ndarray]
    residual_px: dict[int, float]
    error_before: float
    error_after: float
    iterations: int
    n_factors: int
    n_points: int
    notes: list[str] = field(default_factory=list)


def select_observations(poses: dict[int, np.ndarray], obs: dict[int, tuple[np.ndarray, np.ndarray]],
                        landmarks: dict[int, np.ndarray], fixed: set[int], min_depth: float = 1e-6):
    """The observations the window can use.

    A track takes part when its landmark is known, it is in front of every window
    keyframe that observed it (others' observations are dropped) and it still has
    at least two observations, one of them in a keyframe that is not fixed.

    Returns:
        ``(kf (M,), tid (M,), uv (M, 2))`` int64, int64, float64 arrays, grouped by nothing in particular.
    """
    kfs, tids, uvs = [], [], []
    for kf, (ids, pts) in obs.items():
        if kf not in poses or ids.size == 0:
            continue
        known = np.array([t in landmarks for t in ids.tolist()], dtype=bool)
        if not known.any():
            continue
        ids_k, pts_k = ids[known], pts[known]
        X = np.stack([landmarks[t] for t in ids_k.tolist()])
        front = ((X - poses[kf][:3, 3]) @ poses[kf][:3, :3])[:, 2] > min_depth
        kfs.append(np.full(int(front.sum()), kf, dtype=np.int64))
        tids.append(ids_k[front])
        uvs.append(pts_k[front])
    if not kfs:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2))
    kf_a, tid_a, uv_a = np.concatenate(kfs), np.concatenate(tids), np.concatenate(uvs)
    uniq, inv, counts = np.unique(tid_a, return_inverse=True, return_counts=True)
    free = np.zeros(uniq.size, dtype=np.int64)
    np.add.at(free, inv, np.array([k not in fixed for k in kf_a.tolist()], dtype=np.int64))
    keep = (counts[inv] >= 2) & (free[inv] >= 1)
    return kf_a[keep], tid_a[keep], uv_a[keep]


def reprojection_errors(K: np.ndarray, poses: dict[int, np.ndarray], landmarks: dict[int, np.ndarray],
                        kf: np.ndarray, tid: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """``(M,)`` pixel distance between each observation ``uv`` and its point projected
    into its keyframe (``inf`` behind the camera)."""
    err = np.full(kf.size, np.inf)
    for k in np.unique(kf).tolist():
        sel = np.flatnonzero(kf == k)
        p, _ = project(K, poses[k], np.stack([landmarks[t] for t in tid[sel].tolist()]))
        err[sel] = np.linalg.norm(p - uv[sel], axis=1)
    return err


def solve_window(K: np.ndarray, poses: dict[int, np.ndarray], fixed: set[int],
                 obs: dict[int, tuple[np.ndarray, np.ndarray]], landmarks: dict[int, np.ndarray],
                 huber_px: float = 1.0, max_iterations: int = 10, min_points: int = 20,
                 steps: dict[int, tuple] | None = None, step_rot_sigma: float = 1e-3,
                 step_trans_sigma: float = 0.02) -> tuple[WindowSolution | None, bool]:
    """Bundle-adjust the keyframes ``poses`` (those in ``fixed`` held) and the tracks' points.

    Args:
        K: ``(3, 3)`` intrinsics at working resolution.
        poses: keyframe index -> ``(4, 4)`` ``T_world_cam`` (the window, fixed ones included).
        fixed: keyframes of ``poses`` held at their pose (at least one).
        obs: keyframe index -> ``(ids (M,), pixels (M, 2))`` observations (other keyframes ignored).
        landmarks: track id -> ``(3,)`` world point, the starting estimates.
        huber_px: Huber threshold in pixels (noise sigma 1 px).
        max_iterations: Levenberg-Marquardt iterations at most.
        min_points: fewer usable points gives ``valid = False`` (nothing solved).
        steps: keyframe -> (its reference keyframe, measured ``T_ref_k``[, translation sigma]):
            relative-pose factors with sigmas ``step_rot_sigma`` (radians) and the step's own
            translation sigma (trajectory units) or, without one, ``step_trans_sigma`` x the step length.

    Returns:
        ``(WindowSolution, True)``, or ``(None, False)`` when there is too little to solve
        or GTSAM fails (indeterminate system, non-finite result, error not reduced).
    """
    if K.shape != (3, 3):
        raise ValueError(f"K must be (3, 3), got {K.shape}")
    if not fixed or not set(fixed) <= set(poses):
        raise ValueError(f"fixed keyframes {sorted(fixed)} must be a non-empty subset of the window {sorted(poses)}")
    kf, tid, uv = select_observations(poses, obs, landmarks, set(fixed))
    points = np.unique(tid)
    if points.size < min_points or len(poses) - len(fixed) < 1:
        return None, False
    import gtsam

    hold = gtsam.noiseModel.Isotropic.Sigma(6, FIXED_SIGMA)
    X, L = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.L
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for k, T in poses.items():
        values.insert(X(k), gtsam.Pose3(np.asarray(T, dtype=np.float64)))
        if k in fixed:
            graph.add(gtsam.PriorFactorPose3(X(k), gtsam.Pose3(np.asarray(T, dtype=np.float64)), hold))
    for t in points.tolist():
        values.insert(L(t), np.asarray(landmarks[t], dtype=np.float64))
    add_reprojection_factors(graph, K, kf, tid, uv, huber_px, X, L)
    for k, step in (steps or {}).items():
        ref, T_ref_k = step[0], step[1]
        if k in poses and ref in poses:
            tn = float(np.linalg.norm(T_ref_k[:3, 3]))
            t_sigma = float(step[2]) if len(step) > 2 else step_trans_sigma * tn
            sig = np.array([step_rot_sigma] * 3 + [max(t_sigma, 1e-6)] * 3)
            graph.add(gtsam.BetweenFactorPose3(X(ref), X(k), gtsam.Pose3(np.asarray(T_ref_k, dtype=np.float64)),
                                               gtsam.noiseModel.Diagonal.Sigmas(sig)))
    solved, ok = levenberg_marquardt(graph, values, max_iterations)
    if not ok:
        return None, False
    result, e0, e1, iters = solved
    if not e1 <= e0:
        return None, False
    new_poses = {k: np.asarray(result.atPose3(X(k)).matrix(), dtype=np.float64) for k in poses}
    new_points = {t: np.asarray(result.atPoint3(L(t)), dtype=np.float64) for t in points.tolist()}
    if not all(np.isfinite(T).all() for T in new_poses.values()):
        return None, False
    err = reprojection_errors(K, new_poses, new_points, kf, tid, uv)
    worst = np.full(points.size, 0.0)
    np.maximum.at(worst, np.searchsorted(points, tid), err)
    return WindowSolution(new_poses, new_points, dict(zip(points.tolist(), worst.tolist())), float(e0), float(e1),
                          iters, int(kf.size), int(points.size)), True
