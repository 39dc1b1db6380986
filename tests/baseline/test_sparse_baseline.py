"""The sparse (Shi-Tomasi + LK) baseline: depth fusion rule, and a short real run."""

from __future__ import annotations

import json

import numpy as np
import pytest

from trianflow_vo.baseline.sparse import SparseOdometry, run_sparse
from trianflow_vo.camera import PinholeCamera
from trianflow_vo.config import Config
from trianflow_vo.depth.fusion import fuse_log_depth
from trianflow_vo.eval import load_ground_truth
from trianflow_vo.eval.evaluate import evaluate
from trianflow_vo.frame import Branch
from trianflow_vo.io.trajectory import read_trajectory


def test_fuse_log_depth_weighted_mean_in_log():
    d_ref = np.array([2.0, 0.0, 2.0])
    w_ref = np.array([1.0, 0.0, 3.0])
    d_new = np.array([2.2, 5.0, 10.0])  # the last disagrees by far more than exp(0.3): not fused
    w_new = np.array([3.0, 2.0, 1.0])
    d, w = fuse_log_depth(d_ref, w_ref, d_new, w_new)
    assert d[0] == pytest.approx(np.exp((np.log(2.0) + 3.0 * np.log(2.2)) / 4.0))
    assert w[0] == pytest.approx(4.0)
    assert d[1] == pytest.approx(5.0) and w[1] == pytest.approx(2.0)  # no carried depth
    assert d[2] == pytest.approx(10.0) and w[2] == pytest.approx(1.0)


def test_rejects_bad_K():
    # the odometry takes a PinholeCamera now; the camera is what rejects a bad K
    with pytest.raises(ValueError, match="K must be"):
        SparseOdometry(PinholeCamera(np.eye(2), (256, 832)))


def test_static_images_give_identity():
    rng = np.random.default_rng(0)
    img = (rng.uniform(0, 255, (64, 32)).repeat(4, 0).repeat(4, 1)).astype(np.uint8)  # (256, 128) blocky texture
    K = np.array([[200.0, 0.0, 64.0], [0.0, 200.0, 128.0], [0.0, 0.0, 1.0]])
    odo = SparseOdometry(PinholeCamera(K, img.shape), Config())
    recs = [odo.step(i, None, img) for i in range(3)]
    assert [r.branch for r in recs] == [Branch.INIT, Branch.IDENTITY, Branch.IDENTITY]
    assert [r.ref_index for r in recs] == [None, 0, 0] and [r.is_keyframe for r in recs] == [True, False, False]
    for r in recs:
        np.testing.assert_array_equal(r.T_world_cam, np.eye(4))
    assert recs[1].stats.tracks > 100 and recs[1].stats.mean_flow_px == pytest.approx(0.0, abs=1e-3)


def test_sample_one_pose_per_frame_and_sane(sample_seq, tmp_path):
    summary = run_sparse(sample_seq, tmp_path / "run", end=10)
    poses = read_trajectory(tmp_path / "run" / "poses.txt").poses
    frames = np.loadtxt(tmp_path / "run" / "frames.txt", dtype=np.int64)
    assert poses.shape == (10, 4, 4)
    np.testing.assert_array_equal(frames, np.arange(10))
    np.testing.assert_allclose(poses[0], np.eye(4))
    counts = summary["branch_counts"]
    assert sum(counts.values()) == 10
    assert counts.get("two-view", 0) >= 7  # KITTI driving: two-view geometry nearly always
    doc = json.loads((tmp_path / "run" / "run.json").read_text())  # the same run folder as the dense path
    assert doc["status"] == "completed" and doc["odometry"] == "sparse"
    assert doc["config"]["input"]["end"] == 10 and doc["config"]["output"]["plot"] is False
    gt = load_ground_truth(sample_seq / "poses.txt")
    m = evaluate(poses, frames, gt.poses, gt.frames, lengths=[1.0])
    # about 8 m of straight driving: measured 0.9% of the path after Sim(3); a broken tracker is far off
    assert m["ate_rmse"] < 0.03 * m["path_length"]
    # forward motion along +z of the camera, not sideways
    t = poses[-1][:3, 3]
    assert abs(t[2]) > 2.0 * np.hypot(t[0], t[1])
