"""NetworkDepth: a depth network's prediction of each keyframe, cached by frame index.

A fake network counts its calls (no ONNX): the cache is the prior's, not the network's.
"""

from __future__ import annotations

import numpy as np
import pytest

from trianflow_vo.depth.base import ReferenceDepth
from trianflow_vo.depth.network import NetworkDepth
from trianflow_vo.keyframe import Keyframe, Tracks

SIZE = (24, 40)


class CountingNet:
    """DepthNet stand-in: depth = 1 + mean intensity of the image, per pixel; counts calls."""

    name = "counting"

    def __init__(self, dtype=np.float32):
        self.calls: list[tuple[int, int]] = []
        self.dtype = dtype

    def predict(self, image: np.ndarray) -> np.ndarray:
        self.calls.append(image.shape[:2])
        return (1.0 + image.mean(axis=2)).astype(self.dtype)

    def describe(self) -> dict:
        return {"name": self.name, "input_size": [8, 8]}


def image(seed: int, size=SIZE) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 255, (*size, 3), dtype=np.uint8)


def keyframe(index: int, size=SIZE, seed: int | None = None) -> Keyframe:
    return Keyframe(index, image(index if seed is None else seed, size), None, np.eye(4), Tracks.empty())


def test_same_frame_index_is_not_recomputed():
    net = CountingNet()
    prior = NetworkDepth(net)
    kf0 = keyframe(0)
    ref = prior.reference(kf0)
    assert isinstance(ref, ReferenceDepth)
    assert ref.depth.shape == SIZE and ref.depth.dtype == np.float32
    np.testing.assert_allclose(ref.depth, 1.0 + kf0.image.mean(axis=2), rtol=1e-6)
    # dense and trusted as it is: no per-pixel confidence, no tracks
    assert ref.sparse is False and ref.weight is None and ref.track_ids is None
    # pair (0, 1) then pair (0, 2) ...: the same keyframe again is the same array
    assert prior.reference(kf0) is ref
    assert prior.reference(keyframe(0)).depth is ref.depth  # another Keyframe object, same frame index
    moved = np.eye(4)
    moved[:3, 3] = (1.0, 0.0, 0.5)
    assert prior.reference(kf0.with_pose(moved)) is ref  # the same keyframe at a revised pose
    assert len(net.calls) == 1
    prior.reference(keyframe(1))
    prior.reference(keyframe(1))
    assert len(net.calls) == 2


def test_default_cache_of_three_evicts_the_oldest():
    net = CountingNet()
    prior = NetworkDepth(net)  # cache_size 3
    first = {i: prior.reference(keyframe(i)) for i in range(3)}
    assert len(net.calls) == 3
    for i in range(3):  # all three kept
        assert prior.reference(keyframe(i)) is first[i]
    assert len(net.calls) == 3
    prior.reference(keyframe(3))  # a fourth: the oldest (frame 0) falls out
    assert len(net.calls) == 4
    for i in (1, 2, 3):
        prior.reference(keyframe(i))
    assert len(net.calls) == 4
    again = prior.reference(keyframe(0))
    assert len(net.calls) == 5 and again is not first[0]
    np.testing.assert_array_equal(again.depth, first[0].depth)  # recomputed, same result


@pytest.mark.parametrize("n", [1, 2, 5])
def test_cache_of_n_evicts_the_oldest(n):
    net = CountingNet()
    prior = NetworkDepth(net, cache_size=n)
    for i in range(n + 1):
        prior.reference(keyframe(i))
    assert len(net.calls) == n + 1
    for i in range(1, n + 1):  # the newest n are kept
        prior.reference(keyframe(i))
    assert len(net.calls) == n + 1
    prior.reference(keyframe(0))  # the oldest was evicted
    assert len(net.calls) == n + 2


def test_cache_size_must_be_positive():
    with pytest.raises(ValueError, match="cache_size"):
        NetworkDepth(CountingNet(), cache_size=0)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_returned_depth_is_read_only(dtype):
    prior = NetworkDepth(CountingNet(dtype))
    d = prior.reference(keyframe(0)).depth
    assert d.dtype == np.float32 and d.flags.c_contiguous
    assert not d.flags.writeable
    with pytest.raises(ValueError):
        d[0, 0] = 1.0  # the cached map is read-only
    assert prior.reference(keyframe(0)).depth is d  # and still what the cache hands out


def test_other_image_size_for_the_same_index_is_recomputed():
    net = CountingNet()
    prior = NetworkDepth(net)
    small = prior.reference(keyframe(0))
    big = prior.reference(keyframe(0, size=(48, 80)))
    assert net.calls == [SIZE, (48, 80)]
    assert big.depth.shape == (48, 80) and small.depth.shape == SIZE
    assert prior.reference(keyframe(0, size=(48, 80))) is big  # the new size is what is cached now
    assert len(net.calls) == 2


def test_describe_names_the_prior_and_its_network():
    assert NetworkDepth(CountingNet()).describe() == {"name": "network",
                                                      "net": {"name": "counting", "input_size": [8, 8]}}
