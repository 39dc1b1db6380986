"""``benchmarks/depth_scale.py``: units per metre of a keyframe's carried depth against the ground truth."""

from __future__ import annotations

import cv2
import numpy as np
import pytest


@pytest.fixture(scope="module")
def ds(benchmark_module):
    return benchmark_module("depth_scale")


def _texture(h, w, seed=0):
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (h, w)).astype(np.float32), (0, 0), 2.0)
    return cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def test_a_plane_seen_from_a_sideways_step_gives_the_carried_units(ds):
    # a fronto-parallel plane at 2.5 m, the camera moves 6 cm to the right: the image moves
    # 12 px left (f = 500 px); the keyframe carries the plane's depth in units of 40 per metre
    h, w, f, Z, b, units = 240, 320, 500.0, 2.5, 0.06, 40.0
    img0 = _texture(h, w + 40)
    kd = ds.KeyframeDepths()
    kd.K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    kd.gray = {0: np.ascontiguousarray(img0[:, 20:20 + w]), 5: np.ascontiguousarray(img0[:, 32:32 + w])}
    kd.how = {0: "two-view", 5: "pnp"}
    idx = np.arange(0, h * w, 7)
    kd.depth = {0: (idx, np.full(idx.size, Z * units))}
    T = np.tile(np.eye(4), (6, 1, 1))
    T[5, 0, 3] = b
    rows = ds.units_per_metre(kd, T, min_baseline=0.04, min_angle=0.01)
    assert [r["keyframe"] for r in rows] == [0]
    r = rows[0]
    assert r["partner"] == 5 and r["how"] == "two-view" and r["baseline_m"] == pytest.approx(b)
    assert r["used"] > 0.8 * idx.size
    assert r["units_per_m"] == pytest.approx(units, rel=0.02)
    # no partner far enough: no measure, but the row says so
    rows = ds.units_per_metre(kd, T, min_baseline=0.5, min_angle=0.01)
    assert rows[0]["partner"] is None and rows[0]["units_per_m"] is None


def test_kitti_poses_are_checked(ds, tmp_path):
    good = tmp_path / "good.txt"
    good.write_text("1 0 0 1 0 1 0 2 0 0 1 3\n")
    T = ds.load_kitti_poses(good)
    assert T.shape == (1, 4, 4) and T[0, :3, 3].tolist() == [1.0, 2.0, 3.0] and T[0, 3, 3] == 1.0
    tum = tmp_path / "tum.txt"
    tum.write_text("0.0 1 2 3 0 0 0 1\n")
    with pytest.raises(ValueError, match="KITTI layout"):
        ds.load_kitti_poses(tum)
    from trianflow_vo.errors import InputError

    bad = tmp_path / "bad.txt"
    bad.write_text("1 2 3 4 5 6 7\n")
    with pytest.raises(InputError, match="bad.txt:1"):
        ds.load_kitti_poses(bad)
