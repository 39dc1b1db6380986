"""The flow-source interface: OpenCV DIS (weight-free) or an ONNX flow network."""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np


class FlowSource(Protocol):
    """Dense optical flow between two frames at working resolution.

    ``prepare`` is called once per frame with the working-resolution image
    (``(h, w, 3)`` uint8 BGR) and returns whatever the source needs later (a grey
    image, a normalised tensor, ...). ``flow_pair`` returns the forward flow
    (frame a -> b) and the backward flow (b -> a), each ``(h, w, 2)`` float32 in
    pixels, ``flow[y, x] = (dx, dy)``.
    """

    name: str

    def prepare(self, image: np.ndarray) -> Any: ...

    def flow_pair(self, a: Any, b: Any) -> tuple[np.ndarray, np.ndarray]: ...

    def describe(self) -> dict: ...
