"""Pieces every bundle adjustment here shares: the projection, the reprojection factors
and the Levenberg-Marquardt solve.

Used by the pipeline's window (:mod:`~trianflow_vo.ba.window`) and by the benchmark's
whole-clip adjustment (:mod:`~trianflow_vo.eval.image_optimum`); each adds its own gauge
(held poses, a range) around them.

Poses are ``T_world_cam`` ``(4, 4)`` (GTSAM's ``Pose3`` of a camera, z forward);
points are world coordinates; pixels ``(u, v)``. GTSAM is imported inside the
functions that need it.
"""

from __future__ import annotations

import numpy as np


def project(K: np.ndarray, T_world_cam: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of world points, each in its own camera.

    Args:
        K: ``(3, 3)`` intrinsics.
        T_world_cam: ``(M, 4, 4)`` camera of each point, or one ``(4, 4)`` for all.
        X: ``(M, 3)`` world points.

    Returns:
        ``(uv (M, 2), in_front (M,) bool)``; ``uv`` is ``inf`` where the point is not in front.
    """
    T = np.asarray(T_world_cam, dtype=np.float64)
    X = np.asarray(X, dtype=np.float64)
    if T.shape == (4, 4):
        Xc = (X - T[:3, 3]) @ T[:3, :3]
    else:
        Xc = np.einsum("mji,mj->mi", T[:, :3, :3], X - T[:, :3, 3])
    z = Xc[:, 2]
    front = z > 1e-9
    uv = np.full((X.shape[0], 2), np.inf)
    uv[front] = (Xc[front] @ K.T)[:, :2] / z[front, None]
    return uv, front


def add_reprojection_factors(graph, K: np.ndarray, frame: np.ndarray, point: np.ndarray, uv: np.ndarray,
                             huber_px: float, pose_key, point_key) -> None:
    """Add one reprojection factor per observation to the GTSAM ``graph``.

    Args:
        K: ``(3, 3)`` intrinsics (held; skew from ``K[0, 1]``).
        frame: ``(M,)`` int, the observing pose of each observation (passed to ``pose_key``).
        point: ``(M,)`` int, the observed point (passed to ``point_key``).
        uv: ``(M, 2)`` observed pixels.
        huber_px: Huber threshold in pixels; the noise sigma is 1 px.
        pose_key, point_key: GTSAM key makers (``symbol_shorthand.X``, ``.L``).
    """
    import gtsam

    cal = gtsam.Cal3_S2(float(K[0, 0]), float(K[1, 1]), float(K[0, 1]), float(K[0, 2]), float(K[1, 2]))
    noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(float(huber_px)),
                                           gtsam.noiseModel.Isotropic.Sigma(2, 1.0))
    for f, t, p in zip(np.asarray(frame).tolist(), np.asarray(point).tolist(), np.asarray(uv, dtype=np.float64)):
        graph.add(gtsam.GenericProjectionFactorCal3_S2(p, noise, pose_key(f), point_key(t), cal))


def levenberg_marquardt(graph, values, max_iterations: int):
    """Solve ``graph`` from ``values``.

    Returns:
        ``((result, error_before, error_after, iterations), True)``, or ``(None, False)`` when
        GTSAM fails (indeterminate system and friends) or the final error is not finite.
    """
    import gtsam

    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(int(max_iterations))
    try:
        e0 = graph.error(values)
        opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        result = opt.optimize()
        e1 = graph.error(result)
    except RuntimeError:  # IndeterminantLinearSystemException and friends
        return None, False
    if not np.isfinite(e1):
        return None, False
    return (result, float(e0), float(e1), int(opt.iterations())), True
