"""Two-view geometry on synthetic scenes with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from synthetic import K_TEST, angle_between, project, two_view_scene
from trianflow_vo.geometry.epipolar import epipolar_distance, inlier_score, sampson_distance
from trianflow_vo.geometry.essential import choose_pose_cheirality, decompose_essential
from trianflow_vo.geometry.fundamental import eight_point, essential_from_fundamental, fundamental_from_pose
from trianflow_vo.geometry.relative_pose import estimate_relative_pose, refine_pose_sampson
from trianflow_vo.geometry.se3 import invert_T, make_T, rodrigues, rotation_angle, rotation_log, skew
from trianflow_vo.geometry.triangulation import triangulate_midpoint


def test_rodrigues_log_roundtrip():
    rng = np.random.default_rng(1)
    for _ in range(20):
        w = rng.normal(size=3)
        w *= rng.uniform(0.0, 3.0) / np.linalg.norm(w)
        R = rodrigues(w)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.allclose(rotation_log(R), w, atol=1e-8)
        assert rotation_angle(R) == pytest.approx(np.linalg.norm(w), abs=1e-9)


def test_invert_T():
    T = make_T(rodrigues(np.array([0.3, -0.2, 0.1])), np.array([1.0, 2.0, 3.0]))
    assert np.allclose(T @ invert_T(T), np.eye(4))


def test_eight_point_exact():
    pts1, pts2, _, R, t = two_view_scene(n=50)
    F, ok = eight_point(pts1, pts2)
    assert ok
    F_true = fundamental_from_pose(R, t, K_TEST)
    if np.sum(F * F_true) < 0:
        F = -F
    assert np.allclose(F, F_true, atol=1e-8)
    assert epipolar_distance(F, pts1, pts2).max() < 1e-6
    assert np.linalg.matrix_rank(F, tol=1e-10) == 2


def test_eight_point_too_few():
    pts1, pts2, *_ = two_view_scene(n=7)
    _, ok = eight_point(pts1, pts2)
    assert not ok


def test_decompose_and_cheirality_picks_truth():
    pts1, pts2, _, R, t = two_view_scene(n=100)
    E = skew(t) @ R
    cands = decompose_essential(E)
    assert len(cands) == 4
    (Rc, tc), n_front, ok = choose_pose_cheirality(E, pts1, pts2, K_TEST)
    assert ok and n_front == 100
    assert rotation_angle(Rc.T @ R) < 1e-9
    assert angle_between(tc, t) < 1e-6  # sign chosen correctly, not just the line
    # the other three candidates put fewer points in front
    E_from_F = essential_from_fundamental(fundamental_from_pose(R, t, K_TEST), K_TEST)
    (R2, t2), _, ok2 = choose_pose_cheirality(E_from_F, pts1, pts2, K_TEST)
    assert ok2 and rotation_angle(R2.T @ R) < 1e-8 and angle_between(t2, t) < 1e-6


def test_epipolar_and_sampson_distance_known_offset():
    pts1, pts2, _, R, t = two_view_scene(n=20)
    F = fundamental_from_pose(R, t, K_TEST)
    # move pts2 perpendicular to its epipolar line by exactly 2 px
    l = np.concatenate([pts1, np.ones((20, 1))], 1) @ F.T
    nrm = l[:, :2] / np.linalg.norm(l[:, :2], axis=1, keepdims=True)
    moved = pts2 + 2.0 * nrm
    assert np.allclose(epipolar_distance(F, pts1, moved), 2.0, atol=1e-6)
    s = sampson_distance(F, pts1, moved)
    assert np.all(s > 0.9) and np.all(s < 2.0 + 1e-6)  # Sampson splits the error over both images
    m = inlier_score(np.array([0.0, 0.4, 0.6]))
    assert np.allclose(m, [1.0, 1 / 1.4, 0.0])


def test_midpoint_triangulation_exact():
    pts1, pts2, X1, R, t = two_view_scene(n=200)
    X, valid, angle = triangulate_midpoint(pts1, pts2, K_TEST, R, t, min_angle=0.0)
    assert valid.all()
    assert np.allclose(X, X1, rtol=1e-7, atol=1e-7)
    assert np.all(angle > 0)


def test_midpoint_is_closest_approach_midpoint():
    # skewed rays: compare with brute-force least squares of the two ray parameters
    R = rodrigues(np.array([0.0, 0.02, 0.0]))
    t = np.array([-1.0, 0.0, 0.1])
    pts1 = np.array([[400.0, 100.0], [100.0, 200.0]])
    pts2 = np.array([[380.0, 103.0], [60.0, 190.0]])
    X, _, _ = triangulate_midpoint(pts1, pts2, K_TEST, R, t, min_angle=0.0, max_depth=np.inf)
    Kinv = np.linalg.inv(K_TEST)
    for i in range(2):
        d1 = Kinv @ np.r_[pts1[i], 1]
        d2 = R.T @ Kinv @ np.r_[pts2[i], 1]
        c2 = -R.T @ t
        A = np.stack([d1, -d2], 1)
        lam, *_ = np.linalg.lstsq(A, c2, rcond=None)
        mid = 0.5 * (lam[0] * d1 + c2 + lam[1] * d2)
        assert np.allclose(X[i], mid, atol=1e-9)


def test_triangulation_drops_points_behind_and_parallel():
    pts1, pts2, X1, R, t = two_view_scene(n=50)
    # the first five matches are projections of points behind both cameras
    Xb = -X1[:5]
    p1, p2 = pts1.copy(), pts2.copy()
    p1[:5] = project(K_TEST, Xb)
    p2[:5] = project(K_TEST, Xb @ R.T + t)
    _, valid, _ = triangulate_midpoint(p1, p2, K_TEST, R, t, min_angle=0.0)
    assert not valid[:5].any() and valid[5:].all()
    # identical pixels under pure translation along z from the principal point: zero angle
    _, v2, ang = triangulate_midpoint(np.array([[416.0, 128.0]]), np.array([[416.0, 128.0]]), K_TEST, np.eye(3),
                                      np.array([0, 0, 1.0]))
    assert not v2[0] and ang[0] < 1e-9


@pytest.mark.parametrize("method", ["ransac", "magsac", "8point"])
def test_relative_pose_exact(method):
    pts1, pts2, _, R, t = two_view_scene(n=400)
    rel, ok = estimate_relative_pose(pts1, pts2, K_TEST, threshold_px=0.5, method=method)
    assert ok
    assert np.degrees(rotation_angle(rel.R.T @ R)) < 1e-3
    assert angle_between(rel.t, t) < 1e-2
    assert rel.inliers.all()


@pytest.mark.parametrize("method", ["ransac", "magsac", "8point"])
def test_relative_pose_noise_and_outliers(method):
    rng = np.random.default_rng(3)
    pts1, pts2, _, R, t = two_view_scene(n=2000, seed=3)
    noisy = pts2 + rng.normal(scale=0.3, size=pts2.shape)
    n_out = int(0.3 * len(pts1))
    out_idx = rng.choice(len(pts1), n_out, replace=False)
    noisy[out_idx] = rng.uniform([0, 0], [832, 256], size=(n_out, 2))
    rel, ok = estimate_relative_pose(pts1, noisy, K_TEST, threshold_px=1.0, method=method,
                                     rng=np.random.default_rng(0))
    assert ok
    assert np.degrees(rotation_angle(rel.R.T @ R)) < 0.05
    assert angle_between(rel.t, t) < 1.0
    # the outliers are flagged
    flagged = ~rel.inliers
    assert flagged[out_idx].mean() > 0.95
    assert flagged.sum() < n_out * 1.2


def test_refinement_reduces_error():
    rng = np.random.default_rng(5)
    pts1, pts2, _, R, t = two_view_scene(n=1500, seed=5)
    noisy = pts2 + rng.normal(scale=0.5, size=pts2.shape)
    R0 = rodrigues(np.array([0.002, -0.003, 0.001])) @ R
    t0 = t / np.linalg.norm(t) + np.array([0.03, -0.02, 0.0])
    (R1, t1), ok = refine_pose_sampson(R0, t0, pts1, noisy, K_TEST)
    assert ok
    assert rotation_angle(R1.T @ R) < 0.2 * rotation_angle(R0.T @ R)
    assert angle_between(t1, t) < 0.3 * angle_between(t0, t)


def test_pure_rotation_does_not_crash():
    R = rodrigues(np.array([0.0, 0.05, 0.0]))
    pts1, _, X1, _, _ = two_view_scene(n=300, R=R, t=np.zeros(3))
    pts2 = project(K_TEST, X1 @ R.T)
    rel, ok = estimate_relative_pose(pts1, pts2, K_TEST, threshold_px=0.5)
    # no translation: either rejected, or whatever is returned has the right rotation
    if ok:
        assert np.degrees(rotation_angle(rel.R.T @ R)) < 0.5


def test_no_motion_does_not_crash():
    pts1, *_ = two_view_scene(n=300)
    rel, ok = estimate_relative_pose(pts1, pts1.copy(), K_TEST, threshold_px=0.5)
    if ok:
        assert np.degrees(rotation_angle(rel.R)) < 0.5


def test_shape_checks():
    with pytest.raises(ValueError):
        estimate_relative_pose(np.zeros((10, 3)), np.zeros((10, 3)), K_TEST)
    with pytest.raises(ValueError):
        triangulate_midpoint(np.zeros((10, 2)), np.zeros((9, 2)), K_TEST, np.eye(3), np.ones(3))


def test_sampson_jacobian_matches_central_differences():
    """The analytic Jacobian of the refinement (and of the direction uncertainty) against
    central differences of the residual, on noisy matches away from the solution."""
    from trianflow_vo.camera import focal_px
    from trianflow_vo.geometry.relative_pose import (_perturb_pose, _signed_sampson, _tangent_basis,
                                                     normalised_columns, sampson_jacobian)

    rng = np.random.default_rng(3)
    pts1, pts2, _, R, t = two_view_scene(n=400, seed=3)
    pts2 = pts2 + rng.normal(scale=0.7, size=pts2.shape)
    x1, x2 = normalised_columns(pts1, K_TEST), normalised_columns(pts2, K_TEST)
    R0 = rodrigues(np.array([0.01, -0.02, 0.005])) @ R
    t0 = t / np.linalg.norm(t) + np.array([0.05, 0.02, -0.03])
    t0 /= np.linalg.norm(t0)
    B = _tangent_basis(t0)
    f = focal_px(K_TEST)
    r, J = sampson_jacobian(R0, t0, B, x1, x2, f)
    assert J.shape == (len(pts1), 5)
    np.testing.assert_allclose(r, _signed_sampson(R0, t0, x1, x2, f), rtol=1e-12, atol=1e-12)
    eps = 1e-6
    for k in range(5):
        dx = np.zeros(5)
        dx[k] = eps
        num = (_signed_sampson(*_perturb_pose(R0, t0, B, dx), x1, x2, f)
               - _signed_sampson(*_perturb_pose(R0, t0, B, -dx), x1, x2, f)) / (2 * eps)
        np.testing.assert_allclose(J[:, k], num, rtol=1e-5, atol=1e-5 * np.abs(num).max())
