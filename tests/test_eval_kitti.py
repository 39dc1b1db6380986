"""Eval on real KITTI data (../shared): published numbers, and the shipped-clip workflow."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from click.testing import CliRunner

from trianflow_vo.cli.main import main
from trianflow_vo.eval import evaluate_files
from trianflow_vo.io.trajectory import format_kitti_line, format_tum_line, read_trajectory

# KITTI segment metric of kitti-odometry-eval/pred/dfvo_example_1 (see ../shared/README.md)
PUBLISHED = {"09": (2.527535077, 0.287707222), "10": (2.221192217, 0.369334674)}


@pytest.mark.parametrize("seq", sorted(PUBLISHED))
def test_published_kitti_numbers(shared_data, seq):
    d = shared_data / "kitti-odometry-eval"
    m = evaluate_files(d / "pred" / "dfvo_example_1" / f"{seq}.txt", d / "gt_poses" / f"{seq}.txt").metrics
    t_ref, r_ref = PUBLISHED[seq]
    assert m["t_err"] == pytest.approx(t_ref, rel=1e-6)
    assert m["r_err"] == pytest.approx(r_ref, rel=1e-6)
    assert m["align"] == "7dof" and m["num_frames"] == m["num_gt_frames"]
    assert sum(r["num_segments"] for r in m["per_length"]) == m["num_segments"]


def test_published_numbers_through_cli(shared_data, tmp_path):
    d = shared_data / "kitti-odometry-eval"
    out = tmp_path / "m.json"
    res = CliRunner().invoke(
        main, ["eval", "--gt", str(d / "gt_poses" / "10.txt"), "--pred", str(d / "pred" / "dfvo_example_1" / "10.txt"),
               "--json", str(out)]
    )
    assert res.exit_code == 0, res.output
    m = json.loads(out.read_text())
    assert m["t_err"] == pytest.approx(PUBLISHED["10"][0], rel=1e-6)
    assert m["r_err"] == pytest.approx(PUBLISHED["10"][1], rel=1e-6)
    assert "2.2212 %" in res.output


# ----------------------------------------------------------------------------- shipped clip


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

    # the same numbers from evo's alignment + a loop implementation of the devkit metric
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
