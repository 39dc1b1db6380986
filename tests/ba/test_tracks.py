"""Tracks of the back-end: sub-pixel flow sampling, ending rules, spawning, bookkeeping."""

import numpy as np
import pytest

from trianflow_vo.ba.tracks import TrackTable, sample_bilinear, texture_score
from trianflow_vo.geometry.fundamental import fundamental_from_pose

H, W = 64, 96
K = np.array([[80.0, 0.0, 48.0], [0.0, 80.0, 32.0], [0.0, 0.0, 1.0]])


def test_sample_bilinear_is_exact_on_a_linear_field():
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    field = np.stack([2 * xx + 1, -yy + 0.5 * xx, xx * 0 + 7, yy, xx], axis=-1)  # 5 channels: two remap calls
    pts = np.array([[0.0, 0.0], [10.25, 3.5], [W - 1.0, H - 1.0], [50.75, 40.125], [-1.0, 3.0], [3.0, H - 0.5]])
    v, inside = sample_bilinear(field, pts)
    assert inside.tolist() == [True, True, True, True, False, False]
    x, y = pts[:4, 0], pts[:4, 1]
    expect = np.stack([2 * x + 1, -y + 0.5 * x, 7 + 0 * x, y, x], 1)
    np.testing.assert_allclose(v[:4], expect, atol=1e-4)
    assert np.all(v[4:] == 0)
    with pytest.raises(ValueError):
        sample_bilinear(field, np.zeros(3))


def _flows(dx, dy):
    fw = np.zeros((H, W, 2), np.float32)
    fw[..., 0], fw[..., 1] = dx, dy
    return fw, -fw


def _F_for_shift():
    """A fundamental matrix of a sideways step (epipolar lines horizontal): a horizontal shift is consistent."""
    return fundamental_from_pose(np.eye(3), np.array([1.0, 0.0, 0.0]), K)


def _grid_candidates(step=8.0):
    ys, xs = np.mgrid[4:H - 4:step, 4:W - 4:step]
    return np.stack([xs.ravel(), ys.ravel()], 1).astype(float)


def test_tracks_follow_the_flow_subpixel_and_keep_their_ids():
    tt = TrackTable((H, W), cell_px=16, max_tracks=100, fb_px=0.5, epi_px=0.5)
    c = _grid_candidates()
    fw, bw = _flows(1.25, 0.0)
    up = tt.advance(0, 1, fw, bw, _F_for_shift(), c, c + [1.25, 0.0], np.ones((len(c), 3)))
    assert up.born == len(tt) > 0 and up.continued == 0
    ids0, pts0 = tt.ids.copy(), tt.pts.copy()
    # keyframe 0 holds the birth pixels, keyframe 1 the flow end points
    ids_a, pts_a = tt.obs[0]
    np.testing.assert_array_equal(ids_a, ids0)
    np.testing.assert_allclose(tt.obs[1][1], pts0)
    np.testing.assert_allclose(pts_a + [1.25, 0.0], pts0)
    up2 = tt.advance(1, 2, fw, bw, _F_for_shift(), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 3)))
    alive = np.isin(ids0, tt.ids)
    assert up2.continued == alive.sum() and up2.born == 0
    np.testing.assert_allclose(tt.pts, pts0[alive] + [1.25, 0.0], atol=1e-4)
    assert up2.left_image == (~alive).sum()  # only those that reached the right border ended


def test_inconsistent_flow_and_epipolar_outliers_end_tracks():
    tt = TrackTable((H, W), cell_px=16, max_tracks=100, fb_px=0.5, epi_px=0.5, margin_px=0.0)
    c = _grid_candidates()
    fw, bw = _flows(1.0, 0.0)
    tt.advance(0, 1, fw, bw, _F_for_shift(), c, c + [1.0, 0.0], np.ones((len(c), 3)))
    n = len(tt)
    # backward flow disagrees on the left half of the image, forward flow goes vertical on the bottom band
    fw2, bw2 = _flows(1.0, 0.0)
    bw2[:, : W // 2] = 0.0
    fw2[H - 20:, W // 2:] = (0.0, 2.0)
    bw2[H - 20:, W // 2:] = (0.0, -2.0)
    up = tt.advance(1, 2, fw2, bw2, _F_for_shift(), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 3)))
    assert up.inconsistent > 0 and up.epipolar_outliers > 0
    assert up.continued + up.inconsistent + up.epipolar_outliers + up.left_image == n
    assert np.all(tt.pts[:, 0] >= W // 2)  # the survivors are all on the consistent right side
    # without an epipolar geometry (a step without translation) nothing ends for it
    tt2 = TrackTable((H, W), cell_px=16, max_tracks=100, fb_px=0.5, epi_px=0.5, margin_px=0.0)
    tt2.advance(0, 1, fw, bw, None, c, c + [1.0, 0.0], np.ones((len(c), 3)))
    up = tt2.advance(1, 2, fw2, -fw2, None, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 3)))
    assert up.epipolar_outliers == 0


def test_spawning_fills_empty_cells_only_up_to_max_tracks():
    tt = TrackTable((H, W), cell_px=32, max_tracks=5)
    c = _grid_candidates(4.0)
    fw, bw = _flows(0.0, 0.0)
    up = tt.advance(0, 1, fw, bw, None, c, c, np.ones((len(c), 3)))
    assert up.born == 5 and len(tt) == 5
    cells = {(int(x // 32), int(y // 32)) for x, y in tt.pts}
    assert len(cells) == 5  # one per cell
    tt = TrackTable((H, W), cell_px=32, max_tracks=100)
    tt.advance(0, 1, fw, bw, None, c, c, np.ones((len(c), 3)))
    assert len(tt) == 2 * 3  # a 2x3 grid of 32 px cells over 64x96
    up = tt.advance(1, 2, fw, bw, None, c, c, np.ones((len(c), 3)))
    assert up.born == 0  # every cell still has its track
    with pytest.raises(ValueError):
        tt.advance(5, 6, fw, bw, None, c, c, np.ones((len(c), 3)))  # not the newest keyframe


def test_landmarks_end_and_forget():
    tt = TrackTable((H, W), cell_px=16, max_tracks=100)
    c = _grid_candidates()
    X = np.arange(len(c) * 3, dtype=float).reshape(-1, 3)
    fw, bw = _flows(0.5, 0.0)
    tt.advance(0, 1, fw, bw, None, c, c + [0.5, 0], X)
    tid = int(tt.ids[0])
    np.testing.assert_allclose(tt.landmarks[tid], X[0])
    tt.end(np.array([tid]))
    assert tid not in tt.ids and tid not in tt.landmarks and all(tid not in o[0] for o in tt.obs.values())
    tt.advance(1, 2, fw, bw, None, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 3)))
    tt.forget([1, 2])
    assert set(tt.obs) == {1, 2}
    tt.forget([2])
    seen = set(tt.obs[2][0].tolist())
    assert set(tt.landmarks) == seen


def test_texture_score_ranks_a_corner_over_an_edge_over_a_flat_area():
    img = np.zeros((H, W), np.uint8)
    img[32:, 48:] = 200  # one bright quadrant: a corner at (48, 32), edges along x = 48 and y = 32
    pts = np.array([[48.0, 32.0], [48.0, 50.0], [70.0, 32.0], [15.0, 10.0], [80.0, 55.0]])
    sc = texture_score(img, pts, 9)
    corner, edge_v, edge_h, flat_dark, flat_bright = sc
    assert corner > 10 * max(edge_v, edge_h)  # a straight edge pins a patch in one direction only
    assert flat_dark == 0.0 and flat_bright == 0.0
    assert edge_v >= 0.0 and edge_h >= 0.0
    bgr = np.repeat(img[..., None], 3, axis=2)
    np.testing.assert_allclose(texture_score(bgr, pts, 9), sc)  # a BGR image scores as its grey
    np.testing.assert_allclose(texture_score(img, pts + 0.3, 9), sc)  # rounded to the pixel
    assert texture_score(img, np.array([[-5.0, 500.0]]), 9).shape == (1,)  # clamped, not an error
    with pytest.raises(ValueError):
        texture_score(img, pts, 0)
    with pytest.raises(ValueError):
        texture_score(img, pts[:, 0], 9)


def test_spawning_takes_the_best_scored_candidate_of_each_cell():
    fw, bw = _flows(0.0, 0.0)
    c = _grid_candidates(4.0)  # many candidates per 32 px cell
    rng = np.random.default_rng(3)
    score = rng.random(len(c))
    tt = TrackTable((H, W), cell_px=32, max_tracks=100)
    tt.advance(0, 1, fw, bw, None, c, c, np.ones((len(c), 3)), cand_score=score)
    cell = (c[:, 1] // 32).astype(int) * 3 + (c[:, 0] // 32).astype(int)
    best = {k: c[np.flatnonzero(cell == k)[np.argmax(score[cell == k])]] for k in range(6)}
    got = {int(y // 32) * 3 + int(x // 32): (x, y) for x, y in tt.pts}
    assert sorted(got) == list(range(6))
    for k in range(6):
        assert tuple(best[k]) == got[k]
    # short of room: the best cells' winners first
    tt = TrackTable((H, W), cell_px=32, max_tracks=2)
    tt.advance(0, 1, fw, bw, None, c, c, np.ones((len(c), 3)), cand_score=score)
    winners = sorted((score[cell == k].max(), k) for k in range(6))[::-1]
    assert {int(y // 32) * 3 + int(x // 32) for x, y in tt.pts} == {winners[0][1], winners[1][1]}
    # without scores: the first candidate drawn in each cell, as before
    tt = TrackTable((H, W), cell_px=32, max_tracks=100)
    tt.advance(0, 1, fw, bw, None, c, c, np.ones((len(c), 3)))
    first = {k: c[np.flatnonzero(cell == k)[0]] for k in range(6)}
    got = {int(y // 32) * 3 + int(x // 32): (x, y) for x, y in tt.pts}
    assert all(tuple(first[k]) == got[k] for k in range(6))
