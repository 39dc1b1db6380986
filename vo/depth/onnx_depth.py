"""Depth from an exported ONNX depth network (``trianflow-vo export``), via onnxruntime.

:class:`OnnxDepthNet` is the network alone: one image in, one depth map out, every
call a graph call. The per-frame caching and the use of the depth as a prior are
the business of its caller (:mod:`trianflow_vo.depth.network`). Opening, metadata
checks, session settings and the image-to-input conversion are those of every
network (:mod:`trianflow_vo.nets.onnx_runtime`). No torch here.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from trianflow_vo.nets.onnx_runtime import ModelInfo, OnnxModel


class OnnxDepthNet:
    """An exported ResNet18 + DispNet depth network.

    ``predict`` returns ``(h, w)`` float32 depth at the working resolution of the
    image it is given (resized back, bilinear, from the model size when they differ).
    """

    name = "onnx-depth"

    def __init__(self, path: str | Path, threads: int = 2):
        self.model = OnnxModel(path, "depth", threads)

    @property
    def info(self) -> ModelInfo:
        return self.model.info

    @property
    def session(self):
        return self.model.session

    @property
    def threads(self) -> int:
        return self.model.threads

    @property
    def n_inferences(self) -> int:
        """Graph calls so far (one per :meth:`predict`)."""
        return self.model.n_inferences

    def predict(self, image: np.ndarray) -> np.ndarray:
        """Depth ``(h, w)`` float32 (a new, writeable array) of an ``(h, w, 3)`` uint8 BGR image."""
        (depth,) = self.model.run(self.model.to_input(image))
        d = np.ascontiguousarray(depth[0, 0], dtype=np.float32)
        h, w = image.shape[:2]
        if d.shape != (h, w):
            d = cv2.resize(d, (w, h), interpolation=cv2.INTER_LINEAR)
        return d

    def describe(self) -> dict:
        return {"name": self.name, **self.model.describe(), "depth_range": self.info.meta.get("depth_range")}
