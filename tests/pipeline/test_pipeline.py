"""End to end: ``trianflow-vo run`` on real frames, the run folder it writes, and its accuracy.

Accuracy bounds are ATE RMSE after a Sim(3) alignment (``trianflow_vo.eval.evaluate``, 7-DoF
Umeyama on positions) against the sequence's ground truth. Each bound sits between
what the pipeline measures now and what simple failures measure on the same ground
truth (numbers in the comments; "scale decay" = every step 7% shorter than the last,
"straight line" = constant speed, no turn, "yaw bias" = 0.5 deg/step extra rotation).
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from conftest import SAMPLE
from trianflow_vo.cli.main import main
from trianflow_vo.config import Config, load_config, merge_dict
from trianflow_vo.eval.evaluate import evaluate
from trianflow_vo.frame import FrameResult
from trianflow_vo.geometry.se3 import rotation_angle
from trianflow_vo.io.trajectory import quaternion_to_rotation, read_trajectory
from trianflow_vo.observer import Observer


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def read_poses(run_dir: Path) -> np.ndarray:
    """``(N, 4, 4)`` camera-to-world poses of ``run_dir/poses.txt`` (12 numbers a line)."""
    rows = [ln.split() for ln in (run_dir / "poses.txt").read_text().splitlines()]
    assert all(len(r) == 12 for r in rows), "poses.txt lines must have 12 numbers"
    P = np.tile(np.eye(4), (len(rows), 1, 1))
    P[:, :3, :4] = np.asarray(rows, dtype=np.float64).reshape(-1, 3, 4)
    return P


def read_frames(run_dir: Path) -> np.ndarray:
    return np.asarray((run_dir / "frames.txt").read_text().split(), dtype=np.int64)


def ate_of_run(run_dir: Path, gt_path: Path) -> dict:
    gt = read_trajectory(gt_path).poses
    return evaluate(read_poses(run_dir), read_frames(run_dir), gt, lengths=[1.0])


def run_cli(seq: Path, out: Path, *args) -> dict:
    r = invoke("run", seq, "--out", out, *args)
    assert r.exit_code == 0, r.output
    return json.loads((out / "run.json").read_text())


# --------------------------------------------------------------------------- the shipped sample


@pytest.fixture(scope="module")
def sample_stride3(tmp_path_factory) -> tuple[Path, dict]:
    """One default run of the sample at stride 3 (with the plot), shared by several tests."""
    if not SAMPLE.is_dir():
        pytest.skip(f"shipped sample missing at {SAMPLE}")
    out = tmp_path_factory.mktemp("run") / "stride3"
    return out, run_cli(SAMPLE, out, "--stride", "3")


def check_run_folder(out: Path, doc: dict, expected_frames: list[int]) -> None:
    """The outputs agree with each other and with run.json."""
    n = len(expected_frames)
    poses = read_poses(out)
    assert len(poses) == n
    assert read_frames(out).tolist() == expected_frames
    assert np.array_equal(poses[0], np.eye(4))  # first frame at identity
    # rotations stay rotations
    for T in poses:
        assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6)
        assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0, abs=1e-6)
    tum = np.loadtxt(out / "trajectory.tum", ndmin=2)
    assert tum.shape == (n, 8)
    assert tum[:, 0].tolist() == [float(f) for f in expected_frames]  # no times.txt: timestamp = frame index
    assert np.allclose(tum[:, 1:4], poses[:, :3, 3], atol=1e-6)
    for q, T in zip(tum[:, 4:8], poses):  # qx qy qz qw
        assert np.degrees(rotation_angle(quaternion_to_rotation(q).T @ T[:3, :3])) < 1e-3
    assert doc["status"] == "completed" and doc["error"] is None
    assert doc["frames_processed"] == n and doc["frames_skipped"] == 0
    counts = doc["branch_counts"]
    assert counts["init"] == 1
    assert sum(counts.values()) == n
    assert doc["sequence"]["frames_selected"] == n
    assert doc["versions"]["trianflow-vo"]
    assert doc["timing_ms_median"]["flow"] > 0
    assert doc["peak_rss_mb"] > 0
    # frames.tsv: one row per frame with the branch it took, agreeing with the counts
    import csv

    with open(out / "frames.tsv") as fh:
        rows = list(csv.DictReader(fh, delimiter="\t"))
    assert [int(r["frame"]) for r in rows] == expected_frames
    assert {b: sum(r["branch"] == b for r in rows) for b in counts} == counts
    assert all(r["reason"] for r in rows if r["branch"] not in ("two-view",))


def test_sample_stride3_outputs(sample_stride3):
    out, doc = sample_stride3
    check_run_folder(out, doc, list(range(0, 48, 3)))
    assert doc["config"]["input"]["stride"] == 3 and doc["config"]["sampling"]["seed"] == 0
    # config.yaml beside run.json holds the same effective configuration (and reproduces the run)
    assert load_config(out / "config.yaml").to_dict() == doc["config"]
    assert doc["warnings"] == {}
    # the default back-end (window bundle adjustment) revised keyframes as it went, and says so
    assert doc["backend"]["name"] == "window-ba" and doc["backend"]["failures"] == 0
    assert doc["revisions"]["count"] == doc["backend"]["revisions"] > 0
    assert doc["sequence"]["kind"] == "kitti"
    assert doc["working_size_hw"] == [256, 832]
    assert doc["flow_source"]["name"] == "dis" and doc["depth_source"] == {"name": "triangulated"}
    assert doc["branch_counts"]["failed"] == 0
    assert (out / "trajectory.png").stat().st_size > 0


def test_sample_stride3_ate(sample_stride3):
    out, _ = sample_stride3
    m = ate_of_run(out, SAMPLE / "poses.txt")
    assert m["num_frames"] == 16
    assert m["path_length"] == pytest.approx(41.65, abs=0.05)
    # Measured 0.235-0.240 m (seeds 0-3), 0.57% of the 41.7 m path. Bound 0.75% = 0.31 m:
    # this nearly straight path is forgiving -- a constant-speed straight line scores
    # 0.43 m, scale decay 1.9 m, a sign flip half-way 12.7 m.
    assert m["ate_rmse"] < 0.0075 * m["path_length"], m["ate_rmse"]


@pytest.mark.slow
def test_sample_stride1(sample_seq, tmp_path):
    out = tmp_path / "stride1"
    doc = run_cli(sample_seq, out, "--stride", "1", "--no-plot", "-q")
    check_run_folder(out, doc, list(range(48)))
    m = ate_of_run(out, sample_seq / "poses.txt")
    # Measured 0.182 m (seeds 0-1), 0.42% of the 43.7 m path; same 0.75% bound as at stride 3.
    assert m["ate_rmse"] < 0.0075 * m["path_length"], m["ate_rmse"]


def test_eval_after_run(sample_stride3, tmp_path):
    out, _ = sample_stride3
    js = tmp_path / "m.json"
    r = invoke("eval", "--gt", SAMPLE / "poses.txt", "--pred", out, "--lengths", "5,10,20", "--json", js)
    assert r.exit_code == 0, r.output
    assert "Traceback" not in r.output
    metrics = json.loads(js.read_text())
    assert metrics["num_frames"] == 16
    assert metrics["num_segments"] > 0 and metrics["t_err"] is not None
    # the eval command and the library agree
    assert metrics["ate_rmse"] == pytest.approx(ate_of_run(out, SAMPLE / "poses.txt")["ate_rmse"], rel=1e-6)


def test_same_seed_same_poses_other_seed_other_poses(sample_seq, tmp_path):
    args = ("--stride", "3", "--end", "18", "--no-plot", "-q")
    run_cli(sample_seq, tmp_path / "a", *args, "--seed", "7")
    run_cli(sample_seq, tmp_path / "b", *args, "--seed", "7")
    run_cli(sample_seq, tmp_path / "c", *args, "--seed", "8")
    a = (tmp_path / "a" / "poses.txt").read_text()
    assert a == (tmp_path / "b" / "poses.txt").read_text()
    # the seed matters (random match sampling), so the equality above is not vacuous
    assert a != (tmp_path / "c" / "poses.txt").read_text()


# --------------------------------------------------------------------------- interruption and crashes


class RaiseAt(Observer):
    """Observer raising ``exc`` when it sees its ``n``-th frame (after the writer has it)."""

    def __init__(self, n: int, exc: BaseException):
        self.n, self.exc, self.seen, self.closed = n, exc, 0, None

    def on_frame(self, rec: FrameResult) -> None:
        self.seen += 1
        if self.seen == self.n:
            raise self.exc

    def close(self, interrupted: bool = False) -> None:
        self.closed = interrupted


def _library_config() -> Config:
    return merge_dict(Config(), {"input": {"stride": 3}, "output": {"plot": False}}, "test")


def check_partial_run(out: Path, n: int, status: str) -> dict:
    poses = read_poses(out)  # every line complete: 12 numbers
    assert len(poses) == n
    assert np.isfinite(poses).all()
    assert read_frames(out).tolist() == list(range(0, 3 * n, 3))
    assert np.loadtxt(out / "trajectory.tum", ndmin=2).shape == (n, 8)
    doc = json.loads((out / "run.json").read_text())
    assert doc["status"] == status
    assert doc["frames_processed"] == n
    return doc


def test_interrupt_keeps_valid_trajectory(sample_seq, tmp_path):
    from trianflow_vo.pipeline import run

    out = tmp_path / "out"
    bomb = RaiseAt(5, KeyboardInterrupt())
    with pytest.raises(KeyboardInterrupt):
        run(sample_seq, out, _library_config(), observers=[bomb])
    doc = check_partial_run(out, 5, "interrupted")
    assert doc["error"] is None
    assert bomb.closed is True  # observers are told


def test_crash_keeps_valid_trajectory(sample_seq, tmp_path):
    from trianflow_vo.pipeline import run

    out = tmp_path / "out"
    bomb = RaiseAt(4, RuntimeError("boom"))
    with pytest.raises(RuntimeError):
        run(sample_seq, out, _library_config(), observers=[bomb])
    doc = check_partial_run(out, 4, "failed")
    assert "RuntimeError: boom" in doc["error"]
    assert bomb.closed is True  # closed as interrupted after an error too


def test_cli_interrupt_exit_130(sample_seq, tmp_path, monkeypatch):
    import trianflow_vo.pipeline

    real_run = trianflow_vo.pipeline.run

    seen = {}

    def run_with_ctrl_c(seq, out_dir, config=Config(), observers=(), **kwargs):
        seen.update(seq=seq, out_dir=out_dir, config=config)
        return real_run(seq, out_dir, config, observers=[*observers, RaiseAt(3, KeyboardInterrupt())], **kwargs)

    monkeypatch.setattr(trianflow_vo.pipeline, "run", run_with_ctrl_c)
    out = tmp_path / "out"
    r = invoke("run", sample_seq, "--stride", "3", "--out", out, "--no-plot")
    assert r.exit_code == 130, r.output
    assert "Traceback" not in r.output
    assert f"interrupted: the trajectory so far is in {out}" in r.output
    check_partial_run(out, 3, "interrupted")
    # the command passed the sequence, the folder and the flags (as config keys) to the library
    assert seen["seq"] == sample_seq and seen["out_dir"] == out
    assert seen["config"].input.stride == 3 and seen["config"].output.plot is False


# --------------------------------------------------------------------------- static camera


def test_static_camera_gives_identity(sample_seq, tmp_path):
    """The same image five times: every pose is exactly the identity, branch 'identity'."""
    seq = tmp_path / "static"
    seq.mkdir()
    img = cv2.resize(cv2.imread(str(sample_seq / "image_0" / "000010.jpg")), (384, 128), interpolation=cv2.INTER_AREA)
    for i in range(5):
        cv2.imwrite(str(seq / f"{i:04d}.png"), img)
    out = tmp_path / "out"
    doc = run_cli(seq, out, "--intrinsics", "222.4,244.7,187.9,63.0", "--no-plot")
    assert doc["branch_counts"]["identity"] == 4, doc["branch_counts"]
    poses = read_poses(out)
    assert len(poses) == 5
    assert np.array_equal(poses, np.tile(np.eye(4), (5, 1, 1)))  # not noise: exactly identity
    static = [d for d in doc["degraded"] if d["branch"] == "identity"]
    assert [d["frame"] for d in static] == [1, 2, 3, 4]
    assert all("static" in d["reason"] for d in static)
    assert doc["warnings"] == {}  # a static camera is routine (logged with -v), not a warning


# --------------------------------------------------------------------------- shared clips (skipped without ../shared)


@pytest.mark.slow
def test_kitti00_clip_stride3(shared_data, tmp_path):
    seq = shared_data / "kitti00-f0000-0150"
    out = tmp_path / "out"
    doc = run_cli(seq, out, "--stride", "3", "--no-plot", "-q")
    check_run_folder(out, doc, list(range(0, 151, 3)))
    m = ate_of_run(out, seq / "poses.txt")
    assert m["path_length"] == pytest.approx(109.9, abs=0.2)
    # Measured 0.383-0.386 m (seeds 0-2), 0.35% of the 110 m path (target 0.3%).
    # Bound 0.7% = 0.77 m: a yaw bias of 0.5 deg/step already gives 0.89 m, a
    # straight line 9.5 m, scale decay 9.8 m.
    assert m["ate_rmse"] < 0.007 * m["path_length"], m["ate_rmse"]
    # run followed by eval with no flags beyond --gt and --lengths (the latest run under ./runs/)
    import os
    import shutil

    cwd = os.getcwd()
    try:
        os.chdir(tmp_path)
        shutil.copytree(out, tmp_path / "runs" / "kitti00")
        js = tmp_path / "m.json"
        r = invoke("eval", "--gt", seq / "poses.txt", "--lengths", "10,20,30,40,50", "--json", js)
    finally:
        os.chdir(cwd)
    assert r.exit_code == 0, r.output
    metrics = json.loads(js.read_text())
    assert metrics["num_frames"] == 51 and metrics["num_segments"] > 0
    assert metrics["ate_rmse"] == pytest.approx(m["ate_rmse"], rel=1e-6)
    assert 0 < metrics["t_err"] < 5.0  # segment error in %, measured about 2-3%


@pytest.mark.slow
def test_7scenes_clip_stride2(shared_data, tmp_path):
    seq = shared_data / "7scenes-kitchen-f0000-0499"
    out = tmp_path / "out"
    doc = run_cli(seq, out, "--end", "151", "--stride", "2", "--no-plot", "-q")
    check_run_folder(out, doc, list(range(0, 151, 2)))
    assert doc["sequence"]["kind"] == "images" and doc["working_size_hw"] == [512, 640]
    assert doc["branch_counts"]["failed"] == 0
    m = ate_of_run(out, seq / "poses.txt")
    assert m["path_length"] == pytest.approx(1.04, abs=0.01)
    # Measured 0.053 / 0.024 / 0.027 m at seeds 0 / 1 / 2 (5.1% / 2.3% / 2.6% of the 1.04 m
    # path; the target is 2%). Bound 0.075 m (7.2%): 1.4x the worst seed, and below a
    # constant-speed straight line (0.084 m), scale decay (0.13 m), a sign flip half-way (0.14 m).
    assert m["ate_rmse"] < 0.075, m["ate_rmse"]
