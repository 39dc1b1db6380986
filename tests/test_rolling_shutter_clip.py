"""``benchmarks/rolling_shutter_clip.py``: a path through the synthetic room, with a rolling shutter."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from synthetic_sequences import handheld_indoor, intrinsics, render, rot_y


@pytest.fixture(scope="module")
def rs(benchmark_module):
    return benchmark_module("rolling_shutter_clip")


def _write_path(path, yaw_deg_per_frame: float, step_m: float, n: int) -> np.ndarray:
    T = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        T[i, :3, :3] = rot_y(np.radians(yaw_deg_per_frame * i))
        T[i, :3, 3] = [step_m * i, 0.0, 0.0]
    np.savetxt(path, T[:, :3].reshape(n, 12))
    return T


def test_pose_interpolation_is_slerp_and_linear(rs):
    T = np.stack([np.eye(4), np.eye(4)])
    T[1, :3, :3] = rot_y(np.radians(10.0))
    T[1, :3, 3] = [1.0, 2.0, -4.0]
    pose_at = rs.pose_interpolator(T)
    assert np.allclose(pose_at(0.0), T[0]) and np.allclose(pose_at(1.0), T[1])
    mid = pose_at(0.5)
    assert np.allclose(mid[:3, :3], rot_y(np.radians(5.0)), atol=1e-12)
    assert np.allclose(mid[:3, 3], [0.5, 1.0, -2.0])
    assert np.allclose(pose_at(7.0), T[1])  # clamped to the path


def test_global_shutter_is_one_render_and_rolling_rows_follow_their_time(rs, tmp_path):
    size = (48, 64)
    T = _write_path(tmp_path / "poses.txt", yaw_deg_per_frame=2.0, step_m=0.02, n=4)
    K = intrinsics(44.0, 44.0, 31.5, 23.5)
    scene = handheld_indoor(n_frames=2, size=size).scene
    pose_at = rs.pose_interpolator(np.linalg.inv(T[0]) @ T)
    still = rs.render_rolling(scene, pose_at, 1, K, size, readout=0.0, bands=6)
    assert np.array_equal(still, render(scene, pose_at(1.0), K, size))
    rolled = rs.render_rolling(scene, pose_at, 1, K, size, readout=1.0, bands=6)
    # band k of 6 (8 rows) is seen at time 1 + (8k + 4) / 48
    for k in (0, 5):
        ref = render(scene, pose_at(1.0 + (8 * k + 4) / 48.0), K, size)
        assert np.array_equal(rolled[8 * k:8 * k + 8], ref[8 * k:8 * k + 8])
    # 2 degrees a frame moves the bottom band by about 1.5 px against a global shutter
    assert np.abs(rolled[40:].astype(int) - still[40:].astype(int)).mean() > 2.0


def test_clip_folder_holds_the_middle_row_poses(rs, tmp_path):
    T = _write_path(tmp_path / "poses.txt", yaw_deg_per_frame=1.0, step_m=0.01, n=7)
    n = rs.make_clip(tmp_path / "poses.txt", tmp_path / "clip", stride=3, readout=0.5, bands=2, size=(24, 32))
    assert n == 2  # source frames 0 and 3
    written = np.loadtxt(tmp_path / "clip" / "poses.txt").reshape(-1, 3, 4)
    pose_at = rs.pose_interpolator(T)
    assert np.allclose(written[1], pose_at(3.25)[:3], atol=1e-9)
    img = cv2.imread(str(tmp_path / "clip" / "image_0" / "000001.png"), cv2.IMREAD_GRAYSCALE)
    assert img.shape == (24, 32)


def test_a_bad_poses_file_is_a_one_line_error(rs, tmp_path, capsys):
    bad = tmp_path / "poses.txt"
    bad.write_text("1 2 3\n4 5 6\n")
    assert rs.main([str(bad), str(tmp_path / "clip")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and str(bad) in err and "\n" not in err
