"""The window bundle-adjustment back-end inside the pipeline (rendered sequences, known poses)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("gtsam", reason="the window back-end needs gtsam (a dependency of the project)")

from trianflow_vo.backend import DepthCorrection, NoBackend, PoseRevision, make_backend  # noqa: E402
from trianflow_vo.ba.backend import WindowBackend  # noqa: E402
from trianflow_vo.config import BackendConfig, ConfigError  # noqa: E402
from trianflow_vo.keyframe import Tracks  # noqa: E402


def test_window_backend_revises_keyframes_and_reports_in_run_json(long_drive, tmp_path, run_seq):
    doc, poses = run_seq(long_drive, tmp_path / "ba", "backend.window=5")
    be = doc["backend"]
    assert be["name"] == "window-ba" and be["window"] == 5
    assert be["solves"] >= 5 and be["revisions"] >= 5 and be["failures"] == 0
    assert be["ms_total"] > 0 and be["points_median"] >= 30
    assert doc["revisions"]["count"] == be["revisions"] and doc["revisions"]["frames_revised"] > 0
    assert len(poses) == doc["frames_processed"] == 26
    assert np.isfinite(poses).all()


def test_window_0_is_the_pure_two_view_pipeline(drive, tmp_path, run_seq):
    doc0, p0 = run_seq(drive, tmp_path / "w0", "backend.window=0")
    docn, pn = run_seq(drive, tmp_path / "none", "backend.kind=none")
    assert doc0["backend"] == {"name": "none"} and doc0["revisions"]["count"] == 0
    np.testing.assert_array_equal(p0, pn)


@pytest.mark.parametrize("concurrent", ["true", "false"])
def test_a_failing_adjustment_keeps_the_front_end_poses_and_the_run_goes_on(drive, tmp_path, concurrent, run_seq):
    # more points asked for than any window has: every solve fails (in the worker process, or here)
    doc, poses = run_seq(drive, tmp_path / "fail", "backend.window=5", "backend.min_points=100000",
                      f"backend.concurrent={concurrent}")
    _, p0 = run_seq(drive, tmp_path / "w0", "backend.window=0")
    assert doc["status"] == "completed"
    assert doc["backend"]["failures"] == doc["backend"]["solves"] > 0
    assert doc["warnings"]["backend-failed"]["count"] == doc["backend"]["failures"]
    np.testing.assert_array_equal(poses, p0)  # no revision: the front-end's poses


def test_an_implausible_adjustment_is_rejected(drive, tmp_path, monkeypatch, run_seq):
    import trianflow_vo.ba.worker as ba_worker

    real = ba_worker.solve_window

    def wild(*a, **k):
        sol, ok = real(*a, **k)
        if ok:
            for kf in sol.poses:
                sol.poses[kf] = sol.poses[kf].copy()
                sol.poses[kf][:3, 3] += 100.0  # far away
        return sol, ok

    monkeypatch.setattr(ba_worker, "solve_window", wild)  # in this process: not concurrent
    doc, poses = run_seq(drive, tmp_path / "wild", "backend.window=5", "backend.concurrent=false")
    assert doc["backend"]["rejected"] == doc["backend"]["solves"] > 0
    assert np.abs(poses[:, :, 3]).max() < 50


def test_make_backend_and_its_configuration():
    assert isinstance(make_backend(BackendConfig(window=0)), NoBackend)
    assert isinstance(make_backend(BackendConfig(kind="none")), NoBackend)
    K = np.array([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]])
    assert isinstance(make_backend(BackendConfig(), K, (80, 100)), WindowBackend)
    with pytest.raises(ValueError):
        make_backend(BackendConfig())  # needs K and the size
    for bad in ({"window": 2}, {"window": 5, "fixed": 5}, {"huber_px": 0}):
        with pytest.raises(ConfigError):
            BackendConfig(**bad)


def test_revision_depth_correction_maps_the_keyframes_carried_inverse_depth():
    from trianflow_vo.camera import PinholeCamera
    from trianflow_vo.depth.triangulated import TriangulatedDepth
    from trianflow_vo.flow.dis import DisFlow
    from trianflow_vo.keyframe import Keyframe
    from trianflow_vo.odometry import Odometry

    cam = PinholeCamera(np.array([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]]), (80, 100))
    odo = Odometry(cam, DisFlow(), TriangulatedDepth((80, 100)))
    tracks = Tracks(np.arange(4), np.array([[10.0, 10], [20, 20], [30, 30], [40, 40]]),
                    np.array([1.0, 2.0, 4.0, 20.0]), np.ones(4))
    odo.keyframe = Keyframe(7, np.zeros((80, 100, 3), np.uint8), None, np.eye(4), tracks)
    odo.last_step_norm = 1.0
    T = np.eye(4)
    T[0, 3] = 0.5
    # 1 / d' = 2 / d - 0.25: depths 1, 2, 4 become 1 / 1.75, 1 / 0.75, 4; 1 / 20 -> 0.1 - 0.25 < 0: that track ends
    odo.apply_revision(PoseRevision({7: T}, depth_correction={7: DepthCorrection(2.0, -0.25)}), T)
    np.testing.assert_allclose(odo.keyframe.tracks.depth, [1 / 1.75, 1 / 0.75, 4.0])
    np.testing.assert_array_equal(odo.keyframe.tracks.ids, [0, 1, 2])
    np.testing.assert_allclose(odo.keyframe.T_world_cam, T)
    # the step length follows the median change of depth (of the valid tracks: 1/1.75, 2/3, 1)
    np.testing.assert_allclose(odo.last_step_norm, 2 / 3)
    # a scale-only correction (b = 0) is a rescale by 1 / a, without any pose
    odo.apply_revision(PoseRevision({}, depth_correction={7: DepthCorrection(0.5)}), T)
    np.testing.assert_allclose(odo.keyframe.tracks.depth, [2 / 1.75, 2 / 0.75, 8.0])
    for bad in ((-1.0, 0.0), (0.0, 0.0), (1.0, np.nan), (np.inf, 0.0)):
        with pytest.raises(ValueError, match="depth correction"):
            DepthCorrection(*bad)
    with pytest.raises(ValueError, match="DepthCorrection"):
        PoseRevision({7: T}, depth_correction={7: 0.5})


def test_depth_correction_largest_change_is_over_the_ends_and_the_median_of_the_depths():
    depth = np.linspace(1.0, 100.0, 1001)
    # a rescale changes every depth alike: by 1 / a
    np.testing.assert_allclose(DepthCorrection(0.5).largest_change(depth), np.log(2.0))
    # 1 / d' = 1 / d + 0.01: d' / d = 1 / (1 + 0.01 d), largest at the 98th percentile (d = 98.02)
    d98 = np.percentile(depth, 98)
    np.testing.assert_allclose(DepthCorrection(1.0, 0.01).largest_change(depth), np.log1p(0.01 * d98))
    # an offset that cancels a rescale at the median depth still changes the ends
    d50 = np.percentile(depth, 50)
    c = DepthCorrection(2.0, -1.0 / d50)  # a + b d = 1 at d50
    expected = max(abs(np.log(2.0 - np.percentile(depth, q) / d50)) for q in (2, 98))
    np.testing.assert_allclose(c.largest_change(depth), expected)
    assert c.largest_change(depth) > 0.9
    np.testing.assert_allclose(DepthCorrection(0.5).factors(depth), [2.0, 2.0, 2.0])
    # 1 / d' = 1 / d - 0.015: depths beyond 66.7 would end (the 98th percentile, not the median 50.5)
    f = DepthCorrection(1.0, -0.015).factors(depth)
    assert np.isfinite(f[:2]).all() and f[2] == np.inf
    assert DepthCorrection(1.0, -0.015).largest_change(depth) == np.inf
    # spread: 1 for a rescale, else the ratio of the factors at the two ends
    assert DepthCorrection(0.5).spread(depth) == 1.0
    np.testing.assert_allclose(DepthCorrection(1.0, 0.01).spread(depth),
                               (1 + 0.01 * d98) / (1 + 0.01 * np.percentile(depth, 2)))
    assert DepthCorrection(1.0, -0.015).spread(depth) == np.inf


def test_pnp_steps_get_their_own_translation_sigma():
    """Two-view steps: ``step_trans`` x their length; PnP / rotation-only steps (handed-on
    keyframes): ``step_trans_pnp`` x the larger of their length and the median two-view step."""
    cfg = BackendConfig(step_trans=0.02, step_trans_pnp=0.5)
    be = WindowBackend(cfg, np.eye(3), (64, 64))

    def step(t):
        T = np.eye(4)
        T[:3, 3] = t
        return T

    be.steps = {1: (0, step((0, 0, 1.0)), True), 2: (1, step((0, 0, 3.0)), True), 3: (2, step((0, 0, 0.1)), False),
                4: (3, step((0, 0, 0.0)), False), 5: (4, step((0, 0, 4.0)), False)}
    sig = {k: v[2] for k, v in be._step_factors().items()}
    assert sig[1] == pytest.approx(0.02) and sig[2] == pytest.approx(0.06)
    assert sig[3] == pytest.approx(0.5 * 2.0)  # median two-view step 2.0 > its own 0.1
    assert sig[4] == pytest.approx(0.5 * 2.0)  # a rotation-only hand-on: no translation measured
    assert sig[5] == pytest.approx(0.5 * 4.0)



def _ate(p, gt):
    from trianflow_vo.eval.align import umeyama

    (s, R, t), ok = umeyama(p[:, :, 3], gt[: len(p), :, 3])
    assert ok
    return float(np.sqrt(np.mean(np.sum((s * p[:, :, 3] @ R.T + t - gt[: len(p), :, 3]) ** 2, axis=1))))


def test_anchors_are_not_tried_on_a_drive_that_never_comes_back(long_drive, tmp_path, run_seq):
    doc0, p0 = run_seq(long_drive, tmp_path / "off", "backend.window=4", "backend.anchors=0")
    doc, p = run_seq(long_drive, tmp_path / "revisit", "backend.window=4", "backend.anchors=2",
                     "backend.anchor_revisit_ratio=0.5")
    assert doc["backend"]["anchors"] == 2 and doc0["backend"]["anchors"] == 0
    assert doc["backend"]["anchor_tries"] == 0 and doc["backend"]["anchored_windows"] == 0
    np.testing.assert_array_equal(p, p0)


def test_anchors_link_old_keyframes_into_later_windows(tmp_path_factory, tmp_path, run_seq):
    from synthetic_sequences import make_sequence

    # a hand-held camera in a room: it stays near where it was, so older keyframes stay in view
    seq = tmp_path_factory.mktemp("seq") / "room"
    make_sequence("handheld_indoor", seq, n_frames=120, seed=1, size=(240, 320))
    gt = np.loadtxt(seq / "poses.txt").reshape(-1, 3, 4)[::4]
    doc0, p0 = run_seq(seq, tmp_path / "off", "backend.window=4", "input.stride=4", "backend.anchors=0")
    # every old keyframe in view may anchor (the default ratio of 1: no return needed), even those whose tracks
    # still reach the newest keyframe (the rendered room's tracks live long)
    doc, p = run_seq(seq, tmp_path / "any", "backend.window=4", "input.stride=4", "backend.anchors=2",
                     "backend.anchor_max_shared=100000")
    be = doc["backend"]
    assert be["anchored_windows"] >= 2 and be["anchor_links"] >= 2 * 40, be
    assert doc0["backend"]["anchored_windows"] == 0
    assert np.isfinite(p).all() and len(p) == len(p0)
    assert _ate(p, gt) < 1.5 * _ate(p0, gt) + 1e-3, (_ate(p, gt), _ate(p0, gt))
