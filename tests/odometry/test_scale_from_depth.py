"""``scale.source = depth`` (the authors' recipe) on the synthetic box with a perfect depth network.

With the network giving the true depth of every frame, each step's scale is metric:
the recovered translation must equal the true one, on the two-view path (large
flow) and on the PnP path (small flow).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_odometry_synthetic import CAMERA, H, W, BoxFlow, box_depth, trajectory

from trianflow_vo.config import Config, ConfigError, merge_dict
from trianflow_vo.depth.network import NetworkDepth
from trianflow_vo.frame import Branch
from trianflow_vo.geometry.scale import fit_scale_ransac
from trianflow_vo.geometry.se3 import invert_T, rotation_angle
from trianflow_vo.odometry import Odometry


class TrueDepthNet:
    """A 'network' returning the box's true depth; the frame index is written in pixel (0, 0)."""

    def __init__(self, poses):
        self.poses = poses
        self.calls = 0

    def predict(self, image: np.ndarray) -> np.ndarray:
        self.calls += 1
        return box_depth(self.poses[int(image[0, 0, 0])]).astype(np.float32)

    def describe(self) -> dict:
        return {"name": "true-depth"}


def _run(poses):
    cfg = merge_dict(Config(), {"scale": {"source": "depth"}, "depth": {"model": "unused.onnx"}}, "test")
    net = TrueDepthNet(poses)
    odo = Odometry(CAMERA, BoxFlow(poses), NetworkDepth(net), cfg)
    out = []
    for i in range(len(poses)):
        img = np.zeros((H, W, 3), np.uint8)
        img[0, 0, 0] = i
        out.append(odo.step(i, None, img))
    return out, net


@pytest.mark.parametrize("step, branch", [(1.5, Branch.TWO_VIEW), (0.03, Branch.PNP)])
def test_metric_steps_from_true_depth(step, branch):
    poses = trajectory([([0.0, 0.01, 0.0], [0.05, 0.0, step])] * 4)
    results, net = _run(poses)
    assert [r.branch for r in results[1:]] == [branch] * 4, [r.reason for r in results]
    for k in range(1, len(poses)):
        true_rel = invert_T(poses[k - 1]) @ poses[k]
        est_rel = invert_T(results[k - 1].T_world_cam) @ results[k].T_world_cam
        # every frame is the next reference (frame to frame, as the authors)
        assert results[k].ref_index == k - 1 and results[k].is_keyframe
        assert np.linalg.norm(est_rel[:3, 3] - true_rel[:3, 3]) < 0.01 * np.linalg.norm(true_rel[:3, 3])
        assert rotation_angle(est_rel[:3, :3].T @ true_rel[:3, :3]) < 1e-3
    assert net.calls == len(poses)  # each frame's depth computed once


def test_depth_source_needs_a_depth_network():
    cfg = merge_dict(Config(), {"scale": {"source": "depth"}}, "test")
    with pytest.raises(ConfigError, match=r"scale.source.*depth.model"):
        Odometry(CAMERA, BoxFlow([np.eye(4)]), NetworkDepth(TrueDepthNet([np.eye(4)])), cfg)


def test_fit_scale_ransac_ignores_outliers():
    rng = np.random.default_rng(1)
    z = rng.uniform(1, 20, 500)
    d = 2.5 * z + rng.normal(0, 0.1, 500)
    d[:150] = rng.uniform(0.1, 100, 150)  # 30% gross outliers
    s, ok = fit_scale_ransac(z, d, threshold=1.0, trials=100, min_points=100, rng=rng)
    assert ok and s == pytest.approx(2.5, rel=2e-3)
    assert fit_scale_ransac(z[:100], d[:100], min_points=100) == (1.0, False)  # needs more than min_points
    assert not fit_scale_ransac(np.full(200, -1.0), d[:200])[1]
