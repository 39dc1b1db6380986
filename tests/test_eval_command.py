"""`trianflow-vo eval` through click: output, --json, --plot, default --pred, and
one-line errors with a non-zero exit for every kind of bad input."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

from trianflow_vo.cli.main import main
from trianflow_vo.io.trajectory import format_kitti_line

JSON_KEYS = {"t_err", "r_err", "ate_rmse", "rpe_trans", "rpe_rot", "num_frames", "num_segments", "align", "per_length"}


def winding(n: int, seed: int = 0) -> np.ndarray:
    """``(n, 4, 4)`` a smooth drive, ~1 m per frame."""
    rng = np.random.default_rng(seed)
    out = [np.eye(4)]
    for _ in range(n - 1):
        S = np.eye(4)
        S[:3, :3] = Rotation.from_rotvec(rng.normal(0.0, [0.01, 0.04, 0.01])).as_matrix()
        S[:3, 3] = (rng.normal(0, 0.05), rng.normal(0, 0.02), 1.0)
        out.append(out[-1] @ S)
    return np.stack(out)


def write_kitti(path, poses):
    path.write_text("".join(format_kitti_line(T) + "\n" for T in poses))
    return path


def run_eval(*args):
    result = CliRunner().invoke(main, ["eval", *map(str, args)])
    return result


def assert_one_line_error(result, *words):
    """Non-zero exit, click's 'Error: ...' on one line, no traceback."""
    assert result.exit_code != 0, result.output
    assert "Traceback" not in result.output
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error: "), result.stderr
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


@pytest.fixture
def clip(tmp_path):
    """A 120 m ground truth and a prediction with noisy steps, 0.5 x scale."""
    gt = winding(121, seed=1)
    rng = np.random.default_rng(0)
    pred = gt.copy()
    pred[:, :3, 3] = 0.5 * (gt[:, :3, 3] + np.cumsum(rng.normal(0, 0.05, (121, 3)), axis=0))
    return write_kitti(tmp_path / "gt.txt", gt), write_kitti(tmp_path / "pred.txt", pred)


# --------------------------------------------------------------------------- outputs


def test_table_json_and_plot(tmp_path, clip):
    gt, pred = clip
    out_json, out_png = tmp_path / "m.json", tmp_path / "m.png"
    r = run_eval("--gt", gt, "--pred", pred, "--lengths", "20,40,60", "--json", out_json, "--plot", out_png)
    assert r.exit_code == 0, r.output
    m = json.loads(out_json.read_text())
    assert JSON_KEYS <= set(m)
    assert m["align"] == "7dof" and m["num_frames"] == 121 and m["num_segments"] > 0
    assert [row["length"] for row in m["per_length"]] == [20.0, 40.0, 60.0]
    assert 0 < m["t_err"] < 50 and m["ate_rmse"] > 0 and m["rpe_trans"] > 0
    assert abs(m["scale"] - 2.0) < 0.2
    # the table shows the same numbers
    assert f"t_err  {m['t_err']:.4f} %" in r.stdout
    assert f"rmse {m['ate_rmse']:.4f} m" in r.stdout
    data = out_png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000


def test_alignment_option_changes_the_result(tmp_path, clip):
    gt, pred = clip
    res = {}
    for mode in ("7dof", "6dof", "scale", "none"):
        out = tmp_path / f"{mode}.json"
        r = run_eval("--gt", gt, "--pred", pred, "--lengths", "20,40", "--align", mode, "--json", out)
        assert r.exit_code == 0, r.output
        res[mode] = json.loads(out.read_text())
        assert res[mode]["align"] == mode
    # the prediction is half scale: without a scale estimate the error is ~50 %
    assert res["6dof"]["t_err"] > 30 and res["none"]["t_err"] > 30
    assert res["7dof"]["t_err"] < 10 and res["scale"]["t_err"] < 10


def test_short_sequence_says_so_and_suggests_lengths(tmp_path, clip):
    """120 m with the default 100..800 m lengths: only the 100 m segments of the very
    first frames fit; with 500..800 nothing fits -> a note suggesting --lengths, JSON nulls."""
    gt, pred = clip
    out_json, out_png = tmp_path / "m.json", tmp_path / "m.png"
    r = run_eval("--gt", gt, "--pred", pred, "--lengths", "500,800", "--json", out_json, "--plot", out_png)
    assert r.exit_code == 0, r.output
    assert "no segment" in r.stdout and "--lengths 10,20,30,40,50,60,70,80" in r.stdout
    assert "nan" not in r.stdout.lower()
    m = json.loads(out_json.read_text())
    assert m["t_err"] is None and m["r_err"] is None and m["num_segments"] == 0
    assert "--lengths" in m["note"]
    assert out_png.read_bytes()[:4] == b"\x89PNG"


def test_help_states_the_protocol():
    r = CliRunner().invoke(main, ["eval", "--help"])
    assert r.exit_code == 0
    for words in ("Re-base", "Umeyama", "every 10", "--lengths", "t_err", "ATE", "RPE"):
        assert words in r.output


# --------------------------------------------------------------------------- default --pred


def _fake_run(folder, poses, mtime):
    folder.mkdir(parents=True)
    write_kitti(folder / "poses.txt", poses)
    (folder / "frames.txt").write_text("".join(f"{i}\n" for i in range(len(poses))))
    os.utime(folder / "poses.txt", (mtime, mtime))
    os.utime(folder, (mtime, mtime))


def test_pred_defaults_to_latest_run(tmp_path, monkeypatch):
    """Two runs; the newer one (created first, so creation order cannot be what picks it)
    covers 30 frames, the older 60: the JSON's num_frames says which was read."""
    gt = winding(60, seed=2)
    write_kitti(tmp_path / "gt.txt", gt)
    _fake_run(tmp_path / "runs" / "newer", gt[:30], 1_700_000_000)
    _fake_run(tmp_path / "runs" / "older", gt, 1_600_000_000)
    monkeypatch.chdir(tmp_path)
    r = run_eval("--gt", "gt.txt", "--lengths", "5", "--json", "m.json")
    assert r.exit_code == 0, r.output
    assert "using the latest run" in r.stderr and "newer" in r.stderr
    assert json.loads((tmp_path / "m.json").read_text())["num_frames"] == 30


def test_no_run_is_a_clear_error(tmp_path, monkeypatch):
    write_kitti(tmp_path / "gt.txt", winding(10))
    monkeypatch.chdir(tmp_path)
    assert_one_line_error(run_eval("--gt", "gt.txt"), "--pred", "trianflow-vo run")
    (tmp_path / "runs" / "crashed").mkdir(parents=True)  # a run folder without poses.txt
    assert_one_line_error(run_eval("--gt", "gt.txt"), "runs", "--pred")


# --------------------------------------------------------------------------- bad input


GOOD = format_kitti_line(np.eye(4))


def test_bad_values_name_file_and_line(tmp_path, clip):
    gt, _ = clip
    cases = {
        "cols.txt": (f"{GOOD}\n{GOOD}\n1 2 3\n", ":3:", "3 columns"),
        "word.txt": (f"{GOOD}\n{GOOD.replace('0.000000000e+00', 'x1', 1)}\n", ":2:", "not a number"),
        "nan.txt": (f"{GOOD}\n{GOOD.replace('0.000000000e+00', 'NaN', 1)}\n", ":2:", "non-finite"),
        "inf.txt": (f"{GOOD}\n{GOOD}\n{GOOD.replace('0.000000000e+00', 'inf', 1)}\n", ":3:", "non-finite"),
        "five.txt": ("1 2 3 4 5\n", ":1:", "5 columns per line"),
    }
    for name, (text, where, words) in cases.items():
        p = tmp_path / name
        p.write_text(text)
        assert_one_line_error(run_eval("--gt", gt, "--pred", p), f"{p}{where}", words)
    # the same checks apply to the ground truth
    p = tmp_path / "nan.txt"
    assert_one_line_error(run_eval("--gt", p, "--pred", gt), f"{p}:2:", "non-finite")


def test_unmatchable_lengths_refused(tmp_path, clip):
    gt, _ = clip
    p = write_kitti(tmp_path / "strided.txt", winding(121, seed=1)[::3])
    line = assert_one_line_error(run_eval("--gt", gt, "--pred", p), str(p), "41 poses", "121", "frames.txt")
    assert "13 columns" in line


def test_too_few_common_frames(tmp_path, clip):
    gt, _ = clip
    p = tmp_path / "two.txt"
    p.write_text(f"5 {GOOD}\n6 {GOOD}\n500 {GOOD}\n")
    assert_one_line_error(run_eval("--gt", gt, "--pred", p), str(p), "only 2 frame", "at least 3")


def test_degenerate_alignment(tmp_path, clip):
    gt, _ = clip
    still = np.tile(np.eye(4), (121, 1, 1))
    still[:, :3, 3] = [1.0, 2.0, 3.0]
    p = write_kitti(tmp_path / "still.txt", still)
    assert_one_line_error(run_eval("--gt", gt, "--pred", p), str(p), "cannot estimate the 7dof", "--align none")
    r = run_eval("--gt", gt, "--pred", p, "--align", "none", "--lengths", "10")
    assert r.exit_code == 0, r.output


def test_output_folder_missing_is_a_one_line_error(tmp_path, clip):
    """Checked before any work: a --json/--plot inside a missing folder, or "inside" a file."""
    gt, pred = clip
    assert_one_line_error(run_eval("--gt", gt, "--pred", pred, "--json", tmp_path / "no" / "m.json"),
                          "m.json", "not an existing folder")
    assert_one_line_error(run_eval("--gt", gt, "--pred", pred, "--plot", gt / "m.png"),
                          "m.png", "not an existing folder")


def test_tum_ground_truth_needs_a_prediction_with_timestamps(tmp_path, clip):
    _, pred = clip
    gt = tmp_path / "gt.tum"
    gt.write_text("".join(f"{0.1 * i:.6f} {i} 0 0 0 0 0 1\n" for i in range(10)))
    assert_one_line_error(run_eval("--gt", gt, "--pred", pred), str(pred), "TUM", "timestamps")


def test_lengths_are_sorted_and_deduplicated(tmp_path, clip):
    gt, pred = clip
    out = tmp_path / "m.json"
    r = run_eval("--gt", gt, "--pred", pred, "--lengths", "40, 20,40", "--json", out)
    assert r.exit_code == 0, r.output
    assert [row["length"] for row in json.loads(out.read_text())["per_length"]] == [20.0, 40.0]


def test_missing_prediction_and_bad_lengths(tmp_path, clip):
    gt, _ = clip
    assert_one_line_error(run_eval("--gt", gt, "--pred", tmp_path / "nope.txt"), "nope.txt", "no such file")
    for bad in ("10,abc", "-5", "0", "nan"):
        r = run_eval("--gt", gt, "--pred", gt, "--lengths", bad)
        assert r.exit_code == 2 and "Traceback" not in r.output
        assert "--lengths" in r.stderr


# --------------------------------------------------------------------------- real data


@pytest.mark.parametrize(
    "seq, t_err, r_err",
    [("09", 2.527535077, 0.287707222), ("10", 2.221192217, 0.369334674)],
)
def test_published_kitti_numbers_through_cli(shared_data, tmp_path, seq, t_err, r_err):
    root = shared_data / "kitti-odometry-eval"
    out = tmp_path / "m.json"
    r = run_eval("--gt", root / "gt_poses" / f"{seq}.txt", "--pred", root / "pred" / "dfvo_example_1" / f"{seq}.txt",
                 "--json", out)
    assert r.exit_code == 0, r.output
    m = json.loads(out.read_text())
    assert m["t_err"] == pytest.approx(t_err, rel=1e-6)
    assert m["r_err"] == pytest.approx(r_err, rel=1e-6)
    assert JSON_KEYS <= set(m)
    assert f"{t_err:.4f}" in r.stdout
