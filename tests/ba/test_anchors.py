"""Revisit anchors: the predicted flow, its inversion, the links, the candidates and the archive."""

import cv2
import numpy as np
import pytest

from trianflow_vo.ba.anchors import (AnchorArchive, Archived, invert_flow_at, link_points, predicted_flow,
                                     revisit_candidates, warp_to_new)
from trianflow_vo.ba.graph import project
from trianflow_vo.ba.tracks import TrackTable, follow_flow, sample_bilinear
from trianflow_vo.geometry.se3 import invert_T

H, W = 120, 160
K = np.array([[150.0, 0.0, 80.0], [0.0, 150.0, 60.0], [0.0, 0.0, 1.0]])


def _pose(yaw_deg=0.0, t=(0.0, 0.0, 0.0)):
    a = np.radians(yaw_deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[:3, 3] = t
    return T


def _plane_points(T_world_cam, depth, n=300, seed=0):
    """Pixels of the camera ``T_world_cam`` and the world points at ``depth`` along their rays."""
    rng = np.random.default_rng(seed)
    uv = np.c_[rng.uniform(5, W - 6, n), rng.uniform(5, H - 6, n)]
    Xc = np.c_[uv, np.ones(n)] @ np.linalg.inv(K).T * depth
    return uv, Xc @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]


def test_predicted_flow_is_exact_for_a_fronto_parallel_plane():
    T_old, T_new = _pose(), _pose(4.0, (0.3, -0.1, 0.2))
    uv, X = _plane_points(T_old, 4.0)
    flow = predicted_flow(K, invert_T(T_new) @ T_old, uv, np.full(len(uv), 4.0), (H, W), cell_px=16)
    f, _ = sample_bilinear(flow, uv)
    expect, _ = project(K, T_new, X)
    # float32 flow sampled bilinearly at sub-pixel points of a projective field: a few 1e-3 px
    np.testing.assert_allclose(uv + f, expect, atol=5e-3)
    # every pixel moves as the plane predicts, not only the sampled ones
    yy, xx = np.mgrid[0:H:7, 0:W:9]
    g = np.c_[xx.ravel(), yy.ravel()].astype(float)
    Xg = np.c_[g, np.ones(len(g))] @ np.linalg.inv(K).T * 4.0
    pg, _ = project(K, T_new, Xg @ T_old[:3, :3].T + T_old[:3, 3])
    # interpolated between samples every 4 px (second-order error of a projective field: a few 1e-3 px) ...
    np.testing.assert_allclose(g + flow[yy.ravel(), xx.ravel()], pg, atol=5e-3)
    # ... and exact at every pixel when computed at every pixel
    full = predicted_flow(K, invert_T(T_new) @ T_old, uv, np.full(len(uv), 4.0), (H, W), cell_px=16, step=1)
    np.testing.assert_allclose(g + full[yy.ravel(), xx.ravel()], pg, atol=1e-3)
    assert np.abs(full - flow).max() < 5e-3


def test_invert_flow_at_solves_the_fixed_point():
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    bw = np.stack([0.05 * xx - 3.0, -0.03 * yy + 2.0], axis=-1)  # smooth, contracting
    y_true = np.array([[20.0, 30.0], [100.5, 70.25], [140.0, 100.0]])
    f, _ = sample_bilinear(bw, y_true)
    uv_old = y_true + f
    y = invert_flow_at(bw, uv_old, uv_old.copy())
    np.testing.assert_allclose(y, y_true, atol=1e-3)
    # a start that leaves the image is nan, not a wrong pixel
    assert np.isnan(invert_flow_at(bw, np.array([[-500.0, 5.0]]), np.array([[-500.0, 5.0]]))).all()


def _texture(seed=0):
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (H, W)).astype(np.float32), (0, 0), 1.5)
    return np.clip((img - img.mean()) * 3 + 128, 0, 255).astype(np.uint8)


def test_links_through_a_warp_recover_a_turned_zoomed_view_and_the_gate_drops_wrong_points():
    old = _texture()
    # the new view: the old one turned by 25 degrees, 1.3x nearer and moved by (6, -4) px about the centre
    A = cv2.getRotationMatrix2D((W / 2, H / 2), 25.0, 1.3)
    A[:, 2] += [6.0, -4.0]
    new = cv2.warpAffine(old, A, (W, H), borderMode=cv2.BORDER_REFLECT)
    rng = np.random.default_rng(1)
    uv_old = np.c_[rng.uniform(55, W - 55, 120), rng.uniform(40, H - 40, 120)]
    truth = uv_old @ A[:, :2].T + A[:, 2]
    # the poses' prediction is 3 px off (drift): the flow between the warped old image and the new one finds the rest
    Ainv = cv2.invertAffineTransform(A)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    g = np.stack([xx, yy], axis=-1)
    bw0 = (g @ Ainv[:, :2].T + Ainv[:, 2] + [3.0, -2.0] - g).astype(np.float32)  # new -> old, 3 px off
    warped = warp_to_new(old, bw0)
    start = invert_flow_at(bw0, uv_old, truth)
    np.testing.assert_allclose(start, truth - np.array([3.0, -2.0]) @ A[:, :2].T, atol=0.05)  # where the warp put them
    uv_pred = truth + rng.normal(0, 2.0, truth.shape)
    uv_pred[:10] += 60.0  # ten points the poses put far away: the gate drops them
    from trianflow_vo.flow.dis import DisFlow

    dis = DisFlow("medium")
    uv_new, inside, fb = follow_flow(*dis.flow_pair(warped, new), start)
    followed = inside & (fb < 1.0)
    ok = link_points(uv_old, uv_new, followed, uv_pred, ransac_px=1.0, gate_px=20.0)
    assert followed[:10].all() and not ok[:10].any()
    assert ok[10:].mean() > 0.8
    err = np.linalg.norm(uv_new[ok] - truth[ok], axis=1)
    assert np.median(err) < 0.3 and err.max() < 1.5
    # without the warp, the flow between the turned and zoomed views: few follow to the right pixel
    raw, inside_raw, fb_raw = follow_flow(*dis.flow_pair(old, new), uv_old)
    right = inside_raw & (fb_raw < 1.0) & (np.linalg.norm(raw - truth, axis=1) < 1.0)
    assert right.sum() < 0.3 * len(truth)
    # rows that cannot be followed (non-finite, outside, or leaving the image) are invalid, not wrong pixels
    out = np.zeros((H, W, 2), np.float32)
    out[..., 0] = 30.0
    moved, inside, fb = follow_flow(out, -out, np.array([[np.nan, 5.0], [-3.0, 5.0], [W + 2.0, 5.0],
                                                        [W - 10.0, 5.0], [10.0, 5.0]]))
    assert inside.tolist() == [False, False, False, False, True]
    assert np.isinf(fb[:4]).all() and fb[4] == 0.0 and np.isnan(moved[0]).all()
    # a margin: landing within 3 px of the border is not inside
    _, inside_m, _ = follow_flow(out, -out, np.array([[W - 32.0, 5.0], [W - 34.0, 5.0]]), margin_px=3.0)
    assert inside_m.tolist() == [False, True]


def _archived(index, T, X, uv, path):
    return Archived(index, np.zeros((H, W), np.uint8), T, uv, X, path)


def test_revisit_candidates_need_a_return_the_same_view_and_points_in_sight():
    T0 = _pose()
    uv, X = _plane_points(T0, 5.0)
    arc = AnchorArchive(10)
    arc.add(_archived(0, T0, X, uv, 0.0))
    args = (K, (H, W), 30.0, 0.5, 40)
    # a straight drive 2 m ahead: as far as the path travelled -> not a revisit
    assert revisit_candidates(arc, _pose(0, (0, 0, 2.0)), 2.0, *args) == []
    # back near the old keyframe after a 4 m loop: a revisit
    got = revisit_candidates(arc, _pose(3.0, (0.2, 0, 0.1)), 4.0, *args)
    assert [k for k, _ in got] == [0]
    # the same place looking 60 degrees away is not
    assert revisit_candidates(arc, _pose(60.0, (0.2, 0, 0.1)), 4.0, *args) == []
    # ... nor with the ratio loosened but the parallax limit tight
    assert revisit_candidates(arc, _pose(0, (1.0, 0, 0)), 4.0, K, (H, W), 30.0, 0.5, 40, max_parallax_px=5.0) == []
    # a ratio of 1 takes any old keyframe in view, even on a straight drive
    assert [k for k, _ in revisit_candidates(arc, _pose(0, (0, 0, 2.0)), 2.0, K, (H, W), 30.0, 1.0, 40)] == [0]
    # 2.5 m nearer to a plane 5 m away: the points' depths halve; not linked when zoom is capped at 1.25x
    near = _pose(0, (0, 0, 2.5))
    assert [k for k, _ in revisit_candidates(arc, near, 2.5, K, (H, W), 30.0, 1.0, 40)] == [0]
    assert revisit_candidates(arc, near, 2.5, K, (H, W), 30.0, 1.0, 40, max_zoom=1.25) == []
    assert [k for k, _ in revisit_candidates(arc, near, 2.5, K, (H, W), 30.0, 1.0, 40, max_zoom=2.1)] == [0]
    # ... the same cap either way: 2.5 m farther is zoom 1.5
    far = _pose(0, (0, 0, -2.5))
    assert revisit_candidates(arc, far, 2.5, K, (H, W), 30.0, 1.0, 40, max_zoom=1.25) == []
    assert [k for k, _ in revisit_candidates(arc, far, 2.5, K, (H, W), 30.0, 1.0, 40, max_zoom=1.55)] == [0]
    # an old keyframe whose tracks still reach the newest keyframe is already linked: skipped at max_shared
    tracked = AnchorArchive(10)
    tracked.add(Archived(0, np.zeros((H, W), np.uint8), T0, uv, X, 0.0, np.arange(len(uv))))
    live = np.arange(250, 400)  # 50 of its 300 tracks are live
    args1 = (_pose(0, (0, 0, 0.5)), 0.5, K, (H, W), 30.0, 1.0, 40)
    assert [k for k, _ in revisit_candidates(tracked, *args1, live_ids=live, max_shared=51)] == [0]
    assert revisit_candidates(tracked, *args1, live_ids=live, max_shared=50) == []
    assert [k for k, _ in revisit_candidates(tracked, *args1, live_ids=live)] == [0]  # no limit
    # oldest first
    arc.add(_archived(5, _pose(0, (0.05, 0, 0)), X, uv, 1.0))
    got = revisit_candidates(arc, _pose(2.0, (0.1, 0, 0)), 4.0, *args)
    assert [k for k, _ in got] == [0, 5]


def test_the_archive_is_bounded_and_drops_the_most_redundant_view():
    arc = AnchorArchive(3)
    z = np.zeros((0, 3))
    for k, x in [(0, 0.0), (1, 1.0), (2, 1.05), (3, 3.0)]:
        arc.add(_archived(k, _pose(0, (x, 0, 0)), z, np.zeros((0, 2)), x))
    assert len(arc) == 3 and sorted(arc.items) == [0, 2, 3]  # 1 and 2 were nearly one view: the older went
    with pytest.raises(ValueError):
        AnchorArchive(0)


def test_attach_links_an_old_keyframe_into_the_newest():
    tt = TrackTable((H, W), cell_px=16, max_tracks=50)
    fw = np.zeros((H, W, 2), np.float32)
    c = np.array([[20.0, 20.0], [60.0, 40.0]])
    tt.advance(0, 1, fw, fw, None, c, c, np.ones((2, 3)))
    ids = tt.attach(-7, np.array([[5.0, 6.0]]), 1, np.array([[30.0, 30.0]]), np.array([[1.0, 2.0, 3.0]]))
    assert ids.tolist() == [2]
    assert tt.obs[-7][0].tolist() == [2] and tt.obs[1][0].tolist() == [0, 1, 2]
    np.testing.assert_allclose(tt.obs[1][1][-1], [30, 30])
    np.testing.assert_allclose(tt.landmarks[2], [1, 2, 3])
    assert len(tt) == 2  # not followed further: the live tracks are the two born ones
    # once the old keyframe is forgotten the link is gone with it
    tt.forget([1])
    assert -7 not in tt.obs
    with pytest.raises(ValueError, match="not 0"):
        tt.attach(-7, np.zeros((1, 2)), 0, np.zeros((1, 2)), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="one row per track"):
        tt.attach(-7, np.zeros((2, 2)), 1, np.zeros((1, 2)), np.zeros((1, 3)))
