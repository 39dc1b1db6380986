"""trianflow_vo.eval.image_optimum: track linking, triangulation and the full adjustment on
synthetic scenes with known answers; SIFT tracks on rendered frames."""

import numpy as np
import pytest
from synthetic import noise_texture, pose, project_world, render_plane

from trianflow_vo.ba.graph import project
from trianflow_vo.eval.align import umeyama
from trianflow_vo.eval.image_optimum import (
    Observations,
    image_optimum,
    link_tracks,
    sift_matches,
    sift_tracks,
    tracks_from_matches,
    triangulate_tracks,
)
from trianflow_vo.geometry.se3 import rodrigues

pytest.importorskip("gtsam")

K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])


def _ate_percent(T, truth):
    (s, R, t), ok = umeyama(T[:, :3, 3], truth[:, :3, 3])
    assert ok
    e = np.linalg.norm(s * T[:, :3, 3] @ R.T + t - truth[:, :3, 3], axis=1)
    path = np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1).sum()
    return 100 * np.sqrt(np.mean(e ** 2)) / path


def _observe(truth, X):
    """Exact observations of points ``X`` in every frame of ``truth`` they project into; the points
    seen at least twice (row ``j`` = track ``j``) and their observations."""
    frame, track, uv = [], [], []
    for i, T in enumerate(truth):
        p = project_world(K, T, X)
        z = ((X - T[:3, 3]) @ T[:3, :3])[:, 2]
        vis = (z > 1) & (p[:, 0] >= 0) & (p[:, 0] < 640) & (p[:, 1] >= 0) & (p[:, 1] < 480)
        frame.append(np.full(int(vis.sum()), i))
        track.append(np.flatnonzero(vis))
        uv.append(p[vis])
    frame, track, uv = np.concatenate(frame), np.concatenate(track), np.concatenate(uv)
    obs = Observations(frame.astype(np.int64), track.astype(np.int64), uv)
    keep = np.bincount(obs.track, minlength=X.shape[0])[obs.track] >= 2
    return X[np.unique(obs.track[keep])], obs.subset(keep)


def _truth(n=12):
    return np.stack([pose([0, 0.01 * i, 0], [0.05 * i * i / n, 0.02 * np.sin(i), 0.8 * i]) for i in range(n)])


@pytest.fixture
def scene():
    """12 frames driving forward with a gentle turn; 600 points seen by every frame they project into
    (``X`` holds those seen at least twice, row ``j`` = track ``j``)."""
    rng = np.random.default_rng(5)
    truth = _truth()
    X = np.c_[rng.uniform(-15, 15, 600), rng.uniform(-3, 2, 600), rng.uniform(8, 40, 600)]
    return (truth, *_observe(truth, X))


def test_link_tracks_merges_chains_and_drops_a_track_with_two_keypoints_in_one_frame():
    matches = [
        (0, 1, np.array([0, 1]), np.array([0, 1])),  # A: f0k0-f1k0, B: f0k1-f1k1
        (1, 2, np.array([0]), np.array([2])),  # A continues: f1k0-f2k2
        (0, 2, np.array([2]), np.array([1])),  # C: f0k2-f2k1 ...
        (1, 2, np.array([2]), np.array([0])),  # ... and f1k2-f2k0
        (0, 1, np.array([2]), np.array([2])),  # ... joined: C holds f2k1 and f2k0 -> dropped
    ]
    frame, kp, track = link_tracks([3, 3, 3], matches)
    got = sorted(zip(track.tolist(), frame.tolist(), kp.tolist()))
    tracks = {}
    for t, f, k in got:
        tracks.setdefault(t, []).append((f, k))
    assert sorted(tracks.values()) == [[(0, 0), (1, 0), (2, 2)], [(0, 1), (1, 1)]]
    assert sorted(set(track.tolist())) == [0, 1]


def test_triangulate_tracks_recovers_the_points_and_drops_a_shifted_observation(scene):
    truth, X, obs = scene
    Xt, keep = triangulate_tracks(K, truth, obs)
    assert keep.all() and Xt.shape == (obs.n_tracks, 3)
    assert np.abs(Xt - X).max() < 1e-6
    uv = obs.uv.copy()
    uv[0] += 5.0
    Xs, keep2 = triangulate_tracks(K, truth, Observations(obs.frame, obs.track, uv))
    assert not keep2[0] and keep2[1:].sum() >= keep2.size - 1 - 12  # at most its own track's others drop
    # a track seen twice, one observation wrong: the other alone fixes nothing, both go
    two = np.flatnonzero(np.bincount(obs.track) == 2)[0]
    rows = np.flatnonzero(obs.track == two)
    uv = obs.uv.copy()
    uv[rows[1]] += 5.0
    _, keep3 = triangulate_tracks(K, truth, Observations(obs.frame, obs.track, uv))
    assert not keep3[rows].any() and keep3.sum() == keep3.size - 2
    # every point reprojects exactly into the true poses
    p, front = project(K, truth[obs.frame], Xt[obs.track])
    assert front.all() and np.abs(p - obs.uv).max() < 1e-6


def test_triangulate_tracks_leaves_out_tracks_whose_rays_meet_at_a_small_angle(scene):
    truth, X, obs = scene
    # the angle at each point between the rays from its first and last camera
    first = np.array([obs.frame[obs.track == t].min() for t in range(obs.n_tracks)])
    last = np.array([obs.frame[obs.track == t].max() for t in range(obs.n_tracks)])
    a = X - truth[first, :3, 3]
    b = X - truth[last, :3, 3]
    angle = np.degrees(np.arccos(np.sum(a * b, 1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)))
    limit = float(np.median(angle))
    _, keep = triangulate_tracks(K, truth, obs, min_angle_deg=limit)
    kept_tracks = np.unique(obs.track[keep])
    np.testing.assert_array_equal(kept_tracks, np.flatnonzero(angle >= limit))
    assert image_optimum(K, truth, obs, min_angle_deg=90.0) == (None, False)


def test_image_optimum_stays_at_poses_that_explain_the_images(scene):
    truth, _, obs = scene
    opt, ok = image_optimum(K, truth, obs)
    assert ok and len(opt.error_after) == 1
    assert np.abs(opt.T_world_cam[:, :3, 3] - truth[:, :3, 3]).max() < 1e-6
    assert opt.error_after[0] < 1e-8 and opt.residual_px_median < 1e-4
    assert opt.n_points > 300 and opt.n_observations == obs.frame.size


def test_image_optimum_holds_the_scale_when_the_camera_stands_still_at_first():
    rng = np.random.default_rng(6)
    truth = _truth()
    truth[1] = truth[0]  # no motion between the first two frames
    X = np.c_[rng.uniform(-15, 15, 600), rng.uniform(-3, 2, 600), rng.uniform(8, 40, 600)]
    _, obs = _observe(truth, X)
    start = truth.copy()
    start[6:, :3, 3] += (truth[6:, :3, 3] - truth[5, :3, 3]) * 0.05
    opt, ok = image_optimum(K, start, obs)
    assert ok and _ate_percent(opt.T_world_cam, truth) < 0.01
    # the held distance (first to farthest camera) is the start's
    far = np.linalg.norm(start[:, :3, 3] - start[0, :3, 3], axis=1).max()
    assert np.linalg.norm(opt.T_world_cam[:, :3, 3] - opt.T_world_cam[0, :3, 3], axis=1).max() == pytest.approx(far, rel=1e-3)


def test_image_optimum_removes_a_scale_drift_and_rotation_errors(scene):
    truth, _, obs = scene
    rng = np.random.default_rng(0)
    # the start: every step 3 % longer than the one before (a scale drift) and 0.2 deg rotation errors
    start = truth.copy()
    for i in range(2, truth.shape[0]):
        step = truth[i, :3, 3] - truth[i - 1, :3, 3]
        start[i, :3, 3] = start[i - 1, :3, 3] + step * 1.03 ** (i - 1)
        start[i, :3, :3] = start[i, :3, :3] @ rodrigues(rng.normal(0, np.radians(0.2), 3))
    noisy = Observations(obs.frame, obs.track, obs.uv + rng.normal(0, 0.3, obs.uv.shape))
    assert _ate_percent(start, truth) > 1.0
    # the noise alone moves the optimum a little away from the truth: that is the answer to reach
    at_truth, ok = image_optimum(K, truth, noisy)
    assert ok and 0.005 < _ate_percent(at_truth.T_world_cam, truth) < 0.1
    opt, ok = image_optimum(K, start, noisy)
    assert ok and len(opt.error_after) >= 2  # the gate dropped observations at the start; they came back
    assert _ate_percent(opt.T_world_cam, truth) == pytest.approx(_ate_percent(at_truth.T_world_cam, truth), abs=0.002)
    assert opt.n_observations == at_truth.n_observations == noisy.frame.size
    assert opt.error_after[-1] < opt.error_before[0]
    assert 0.2 < opt.residual_px_median < 0.4  # the matching noise (0.3 px) is what is left


def test_image_optimum_ignores_outlier_observations(scene):
    truth, _, obs = scene
    rng = np.random.default_rng(1)
    uv = obs.uv.copy()
    bad = rng.random(uv.shape[0]) < 0.05
    uv[bad] += rng.choice([-1, 1], (int(bad.sum()), 2)) * rng.uniform(5, 30, (int(bad.sum()), 2))
    start = truth.copy()
    start[5:, :3, 3] += (truth[5:, :3, 3] - truth[4, :3, 3]) * 0.05
    opt, ok = image_optimum(K, start, Observations(obs.frame, obs.track, uv))
    assert ok
    assert _ate_percent(opt.T_world_cam, truth) < 0.05


def test_image_optimum_rejects_bad_input_and_reports_too_few_points(scene):
    truth, _, obs = scene
    with pytest.raises(ValueError, match="T_world_cam"):
        image_optimum(K, truth[:1], obs)
    with pytest.raises(ValueError, match="same camera centre"):
        image_optimum(K, np.stack([truth[0]] * truth.shape[0]), obs)
    with pytest.raises(ValueError, match="outside"):
        image_optimum(K, truth[:5], obs)
    few = obs.subset(obs.track < 10)
    assert image_optimum(K, truth, few) == (None, False)


def test_sift_tracks_on_rendered_frames_span_several_frames_and_fit_the_true_poses():
    tex = noise_texture(600, 800, seed=2)
    n = 5
    truth = np.stack([pose([0, 0.01 * i, 0], [0.3 * i, 0.0, 0.5 * i]) for i in range(n)])
    frames = [render_plane(tex, T, K) for T in truth]
    obs = sift_tracks(lambda i: frames[i], K, truth, overlap=3)
    span = np.bincount(obs.track)
    assert obs.n_tracks > 100 and np.median(span) >= 3
    Xt, keep = triangulate_tracks(K, truth, obs)
    assert keep.mean() > 0.95
    # the points lie on the plane z = 12 + 4 (x + 6) / 12
    X = Xt[np.unique(obs.track[keep])]
    assert np.median(np.abs(X[:, 2] - (12 + 4 * (X[:, 0] + 6) / 12))) < 0.05
    with pytest.raises(ValueError, match="overlap"):
        sift_tracks(lambda i: frames[i], K, truth, overlap=0)
    # the matches do not depend on the poses: built once, filtered for any trajectory of those frames
    m = sift_matches(lambda i: frames[i], n, overlap=3)
    again = tracks_from_matches(K, truth, m)
    np.testing.assert_array_equal(again.uv, obs.uv)
    with pytest.raises(ValueError, match="4 poses for 5 frames"):
        tracks_from_matches(K, truth[:4], m)
