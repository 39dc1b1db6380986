"""``trianflow-vo eval`` end to end on files: formats, association, outputs, bad input."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from click.testing import CliRunner

from trianflow_vo.cli.main import main
from trianflow_vo.io.trajectory import format_kitti_line, format_tum_line


def straight(frames, step=1.0):
    """Poses at the given frame indices of a camera moving ``step`` m/frame along z."""
    T = np.tile(np.eye(4), (len(frames), 1, 1))
    T[:, 2, 3] = step * np.asarray(frames, float)
    return T


def write_kitti(path, T, frames=None):
    lines = [format_kitti_line(t) for t in T]
    if frames is not None:
        lines = [f"{f} {ln}" for f, ln in zip(frames, lines)]
    path.write_text("\n".join(lines) + "\n")
    return path


def write_tum(path, times, T):
    path.write_text("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(format_tum_line(s, t) for s, t in zip(times, T)) + "\n")
    return path


def write_run(folder, frames, T, times=None):
    folder.mkdir(parents=True, exist_ok=True)
    write_kitti(folder / "poses.txt", T)
    (folder / "frames.txt").write_text("\n".join(str(f) for f in frames) + "\n")
    write_tum(folder / "trajectory.tum", frames if times is None else times, T)
    (folder / "run.json").write_text("{}\n")
    return folder


def invoke(*args):
    return CliRunner().invoke(main, ["eval", *map(str, args)])


@pytest.fixture
def gt100(tmp_path):
    return write_kitti(tmp_path / "gt.txt", straight(range(100)))


def test_strided_run_folder_known_drift(tmp_path, gt100):
    e = 0.02
    frames = list(range(0, 100, 3))
    run = write_run(tmp_path / "runs" / "r1", frames, straight(frames, 1.0 + e))
    out = tmp_path / "m.json"
    res = invoke("--gt", gt100, "--pred", run, "--align", "none", "--lengths", "9,30", "--json", out)
    assert res.exit_code == 0, res.output
    m = json.loads(out.read_text())
    assert m["num_frames"] == len(frames) and m["matched_by"] == "frame index"
    rows = {r["length"]: r for r in m["per_length"]}
    # kept frames are 3 m apart: L=9 ends 12 m later, L=30 ends 33 m later
    assert rows[9.0]["t_err"] == pytest.approx(100 * e * 12 / 9, rel=1e-9)
    assert rows[30.0]["t_err"] == pytest.approx(100 * e * 33 / 30, rel=1e-9)
    # first frames every 10 kept frames: positions 0, 10, 20, 30 of 0..33; an end needs
    # position + 4 (L=9) or + 11 (L=30) <= 33, so the first frame 30 has none
    assert rows[9.0]["num_segments"] == 3 and rows[30.0]["num_segments"] == 3
    for key in ("t_err", "r_err", "ate_rmse", "rpe_trans", "rpe_rot", "num_frames", "num_segments", "align", "per_length"):
        assert key in m
    assert "frames.txt" in res.output


def test_thirteen_columns_with_missing_frames(tmp_path, gt100):
    frames = [f for f in range(100) if f % 7 != 3]
    pred = write_kitti(tmp_path / "p13.txt", straight(frames, 0.5), frames)  # half scale
    res = invoke("--gt", gt100, "--pred", pred, "--lengths", "10,20", "--json", tmp_path / "m.json")
    assert res.exit_code == 0, res.output
    m = json.loads((tmp_path / "m.json").read_text())
    assert m["num_frames"] == len(frames) and m["num_pred_frames"] == len(frames) and m["num_gt_frames"] == 100
    assert m["t_err"] < 1e-9 and m["scale"] == pytest.approx(2.0)


def test_twelve_columns_different_length_refused(tmp_path, gt100):
    pred = write_kitti(tmp_path / "p.txt", straight(range(50)))
    res = invoke("--gt", gt100, "--pred", pred)
    assert res.exit_code != 0
    assert f"{pred}: 50 poses but the ground truth" in res.output and "frames.txt" in res.output
    assert "Traceback" not in res.output


def test_frames_file_count_mismatch(tmp_path, gt100):
    run = write_run(tmp_path / "run", [0, 1, 2, 3], straight([0, 1, 2, 3]))
    (run / "frames.txt").write_text("0\n1\n2\n")
    res = invoke("--gt", gt100, "--pred", run)
    assert res.exit_code != 0 and "3 frame indices for 4 poses" in res.output


def test_tum_association(tmp_path):
    times = np.arange(60) * 0.1 + 1000.0
    gt = write_tum(tmp_path / "gt.tum", times, straight(range(60)))
    pred = write_tum(tmp_path / "p.tum", times[::2] + 0.004, straight(range(0, 60, 2), 3.0))
    res = invoke("--gt", gt, "--pred", pred, "--lengths", "5,10", "--json", tmp_path / "m.json")
    assert res.exit_code == 0, res.output
    m = json.loads((tmp_path / "m.json").read_text())
    assert m["matched_by"] == "timestamp" and m["num_frames"] == 30
    assert m["t_err"] < 1e-9 and m["scale"] == pytest.approx(1 / 3)
    # too strict a tolerance: nothing matches
    res = invoke("--gt", gt, "--pred", pred, "--max-time-diff", "0.001")
    assert res.exit_code != 0 and "only 0 frame(s) in common" in res.output
    # a run folder against TUM ground truth uses its trajectory.tum
    run = write_run(tmp_path / "run", list(range(0, 60, 2)), straight(range(0, 60, 2)), times=times[::2])
    res = invoke("--gt", gt, "--pred", run, "--lengths", "5")
    assert res.exit_code == 0, res.output
    assert "trajectory.tum" in res.output and "matched by timestamp" in res.output


def test_tum_prediction_against_kitti_ground_truth(tmp_path, gt100):
    pred = write_tum(tmp_path / "p.tum", np.arange(0, 100, 2), straight(range(0, 100, 2)))
    res = invoke("--gt", gt100, "--pred", pred, "--lengths", "10")
    assert res.exit_code == 0, res.output
    assert "50 common" in res.output
    write_tum(pred, np.arange(0, 100, 2) * 0.1 + 0.05, straight(range(0, 100, 2)))
    res = invoke("--gt", gt100, "--pred", pred)
    assert res.exit_code != 0 and "TUM timestamps cannot be matched" in res.output
    # a kitti prediction cannot be matched to TUM ground truth
    gt_tum = write_tum(tmp_path / "gt.tum", np.arange(100) * 0.1, straight(range(100)))
    res = invoke("--gt", gt_tum, "--pred", gt100)
    assert res.exit_code != 0 and "has none" in res.output


def test_bad_input_one_line_errors(tmp_path, gt100):
    bad = tmp_path / "bad.txt"
    lines = gt100.read_text().splitlines()
    lines[41] = lines[41].replace(lines[41].split()[3], "nan", 1)
    bad.write_text("\n".join(lines) + "\n")
    res = invoke("--gt", gt100, "--pred", bad)
    assert res.exit_code == 1
    assert f"{bad}:42: non-finite" in res.output and "Traceback" not in res.output
    res = invoke("--gt", bad, "--pred", gt100)
    assert res.exit_code == 1 and f"{bad}:42:" in res.output
    # fewer than 3 common frames
    few = write_kitti(tmp_path / "few.txt", straight([0, 1]), [0, 1])
    res = invoke("--gt", gt100, "--pred", few)
    assert res.exit_code == 1 and "only 2 frame(s) in common" in res.output
    # degenerate: the prediction never moves
    still = write_kitti(tmp_path / "still.txt", straight(range(100), 0.0))
    res = invoke("--gt", gt100, "--pred", still)
    assert res.exit_code == 1 and "cannot estimate the 7dof alignment" in res.output
    assert "Traceback" not in res.output
    res = invoke("--gt", gt100, "--pred", still, "--align", "none", "--lengths", "10")
    assert res.exit_code == 0, res.output
    # missing prediction, bad lengths
    res = invoke("--gt", gt100, "--pred", tmp_path / "nope")
    assert res.exit_code == 1 and "no such file or folder" in res.output
    res = invoke("--gt", gt100, "--pred", gt100, "--lengths", "10,abc")
    assert res.exit_code == 2 and "comma-separated" in res.output
    res = invoke("--gt", gt100, "--pred", gt100, "--lengths", "10,-5")
    assert res.exit_code == 2


def test_default_pred_is_latest_run(tmp_path, gt100, monkeypatch):
    monkeypatch.chdir(tmp_path)
    res = invoke("--gt", gt100)
    assert res.exit_code == 1 and "runs" in res.output and "--pred" in res.output
    (tmp_path / "runs" / "empty").mkdir(parents=True)
    res = invoke("--gt", gt100)
    assert res.exit_code == 1 and "no run folder with a poses.txt" in res.output
    old = write_run(tmp_path / "runs" / "b-old", list(range(100)), straight(range(100), 2.0))
    new = write_run(tmp_path / "runs" / "a-new", list(range(0, 100, 5)), straight(range(0, 100, 5), 2.0))
    os.utime(old / "poses.txt", (1_000_000, 1_000_000))
    res = invoke("--gt", gt100, "--lengths", "10")
    assert res.exit_code == 0, res.output
    assert "a-new" in res.output and "20 common" in res.output


def test_short_sequence_says_so_and_writes_plot(tmp_path):
    gt = write_kitti(tmp_path / "gt.txt", straight(range(40)))
    png = tmp_path / "p.png"
    res = invoke("--gt", gt, "--pred", gt, "--json", tmp_path / "m.json", "--plot", png)
    assert res.exit_code == 0, res.output
    assert "no segment" in res.output and "--lengths" in res.output and "nan" not in res.output.lower()
    m = json.loads((tmp_path / "m.json").read_text())
    assert m["t_err"] is None and m["num_segments"] == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_help_states_protocol():
    res = CliRunner().invoke(main, ["eval", "--help"])
    assert res.exit_code == 0
    for words in ("Re-base", "Umeyama", "every 10 kept", "t_err", "ATE", "RPE"):
        assert words in res.output
