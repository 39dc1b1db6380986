"""Calibration parsing: KITTI P<n> lines by name, K files, fx fy cx cy, --intrinsics strings."""

from __future__ import annotations

import numpy as np
import pytest

from trianflow_vo.errors import InputError
from trianflow_vo.io.calib import (
    TUM_INTRINSICS,
    intrinsics_matrix,
    kitti_camera_for_folder,
    parse_intrinsics,
    read_calib_file,
    read_kitti_calib,
    read_kitti_projections,
    tum_default_intrinsics,
)


def p_line(key: str, fx: float, fy: float, cx: float, cy: float, tx: float = 0.0) -> str:
    P = np.array([[fx, 0, cx, tx], [0, fy, cy, 0], [0, 0, 1, 0]], dtype=float)
    return f"{key}: " + " ".join(f"{v:.12e}" for v in P.reshape(-1))


def K_of(fx, fy, cx, cy):
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=float)


@pytest.fixture
def kitti_calib(tmp_path):
    """Four cameras with distinct intrinsics; P0 is deliberately the LAST line."""
    path = tmp_path / "calib.txt"
    path.write_text(
        "\n".join(
            [
                p_line("P2", 700.0, 701.0, 600.0, 180.0, tx=45.0),
                p_line("P3", 702.0, 703.0, 601.0, 181.0, tx=-330.0),
                p_line("P1", 704.0, 705.0, 602.0, 182.0, tx=-380.0),
                "Tr: " + " ".join(["1"] + ["0"] * 11),
                p_line("P0", 706.0, 707.0, 603.0, 183.0),
            ]
        )
        + "\n"
    )
    return path


def test_intrinsics_matrix_exact():
    K = intrinsics_matrix(718.856, 718.0, 607.1928, 185.2157)
    assert K.dtype == np.float64 and K.shape == (3, 3)
    np.testing.assert_array_equal(K, K_of(718.856, 718.0, 607.1928, 185.2157))
    with pytest.raises(ValueError):
        intrinsics_matrix(0, 1, 2, 3)
    with pytest.raises(ValueError):
        intrinsics_matrix(1, float("nan"), 2, 3)


@pytest.mark.parametrize("text", ["718.856,718.856,607.1928,185.2157", " 718.856, 718.856 ,607.1928,185.2157 ", "718.856 718.856 607.1928 185.2157"])
def test_parse_intrinsics_ok(text):
    assert parse_intrinsics(text) == (718.856, 718.856, 607.1928, 185.2157)


@pytest.mark.parametrize("text", ["1,2,3", "1,2,3,4,5", "a,b,c,d", "0,1,2,3", "-5,5,1,1", "1,inf,2,3", ""])
def test_parse_intrinsics_bad(text):
    with pytest.raises(InputError, match="intrinsics"):
        parse_intrinsics(text)


def test_kitti_camera_for_folder():
    assert kitti_camera_for_folder("image_0") == "P0"
    assert kitti_camera_for_folder("/x/y/image_2") == "P2"
    with pytest.raises(ValueError):
        kitti_camera_for_folder("images")


def test_kitti_line_chosen_by_name_not_position(kitti_calib):
    np.testing.assert_array_equal(read_kitti_calib(kitti_calib, "P0"), K_of(706, 707, 603, 183))
    np.testing.assert_array_equal(read_kitti_calib(kitti_calib, "P2"), K_of(700, 701, 600, 180))
    np.testing.assert_array_equal(read_kitti_calib(kitti_calib, kitti_camera_for_folder("image_3")), K_of(702, 703, 601, 181))
    # auto detection takes P0 even though it is the last line
    np.testing.assert_array_equal(read_calib_file(kitti_calib), K_of(706, 707, 603, 183))
    np.testing.assert_array_equal(read_calib_file(kitti_calib, "P2"), K_of(700, 701, 600, 180))
    mats = read_kitti_projections(kitti_calib)
    assert sorted(mats) == ["P0", "P1", "P2", "P3"]
    assert mats["P0"][1] == 5 and mats["P2"][1] == 1
    assert mats["P2"][0][0, 3] == 45.0


def test_kitti_missing_camera_lists_what_exists(kitti_calib):
    with pytest.raises(InputError) as e:
        read_kitti_calib(kitti_calib, "P5")
    assert e.value.path == str(kitti_calib)
    assert "P5" in str(e.value) and "P0, P1, P2, P3" in str(e.value)


def test_kitti_single_projection_is_used(tmp_path):
    f = tmp_path / "c.txt"
    f.write_text(p_line("P2", 1.0, 2.0, 3.0, 4.0) + "\n")
    np.testing.assert_array_equal(read_calib_file(f), K_of(1, 2, 3, 4))
    f.write_text(p_line("P1", 1.0, 2.0, 3.0, 4.0) + "\n" + p_line("P2", 5.0, 6.0, 7.0, 8.0) + "\n")
    with pytest.raises(InputError, match="which projection"):
        read_calib_file(f)


def test_kitti_raw_rect_key_synonym(tmp_path):
    f = tmp_path / "calib_cam_to_cam.txt"
    f.write_text("calib_time: 09-Jan-2012 13:57:47\n" + p_line("P_rect_02", 721.5, 721.5, 609.5, 172.8) + "\n")
    np.testing.assert_array_equal(read_kitti_calib(f, "P2"), K_of(721.5, 721.5, 609.5, 172.8))


@pytest.mark.parametrize(
    "bad, expect",
    [
        ("P0: 1 2 3 4 5 6 7 8 9 10 11", "12 numbers, got 11"),
        ("P0: 1 2 3 4 5 6 7 8 9 10 11 x", "non-numeric"),
        ("this is not a key value line", "malformed calibration line"),
    ],
)
def test_kitti_malformed_line_names_file_and_line(tmp_path, bad, expect):
    f = tmp_path / "calib.txt"
    f.write_text(p_line("P2", 1, 1, 1, 1) + "\n\n" + bad + "\n" + p_line("P1", 1, 1, 1, 1) + "\n")
    with pytest.raises(InputError) as e:
        read_calib_file(f)
    assert e.value.line == 3
    assert str(e.value).startswith(f"{f}:3: ")
    assert expect in str(e.value)


def test_kitti_duplicate_key(tmp_path):
    f = tmp_path / "calib.txt"
    f.write_text(p_line("P0", 1, 1, 1, 1) + "\n" + p_line("P0", 2, 2, 2, 2) + "\n")
    with pytest.raises(InputError, match="twice") as e:
        read_kitti_calib(f)
    assert e.value.line == 2


def test_K_file_3x3(tmp_path):
    f = tmp_path / "K.txt"
    f.write_text("# camera matrix\n500 0 320\n0 505 240\n\n0 0 1\n")
    np.testing.assert_array_equal(read_calib_file(f), K_of(500, 505, 320, 240))
    f.write_text("500, 0.5, 320\n0, 505, 240\n0, 0, 1\n")  # commas, skew kept
    K = read_calib_file(f)
    assert K[0, 1] == 0.5 and K[1, 1] == 505


def test_fx_fy_cx_cy_line(tmp_path):
    f = tmp_path / "intr.txt"
    f.write_text("525.0 526.0 319.5 239.5\n")
    np.testing.assert_array_equal(read_calib_file(f), K_of(525, 526, 319.5, 239.5))


@pytest.mark.parametrize(
    "content, line, expect",
    [
        ("500 0 320\n0 505 240 7\n0 0 1\n", 2, "4 numbers in a row of K"),
        ("500 0 320\n0 505\n0 0 1\n", 2, "2 numbers in a row of K"),
        ("1 2 3\n", 1, "3 numbers"),
        ("525 526 abc 239.5\n", 1, "non-numeric"),
        ("# c\n1 2 3\n4 5 6\n", 3, "2 numeric lines"),
        ("500 0 320\n0 505 240\n0 0 1\n0 0 0\n", 4, "4 numeric lines"),
        ("-525 526 319.5 239.5\n", 1, "positive"),
    ],
)
def test_malformed_numeric_calib(tmp_path, content, line, expect):
    f = tmp_path / "calib.txt"
    f.write_text(content)
    with pytest.raises(InputError) as e:
        read_calib_file(f)
    assert e.value.path == str(f) and e.value.line == line, str(e.value)
    assert expect in str(e.value)


def test_K_file_not_intrinsics(tmp_path):
    f = tmp_path / "K.txt"
    f.write_text("500 0 320\n0 505 240\n0 0 2\n")
    with pytest.raises(InputError, match="not an intrinsics matrix"):
        read_calib_file(f)


def test_empty_and_missing_calib(tmp_path):
    f = tmp_path / "calib.txt"
    f.write_text("\n# only a comment\n")
    with pytest.raises(InputError, match="empty"):
        read_calib_file(f)
    with pytest.raises(InputError, match="not found") as e:
        read_calib_file(tmp_path / "nope.txt")
    assert e.value.path == str(tmp_path / "nope.txt")


def test_tum_defaults():
    vals, cam = tum_default_intrinsics("/data/rgbd_dataset_freiburg2_desk")
    assert cam == "freiburg2" and vals == TUM_INTRINSICS["freiburg2"]
    assert tum_default_intrinsics("rgbd_dataset_freiburg1_xyz")[0] == (517.3, 516.5, 318.6, 255.3)
    assert tum_default_intrinsics("rgbd_dataset_freiburg3_long_office_household")[0] == (535.4, 539.2, 320.1, 247.6)
    assert tum_default_intrinsics("my_walk") is None


def test_shared_kitti00_vs_06_matrices(shared_data):
    """KITTI 00-02 and 04-12 use different cameras: read each sequence's own calib."""
    K00 = read_calib_file(shared_data / "kitti00-f0000-0150" / "calib.txt")
    K06 = read_calib_file(shared_data / "kitti06-f0000-0050" / "calib.txt")
    np.testing.assert_allclose(K00, K_of(718.856, 718.856, 607.1928, 185.2157), rtol=0, atol=1e-9)
    np.testing.assert_allclose(K06, K_of(707.0912, 707.0912, 601.8873, 183.1104), rtol=0, atol=1e-9)
    # P1 of 06 is the right camera of the rectified pair: same K, a baseline in t
    np.testing.assert_array_equal(read_kitti_calib(shared_data / "kitti06-f0000-0050" / "calib.txt", "P1"), K06)
    with pytest.raises(InputError, match="no P2"):
        read_kitti_calib(shared_data / "kitti06-f0000-0050" / "calib.txt", "P2")
