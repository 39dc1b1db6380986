"""Optical flow from an exported ONNX flow network (``trianflow-vo export``), via onnxruntime.

Opening, metadata checks, session settings and the image-to-input conversion are
those of every network (:mod:`trianflow_vo.nets.onnx_runtime`). No torch here.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from trianflow_vo.nets.onnx_runtime import ModelInfo, OnnxModel


@dataclass(frozen=True)
class PreparedFrame:
    """What :meth:`OnnxFlow.prepare` returns: the graph input and the working size."""

    tensor: np.ndarray  # (1, 3, H, W) float32
    hw: tuple[int, int]  # working (h, w)


def _flow_to_working(flow_chw: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    """``(2, H, W)`` flow in model pixels -> ``(h, w, 2)`` float32 in working pixels."""
    H, W = flow_chw.shape[1:]
    h, w = hw
    flow = np.ascontiguousarray(flow_chw.transpose(1, 2, 0), dtype=np.float32)
    if (H, W) == (h, w):
        return flow
    flow = cv2.resize(flow, (w, h), interpolation=cv2.INTER_LINEAR)
    flow[..., 0] *= w / W
    flow[..., 1] *= h / H
    return flow


class OnnxFlow:
    """A :class:`vo.flow.base.FlowSource` running an exported PWC-Net.

    ``flow_pair`` gets the forward and backward flow from one graph call (shared
    feature pyramid, both directions decoded as one batch). When the working size
    differs from the model's input size, images are resized to the model size and
    the flow is resized back and its values rescaled to working pixels. Masks
    (M_s, M_o) are computed by the caller with :mod:`vo.flow.masks` (numpy), which
    measured faster than in-graph masks (benchmarks/NETWORK.md).
    """

    name = "onnx-pwc"

    def __init__(self, path: str | Path, threads: int = 2):
        self.model = OnnxModel(path, "flow", threads)

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
        """Graph calls so far (one per :meth:`flow_pair`)."""
        return self.model.n_inferences

    def prepare(self, image: np.ndarray) -> PreparedFrame:
        """``(h, w, 3)`` uint8 BGR at working resolution -> :class:`PreparedFrame`."""
        return PreparedFrame(self.model.to_input(image), (int(image.shape[0]), int(image.shape[1])))

    def flow_pair(self, a: PreparedFrame, b: PreparedFrame) -> tuple[np.ndarray, np.ndarray]:
        """Forward (a -> b) and backward (b -> a) flow, each ``(h, w, 2)`` float32 working pixels."""
        if a.hw != b.hw:
            raise ValueError(f"frames of different working sizes: {a.hw} and {b.hw}")
        fw, bw = self.model.run(a.tensor, b.tensor)  # outputs flow_fw, flow_bw
        return _flow_to_working(fw[0], a.hw), _flow_to_working(bw[0], a.hw)

    def describe(self) -> dict:
        return {"name": self.name, **self.model.describe()}
