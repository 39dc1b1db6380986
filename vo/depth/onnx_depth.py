"""Depth from an exported ONNX depth network (``trianflow-vo export``), via onnxruntime.

A network depth is a metric prior: the pipeline aligns the triangulated structure
to it. Each frame's depth is computed once and kept in a small cache keyed by frame
index, so both pairs a frame belongs to reuse it. No torch here.
"""

from __future__ import annotations

from collections import OrderedDict
from pathlib import Path

import cv2
import numpy as np

from trianflow_vo.flow.onnx_flow import open_model, to_model_input


class OnnxDepth:
    """A :class:`vo.depth.base.DepthSource` running an exported ResNet18 + DispNet depth net.

    ``predict`` returns ``(h, w)`` float32 depth at the working resolution of the
    image it is given (resized back from the model size when they differ). The
    returned array is the cached one and is read-only.
    """

    name = "onnx-depth"
    is_metric_prior = True

    def __init__(self, path: str | Path, threads: int = 2, cache_size: int = 3):
        if cache_size < 1:
            raise ValueError("cache_size must be >= 1")
        self.session, self.info = open_model(path, "depth", threads)
        self.threads = int(threads)
        self.cache_size = int(cache_size)
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()
        self.n_inferences = 0

    def predict(self, frame_index: int, image: np.ndarray) -> np.ndarray:
        """Depth ``(h, w)`` float32 of frame ``frame_index`` from its ``(h, w, 3)`` uint8 BGR image."""
        hit = self._cache.get(frame_index)
        if hit is not None and hit.shape == image.shape[:2]:
            self._cache.move_to_end(frame_index)
            return hit
        (depth,) = self.session.run(["depth"], {"image": to_model_input(image, self.info)})
        self.n_inferences += 1
        d = np.ascontiguousarray(depth[0, 0], dtype=np.float32)
        h, w = image.shape[:2]
        if d.shape != (h, w):
            d = cv2.resize(d, (w, h), interpolation=cv2.INTER_LINEAR)
        d.flags.writeable = False
        self._cache[frame_index] = d
        self._cache.move_to_end(frame_index)
        while len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)
        return d

    def observe(self, frame_index: int, pts: np.ndarray, depth: np.ndarray, weight: np.ndarray) -> None:
        """A network ignores depth observed by the pipeline."""

    def forget(self, frame_index: int) -> None:
        self._cache.pop(frame_index, None)

    def describe(self) -> dict:
        return {"name": self.name, "path": str(self.info.path), "input_size": list(self.info.input_size),
                "channel_order": self.info.channel_order, "threads": self.threads,
                "depth_range": self.info.meta.get("depth_range"),
                "exported_with_version": self.info.version, "config": self.info.config}
