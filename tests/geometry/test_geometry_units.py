"""Unit tests of the smaller pieces: scale alignment, PnP, rotation fit, masks,
working size and intrinsics scaling (the triangulated depth: tests/depth/test_triangulated.py)."""

from __future__ import annotations

import numpy as np
import pytest

from synthetic import K_TEST, project, two_view_scene
from trianflow_vo.camera import scale_intrinsics, working_size
from trianflow_vo.flow.masks import fb_distance, flow_scores, occlusion_mask, range_map
from trianflow_vo.camera import unproject as backproject
from trianflow_vo.geometry.pnp import solve_pnp
from trianflow_vo.geometry.rotation import fit_rotation
from trianflow_vo.geometry.scale import align_scale, fit_inverse_depth_affine, inverse_depth_offset_t, weighted_median
from trianflow_vo.geometry.se3 import rodrigues, rotation_angle


# --------------------------------------------------------------------------- scale
def test_weighted_median():
    assert weighted_median(np.array([1.0, 2.0, 3.0]), np.ones(3)) == 2.0
    # a heavy weight pulls the median to its value
    assert weighted_median(np.array([1.0, 2.0, 3.0]), np.array([1.0, 1.0, 10.0])) == 3.0


def test_align_scale_recovers_known_factor_with_outliers():
    rng = np.random.default_rng(0)
    d_tri = rng.uniform(2.0, 40.0, 1000)
    d_ref = 3.7 * d_tri * np.exp(rng.normal(0, 0.02, 1000))
    bad = rng.choice(1000, 300, replace=False)  # 30% gross outliers
    d_ref[bad] = rng.uniform(0.5, 100.0, 300)
    d_ref[:50] = 0.0  # unknown reference depth is ignored
    s, ok = align_scale(d_tri, d_ref)
    assert ok and s == pytest.approx(3.7, rel=0.01)
    # weights: the outliers get no say when they have no weight
    w = np.ones(1000)
    w[bad] = 0.0
    s_w, ok = align_scale(d_tri, d_ref, weights=w)
    assert ok and s_w == pytest.approx(3.7, rel=0.005)


def test_align_scale_too_few_points():
    s, ok = align_scale(np.array([1.0, 2.0]), np.array([2.0, 4.0]), min_points=10)
    assert not ok
    with pytest.raises(ValueError):
        align_scale(np.ones(3), np.ones(4))


# --------------------------------------------------------------------------- PnP
def test_inverse_depth_affine_recovers_a_known_offset_with_noise_and_outliers():
    rng = np.random.default_rng(3)
    z_true = rng.uniform(1.0, 10.0, 400)
    a0, b0 = 0.8, 0.05  # 1 / z_true = a0 / z_est + b0
    z_est = a0 / (1.0 / z_true - b0 + rng.normal(0, 2e-3, z_true.size))
    z_est[:40] = rng.uniform(1.0, 30.0, 40)  # outliers
    (a, b), ok = fit_inverse_depth_affine(z_est, z_true)
    assert ok and abs(a - a0) < 0.02 and abs(b - b0) < 3e-3
    # no single scale fits such a depth: one fitted on the far points is wrong for the near ones
    far, near = z_true > 6, z_true < 2
    s, _ = align_scale(z_est[far], z_true[far])
    assert abs(np.median(z_true[near] / z_est[near]) / s - 1) > 0.1
    corrected = 1.0 / (a / z_est + b)
    assert np.median(np.abs(np.log(corrected[40:] / z_true[40:]))) < 0.01


def test_inverse_depth_affine_without_depth_spread_is_a_scale():
    z = np.full(50, 4.0) * np.exp(np.random.default_rng(0).normal(0, 0.01, 50))
    (a, b), ok = fit_inverse_depth_affine(z, 2.0 * z)
    assert ok and b == 0.0 and a == pytest.approx(0.5)
    assert fit_inverse_depth_affine(np.ones(5), np.ones(5), min_points=10)[1] is False
    with pytest.raises(ValueError):
        fit_inverse_depth_affine(np.ones(3), np.ones(4))


def test_inverse_depth_offset_t_standard_error_matches_the_scatter_of_fits():
    """Known answer by Monte Carlo: over many noisy draws of the same scene, the spread of the
    fitted offset b / a is the standard error the t statistic divides by; with no offset |t| is
    mostly under 2, with one of ten standard errors it is about 10."""
    rng = np.random.default_rng(5)
    z_true = rng.uniform(1.0, 10.0, 60)
    sigma = 4e-3

    def draw(b0):
        z_est = 1.0 / (1.0 / z_true - b0 + rng.normal(0, sigma, z_true.size))
        (a, b), ok = fit_inverse_depth_affine(z_est, z_true, min_points=10)
        t, t_ok = inverse_depth_offset_t(z_est, z_true, a, b)
        assert ok and t_ok
        return b / a, t

    zero = np.array([draw(0.0) for _ in range(400)])
    se_empirical = zero[:, 0].std()
    se_claimed = np.median(np.abs(zero[:, 0] / zero[:, 1]))
    assert se_claimed == pytest.approx(se_empirical, rel=0.2)
    assert np.mean(np.abs(zero[:, 1]) < 2) > 0.9
    big = np.array([draw(10 * se_empirical) for _ in range(100)])
    assert 7 < np.median(big[:, 1]) < 13


def test_inverse_depth_offset_t_edge_cases():
    z = np.linspace(1.0, 5.0, 20)
    assert inverse_depth_offset_t(z, z, 1.0, 0.0) == (0.0, True)  # exact fit, no offset
    t, ok = inverse_depth_offset_t(z, 1.0 / (1.0 / z + 0.1), 1.0, 0.1)
    assert ok and t > 1e6  # an exact fit with an offset: certain (up to rounding)
    assert inverse_depth_offset_t(z[:2], z[:2], 1.0, 0.0)[1] is False
    assert inverse_depth_offset_t(z, z, -1.0, 0.0)[1] is False
    with pytest.raises(ValueError):
        inverse_depth_offset_t(np.ones(3), np.ones(4), 1.0, 0.0)


def test_pnp_exact_and_with_outliers():
    R = rodrigues(np.array([0.01, -0.03, 0.02]))
    t = np.array([0.2, -0.1, 1.5])
    pts1, pts2, X1, _, _ = two_view_scene(n=400, R=R, t=t, seed=2)
    (R_est, t_est, inl), ok = solve_pnp(X1, pts2, K_TEST)
    assert ok and inl.all()
    assert np.degrees(rotation_angle(R_est.T @ R)) < 1e-4
    assert np.allclose(t_est, t, atol=1e-5)  # metric: the scale comes from the depth
    rng = np.random.default_rng(1)
    noisy = pts2 + rng.normal(0, 0.3, pts2.shape)
    out = rng.choice(400, 120, replace=False)
    noisy[out] = rng.uniform([0, 0], [832, 256], (120, 2))
    (R_est, t_est, inl), ok = solve_pnp(X1, noisy, K_TEST, reproj_px=1.0)
    assert ok
    assert np.degrees(rotation_angle(R_est.T @ R)) < 0.1
    assert np.linalg.norm(t_est - t) < 0.02 * np.linalg.norm(t)
    assert inl[out].mean() < 0.1


def test_pnp_too_few_points_is_invalid_not_an_error():
    _, ok = solve_pnp(np.ones((5, 3)), np.ones((5, 2)), K_TEST)
    assert not ok
    with pytest.raises(ValueError):
        solve_pnp(np.ones((10, 3)), np.ones((9, 2)), K_TEST)


def test_backproject_inverts_projection():
    _, _, X1, _, _ = two_view_scene(n=50)
    pts = project(K_TEST, X1)
    assert np.allclose(backproject(pts, X1[:, 2], K_TEST), X1)


# --------------------------------------------------------------------------- rotation fit
def test_fit_rotation_pure_rotation_has_no_parallax():
    R = rodrigues(np.array([0.02, 0.04, -0.01]))
    pts1, _, X1, _, _ = two_view_scene(n=300, R=R, t=np.zeros(3))
    pts2 = project(K_TEST, X1 @ R.T)
    R_est, par = fit_rotation(pts1, pts2, K_TEST)
    assert np.degrees(rotation_angle(R_est.T @ R)) < 1e-6
    assert par.max() < 1e-6


def test_fit_rotation_leaves_parallax_of_translation():
    pts1, pts2, _, _, _ = two_view_scene(n=300, R=np.eye(3), t=np.array([0.3, 0.0, 0.0]), depth=(5, 10))
    _, par = fit_rotation(pts1, pts2, K_TEST)
    # sideways motion of 0.3 at 5-10 m: 14-29 px of disparity; the rotation fit absorbs the mean
    # part, the depth-dependent rest stays as parallax
    assert np.median(par) > 2.0


# --------------------------------------------------------------------------- masks
def test_forward_backward_distance_of_consistent_flows_is_zero():
    h, w = 32, 48
    fw = np.zeros((h, w, 2), np.float32)
    fw[..., 0] = 3.0
    bw = -fw
    d = fb_distance(fw, bw)
    assert np.allclose(d[:, : w - 4], 0.0, atol=1e-5)
    # inconsistent backward flow: distance equals the inconsistency
    assert np.allclose(fb_distance(fw, np.zeros_like(fw))[:, : w - 4], 3.0, atol=1e-5)


def test_range_map_and_occlusion_of_a_shift():
    h, w = 32, 64
    fw = np.zeros((h, w, 2), np.float32)
    fw[..., 0] = 4.0  # frame b is frame a shifted 4 px right
    bw = -fw
    rm = range_map(np.zeros((h, w, 2), np.float32))
    assert np.allclose(rm, 1.0)  # identity: every pixel receives exactly one
    m_o = occlusion_mask(fw, bw)
    # pixels whose forward flow leaves frame b (the last 4 columns) are invalid, the rest valid
    assert m_o[:, : w - 5].min() == 1.0
    assert m_o[:, w - 3:].max() == 0.0
    d_fb, m_s, m_o2 = flow_scores(fw, bw)
    assert np.allclose(m_s[:, : w - 5], 10.0, atol=1e-3)  # 1 / (0.1 + 0)
    assert np.array_equal(m_o, m_o2)


# --------------------------------------------------------------------------- camera
def test_working_size():
    assert working_size(376, 1241) == (256, 832)  # KITTI 00-02
    assert working_size(370, 1226) == (256, 832)  # KITTI 04-12
    assert working_size(480, 640) == (512, 640)
    h, w = working_size(1080, 1920)
    assert w == 832 and h % 64 == 0 and w % 64 == 0
    assert working_size(376, 1241, (128, 384)) == (128, 384)


def test_scale_intrinsics_maps_points_like_resize():
    K = np.array([[718.856, 0.0, 607.1928], [0.0, 718.856, 185.2157], [0.0, 0.0, 1.0]])
    K2 = scale_intrinsics(K, (376, 1241), (256, 832))
    X = np.array([[1.0, -0.5, 10.0], [-3.0, 1.0, 20.0]])
    u = project(K, X)
    u2 = project(K2, X)
    sx, sy = 832 / 1241, 256 / 376
    assert np.allclose(u2[:, 0], (u[:, 0] + 0.5) * sx - 0.5)
    assert np.allclose(u2[:, 1], (u[:, 1] + 0.5) * sy - 0.5)
    with pytest.raises(ValueError):
        scale_intrinsics(np.eye(4), (1, 1), (1, 1))
