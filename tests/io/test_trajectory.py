"""Trajectory files (trianflow_vo.io.trajectory): round trips with the writers into evo's
types, quaternion conventions, and every bad input naming its file and line."""

from __future__ import annotations

import math

import numpy as np
import pytest
from evo.core.trajectory import PosePath3D, PoseTrajectory3D
from scipy.spatial.transform import Rotation

from trianflow_vo.errors import InputError
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
    assert type(traj.traj) is PosePath3D and traj.traj.num_poses == 20 and len(traj) == 20
    np.testing.assert_allclose(traj.poses, T, rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(np.array(traj.traj.poses_se3), traj.poses)
    np.testing.assert_array_equal(traj.lines, np.arange(1, 21))


def test_quaternion_matches_scipy_both_ways():
    """Independent reference: scipy's (x, y, z, w) convention, Hamilton, active rotation."""
    rng = np.random.default_rng(1)
    for q in rng.normal(size=(50, 4)):
        q = q / np.linalg.norm(q)
        np.testing.assert_allclose(quaternion_to_rotation(q), Rotation.from_quat(q).as_matrix(), atol=1e-12)
        # a scaled quaternion is normalised first
        np.testing.assert_allclose(quaternion_to_rotation(3 * q), Rotation.from_quat(q).as_matrix(), atol=1e-12)
        R = Rotation.from_quat(q).as_matrix()
        q_ours = rotation_to_quaternion(R)
        assert q_ours[3] >= 0
        np.testing.assert_allclose(q_ours, q * np.sign(q[3]), atol=1e-12)


@pytest.mark.parametrize("R", HALF_TURNS + [np.eye(3), rot([0.2, 0.3, 0.9], 2.5)])
def test_quaternion_round_trip_including_half_turns(R):
    """180-degree rotations have qw = 0 (trace -1): the conversion must not divide by
    ~0, and both signs of q are the same rotation."""
    q = rotation_to_quaternion(R)
    assert np.linalg.norm(q) == pytest.approx(1.0)
    np.testing.assert_allclose(quaternion_to_rotation(q), R, atol=1e-9)
    np.testing.assert_allclose(quaternion_to_rotation(-q), R, atol=1e-9)


def test_tum_round_trip_with_half_turns(tmp_path):
    """Writer -> reader keeps poses (9 decimals), timestamps (6 decimals) and sorts by
    time; comments and blank lines are skipped, a missing final newline is fine."""
    T = random_poses(len(HALF_TURNS) + 10, seed=2)
    T[: len(HALF_TURNS), :3, :3] = HALF_TURNS
    times = 1305031102.0 + 0.033 * np.arange(T.shape[0])
    order = np.random.default_rng(3).permutation(T.shape[0])
    p = tmp_path / "traj.tum"
    p.write_text("# timestamp tx ty tz qx qy qz qw\n\n" + "\n".join(format_tum_line(times[i], T[i]) for i in order))
    traj = read_trajectory(p)
    assert traj.kind == "tum" and traj.frames is None
    assert isinstance(traj.traj, PoseTrajectory3D)
    np.testing.assert_allclose(traj.timestamps, times, atol=2e-6)
    assert np.all(np.diff(traj.timestamps) > 0)
    np.testing.assert_allclose(traj.poses, T, atol=1e-8)
    # line numbers follow the file (header is line 1, then a blank line), reordered with the rows
    np.testing.assert_array_equal(traj.lines, 3 + np.argsort(order))


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
    assert traj.kind == "kitti-indexed" and type(traj.traj) is PosePath3D
    np.testing.assert_array_equal(traj.frames, [2, 5, 7])
    np.testing.assert_allclose(traj.poses, T[[1, 2, 0]], atol=1e-9)
    np.testing.assert_array_equal(traj.lines, [4, 5, 2])


# --------------------------------------------------------------------------- bad input

GOOD = format_kitti_line(np.eye(4))
IDENTITY = "1 0 0 0 0 1 0 0 0 0 1 0"


@pytest.mark.parametrize(
    "text, line, words",
    [
        (f"{GOOD}\n{GOOD}\n1 2 3 4 5 6 7 8 9 10 11\n", 3, "11 columns"),
        (f"{IDENTITY}\n{IDENTITY} 5 6\n", 2, "14 columns, but the first trajectory line has 12"),
        ("1 2 3 4 5 6 7\n", 1, "7 columns per line"),
        ("1 2 3 4 5\n", 1, "5 columns per line"),
        (f"# header\n{GOOD}\n{GOOD.replace('0.000000000e+00', 'abc', 1)}\n", 3, "not a number: 'abc'"),
        (f"{IDENTITY}\n1 0 0 x 0 1 0 0 0 0 1 0\n", 2, "not a number"),
        (f"{GOOD}\n{GOOD.replace('0.000000000e+00', 'nan', 1)}\n", 2, "non-finite"),
        (f"{IDENTITY}\n\n1 0 0 nan 0 1 0 0 0 0 1 0\n", 3, "non-finite"),  # blank lines still count
        (f"{GOOD}\n{GOOD}\n{GOOD}\n{GOOD.replace('1.000000000e+00', 'inf', 1)}\n", 4, "non-finite"),
        (f"{GOOD}\n{GOOD.replace('1.000000000e+00', '-Infinity', 1)}\n", 2, "non-finite"),
        (f"{GOOD}\n" + "2 0 0 0 0 1 0 0 0 0 1 0\n", 2, "not a rotation"),
        (f"0 {GOOD}\n1.5 {GOOD}\n", 2, "integer frame index"),
        (f"1.5 {IDENTITY}\n", 1, "integer frame index"),
        (f"3 {GOOD}\n1 {GOOD}\n3 {GOOD}\n", 3, "repeated frame index"),
        (f"3 {IDENTITY}\n3 {IDENTITY}\n", 2, "repeated frame index"),
        ("0.0 1 2 3 0 0 0 1\n0.1 1 2 3 0 0 0 0\n", 2, "zero quaternion"),
        ("0 0 0 0 0 0 0 0\n", 1, "zero quaternion"),
        ("0.0 1 2 3 0 0 0 1\n0.0 1 2 3 0 0 0 1\n", 2, "repeated timestamp"),
    ],
)
def test_bad_trajectory_names_file_and_line(tmp_path, text, line, words):
    p = tmp_path / "bad.txt"
    p.write_text(text)
    with pytest.raises(InputError) as exc:
        read_trajectory(p)
    msg = str(exc.value)
    assert msg.startswith(f"{p}:{line}: "), msg
    assert exc.value.path == str(p) and exc.value.line == line
    assert words in exc.value.message
    assert "\n" not in msg


def test_byte_order_mark_and_crlf_are_accepted(tmp_path):
    """Files saved by Windows tools: a UTF-8 BOM before the first number, CRLF endings."""
    p = tmp_path / "win.txt"
    p.write_bytes(b"\xef\xbb\xbf" + f"{GOOD}\r\n{GOOD}\r\n".encode())
    traj = read_trajectory(p)
    np.testing.assert_allclose(traj.poses, np.tile(np.eye(4), (2, 1, 1)))


def test_empty_trajectory_file(tmp_path):
    p = tmp_path / "e.txt"
    p.write_text("# only a comment\n\n")
    with pytest.raises(InputError, match="no poses") as exc:
        read_trajectory(p)
    assert str(exc.value).startswith(str(p))


def test_frame_indices(tmp_path):
    p = tmp_path / "frames.txt"
    p.write_text("0\n3\n6\n")
    idx, lines = read_frame_indices(p)
    assert idx.tolist() == [0, 3, 6] and lines.tolist() == [1, 2, 3]


@pytest.mark.parametrize(
    "text, line, words",
    [
        ("0\n3\nx\n", 3, "not a number"),
        ("0\na\n", 2, "not a number"),
        ("0\n-3\n", 2, "non-negative"),
        ("0\n-1\n", 2, "non-negative"),
        ("0\n2\n0\n", 3, "repeated"),
        ("0\n4\n4\n", 3, "repeated"),
        ("0 1\n", 1, "one frame index"),
        ("0\n1 2\n", 2, "columns"),
        ("0\n2.5\n", 2, "integer"),
        ("0\n3.5\n", 2, "integer"),
    ],
)
def test_bad_frames_file(tmp_path, text, line, words):
    p = tmp_path / "frames.txt"
    p.write_text(text)
    with pytest.raises(InputError) as exc:
        read_frame_indices(p)
    assert str(exc.value).startswith(f"{p}:{line}: ") and words in str(exc.value)
    assert exc.value.line == line
