"""trianflow_vo.eval.consistency: known answers on synthetic scenes, then matching on images."""

import numpy as np
import pytest

from trianflow_vo.eval.consistency import (
    MIN_MATCHES,
    SiftMatcher,
    consistency_table,
    epipolar_residual,
    step_scale_log_ratio,
)
from synthetic import noise_texture, pose, project_world, render_plane

from trianflow_vo.geometry.se3 import rodrigues

K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])


@pytest.fixture
def scene():
    rng = np.random.default_rng(3)
    X = np.c_[rng.uniform(-4, 4, 300), rng.uniform(-3, 3, 300), rng.uniform(6, 20, 300)]
    poses = [pose([0, 0.0, 0], [0, 0, 0]), pose([0, 0.02, 0], [0.1, 0, 1.0]),
             pose([0, 0.04, 0.01], [0.25, 0.05, 2.1])]
    return X, poses, [project_world(K, T, X) for T in poses]


def test_epipolar_residual_zero_for_the_true_poses_and_grows_with_a_rotation_error(scene):
    X, (Ta, Tb, _), (pa, pb, _) = scene
    r, ok = epipolar_residual(K, Ta, Tb, pa, pb)
    assert ok and r < 1e-6
    wrong = Tb.copy()
    wrong[:3, :3] = wrong[:3, :3] @ rodrigues(np.array([0.0, np.radians(0.3), 0.0]))
    r2, ok2 = epipolar_residual(K, Ta, wrong, pa, pb)
    assert ok2 and r2 > 0.3  # 0.3 deg at f = 500 px moves points by ~2.6 px; part of it is along the epipolar lines


def test_epipolar_residual_ignores_outliers_above_the_cap(scene):
    _, (Ta, Tb, _), (pa, pb, _) = scene
    pb = pb.copy()
    pb[:100] += 40.0  # a third of the matches wrong
    r, ok = epipolar_residual(K, Ta, Tb, pa, pb, cap_px=3.0)
    assert ok and r < 1e-6


def test_epipolar_residual_invalid_without_translation_or_matches(scene):
    _, (Ta, Tb, _), (pa, pb, _) = scene
    assert epipolar_residual(K, Ta, Ta, pa, pa)[1] is False
    assert epipolar_residual(K, Ta, Tb, pa[:MIN_MATCHES - 1], pb[:MIN_MATCHES - 1])[1] is False


def test_step_scale_zero_for_consistent_steps(scene):
    _, (Ta, Tb, Tc), (pa, pb, pc) = scene
    s, ok = step_scale_log_ratio(K, Ta, Tb, Tc, pa, pb, pc)
    assert ok and abs(s) < 1e-9


def test_step_scale_measures_a_too_long_second_step(scene):
    _, (Ta, Tb, Tc), (pa, pb, pc) = scene
    # the second step 5 % too long: depths from (b, c) come out 5 % deeper, log ratio -log(1.05)
    Tc_long = Tc.copy()
    Tc_long[:3, 3] = Tb[:3, 3] + 1.05 * (Tc[:3, 3] - Tb[:3, 3])
    s, ok = step_scale_log_ratio(K, Ta, Tb, Tc_long, pa, pb, pc)
    assert ok and s == pytest.approx(-np.log(1.05), abs=1e-9)
    # a whole trajectory scaled changes nothing
    S = [T.copy() for T in (Ta, Tb, Tc)]
    for T in S:
        T[:3, 3] *= 3.0
    assert step_scale_log_ratio(K, *S, pa, pb, pc)[0] == pytest.approx(0.0, abs=1e-9)


def test_step_scale_with_noisy_pixels_stays_near_zero(scene):
    _, (Ta, Tb, Tc), (pa, pb, pc) = scene
    rng = np.random.default_rng(0)
    noisy = [p + rng.normal(0, 0.1, p.shape) for p in (pa, pb, pc)]
    s, ok = step_scale_log_ratio(K, Ta, Tb, Tc, *noisy)
    assert ok and abs(s) < 0.01


def test_bad_shapes_raise(scene):
    _, (Ta, Tb, Tc), (pa, pb, pc) = scene
    with pytest.raises(ValueError, match="pts_a, pts_b"):
        epipolar_residual(K, Ta, Tb, pa, pb[:-1])
    with pytest.raises(ValueError, match="T_world_b"):
        epipolar_residual(K, Ta, Tb[:3], pa, pb)
    with pytest.raises(ValueError, match="trajectory 'x'"):
        consistency_table(lambda i: None, K, {"x": np.zeros((1, 4, 4))})


def test_sift_matcher_finds_a_known_shift():
    big = noise_texture(300, 400)
    a, b = big[20:260, 20:340], big[23:263, 15:335]  # a texture point at a's (u, v) is at b's (u + 5, v - 3)
    m = SiftMatcher(n_features=500)
    (pa, da), (pb, db) = m.features("a", lambda: a), m.features("b", lambda: b)
    ia, ib = m.match(da, db)
    assert ia.size > 50
    d = np.median(pa[ia] - pb[ib], axis=0)
    assert d == pytest.approx([-5.0, 3.0], abs=0.05)
    assert m.features("a", lambda: pytest.fail("a cached image is read again"))[0] is pa
    m.forget({"b"})
    assert "a" not in m._cache and "b" in m._cache


def test_consistency_table_prefers_the_true_trajectory_over_a_perturbed_one():
    """Rendered frames of a textured plane: the true poses fit, a trajectory with a wrong step does not."""
    tex = noise_texture(600, 800, seed=1)
    n = 5
    truth = np.stack([pose([0, 0.01 * i, 0], [0.3 * i, 0.0, 0.5 * i]) for i in range(n)])
    frames = [render_plane(tex, T, K) for T in truth]  # a slanted textured plane
    bad = truth.copy()
    bad[2:, :3, 3] += (bad[2:, :3, 3] - bad[1, :3, 3]) * 0.1  # every step from frame 1 on 10 % longer
    bad[3][:3, :3] = bad[3][:3, :3] @ rodrigues(np.array([0.0, 0.0, np.radians(0.5)]))
    table = consistency_table(lambda i: frames[i], K, {"truth": truth, "bad": bad})
    s = table.summary()
    assert s["truth"]["pairs"] == n - 1 and s["truth"]["triples"] >= n - 3
    assert s["truth"]["epipolar_px_median"] < 0.3
    assert np.nanmax(table.epipolar_px["bad"][2:4]) > 3 * np.nanmax(table.epipolar_px["truth"][2:4])
    # the step 1 -> 2 is 10 % longer than step 0 -> 1 in 'bad': log ratio about -log(1.1) at the middle frame 1
    assert table.scale_log_ratio["truth"][0] == pytest.approx(0.0, abs=0.01)
    assert table.scale_log_ratio["bad"][0] == pytest.approx(-np.log(1.1), abs=0.015)
