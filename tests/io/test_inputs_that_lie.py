"""Inputs that are not what they claim: a text file passed as a video, a truncated video,
corrupt frames in a folder. Each is refused in one line or reported (stderr and run.json),
never processed silently."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from trianflow_vo.cli.main import main
from trianflow_vo.errors import InputError
from trianflow_vo.frames import Frame, Shortfall
from trianflow_vo.io.sequence import VIDEO_EXTENSIONS, open_sequence

SMALL_HW = (128, 384)
# KITTI 00 P0 scaled from 1241x376 to 384x128
INTR = "222.444,244.717,187.890,63.052"
EXPECTED = "expected a sequence folder"


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def one_error_line(res, *needles: str) -> str:
    assert res.exit_code == 1, res.output
    assert isinstance(res.exception, SystemExit), repr(res.exception)
    assert "Traceback" not in res.output
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error: "), res.stderr
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


def sample_frames(sample: Path, n: int, step: int = 2) -> list[np.ndarray]:
    out = []
    for i in range(n):
        img = cv2.imread(str(sample / "image_0" / f"{i * step:06d}.jpg"), cv2.IMREAD_COLOR)
        assert img is not None
        out.append(cv2.resize(img, (SMALL_HW[1], SMALL_HW[0]), interpolation=cv2.INTER_AREA))
    return out


def write_avi(path: Path, frames: list[np.ndarray], fps: float = 10.0) -> Path:
    h, w = frames[0].shape[:2]
    wr = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    assert wr.isOpened()
    for f in frames:
        wr.write(f)
    wr.release()
    return path


def cut(path: Path, fraction: float) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])


# --------------------------------------------------------------------------- item 8: not a video


def test_text_file_is_not_a_video(tmp_path):
    """FFmpeg's tty demuxer would decode a .txt as frames of rendered text: refused by suffix."""
    txt = tmp_path / "notes.txt"
    txt.write_text("these are not frames\n" * 40)
    with pytest.raises(InputError) as e:
        open_sequence(txt, intrinsics=(100, 100, 50, 50))
    assert e.value.path == str(txt)
    assert ".txt" in e.value.message and EXPECTED in e.value.message
    assert "video file" in e.value.message and "image folder" in e.value.message
    # and through the CLI: one line naming the file and what was expected
    one_error_line(invoke("run", txt, "--intrinsics", INTR, "--out", tmp_path / "out"), str(txt), EXPECTED)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("name", ["poses.csv", "README", "clip.avi.part", "model.onnx"])
def test_other_files_are_not_videos(tmp_path, name):
    p = tmp_path / name
    p.write_bytes(b"\x00\x01 not a video " * 100)
    with pytest.raises(InputError, match=EXPECTED) as e:
        open_sequence(p, intrinsics=(100, 100, 50, 50))
    assert e.value.path == str(p)


def test_video_suffix_with_garbage_inside_says_what_was_expected(tmp_path):
    p = tmp_path / "clip.mkv"
    p.write_bytes(b"\x00garbage, not matroska" * 100)
    with pytest.raises(InputError, match="cannot be opened") as e:
        open_sequence(p, intrinsics=(100, 100, 50, 50))
    assert EXPECTED in e.value.message and e.value.path == str(p)


def test_known_container_suffixes_are_accepted(tmp_path):
    assert {".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv", ".flv", ".ts"} <= VIDEO_EXTENSIONS
    assert ".txt" not in VIDEO_EXTENSIONS
    frames = [np.full((48, 64, 3), 20 * i, np.uint8) for i in range(6)]
    seq = open_sequence(write_avi(tmp_path / "CLIP.AVI", frames), intrinsics=(50, 50, 32, 24))  # case-insensitive
    assert seq.kind == "video" and len(seq) == 6


# --------------------------------------------------------------------------- item 9: truncated video


def test_truncated_video_reader_reports_the_shortfall(tmp_path):
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 255, (96, 128, 3), dtype=np.uint8) for _ in range(40)]
    path = write_avi(tmp_path / "clip.avi", frames)
    full = open_sequence(path, intrinsics=(50, 50, 64, 48))
    assert len([f for f in full if isinstance(f, Frame)]) == 40 and full.shortfall is None
    cut(path, 0.5)
    seq = open_sequence(path, intrinsics=(50, 50, 64, 48), stride=3)
    assert seq.n_source_frames == 40  # the container still states 40
    got = [f.index for f in seq if isinstance(f, Frame)]
    assert 5 < len(got) < 14
    sf = seq.shortfall
    assert isinstance(sf, Shortfall)
    assert sf.stated == 40 and sf.source == str(path)
    assert got[-1] < sf.decoded <= got[-1] + 3
    assert sf.missing == len(seq) - len(got) > 0
    assert str(path) in sf.message and "40" in sf.message and "truncated" in sf.message
    # an end before the cut: nothing missing, nothing reported
    short = open_sequence(path, intrinsics=(50, 50, 64, 48), end=5)
    assert len(list(short)) == 5 and short.shortfall is None


def test_truncated_video_run_warns_on_stderr_and_in_run_json(sample_seq, tmp_path):
    path = write_avi(tmp_path / "drive.avi", sample_frames(sample_seq, 12))
    cut(path, 0.55)
    out = tmp_path / "out"
    res = invoke("run", path, "--intrinsics", INTR, "--out", out, "--no-plot")
    assert res.exit_code == 0, res.output
    warn = [ln for ln in res.stderr.splitlines() if ln.startswith("warning:") and "truncated" in ln]
    assert len(warn) == 1 and str(path) in warn[0] and "12 frames the container states" in warn[0], res.stderr
    doc = json.loads((out / "run.json").read_text())
    assert doc["status"] == "completed"
    group = doc["warnings"]["truncated-input"]
    assert group["count"] == 1 and group["items"][0]["message"] == warn[0].removeprefix("warning: ")
    n_done = doc["frames_processed"]
    assert 2 <= n_done < 12
    assert f"{12 - n_done} selected frame(s) missing" in warn[0]


def test_complete_video_run_has_no_truncation_warning(sample_seq, tmp_path):
    path = write_avi(tmp_path / "drive.avi", sample_frames(sample_seq, 4))
    res = invoke("run", path, "--intrinsics", INTR, "--out", tmp_path / "out", "--no-plot")
    assert res.exit_code == 0, res.output
    assert "truncated" not in res.stderr
    assert "truncated-input" not in json.loads((tmp_path / "out" / "run.json").read_text())["warnings"]


# --------------------------------------------------------------------------- item 10: corrupt frames in a folder


def test_corrupt_frames_are_skipped_named_and_all_kept_in_run_json(sample_seq, tmp_path):
    """12 bad files (more than any 'first 10' cut-off) of three kinds among 15 frames: each
    skipped, each named on stderr, all in run.json's skipped list and its warnings group."""
    seq = tmp_path / "seq"
    seq.mkdir()
    frames = sample_frames(sample_seq, 15, step=1)
    files = []
    for i, img in enumerate(frames):
        p = seq / f"{i:06d}.png"
        assert cv2.imwrite(str(p), img)
        files.append(p)
    bad = list(range(2, 14))
    for k, i in enumerate(bad):
        if k % 3 == 0:
            cut(files[i], 0.3)  # truncated PNG
        elif k % 3 == 1:
            files[i].write_bytes(b"")  # empty file
        else:
            files[i].write_bytes(b"GIF89a not a png at all" * 20)  # not an image
    out = tmp_path / "out"
    res = invoke("run", seq, "--intrinsics", INTR, "--out", out, "--no-plot")
    assert res.exit_code == 0, res.output
    skipped_lines = [ln for ln in res.stderr.splitlines() if ln.startswith("warning:") and ": skipped (" in ln]
    assert len(skipped_lines) == len(bad), res.stderr
    for i, ln in zip(bad, skipped_lines):
        assert ln.startswith(f"warning: {files[i]}: skipped ("), ln
    doc = json.loads((out / "run.json").read_text())
    assert doc["status"] == "completed"
    assert doc["frames_skipped"] == len(bad)
    assert [s["frame"] for s in doc["skipped"]] == bad
    assert [s["source"] for s in doc["skipped"]] == [str(files[i]) for i in bad]
    reasons = [s["reason"] for s in doc["skipped"]]
    assert any("empty" in r for r in reasons) and any("decode" in r for r in reasons)
    group = doc["warnings"]["skipped-frame"]
    assert group["count"] == len(bad) == len(group["items"])  # all of them, not the first 10
    assert [it["frame"] for it in group["items"]] == bad
    assert [it["message"] for it in group["items"]] == [ln.removeprefix("warning: ") for ln in skipped_lines]
    # grouped by kind: every group has a count and all its items
    for kind, g in doc["warnings"].items():
        assert set(g) == {"count", "items"} and g["count"] == len(g["items"]), kind
    assert (out / "frames.txt").read_text().split() == ["0", "1", "14"]
