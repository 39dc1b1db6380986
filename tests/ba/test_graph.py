"""trianflow_vo.ba.graph: the projection, the reprojection factors and the solve shared by
the window and the whole-clip adjustment."""

import numpy as np
import pytest

from trianflow_vo.ba.graph import add_reprojection_factors, levenberg_marquardt, project

K = np.array([[500.0, 0.0, 320.0], [0.0, 400.0, 240.0], [0.0, 0.0, 1.0]])


def _cam(yaw_deg: float, centre) -> np.ndarray:
    a = np.radians(yaw_deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]]
    T[:3, 3] = centre
    return T


def test_project_known_pixels_and_points_behind():
    T = _cam(90.0, (1.0, 0.0, 0.0))  # looks along +x (its z axis is world +x)
    X = np.array([[3.0, 0.0, 0.0], [5.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    uv, front = project(K, T, X)
    assert front.tolist() == [True, True, False]
    np.testing.assert_allclose(uv[0], [320.0, 240.0], atol=1e-12)
    # 4 m ahead, 1 m down (y), 0 sideways
    np.testing.assert_allclose(uv[1], [320.0, 240.0 + 400.0 / 4.0], atol=1e-12)
    assert np.isinf(uv[2]).all()
    # one camera per point gives the same as one camera for all
    uv_m, front_m = project(K, np.repeat(T[None], 3, axis=0), X)
    np.testing.assert_array_equal(front_m, front)
    np.testing.assert_allclose(uv_m[:2], uv[:2], atol=1e-12)


def test_reprojection_factors_recover_a_moved_camera():
    gtsam = pytest.importorskip("gtsam", reason="the adjustment needs gtsam (a dependency of the project)")
    rng = np.random.default_rng(0)
    P = np.c_[rng.uniform(-2, 2, 40), rng.uniform(-1, 1, 40), rng.uniform(4, 8, 40)]
    truth = [_cam(0.0, (0, 0, 0)), _cam(5.0, (0.5, 0.0, 0.1))]
    frame = np.repeat([0, 1], len(P))
    point = np.tile(np.arange(len(P)), 2)
    uv = np.concatenate([project(K, T, P)[0] for T in truth])
    X, L = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.L
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    # the gauge: the first camera held, and the distance between the two (the scale)
    graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(truth[0]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-4)))
    graph.add(gtsam.RangeFactorPose3(X(0), X(1), float(np.linalg.norm(truth[1][:3, 3])),
                                     gtsam.noiseModel.Isotropic.Sigma(1, 1e-4)))
    start = truth[1].copy()
    start[:3, 3] += (0.05, -0.03, 0.02)
    values.insert(X(0), gtsam.Pose3(truth[0]))
    values.insert(X(1), gtsam.Pose3(start))
    for q in range(len(P)):
        values.insert(L(q), P[q] + rng.normal(0, 0.05, 3))
    add_reprojection_factors(graph, K, frame, point, uv, 1.0, X, L)
    assert graph.size() == 2 + frame.size
    solved, ok = levenberg_marquardt(graph, values, 100)
    assert ok
    result, e0, e1, iters = solved
    assert e1 < 1e-9 * e0 and iters >= 1
    np.testing.assert_allclose(result.atPose3(X(1)).matrix(), truth[1], atol=1e-5)


def test_levenberg_marquardt_refuses_a_non_finite_error():
    gtsam = pytest.importorskip("gtsam", reason="the adjustment needs gtsam (a dependency of the project)")
    X, L = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.L
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    values.insert(X(0), gtsam.Pose3(np.eye(4)))
    values.insert(L(0), np.array([0.0, 0.0, 5.0]))
    graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(np.eye(4)), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    add_reprojection_factors(graph, K, np.array([0]), np.array([0]), np.array([[np.nan, 240.0]]), 1.0, X, L)
    assert levenberg_marquardt(graph, values, 10) == (None, False)
    # the same graph with a finite pixel solves
    ok_graph = gtsam.NonlinearFactorGraph()
    ok_graph.add(graph.at(0))
    add_reprojection_factors(ok_graph, K, np.array([0]), np.array([0]), np.array([[330.0, 240.0]]), 1.0, X, L)
    assert levenberg_marquardt(ok_graph, values, 10)[1]
