"""PinholeCamera: resizing, projection and back-projection agree with the free functions."""

from __future__ import annotations

import numpy as np
import pytest

from trianflow_vo.camera import PinholeCamera, focal_px, project, scale_intrinsics, unproject

K = np.array([[700.0, 0.0, 600.0], [0.0, 710.0, 180.0], [0.0, 0.0, 1.0]])


def test_resized_camera_scales_intrinsics_like_cv2_resize():
    cam = PinholeCamera(K, (376, 1241)).resized((256, 832))
    assert cam.size_hw == (256, 832)
    assert np.array_equal(cam.K, scale_intrinsics(K, (376, 1241), (256, 832)))
    # the centre of the image stays the centre: (u + 0.5) * s - 0.5
    assert cam.K[0, 2] == pytest.approx((600.0 + 0.5) * 832 / 1241 - 0.5)


def test_project_unproject_round_trip_and_validity():
    cam = PinholeCamera(K, (376, 1241))
    rng = np.random.default_rng(0)
    pts = rng.uniform([0, 0], [1240, 375], (50, 2))
    depth = rng.uniform(1, 80, 50)
    X = cam.unproject(pts, depth)
    assert np.allclose(X[:, 2], depth)
    uv, valid = cam.project(X)
    assert valid.all() and np.allclose(uv, pts)
    assert np.allclose(project(X, K), pts) and np.allclose(unproject(pts, depth, K), X)
    behind_or_out = np.array([[0.0, 0.0, -1.0], [1000.0, 0.0, 1.0]])
    uv, valid = cam.project(behind_or_out)
    assert not valid.any() and np.isnan(uv[0]).all()


def test_bad_camera_is_refused():
    with pytest.raises(ValueError, match=r"K must be \(3, 3\)"):
        PinholeCamera(np.eye(2), (10, 10))
    with pytest.raises(ValueError, match="positive"):
        PinholeCamera(K, (0, 10))
    cam = PinholeCamera(K, (10, 10))
    with pytest.raises(ValueError):
        cam.K[0, 0] = 1.0


def test_focal_px_is_the_geometric_mean_of_the_axes():
    K2 = np.array([[400.0, 0.0, 320.0], [0.0, 900.0, 240.0], [0.0, 0.0, 1.0]])
    assert focal_px(K2) == pytest.approx(600.0)
    # a small angle's square footprint in pixels has the area of the true (a fx by a fy) one
    a = 1e-3
    assert (a * focal_px(K2)) ** 2 == pytest.approx((a * 400.0) * (a * 900.0))
    assert focal_px(K) == pytest.approx(np.sqrt(700.0 * 710.0))
