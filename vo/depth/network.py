"""Depth of each keyframe from a depth network (the paper's inference)."""

from __future__ import annotations

from collections import OrderedDict
from typing import Protocol

import numpy as np

from trianflow_vo.depth.base import ReferenceDepth
from trianflow_vo.keyframe import Keyframe


class DepthNet(Protocol):
    """A depth network: ``predict(image (h, w, 3) uint8 BGR) -> (h, w) float32 depth``."""

    def predict(self, image: np.ndarray) -> np.ndarray: ...

    def describe(self) -> dict: ...


class NetworkDepth:
    """:class:`~trianflow_vo.depth.base.DepthPrior` from a depth network.

    The prediction is dense and trusted as it is: the triangulated structure of
    each step is aligned to it. Each frame's depth is computed once and kept in a
    small cache keyed by frame index (the returned arrays are read-only).

    Args:
        net: a :class:`DepthNet` (e.g. :class:`trianflow_vo.depth.onnx_depth.OnnxDepthNet`).
        cache_size: frames kept.
    """

    name = "network"

    def __init__(self, net: DepthNet, cache_size: int = 3):
        if cache_size < 1:
            raise ValueError("cache_size must be >= 1")
        self.net = net
        self.cache_size = int(cache_size)
        self._cache: OrderedDict[int, ReferenceDepth] = OrderedDict()

    def reference(self, keyframe: Keyframe) -> ReferenceDepth:
        hit = self._cache.get(keyframe.index)
        if hit is not None and hit.depth.shape == keyframe.image.shape[:2]:
            self._cache.move_to_end(keyframe.index)
            return hit
        d = np.ascontiguousarray(self.net.predict(keyframe.image), dtype=np.float32)
        d.flags.writeable = False
        ref = ReferenceDepth(depth=d)
        self._cache[keyframe.index] = ref
        self._cache.move_to_end(keyframe.index)
        while len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)
        return ref

    def describe(self) -> dict:
        return {"name": self.name, "net": self.net.describe()}
