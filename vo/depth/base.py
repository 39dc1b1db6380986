"""The depth-source interface: depth carried by triangulation, or a depth network."""

from __future__ import annotations

from typing import Protocol

import numpy as np


class DepthSource(Protocol):
    """Depth of a frame, used to fix the scale of each two-view step and for PnP.

    ``predict`` returns an ``(h, w)`` float32 depth map at working resolution for the
    frame with source index ``frame_index`` (0 where unknown), or None when the
    source has nothing for it yet. A network computes it once per frame (cached), a
    triangulation-carried source returns what earlier steps put there.

    ``is_metric_prior`` is True for network depth: the pipeline then aligns the
    triangulated structure to it (the paper's inference). For the triangulated
    source it is False: depth is already in the trajectory's scale.

    ``observe`` receives, after each two-view or PnP step, depth of frame
    ``frame_index`` in the trajectory's scale at pixels ``pts`` ``(N, 2)`` with
    per-point weights ``(N,)``: the weight-free source keeps it, a network ignores it.
    """

    name: str
    is_metric_prior: bool

    def predict(self, frame_index: int, image: np.ndarray) -> np.ndarray | None: ...

    def observe(self, frame_index: int, pts: np.ndarray, depth: np.ndarray, weight: np.ndarray) -> None: ...

    def forget(self, frame_index: int) -> None: ...

    def describe(self) -> dict: ...
