"""`trianflow-vo eval` through click: the table, --json, --plot (through evo's plotting,
stdout kept clean), --align, --lengths, --max-time-diff, the default --pred, one-line
errors with a non-zero exit for every kind of bad input, and real KITTI data on ../shared."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from synthetic import winding
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

from trianflow_vo.cli.main import main
from trianflow_vo.io.trajectory import format_kitti_line, format_tum_line, read_trajectory

REPO = Path(__file__).resolve().parents[2]
JSON_KEYS = {"t_err", "r_err", "ate_rmse", "rpe_trans", "rpe_rot", "num_frames", "num_segments", "align", "per_length"}
PUBLISHED = {"09": (2.527535077, 0.287707222), "10": (2.221192217, 0.369334674)}


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


def run_eval(*args):
    return CliRunner().invoke(main, ["eval", *map(str, args)])


def assert_one_line_error(result, *words):
    """Exit code 1, click's 'Error: ...' on one line, no traceback."""
    assert result.exit_code == 1, result.output
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


@pytest.fixture
def gt100(tmp_path):
    return write_kitti(tmp_path / "gt100.txt", straight(range(100)))


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


@pytest.mark.parametrize("case", ["120m-long-lengths", "40m-default-lengths"])
def test_short_sequence_says_so_suggests_lengths_and_writes_plot(tmp_path, clip, case):
    """120 m with 500..800 m lengths, or a 40 m straight clip (evaluated against itself)
    with the default 100..800 m: nothing fits -> a note suggesting --lengths, JSON nulls,
    no NaN anywhere, and the plot is still written."""
    if case == "120m-long-lengths":
        gt, pred = clip
        extra, suggestion = ("--lengths", "500,800"), "--lengths 10,20,30,40,50,60,70,80"
    else:
        gt = pred = write_kitti(tmp_path / "gt40.txt", straight(range(40)))
        extra, suggestion = (), "--lengths"
    out_json, out_png = tmp_path / "m.json", tmp_path / "m.png"
    r = run_eval("--gt", gt, "--pred", pred, *extra, "--json", out_json, "--plot", out_png)
    assert r.exit_code == 0, r.output
    assert "no segment" in r.stdout and suggestion in r.stdout
    assert "nan" not in r.stdout.lower()
    m = json.loads(out_json.read_text())
    assert m["t_err"] is None and m["r_err"] is None and m["num_segments"] == 0
    assert "--lengths" in m["note"]
    assert out_png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_help_states_the_protocol():
    r = CliRunner().invoke(main, ["eval", "--help"])
    assert r.exit_code == 0
    for words in ("Re-base", "Umeyama", "every 10 kept", "--lengths", "t_err", "ATE", "RPE"):
        assert words in r.output


def test_lengths_are_sorted_and_deduplicated(tmp_path, clip):
    gt, pred = clip
    out = tmp_path / "m.json"
    r = run_eval("--gt", gt, "--pred", pred, "--lengths", "40, 20,40", "--json", out)
    assert r.exit_code == 0, r.output
    assert [row["length"] for row in json.loads(out.read_text())["per_length"]] == [20.0, 40.0]


def _cli_subprocess(args, home, cwd):
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "MPLBACKEND")}
    env["HOME"] = str(home)
    return subprocess.run([sys.executable, "-m", "trianflow_vo.cli", *map(str, args)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=300)


def test_plot_goes_through_evo_and_stdout_stays_clean(tmp_path, clip):
    """A first use of evo's plotting (fresh HOME: evo writes ~/.evo/settings.json and prints
    so) leaves the tool's stdout to the report and its own lines, and stderr empty."""
    gt, pred = clip
    home = tmp_path / "home"
    home.mkdir()
    png = tmp_path / "p.png"
    res = _cli_subprocess(["eval", "--gt", gt, "--pred", pred, "--lengths", "20,40", "--plot", png], home, tmp_path)
    assert res.returncode == 0, res.stderr
    assert (home / ".evo" / "settings.json").is_file()  # evo's plotting was imported
    assert res.stdout.splitlines()[0].startswith("prediction   ") and res.stdout.rstrip().endswith(f"wrote {png}")
    assert ".evo" not in res.stdout and "Initialized" not in res.stdout
    assert res.stderr == ""
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_plot_falls_back_when_evo_cannot_write_its_settings(tmp_path, clip):
    """HOME unusable (here: below a regular file, so ~/.evo cannot be created, as on a
    read-only HOME): evo's plotting cannot be imported; the figure is drawn with matplotlib
    directly, a one-line warning on stderr says so, stdout is the same as ever."""
    gt, pred = clip
    (tmp_path / "file").write_text("")
    png = tmp_path / "p.png"
    res = _cli_subprocess(["eval", "--gt", gt, "--pred", pred, "--lengths", "20,40", "--plot", png],
                          tmp_path / "file" / "home", tmp_path)
    assert res.returncode == 0, res.stderr
    warning = [ln for ln in res.stderr.splitlines() if "evo's plotting is unavailable" in ln]
    assert len(warning) == 1 and warning[0].startswith("warning: evo's plotting is unavailable"), res.stderr
    assert res.stdout.splitlines()[0].startswith("prediction   ") and res.stdout.rstrip().endswith(f"wrote {png}")
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000


# --------------------------------------------------------------------------- association


@pytest.mark.parametrize(
    "n, e, lengths, expected, rel",
    [
        # kept frames are 3 m apart: L=9 ends 12 m later, L=30 ends 33 m later; first frames at
        # positions 0, 10, 20, 30 of 0..33 and an end needs position + 4 (+ 11) <= 33
        (100, 0.02, (9, 30), {9: (100 * 0.02 * 12 / 9, 3), 30: (100 * 0.02 * 33 / 30, 3)}, 1e-9),
        # 301 frames, 101 kept: L = 30 ends 11 kept frames later (33 m), L = 60 21 later (63 m),
        # with first kept frames 0, 10, ... and end <= 100: 9 and 8 segments
        (301, 0.01, (30, 60), {30: (1.1, 9), 60: (1.05, 8)}, 1e-6),
    ],
)
def test_strided_run_folder_known_drift(tmp_path, n, e, lengths, expected, rel):
    """A `run --stride 3` folder (poses.txt + frames.txt) of a straight gt with (1 + e)
    too long motion: the segment metric works on the kept frames."""
    gt = write_kitti(tmp_path / "gt.txt", straight(range(n)))
    frames = list(range(0, n, 3))
    run = write_run(tmp_path / "runs" / "r1", frames, straight(frames, 1.0 + e))
    out = tmp_path / "m.json"
    res = run_eval("--gt", gt, "--pred", run, "--align", "none", "--lengths", ",".join(map(str, lengths)),
                   "--json", out)
    assert res.exit_code == 0, res.output
    m = json.loads(out.read_text())
    assert JSON_KEYS <= set(m)
    assert m["num_frames"] == len(frames) and m["num_pred_frames"] == len(frames) and m["num_gt_frames"] == n
    assert m["matched_by"] == "frame index"
    assert "frames.txt" in m["pred"] and "frames.txt" in res.output
    rows = {r["length"]: r for r in m["per_length"]}
    for L, (t_err, count) in expected.items():
        assert rows[float(L)]["t_err"] == pytest.approx(t_err, rel=rel)
        assert rows[float(L)]["num_segments"] == count
    # 7dof removes the drift
    res = run_eval("--gt", gt, "--pred", run, "--lengths", ",".join(map(str, lengths)), "--json", out)
    assert res.exit_code == 0, res.output
    assert json.loads(out.read_text())["t_err"] == pytest.approx(0.0, abs=1e-6)


def test_max_time_diff_option(tmp_path):
    """TUM against TUM, the prediction every other frame, 4 ms late and 3x too long: matched
    by timestamp within the default 0.02 s, nothing in common within 0.001 s."""
    times = np.arange(60) * 0.1 + 1000.0
    gt = write_tum(tmp_path / "gt.tum", times, straight(range(60)))
    pred = write_tum(tmp_path / "p.tum", times[::2] + 0.004, straight(range(0, 60, 2), 3.0))
    res = run_eval("--gt", gt, "--pred", pred, "--lengths", "5,10", "--json", tmp_path / "m.json")
    assert res.exit_code == 0, res.output
    m = json.loads((tmp_path / "m.json").read_text())
    assert m["matched_by"] == "timestamp" and m["num_frames"] == 30
    assert m["t_err"] < 1e-9 and m["scale"] == pytest.approx(1 / 3)
    assert_one_line_error(run_eval("--gt", gt, "--pred", pred, "--max-time-diff", "0.001"),
                          str(pred), "only 0 frame(s) in common")


def test_pred_defaults_to_latest_run(tmp_path, monkeypatch):
    """No runs folder, an empty one, a run without poses.txt: clear errors. Then two runs;
    the newer one (created first and sorted first, so neither creation order nor name can
    be what picks it) covers 30 frames, the older 60: num_frames says which was read."""
    gt = winding(60, seed=2)
    write_kitti(tmp_path / "gt.txt", gt)
    monkeypatch.chdir(tmp_path)
    assert_one_line_error(run_eval("--gt", "gt.txt"), "runs folder", "--pred", "trianflow-vo run")
    (tmp_path / "runs" / "crashed").mkdir(parents=True)  # a run folder without poses.txt
    assert_one_line_error(run_eval("--gt", "gt.txt"), "runs", "no run folder with a poses.txt", "--pred")
    for name, poses, mtime in (("a-newer", gt[:30], 1_700_000_000), ("b-older", gt, 1_600_000_000)):
        folder = write_run(tmp_path / "runs" / name, list(range(len(poses))), poses)
        os.utime(folder / "poses.txt", (mtime, mtime))
        os.utime(folder, (mtime, mtime))
    r = run_eval("--gt", "gt.txt", "--lengths", "5", "--json", "m.json")
    assert r.exit_code == 0, r.output
    assert "using the latest run" in r.stderr and "a-newer" in r.stderr
    assert "30 common" in r.stdout
    assert json.loads((tmp_path / "m.json").read_text())["num_frames"] == 30


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
    """12 numbers per line, 41 lines against a 121-line ground truth, no frames.txt: which
    frames are they? Refused, naming the file, both counts and the two ways out."""
    gt, _ = clip
    p = write_kitti(tmp_path / "strided.txt", winding(121, seed=1)[::3])
    line = assert_one_line_error(run_eval("--gt", gt, "--pred", p), f"Error: {p}: 41 poses but the ground truth {gt} has 121",
                                 "frames.txt")
    assert "13 columns" in line


def test_frames_file_count_mismatch(tmp_path, gt100):
    run = write_run(tmp_path / "run", [0, 1, 2, 3], straight([0, 1, 2, 3]))
    (run / "frames.txt").write_text("0\n1\n2\n")
    assert_one_line_error(run_eval("--gt", gt100, "--pred", run), str(run / "frames.txt"),
                          "3 frame indices for 4 poses")


def test_too_few_common_frames(tmp_path, clip):
    gt, _ = clip
    p = tmp_path / "two.txt"
    p.write_text(f"5 {GOOD}\n6 {GOOD}\n500 {GOOD}\n")
    assert_one_line_error(run_eval("--gt", gt, "--pred", p), str(p), "only 2 frame(s) in common", "at least 3")


def test_degenerate_alignment(tmp_path, clip):
    gt, _ = clip
    still = np.tile(np.eye(4), (121, 1, 1))
    still[:, :3, 3] = [1.0, 2.0, 3.0]
    p = write_kitti(tmp_path / "still.txt", still)
    assert_one_line_error(run_eval("--gt", gt, "--pred", p), str(p), "cannot estimate the 7dof alignment", "--align none")
    r = run_eval("--gt", gt, "--pred", p, "--align", "none", "--lengths", "10")
    assert r.exit_code == 0, r.output


def test_output_folder_missing_is_a_one_line_error(tmp_path, clip):
    """Checked before any work: a --json/--plot inside a missing folder, or "inside" a file."""
    gt, pred = clip
    assert_one_line_error(run_eval("--gt", gt, "--pred", pred, "--json", tmp_path / "no" / "m.json"),
                          "m.json", "not an existing folder")
    assert_one_line_error(run_eval("--gt", gt, "--pred", pred, "--plot", gt / "m.png"),
                          "m.png", "not an existing folder")


def test_tum_needs_timestamps_on_both_sides(tmp_path, clip, gt100):
    """A TUM ground truth needs a prediction with timestamps; a TUM prediction with real
    (non-integer) times cannot be matched to a frame-indexed ground truth without frames.txt."""
    _, pred = clip
    gt = tmp_path / "gt.tum"
    gt.write_text("".join(f"{0.1 * i:.6f} {i} 0 0 0 0 0 1\n" for i in range(10)))
    assert_one_line_error(run_eval("--gt", gt, "--pred", pred), str(pred), "TUM", "timestamps", "has none")
    p = write_tum(tmp_path / "p.tum", np.arange(0, 100, 2) * 0.1 + 0.05, straight(range(0, 100, 2)))
    assert_one_line_error(run_eval("--gt", gt100, "--pred", p), str(p), "TUM timestamps cannot be matched")


def test_missing_prediction_and_bad_lengths(tmp_path, clip):
    gt, _ = clip
    assert_one_line_error(run_eval("--gt", gt, "--pred", tmp_path / "nope.txt"), "nope.txt", "no such file or folder")
    for bad in ("10,abc", "-5", "0", "nan", "10,-5"):
        r = run_eval("--gt", gt, "--pred", gt, "--lengths", bad)
        assert r.exit_code == 2 and "Traceback" not in r.output
        assert "--lengths" in r.stderr
    assert "comma-separated" in run_eval("--gt", gt, "--pred", gt, "--lengths", "10,abc").stderr


# --------------------------------------------------------------------------- real data


@pytest.mark.parametrize("seq", sorted(PUBLISHED))
def test_published_kitti_numbers_through_cli(shared_data, tmp_path, seq):
    root = shared_data / "kitti-odometry-eval"
    t_err, r_err = PUBLISHED[seq]
    out = tmp_path / "m.json"
    r = run_eval("--gt", root / "gt_poses" / f"{seq}.txt", "--pred", root / "pred" / "dfvo_example_1" / f"{seq}.txt",
                 "--json", out)
    assert r.exit_code == 0, r.output
    m = json.loads(out.read_text())
    assert m["t_err"] == pytest.approx(t_err, rel=1e-6)
    assert m["r_err"] == pytest.approx(r_err, rel=1e-6)
    assert JSON_KEYS <= set(m)
    assert f"{t_err:.4f} %" in r.stdout


def _rot_y(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _perturbed_run(folder, gt, stride, scale_drift, yaw_drift, noise=0.0, seed=0):
    """A fake run folder: the ground truth every ``stride`` frames, its relative motions
    scaled by ``1 + scale_drift`` and turned by ``yaw_drift`` rad (plus ``noise`` rad of random yaw), then
    moved by an arbitrary similarity (as a monocular method's world frame would be)."""
    rng = np.random.default_rng(seed)
    frames = np.arange(0, gt.shape[0], stride)
    G = gt[frames]
    T = [np.eye(4)]
    for i in range(len(frames) - 1):
        M = np.linalg.inv(G[i]) @ G[i + 1]
        M[:3, 3] *= 1 + scale_drift
        N = np.eye(4)
        N[:3, :3] = _rot_y(yaw_drift + noise * rng.normal())
        T.append(T[-1] @ M @ N)
    T = np.array(T)
    S = np.eye(4)
    S[:3, :3] = _rot_y(0.8)
    T[:, :3, 3] *= 0.3
    T = S @ T
    folder.mkdir(parents=True)
    (folder / "poses.txt").write_text("\n".join(format_kitti_line(t) for t in T) + "\n")
    (folder / "frames.txt").write_text("\n".join(str(f) for f in frames) + "\n")
    (folder / "trajectory.tum").write_text("\n".join(format_tum_line(float(f), t) for f, t in zip(frames, T)) + "\n")
    (folder / "run.json").write_text("{}\n")
    return frames, T


def _reference_segment_metric(gt, pred, lengths, step=10):
    """The devkit definition written as plain loops (an independent check of the vectorised one)."""
    dist = [0.0]
    for i in range(1, len(gt)):
        dist.append(dist[-1] + float(np.linalg.norm(gt[i, :3, 3] - gt[i - 1, :3, 3])))
    t_errs, r_errs = [], []
    for first in range(0, len(gt), step):
        for L in lengths:
            last = next((i for i in range(first, len(gt)) if dist[i] > dist[first] + L), None)
            if last is None:
                continue
            dg = np.linalg.inv(gt[first]) @ gt[last]
            dp = np.linalg.inv(pred[first]) @ pred[last]
            E = np.linalg.inv(dp) @ dg
            t_errs.append(np.linalg.norm(E[:3, 3]) / L)
            r_errs.append(np.arccos(max(min(0.5 * (np.trace(E[:3, :3]) - 1), 1.0), -1.0)) / L)
    return 100 * np.mean(t_errs), np.degrees(np.mean(r_errs)) * 100, len(t_errs)


def test_run_then_eval_on_kitti_clip(shared_data, tmp_path, monkeypatch):
    gt_path = shared_data / "kitti00-f0000-0150" / "poses.txt"
    gt = read_trajectory(gt_path).poses
    lengths = [10, 20, 30, 40, 50]

    # 1) a perfect (up to similarity) strided run: zero error after 7dof
    _perturbed_run(tmp_path / "runs" / "exact", gt, 3, 0.0, 0.0)
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(main, ["eval", "--gt", str(gt_path), "--pred", "runs/exact", "--lengths", "10,20,30,40,50",
                                    "--json", "exact.json"])
    assert res.exit_code == 0, res.output
    m = json.loads((tmp_path / "exact.json").read_text())
    assert m["num_frames"] == 51 and m["t_err"] < 1e-6 and m["ate_rmse"] < 1e-6
    assert m["scale"] == pytest.approx(1 / 0.3, rel=1e-9)

    # 2) the latest run (default --pred), with 2 % scale drift and 0.002 rad/frame yaw drift
    frames, T = _perturbed_run(tmp_path / "runs" / "drift", gt, 3, 0.02, 0.002, noise=1e-4)
    os.utime(tmp_path / "runs" / "exact" / "poses.txt", (1_000_000, 1_000_000))
    res = CliRunner().invoke(main, ["eval", "--gt", str(gt_path), "--lengths", "10,20,30,40,50", "--json", "drift.json"])
    assert res.exit_code == 0, res.output
    assert "runs/drift" in res.output
    m = json.loads((tmp_path / "drift.json").read_text())
    assert m["num_frames"] == len(frames) and m["num_segments"] > 5

    # the same numbers from evo's own alignment + a loop implementation of the devkit metric
    from evo.core.trajectory import PosePath3D

    G = np.linalg.inv(gt[0]) @ gt[frames]
    P = np.linalg.inv(T[0]) @ T
    est = PosePath3D(poses_se3=list(P))
    est.align(PosePath3D(poses_se3=list(G)), correct_scale=True)
    t_ref, r_ref, n_ref = _reference_segment_metric(G, np.array(est.poses_se3), lengths)
    assert m["num_segments"] == n_ref
    assert m["t_err"] == pytest.approx(t_ref, rel=1e-6)
    assert m["r_err"] == pytest.approx(r_ref, rel=1e-6)
    # the yaw drift is 0.002 rad per kept frame; kept frames are path/50 m apart (~2.2 m),
    # so about 5.2 deg/100 m (a bit more: segments end just past L)
    per_100m = np.degrees(0.002) / (m["path_length"] / (len(frames) - 1)) * 100
    assert per_100m < m["r_err"] < 1.2 * per_100m
    assert m["t_err"] > 0.5
