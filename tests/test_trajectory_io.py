"""Trajectory readers: formats, sorting, and errors that name the file and line."""

from __future__ import annotations

import numpy as np
import pytest

from trianflow_vo.errors import InputError
from trianflow_vo.io.trajectory import (
    format_kitti_line,
    format_tum_line,
    quaternion_to_rotation,
    read_frame_indices,
    read_trajectory,
    rotation_to_quaternion,
)


def _rot(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _poses(n, seed=0):
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        T[i, :3, :3] = _rot(rng.normal(size=3), rng.uniform(-3, 3))
        T[i, :3, 3] = rng.normal(size=3) * 10
    return T


def test_kitti_round_trip(tmp_path):
    T = _poses(5)
    p = tmp_path / "p.txt"
    p.write_text("\n".join(format_kitti_line(t) for t in T) + "\n")
    tr = read_trajectory(p)
    assert tr.kind == "kitti" and tr.frames is None and tr.timestamps is None
    np.testing.assert_allclose(tr.poses, T, atol=1e-8)
    assert tr.lines.tolist() == [1, 2, 3, 4, 5]


def test_tum_round_trip_sorted_with_comments(tmp_path):
    T = _poses(4, seed=1)
    times = [3.0, 1.0, 2.0, 0.5]
    p = tmp_path / "t.tum"
    p.write_text("# timestamp tx ty tz qx qy qz qw\n\n" + "\n".join(format_tum_line(s, t) for s, t in zip(times, T)))
    tr = read_trajectory(p)
    assert tr.kind == "tum"
    order = np.argsort(times)
    np.testing.assert_allclose(tr.timestamps, np.sort(times))
    np.testing.assert_allclose(tr.poses, T[order], atol=1e-8)
    assert tr.lines.tolist() == [6, 4, 5, 3]


def test_quaternion_conversions_inverse():
    for i, T in enumerate(_poses(20, seed=2)):
        q = rotation_to_quaternion(T[:3, :3])
        np.testing.assert_allclose(quaternion_to_rotation(q), T[:3, :3], atol=1e-12)
        # scaled quaternion: normalised
        np.testing.assert_allclose(quaternion_to_rotation(3 * q), T[:3, :3], atol=1e-12)


def test_indexed_kitti_sorted_by_frame(tmp_path):
    T = _poses(3, seed=3)
    p = tmp_path / "p13.txt"
    p.write_text("\n".join(f"{f} {format_kitti_line(t)}" for f, t in zip([7, 2, 5], T)))
    tr = read_trajectory(p)
    assert tr.kind == "kitti-indexed"
    assert tr.frames.tolist() == [2, 5, 7]
    np.testing.assert_allclose(tr.poses[0], T[1], atol=1e-8)


def _kitti_identity():
    return "1 0 0 0 0 1 0 0 0 0 1 0"


@pytest.mark.parametrize(
    "text, line, words",
    [
        (f"{_kitti_identity()}\n{_kitti_identity()} 5 6\n", 2, "columns"),
        (f"{_kitti_identity()}\n1 0 0 x 0 1 0 0 0 0 1 0\n", 2, "not a number"),
        (f"{_kitti_identity()}\n\n1 0 0 nan 0 1 0 0 0 0 1 0\n", 3, "non-finite"),
        (f"{_kitti_identity()}\n1 0 0 inf 0 1 0 0 0 0 1 0\n", 2, "non-finite"),
        ("1 2 3 4 5\n", 1, "5 columns"),
        (f"{_kitti_identity()}\n2 0 0 0 0 1 0 0 0 0 1 0\n", 2, "not a rotation"),
        ("0 0 0 0 0 0 0 0\n", 1, "zero quaternion"),
        (f"1.5 {_kitti_identity()}\n", 1, "integer frame index"),
        (f"3 {_kitti_identity()}\n3 {_kitti_identity()}\n", 2, "repeated frame index"),
    ],
)
def test_bad_trajectory_names_file_and_line(tmp_path, text, line, words):
    p = tmp_path / "bad.txt"
    p.write_text(text)
    with pytest.raises(InputError) as ei:
        read_trajectory(p)
    assert ei.value.path == str(p) and ei.value.line == line
    assert words in ei.value.message
    assert str(ei.value).startswith(f"{p}:{line}: ")


def test_empty_trajectory(tmp_path):
    p = tmp_path / "e.txt"
    p.write_text("# nothing\n\n")
    with pytest.raises(InputError, match="no poses"):
        read_trajectory(p)


def test_frame_indices(tmp_path):
    p = tmp_path / "frames.txt"
    p.write_text("0\n3\n6\n")
    idx, lines = read_frame_indices(p)
    assert idx.tolist() == [0, 3, 6] and lines.tolist() == [1, 2, 3]
    for text, line in [("0\n3.5\n", 2), ("0\n-1\n", 2), ("0\n1 2\n", 2), ("0\n4\n4\n", 3), ("0\na\n", 2)]:
        p.write_text(text)
        with pytest.raises(InputError) as ei:
            read_frame_indices(p)
        assert ei.value.line == line, text
