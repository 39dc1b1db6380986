"""``trianflow-vo run`` through click's CliRunner: exit codes and one-line messages for bad input.

Every error case checks three things: a non-zero exit, a one-line message naming
what is wrong (the file, and the line for calibration files), and no traceback
(the exception CliRunner saw is the SystemExit that click raises, nothing else).
Sequences are tiny: a few frames of the shipped sample downscaled to 128x384.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from trianflow_vo.cli.main import main
from trianflow_vo.geometry.se3 import rodrigues

SMALL_HW = (128, 384)  # non-KITTI working size: used as is (multiples of 64, long side < 832)


def _small_intrinsics() -> str:
    """KITTI 00 P0 intrinsics (1241x376) scaled to SMALL_HW, as --intrinsics text."""
    sx, sy = SMALL_HW[1] / 1241.0, SMALL_HW[0] / 376.0
    fx, fy, cx, cy = 718.856 * sx, 718.856 * sy, 607.1928 * sx, 185.2157 * sy
    return f"{fx:.3f},{fy:.3f},{cx:.3f},{cy:.3f}"


INTR = _small_intrinsics()
K_SMALL = np.array([[float(INTR.split(",")[0]), 0.0, float(INTR.split(",")[2])],
                    [0.0, float(INTR.split(",")[1]), float(INTR.split(",")[3])], [0.0, 0.0, 1.0]])


def write_frames(sample: Path, folder: Path, n: int, step: int = 2, ext: str = ".png") -> list[Path]:
    """``n`` sample frames (every ``step``-th) downscaled to SMALL_HW, written as 000000.png, ..."""
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for i in range(n):
        img = cv2.imread(str(sample / "image_0" / f"{i * step:06d}.jpg"), cv2.IMREAD_COLOR)
        assert img is not None
        img = cv2.resize(img, (SMALL_HW[1], SMALL_HW[0]), interpolation=cv2.INTER_AREA)
        p = folder / f"{i:06d}{ext}"
        assert cv2.imwrite(str(p), img)
        out.append(p)
    return out


def truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 3])


def write_rotating_frames(sample: Path, folder: Path, n: int, yaw_rad: float = 0.006) -> list[Path]:
    """``n`` views of one sample frame from a camera turning ``yaw_rad`` per frame about its
    centre (image warped by ``K R K^-1``): flow without parallax, so rotation-only frames."""
    folder.mkdir(parents=True, exist_ok=True)
    img = cv2.imread(str(sample / "image_0" / "000010.jpg"), cv2.IMREAD_COLOR)
    img = cv2.resize(img, (SMALL_HW[1], SMALL_HW[0]), interpolation=cv2.INTER_AREA)
    out = []
    for i in range(n):
        Hm = K_SMALL @ rodrigues(np.array([0.0, yaw_rad * i, 0.0])) @ np.linalg.inv(K_SMALL)
        warped = cv2.warpPerspective(img, Hm, (SMALL_HW[1], SMALL_HW[0]), flags=cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_REFLECT)
        p = folder / f"{i:06d}.png"
        assert cv2.imwrite(str(p), warped)
        out.append(p)
    return out


def invoke(*args: str):
    return CliRunner().invoke(main, [str(a) for a in args])


def warning_lines(output: str) -> list[str]:
    return [ln for ln in output.splitlines() if ln.startswith("warning:")]


def assert_user_error(result, *needles: str, code: int | None = None) -> str:
    """Non-zero exit, no traceback, every needle in the output; returns the error line."""
    assert result.exit_code != 0, result.output
    if code is not None:
        assert result.exit_code == code, result.output
    assert isinstance(result.exception, SystemExit), repr(result.exception)
    assert "Traceback" not in result.output
    err_lines = [ln for ln in result.output.splitlines() if ln.startswith("Error")]
    assert len(err_lines) == 1, result.output
    for needle in needles:
        assert needle in result.output, (needle, result.output)
    return err_lines[0]


# --------------------------------------------------------------------------- help


def test_group_help_lists_commands():
    r = invoke("--help")
    assert r.exit_code == 0, r.output
    for name in ("run", "eval", "export", "view"):
        assert name in r.output


def test_run_help():
    r = invoke("run", "--help")
    assert r.exit_code == 0, r.output
    for opt in ("--stride", "--intrinsics", "--calib", "--size", "--out", "--quiet"):
        assert opt in r.output


# --------------------------------------------------------------------------- errors before any frame


def test_missing_path(tmp_path):
    missing = tmp_path / "no_such_seq"
    r = invoke("run", missing, "--out", tmp_path / "out")
    line = assert_user_error(r, str(missing), code=1)
    assert "no such file" in line
    assert not (tmp_path / "out").exists()


def test_empty_folder(tmp_path):
    (tmp_path / "empty").mkdir()
    r = invoke("run", tmp_path / "empty", "--intrinsics", INTR, "--out", tmp_path / "out")
    line = assert_user_error(r, str(tmp_path / "empty"), code=1)
    assert "no images" in line


def test_images_without_intrinsics_says_how_to_give_them(sample_seq, tmp_path):
    write_frames(sample_seq, tmp_path / "seq", 3)
    r = invoke("run", tmp_path / "seq", "--out", tmp_path / "out")
    line = assert_user_error(r, str(tmp_path / "seq"), code=1)
    assert "no camera intrinsics" in line
    assert "--intrinsics" in line and "--calib" in line


def test_malformed_calib_line_in_folder_names_file_and_line(sample_seq, tmp_path):
    seq = tmp_path / "seq"
    write_frames(sample_seq, seq, 3)
    (seq / "calib.txt").write_text("# K\n100 0 64\n0 100 x\n0 0 1\n")
    r = invoke("run", seq, "--out", tmp_path / "out")
    assert_user_error(r, f"{seq / 'calib.txt'}:3:", "malformed", code=1)


def test_malformed_kitti_calib_line_names_file_and_line(sample_seq, tmp_path):
    seq = tmp_path / "kitti"
    write_frames(sample_seq, seq / "image_0", 3)
    (seq / "calib.txt").write_text("P0: 1 0 0 0 0 1 0 0 0 0 1 0\nP1: 1 0 0 0 0 1\n")
    r = invoke("run", seq, "--out", tmp_path / "out")
    assert_user_error(r, f"{seq / 'calib.txt'}:2:", "12 numbers", code=1)


def test_malformed_calib_option_file(sample_seq, tmp_path):
    write_frames(sample_seq, tmp_path / "seq", 3)
    calib = tmp_path / "cam.txt"
    calib.write_text("fx fy cx cy\n")
    r = invoke("run", tmp_path / "seq", "--calib", calib, "--out", tmp_path / "out")
    assert_user_error(r, f"{calib}:1:", code=1)


@pytest.mark.parametrize(
    "args, needle",
    [
        (("--stride", "0"), "--stride"),
        (("--stride", "-2"), "--stride"),
        (("--size", "100x7"), "--size"),
        (("--size", "banana"), "--size"),
        (("--intrinsics", "1,2,3"), "--intrinsics"),
        (("--intrinsics", "0,100,50,50"), "--intrinsics"),
    ],
)
def test_bad_options_are_usage_errors(sample_seq, tmp_path, args, needle):
    write_frames(sample_seq, tmp_path / "seq", 2)
    extra = () if "--intrinsics" in args else ("--intrinsics", INTR)
    r = invoke("run", tmp_path / "seq", *extra, *args, "--out", tmp_path / "out")
    assert_user_error(r, needle, code=2)
    assert not (tmp_path / "out").exists()


def test_intrinsics_and_calib_together(sample_seq, tmp_path):
    write_frames(sample_seq, tmp_path / "seq", 2)
    calib = tmp_path / "cam.txt"
    calib.write_text("100 100 64 64\n")
    r = invoke("run", tmp_path / "seq", "--intrinsics", INTR, "--calib", calib, "--out", tmp_path / "out")
    # the conflict can come from --config/--set as well as the flags: the message names both config keys
    assert_user_error(r, "intrinsics", "calibration file", "input.intrinsics", "input.calib", code=2)


def test_video_that_cannot_be_opened(tmp_path):
    video = tmp_path / "x.mp4"
    video.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    r = invoke("run", video, "--intrinsics", INTR, "--out", tmp_path / "out")
    line = assert_user_error(r, str(video), code=1)
    assert "video" in line


def test_single_frame_selected(sample_seq, tmp_path):
    write_frames(sample_seq, tmp_path / "seq", 3)
    r = invoke("run", tmp_path / "seq", "--intrinsics", INTR, "--stride", "5", "--out", tmp_path / "out")
    assert_user_error(r, "fewer than two frames", code=1)


# --------------------------------------------------------------------------- frames that fail while running


def test_fewer_than_two_usable_frames(sample_seq, tmp_path):
    seq = tmp_path / "seq"
    files = write_frames(sample_seq, seq, 2)
    truncate(files[1])
    r = invoke("run", seq, "--intrinsics", INTR, "--out", tmp_path / "out", "--no-plot")
    line = assert_user_error(r, code=1)
    assert "fewer than two usable frames" in line
    # the skipped file is named in a warning, and what was done is still on disk
    assert f"warning: {files[1]}: skipped" in r.output
    poses = (tmp_path / "out" / "poses.txt").read_text().splitlines()
    assert len(poses) == 1
    doc = json.loads((tmp_path / "out" / "run.json").read_text())
    assert [s["source"] for s in doc["skipped"]] == [str(files[1])]


def test_fewer_than_two_usable_frames_run_json_says_failed(sample_seq, tmp_path):
    seq = tmp_path / "seq"
    files = write_frames(sample_seq, seq, 2)
    truncate(files[1])
    r = invoke("run", seq, "--intrinsics", INTR, "--out", tmp_path / "out", "--no-plot")
    assert r.exit_code == 1
    doc = json.loads((tmp_path / "out" / "run.json").read_text())
    assert doc["status"] == "failed"
    assert "fewer than two usable frames" in doc["error"]


@pytest.mark.parametrize("ext", [".png", ".jpg"])
def test_truncated_image_in_the_middle_is_skipped(sample_seq, tmp_path, ext):
    seq = tmp_path / "seq"
    files = write_frames(sample_seq, seq, 4, ext=ext)
    truncate(files[2])
    out = tmp_path / "out"
    r = invoke("run", seq, "--intrinsics", INTR, "--out", out, "--no-plot")
    assert r.exit_code == 0, r.output
    assert r.exception is None
    warnings = [ln for ln in r.output.splitlines() if ln.startswith("warning:") and "skipped" in ln]
    assert len(warnings) == 1 and str(files[2]) in warnings[0], r.output
    assert (out / "frames.txt").read_text().split() == ["0", "1", "3"]
    assert len((out / "poses.txt").read_text().splitlines()) == 3
    doc = json.loads((out / "run.json").read_text())
    assert doc["status"] == "completed"
    assert doc["frames_skipped"] == 1
    assert doc["skipped"][0]["frame"] == 2
    assert doc["skipped"][0]["source"] == str(files[2])
    assert "truncated" in doc["skipped"][0]["reason"] or "decode" in doc["skipped"][0]["reason"]
    # and in run.json's warnings, grouped by kind
    group = doc["warnings"]["skipped-frame"]
    assert group["count"] == 1 and group["items"][0]["frame"] == 2
    assert group["items"][0]["message"] == warnings[0].removeprefix("warning: ")


def test_mixed_sizes_warn_and_skip(sample_seq, tmp_path):
    seq = tmp_path / "seq"
    files = write_frames(sample_seq, seq, 4)
    odd = cv2.resize(cv2.imread(str(files[1])), (SMALL_HW[1] // 2, SMALL_HW[0] // 2))
    cv2.imwrite(str(files[1]), odd)
    out = tmp_path / "out"
    r = invoke("run", seq, "--intrinsics", INTR, "--out", out, "--no-plot")
    assert r.exit_code == 0, r.output
    warnings = [ln for ln in r.output.splitlines() if ln.startswith("warning:") and str(files[1]) in ln]
    assert len(warnings) == 1 and "differs" in warnings[0], r.output
    doc = json.loads((out / "run.json").read_text())
    assert [s["frame"] for s in doc["skipped"]] == [1]
    assert (out / "frames.txt").read_text().split() == ["0", "2", "3"]


def test_quiet_prints_only_the_output_folder(sample_seq, tmp_path):
    seq = tmp_path / "seq"
    files = write_frames(sample_seq, seq, 3)
    truncate(files[1])
    out = tmp_path / "out"
    r = invoke("run", seq, "--intrinsics", INTR, "--out", out, "--no-plot", "-q")
    assert r.exit_code == 0, r.output
    assert "warning" not in r.output
    assert r.output.strip() == f"wrote {out}"
    # quiet hides the warning, not the record of it
    assert json.loads((out / "run.json").read_text())["frames_skipped"] == 1


def test_default_out_dir_under_runs(sample_seq, tmp_path, monkeypatch):
    seq = tmp_path / "seq"
    write_frames(sample_seq, seq, 2)
    monkeypatch.chdir(tmp_path)
    r1 = invoke("run", seq, "--intrinsics", INTR, "--no-plot", "-q")
    r2 = invoke("run", seq, "--intrinsics", INTR, "--no-plot", "-q")
    assert r1.exit_code == 0 and r2.exit_code == 0, r1.output + r2.output
    runs = sorted((tmp_path / "runs").iterdir())
    assert len(runs) == 2  # a second run in the same second does not overwrite the first
    for d in runs:
        assert d.name.startswith("seq-")
        assert len((d / "poses.txt").read_text().splitlines()) == 2


# --------------------------------------------------------------------------- how warnings are printed


def test_per_frame_warnings_are_one_summary_line_per_kind(sample_seq, tmp_path):
    """A skipped file is a warning at once; rotation-only frames are one line at the end."""
    seq = tmp_path / "seq"
    files = write_rotating_frames(sample_seq, seq, 8)
    truncate(files[3])
    out = tmp_path / "out"
    r = invoke("run", seq, "--intrinsics", INTR, "--out", out, "--no-plot")
    assert r.exit_code == 0, r.output
    lines = r.output.splitlines()
    warnings = warning_lines(r.output)
    assert len(warnings) == 2, r.output
    assert warnings[0].startswith(f"warning: {files[3]}: skipped (")
    assert warnings[1] == ("warning: 6 frames solved by rotation only: frame 1, 2, 4, 5, 6, ... "
                           "(all in run.json, frames.tsv)"), r.output
    # the skip when it happens, the summary after the last frame, before the closing summary
    summary = next(i for i, ln in enumerate(lines) if ln.startswith("7 frames (1 skipped)"))
    assert lines.index(warnings[0]) < lines.index(warnings[1]) < summary
    assert "rotation-only 6" in lines[summary]
    assert not any(ln.startswith("frame ") for ln in lines)  # no line per frame without -v
    doc = json.loads((out / "run.json").read_text())
    assert doc["branch_counts"]["rotation"] == 6
    rot = doc["warnings"]["rotation-only"]
    assert rot["count"] == 6 and [i["frame"] for i in rot["items"]] == [1, 2, 4, 5, 6, 7]  # all kept
    assert all("rotation only" in i["message"] for i in rot["items"])
    assert doc["warnings"]["skipped-frame"]["count"] == 1


def test_verbose_shows_each_frame_and_quiet_none(sample_seq, tmp_path):
    seq = tmp_path / "seq"
    write_rotating_frames(sample_seq, seq, 4)
    r = invoke("run", seq, "--intrinsics", INTR, "--out", tmp_path / "v", "--no-plot", "-v")
    assert r.exit_code == 0, r.output
    per_frame = [ln for ln in r.output.splitlines() if ln.startswith("frame ")]
    assert [ln.split(":")[0] for ln in per_frame] == ["frame 1", "frame 2", "frame 3"], r.output
    assert all(": rotation (" in ln and "no depth yet" in ln for ln in per_frame)
    assert len(warning_lines(r.output)) == 1  # still summarised once
    r = invoke("run", seq, "--intrinsics", INTR, "--out", tmp_path / "q", "--no-plot", "-q")
    assert r.exit_code == 0, r.output
    assert r.output.strip() == f"wrote {tmp_path / 'q'}"
    assert json.loads((tmp_path / "q" / "run.json").read_text())["warnings"]["rotation-only"]["count"] == 3


def test_routine_branches_only_with_verbose(sample_seq, tmp_path):
    """A static camera is normal operation: no warning, and a line per frame only with -v."""
    seq = tmp_path / "seq"
    files = write_frames(sample_seq, seq, 1)
    for i in (1, 2):
        (seq / f"{i:06d}.png").write_bytes(files[0].read_bytes())
    r = invoke("run", seq, "--intrinsics", INTR, "--out", tmp_path / "a", "--no-plot")
    assert r.exit_code == 0, r.output
    assert warning_lines(r.output) == [], r.output
    assert not any(ln.startswith("frame ") for ln in r.output.splitlines()), r.output
    assert "camera static" not in r.output and "static 2" in r.output
    r = invoke("run", seq, "--intrinsics", INTR, "--out", tmp_path / "b", "--no-plot", "-v")
    assert r.exit_code == 0, r.output
    assert warning_lines(r.output) == []
    per_frame = [ln for ln in r.output.splitlines() if ln.startswith("frame ")]
    assert len(per_frame) == 2 and all(": identity (" in ln and "camera static" in ln for ln in per_frame), r.output
    assert json.loads((tmp_path / "b" / "run.json").read_text())["warnings"] == {}
