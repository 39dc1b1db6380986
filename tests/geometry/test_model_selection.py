"""GRIC model selection (general motion vs rotation only) and the direction uncertainty."""

import numpy as np
import pytest
from synthetic import K_TEST, project, two_view_scene

from trianflow_vo.geometry.epipolar import sampson_distance
from trianflow_vo.geometry.fundamental import fundamental_from_pose
from trianflow_vo.geometry.model_selection import direction_sigma, gric, noise_sigma, select_motion_model
from trianflow_vo.geometry.relative_pose import refine_pose_sampson
from trianflow_vo.geometry.rotation import fit_rotation
from trianflow_vo.geometry.se3 import rodrigues


def test_gric_known_values():
    n = 10
    # perfect fit: only the penalty terms, ln(4) d n + ln(4 n) k
    assert gric(np.zeros(n), 1.0, d=3, k=5) == pytest.approx(np.log(4) * 3 * n + np.log(40) * 5)
    # one residual of 1 sigma adds 1; a gross outlier is capped at 2 (r - d)
    assert gric(np.r_[np.zeros(n - 1), 1.0], 1.0, 3, 5) == pytest.approx(1 + np.log(4) * 3 * n + np.log(40) * 5)
    capped = gric(np.r_[np.zeros(n - 1), 100.0], 1.0, 2, 3)
    assert capped == pytest.approx(2 * (4 - 2) + np.log(4) * 2 * n + np.log(40) * 3)
    assert gric(np.ones(n), 2.0, 3, 5) < gric(np.ones(n), 1.0, 3, 5)  # larger noise, smaller penalty
    with pytest.raises(ValueError):
        gric(np.ones(3), 0.0, 3, 5)


def test_noise_sigma_is_robust_and_floored():
    rng = np.random.default_rng(0)
    e = np.abs(rng.normal(0, 0.3, 5000))
    e[:500] = 50.0  # 10 % gross outliers barely move it
    assert noise_sigma(e) == pytest.approx(0.3, rel=0.15)
    assert noise_sigma(np.zeros(10), floor_px=0.05) == 0.05


def _residuals(pts1, pts2, R, t):
    F = fundamental_from_pose(R, t / np.linalg.norm(t), K_TEST)
    _, par = fit_rotation(pts1, pts2, K_TEST)
    return sampson_distance(F, pts1, pts2), par


@pytest.mark.parametrize("noise", [0.1, 0.5])
def test_pure_rotation_selects_rotation(noise):
    rng = np.random.default_rng(1)
    R = rodrigues(np.array([0.01, 0.04, 0.0]))
    pts1, _, X1, _, _ = two_view_scene(n=2000, R=R, t=np.zeros(3), seed=2)
    pts2 = project(K_TEST, X1 @ R.T) + rng.normal(0, noise, (2000, 2))
    pts1 = pts1 + rng.normal(0, noise, (2000, 2))
    # the essential matrix fitted to the noise: any direction; take the one a solver would find
    t_fit = np.array([0.0, 0.0, 1.0])
    (Rf, tf), ok = refine_pose_sampson(R, t_fit, pts1, pts2, K_TEST, scale_px=noise)
    s, par = _residuals(pts1, pts2, Rf, tf)
    test = select_motion_model(s, par)
    assert not test.general, test
    assert test.gric_rotation <= test.gric_general


def test_translation_with_parallax_selects_general_motion():
    rng = np.random.default_rng(3)
    R = rodrigues(np.array([0.0, 0.02, 0.0]))
    t = np.array([0.05, 0.0, 1.0])
    pts1, pts2, _, _, _ = two_view_scene(n=2000, R=R, t=t, seed=4, depth=(5.0, 40.0))
    pts2 = pts2 + rng.normal(0, 0.2, pts2.shape)
    s, par = _residuals(pts1, pts2, R, t)
    assert np.median(par) > 2.0
    test = select_motion_model(s, par)
    assert test.general and test.sigma_px == pytest.approx(0.2, rel=0.35)


def test_translation_drowned_in_noise_selects_rotation():
    """A step whose parallax is well under the noise carries no usable translation."""
    rng = np.random.default_rng(5)
    R = rodrigues(np.array([0.0, 0.02, 0.0]))
    t = np.array([0.0, 0.0, 0.002])  # 2 mm at 5-40 m: parallax ~0.05 px
    pts1, pts2, _, _, _ = two_view_scene(n=2000, R=R, t=t, seed=6, depth=(5.0, 40.0))
    pts2 = pts2 + rng.normal(0, 0.5, pts2.shape)
    (Rf, tf), _ = refine_pose_sampson(R, t, pts1, pts2, K_TEST, scale_px=0.5)
    s, par = _residuals(pts1, pts2, Rf, tf)
    assert not select_motion_model(s, par).general


def test_direction_sigma_matches_the_spread_of_estimates():
    """First-order sigma against the spread of refined directions over noise draws."""
    R = rodrigues(np.array([0.0, 0.01, 0.0]))
    t = np.array([0.2, 0.0, 1.0])
    t /= np.linalg.norm(t)
    pts1, pts2, _, _, _ = two_view_scene(n=400, R=R, t=t * 0.5, seed=7, depth=(4.0, 30.0))
    noise = 0.5
    sig, ok = direction_sigma(R, t, pts1, pts2, K_TEST, noise)
    assert ok and 0 < sig < 0.1
    rng = np.random.default_rng(8)
    angles = []
    for _ in range(40):
        q2 = pts2 + rng.normal(0, noise, pts2.shape)
        (Rf, tf), _ = refine_pose_sampson(R, t, pts1, q2, K_TEST, scale_px=noise)
        angles.append(np.arccos(np.clip(tf @ t, -1, 1)))
    # the angle to the truth is the norm of a 2-D error: its RMS is sqrt(2) sigma for equal axes,
    # between sigma and sqrt(2) sigma in general
    rms = float(np.sqrt(np.mean(np.square(angles))))
    assert 0.6 * sig < rms < 1.6 * np.sqrt(2) * sig, (rms, sig)


def test_direction_sigma_grows_as_the_baseline_shrinks_and_with_fewer_independent_matches():
    R = np.eye(3)
    sigs = []
    for b in (1.0, 0.1, 0.01):
        t = np.array([0.1, 0.0, 1.0]) * b
        pts1, pts2, _, _, _ = two_view_scene(n=1000, R=R, t=t, seed=9, depth=(4.0, 30.0))
        sig, ok = direction_sigma(R, t, pts1, pts2, K_TEST, 0.3)
        assert ok
        sigs.append(sig)
    assert sigs[0] < sigs[1] < sigs[2]
    t = np.array([0.1, 0.0, 1.0])
    pts1, pts2, _, _, _ = two_view_scene(n=1000, R=R, t=t, seed=9, depth=(4.0, 30.0))
    all_, _ = direction_sigma(R, t, pts1, pts2, K_TEST, 0.3)
    few, _ = direction_sigma(R, t, pts1, pts2, K_TEST, 0.3, n_independent=100)
    assert few == pytest.approx(all_ * np.sqrt(10), rel=1e-6)
    assert direction_sigma(R, t, pts1[:4], pts2[:4], K_TEST, 0.3) == (float("inf"), False)


def test_select_motion_model_checks_shapes():
    with pytest.raises(ValueError):
        select_motion_model(np.zeros(3), np.zeros(4))
