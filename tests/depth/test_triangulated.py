"""The weight-free depth prior: tracks splatted to a sparse map, made once per keyframe."""

from __future__ import annotations

import numpy as np
import pytest

import trianflow_vo.depth.triangulated as triangulated
from trianflow_vo.depth.base import ReferenceDepth
from trianflow_vo.depth.triangulated import TriangulatedDepth, splat_tracks
from trianflow_vo.keyframe import Keyframe, Tracks

SIZE = (10, 20)  # (h, w)


def tracks(pts, depth, weight, ids=None) -> Tracks:
    n = len(depth)
    return Tracks(np.arange(100, 100 + n) if ids is None else ids, np.asarray(pts, float), depth, weight)


def keyframe(index: int, trk: Tracks) -> Keyframe:
    return Keyframe(index, np.zeros((*SIZE, 3), np.uint8), None, np.eye(4), trk)


# --------------------------------------------------------------------------- splat_tracks
@pytest.mark.parametrize("order", [[0, 1, 2], [1, 0, 2], [2, 1, 0]], ids=["heavy-last", "heavy-first", "reversed"])
def test_highest_weight_wins_a_shared_pixel(order):
    pts = np.array([[3.2, 4.6], [3.4, 4.8], [15.0, 2.0]])  # the first two round to (x=3, y=5)
    depth = np.array([5.0, 7.0, 9.0])
    weight = np.array([1.0, 2.0, 1.0])
    ids = np.array([11, 22, 33])
    o = np.array(order)
    d, w, i = splat_tracks(Tracks(ids[o], pts[o], depth[o], weight[o]), SIZE)
    assert d.shape == w.shape == i.shape == SIZE
    assert d.dtype == np.float32 and w.dtype == np.float32 and i.dtype == np.int64
    # the winner's depth, weight and id, whatever the order of the tracks
    assert d[5, 3] == 7.0 and w[5, 3] == 2.0 and i[5, 3] == 22
    assert d[2, 15] == 9.0 and w[2, 15] == 1.0 and i[2, 15] == 33
    assert (d > 0).sum() == 2 and (w > 0).sum() == 2 and (i >= 0).sum() == 2
    # no track: depth 0, weight 0, id -1
    empty = np.ones(SIZE, bool)
    empty[5, 3] = empty[2, 15] = False
    assert (d[empty] == 0).all() and (w[empty] == 0).all() and (i[empty] == -1).all()


def test_outside_the_image_and_bad_depths_are_ignored():
    h, w = SIZE
    pts = [[-1.0, 0.0],  # left of the image
           [0.0, -0.6],  # rounds to row -1
           [w - 0.4, 3.0],  # rounds to column w
           [3.0, h - 0.5 + 1e-6],  # rounds to row h
           [1.0, 1.0],  # NaN depth
           [2.0, 2.0],  # negative depth
           [3.0, 3.0],  # zero depth
           [4.0, 4.0],  # infinite depth
           [w - 0.6, h - 0.6]]  # the last pixel: kept
    depth = np.array([1.0, 1.0, 1.0, 1.0, np.nan, -1.0, 0.0, np.inf, 4.0])
    d, wt, ids = splat_tracks(tracks(pts, depth, np.full(9, 5.0)), SIZE)
    assert (d > 0).sum() == 1 and (wt > 0).sum() == 1 and (ids >= 0).sum() == 1
    assert d[h - 1, w - 1] == 4.0 and ids[h - 1, w - 1] == 108
    assert np.isfinite(d).all()
    # a bad track on a pixel does not hide a good one there, even with a higher weight
    d2, _, ids2 = splat_tracks(tracks([[1.0, 1.0], [1.0, 1.0]], np.array([np.nan, 3.0]), np.array([9.0, 1.0]),
                                      ids=np.array([1, 2])), SIZE)
    assert d2[1, 1] == 3.0 and ids2[1, 1] == 2


def test_ids_are_carried_to_their_pixels():
    rng = np.random.default_rng(0)
    flat = rng.choice(SIZE[0] * SIZE[1], 30, replace=False)  # distinct pixels
    yx = np.stack(np.unravel_index(flat, SIZE), 1)
    pts = yx[:, ::-1] + rng.uniform(-0.45, 0.45, (30, 2))  # (x, y), sub-pixel
    ids = rng.permutation(1000)[:30]
    depth = rng.uniform(1, 50, 30)
    d, w, imap = splat_tracks(Tracks(ids, pts, depth, np.ones(30)), SIZE)
    np.testing.assert_array_equal(imap[yx[:, 0], yx[:, 1]], ids)
    np.testing.assert_allclose(d[yx[:, 0], yx[:, 1]], depth.astype(np.float32))
    assert (imap >= 0).sum() == 30


def test_no_tracks_give_empty_maps():
    d, w, i = splat_tracks(Tracks.empty(), SIZE)
    assert not d.any() and not w.any() and (i == -1).all()


# --------------------------------------------------------------------------- TriangulatedDepth.reference
def test_reference_is_none_without_tracks():
    prior = TriangulatedDepth(SIZE)
    assert prior.reference(keyframe(0, Tracks.empty())) is None
    assert prior.describe() == {"name": "triangulated"}


def test_reference_is_the_sparse_map_with_weights_and_ids():
    trk = tracks([[3.2, 4.6], [3.4, 4.8], [15.0, 2.0]], np.array([5.0, 7.0, 9.0]), np.array([1.0, 2.0, 1.0]))
    ref = TriangulatedDepth(SIZE).reference(keyframe(4, trk))
    assert isinstance(ref, ReferenceDepth)
    assert ref.sparse is True  # only some pixels have depth: worth sampling on purpose
    d, w, i = splat_tracks(trk, SIZE)
    np.testing.assert_array_equal(ref.depth, d)
    np.testing.assert_array_equal(ref.weight, w)
    np.testing.assert_array_equal(ref.track_ids, i)
    assert ref.track_ids[5, 3] == 101


def test_reference_is_computed_once_per_keyframe(monkeypatch):
    calls = []
    real = triangulated.splat_tracks

    def counting(trk, size_hw):
        calls.append(size_hw)
        return real(trk, size_hw)

    monkeypatch.setattr(triangulated, "splat_tracks", counting)
    prior = TriangulatedDepth(SIZE)
    trk = tracks([[1.0, 1.0], [5.0, 5.0]], np.array([2.0, 3.0]), np.ones(2))
    kf = keyframe(3, trk)
    first = prior.reference(kf)
    assert prior.reference(kf) is first  # every frame solved against this keyframe asks again
    moved = np.eye(4)
    moved[0, 3] = 1.0
    assert prior.reference(kf.with_pose(moved)) is first  # a revised pose: same tracks, same map
    assert calls == [SIZE]
    # the next keyframe has its own map
    trk2 = tracks([[7.0, 2.0]], np.array([4.0]), np.ones(1))
    second = prior.reference(keyframe(6, trk2))
    assert len(calls) == 2 and second is not first
    assert second.depth[2, 7] == 4.0 and (second.depth > 0).sum() == 1
    assert prior.reference(keyframe(6, trk2)) is second
    assert len(calls) == 2
