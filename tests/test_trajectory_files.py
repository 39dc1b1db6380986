"""Trajectory file readers (trianflow_vo.io.trajectory, trianflow_vo.eval.loader): round trips with the
writers, quaternion conventions, and every bad input naming its file and line."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from trianflow_vo.errors import InputError
from trianflow_vo.eval.loader import associate, find_latest_run, load_ground_truth, load_prediction
from trianflow_vo.io.trajectory import (
    format_kitti_line,
    format_tum_line,
    quaternion_to_rotation,
    read_frame_indices,
    read_trajectory,
    rotation_to_quaternion,
)


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    T[:, :3, 3] = rng.normal(0, 50, (n, 3))
    return T


def rot(axis, angle) -> np.ndarray:
    axis = np.asarray(axis, dtype=float)
    return Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()


HALF_TURNS = [
    rot([1, 0, 0], math.pi),
    rot([0, 1, 0], math.pi),
    rot([0, 0, 1], math.pi),
    rot([1, 1, 0], math.pi),
    rot([1, -2, 3], math.pi),
    rot([0, 1, 1], math.pi - 1e-7),
]


# --------------------------------------------------------------------------- round trips


def test_kitti_round_trip(tmp_path):
    T = random_poses(20)
    p = tmp_path / "poses.txt"
    p.write_text("".join(format_kitti_line(x) + "\n" for x in T))
    traj = read_trajectory(p)
    assert traj.kind == "kitti" and traj.frames is None and traj.timestamps is None
    np.testing.assert_allclose(traj.poses, T, rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(traj.lines, np.arange(1, 21))


def test_quaternion_matches_scipy_both_ways():
    """Independent reference: scipy's (x, y, z, w) convention, Hamilton, active rotation."""
    rng = np.random.default_rng(1)
    for q in rng.normal(size=(50, 4)):
        q = q / np.linalg.norm(q)
        np.testing.assert_allclose(quaternion_to_rotation(q), Rotation.from_quat(q).as_matrix(), atol=1e-12)
        R = Rotation.from_quat(q).as_matrix()
        q_ours = rotation_to_quaternion(R)
        assert q_ours[3] >= 0
        np.testing.assert_allclose(q_ours, q * np.sign(q[3]), atol=1e-12)


@pytest.mark.parametrize("R", HALF_TURNS + [np.eye(3), rot([0.2, 0.3, 0.9], 2.5)])
def test_quaternion_round_trip_including_half_turns(R):
    """180-degree rotations have qw = 0 (trace -1): the conversion must pick the branch
    that does not divide by ~0, and both signs of q are the same rotation."""
    q = rotation_to_quaternion(R)
    assert np.linalg.norm(q) == pytest.approx(1.0)
    np.testing.assert_allclose(quaternion_to_rotation(q), R, atol=1e-9)
    np.testing.assert_allclose(quaternion_to_rotation(-q), R, atol=1e-9)


def test_tum_round_trip_with_half_turns(tmp_path):
    """Writer -> reader keeps poses (9 decimals), timestamps (6 decimals) and sorts by time."""
    T = random_poses(len(HALF_TURNS) + 10, seed=2)
    T[: len(HALF_TURNS), :3, :3] = HALF_TURNS
    times = 1305031102.0 + 0.033 * np.arange(T.shape[0])
    order = np.random.default_rng(3).permutation(T.shape[0])
    p = tmp_path / "traj.tum"
    p.write_text("# timestamp tx ty tz qx qy qz qw\n" + "".join(format_tum_line(times[i], T[i]) + "\n" for i in order))
    traj = read_trajectory(p)
    assert traj.kind == "tum" and traj.frames is None
    np.testing.assert_allclose(traj.timestamps, times, atol=2e-6)
    np.testing.assert_allclose(traj.poses, T, atol=1e-8)
    # line numbers follow the file (header is line 1), reordered with the rows
    np.testing.assert_array_equal(traj.lines, 2 + np.argsort(order))


def test_tum_line_reads_qw_last(tmp_path):
    """A 90-degree turn about z written by hand as (qx, qy, qz, qw) = (0, 0, s, s)."""
    s = math.sqrt(0.5)
    p = tmp_path / "t.tum"
    p.write_text(f"0.0 1 2 3 0 0 {s} {s}\n")
    T = read_trajectory(p).poses[0]
    np.testing.assert_allclose(T[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [1, 2, 3])


def test_indexed_kitti_sorted_by_frame_with_comments_and_blank_lines(tmp_path):
    T = random_poses(3, seed=4)
    p = tmp_path / "p13.txt"
    p.write_text(
        "# frame r00 ... t2\n"
        f"7 {format_kitti_line(T[0])}\n"
        "\n"
        f"2 {format_kitti_line(T[1])}\n"
        f"5, {format_kitti_line(T[2]).replace(' ', ', ')}\n"  # commas are accepted
    )
    traj = read_trajectory(p)
    assert traj.kind == "kitti-indexed"
    np.testing.assert_array_equal(traj.frames, [2, 5, 7])
    np.testing.assert_allclose(traj.poses, T[[1, 2, 0]], atol=1e-9)
    np.testing.assert_array_equal(traj.lines, [4, 5, 2])


def test_frames_file_and_run_folder(tmp_path):
    T = random_poses(4, seed=5)
    run = tmp_path / "run"
    run.mkdir()
    (run / "poses.txt").write_text("".join(format_kitti_line(x) + "\n" for x in T))
    (run / "frames.txt").write_text("0\n3\n6\n9\n")
    traj, desc = load_prediction(run)
    np.testing.assert_array_equal(traj.frames, [0, 3, 6, 9])
    assert "poses.txt" in desc and "frames.txt" in desc
    idx, lines = read_frame_indices(run / "frames.txt")
    np.testing.assert_array_equal(idx, [0, 3, 6, 9])


def test_find_latest_run_uses_modification_time(tmp_path):
    import os

    runs = tmp_path / "runs"
    for name, mtime in (("b_old", 1_000_000_000), ("a_new", 1_100_000_000)):
        (runs / name).mkdir(parents=True)
        (runs / name / "poses.txt").write_text(format_kitti_line(np.eye(4)) + "\n")
        os.utime(runs / name / "poses.txt", (mtime, mtime))
    (runs / "not_a_run").mkdir()
    assert find_latest_run(runs).name == "a_new"
    with pytest.raises(InputError, match="runs folder"):
        find_latest_run(tmp_path / "nothing")


# --------------------------------------------------------------------------- bad input

GOOD = format_kitti_line(np.eye(4))


def _write(tmp_path, text, name="bad.txt"):
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.mark.parametrize(
    "text, line, words",
    [
        (f"{GOOD}\n{GOOD}\n1 2 3 4 5 6 7 8 9 10 11\n", 3, "11 columns"),
        ("1 2 3 4 5 6 7\n", 1, "7 columns per line"),
        (f"# header\n{GOOD}\n{GOOD.replace('0.000000000e+00', 'abc', 1)}\n", 3, "not a number: 'abc'"),
        (f"{GOOD}\n{GOOD.replace('0.000000000e+00', 'nan', 1)}\n", 2, "non-finite"),
        (f"{GOOD}\n{GOOD}\n{GOOD}\n{GOOD.replace('1.000000000e+00', 'inf', 1)}\n", 4, "non-finite"),
        (f"{GOOD}\n{GOOD.replace('1.000000000e+00', '-Infinity', 1)}\n", 2, "non-finite"),
        (f"{GOOD}\n" + "2 0 0 0 0 1 0 0 0 0 1 0\n", 2, "not a rotation"),
        (f"0 {GOOD}\n1.5 {GOOD}\n", 2, "integer frame index"),
        (f"3 {GOOD}\n1 {GOOD}\n3 {GOOD}\n", 3, "repeated frame index"),
        ("0.0 1 2 3 0 0 0 1\n0.1 1 2 3 0 0 0 0\n", 2, "zero quaternion"),
        ("0.0 1 2 3 0 0 0 1\n0.0 1 2 3 0 0 0 1\n", 2, "repeated timestamp"),
    ],
)
def test_bad_trajectory_names_file_and_line(tmp_path, text, line, words):
    p = _write(tmp_path, text)
    with pytest.raises(InputError) as exc:
        read_trajectory(p)
    msg = str(exc.value)
    assert msg.startswith(f"{p}:{line}: "), msg
    assert words in msg
    assert "\n" not in msg


def test_byte_order_mark_and_crlf_are_accepted(tmp_path):
    """Files saved by Windows tools: a UTF-8 BOM before the first number, CRLF endings."""
    p = tmp_path / "win.txt"
    p.write_bytes(b"\xef\xbb\xbf" + f"{GOOD}\r\n{GOOD}\r\n".encode())
    traj = read_trajectory(p)
    np.testing.assert_allclose(traj.poses, np.tile(np.eye(4), (2, 1, 1)))


def test_empty_trajectory_file(tmp_path):
    p = _write(tmp_path, "# only a comment\n\n")
    with pytest.raises(InputError, match="no poses") as exc:
        read_trajectory(p)
    assert str(exc.value).startswith(str(p))


@pytest.mark.parametrize(
    "text, line, words",
    [("0\n3\nx\n", 3, "not a number"), ("0\n-3\n", 2, "non-negative"), ("0\n2\n0\n", 3, "repeated"),
     ("0 1\n", 1, "one frame index"), ("0\n2.5\n", 2, "integer")],
)
def test_bad_frames_file(tmp_path, text, line, words):
    p = _write(tmp_path, text, "frames.txt")
    with pytest.raises(InputError) as exc:
        read_frame_indices(p)
    assert str(exc.value).startswith(f"{p}:{line}: ") and words in str(exc.value)


def test_frames_file_with_wrong_count(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "poses.txt").write_text(f"{GOOD}\n{GOOD}\n{GOOD}\n")
    (run / "frames.txt").write_text("0\n3\n")
    with pytest.raises(InputError, match="2 frame indices for 3 poses"):
        load_prediction(run)


def test_unmatchable_prediction_is_refused_with_explanation(tmp_path):
    """12 numbers per line, 5 lines against a 7-line ground truth, no frames.txt:
    which frames are they? Refused, naming both counts and the two ways out."""
    gt = load_ground_truth(_write(tmp_path, "".join(f"{format_kitti_line(T)}\n" for T in random_poses(7)), "gt.txt"))
    pred_path = tmp_path / "pred" / "p.txt"
    pred_path.parent.mkdir()
    pred_path.write_text("".join(f"{format_kitti_line(T)}\n" for T in random_poses(5)))
    pred, _ = load_prediction(pred_path)
    with pytest.raises(InputError) as exc:
        associate(pred, gt)
    msg = str(exc.value)
    assert msg.startswith(str(pred_path)) and "5 poses" in msg and "has 7" in msg
    assert "frames.txt" in msg and "13 columns" in msg


def test_prediction_path_missing(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        load_prediction(tmp_path / "nope")
    (tmp_path / "empty_run").mkdir()
    with pytest.raises(InputError, match="not a run folder"):
        load_prediction(tmp_path / "empty_run")
