"""Per-frame results handed to observers (Rerun logger, progress bar, writers)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np


@dataclass
class FrameRecord:
    """What the pipeline knows after processing one frame.

    Attributes:
        line: 0-based output line (position in ``poses.txt``).
        frame_index: source frame index (as in ``frames.txt``).
        timestamp: seconds or None.
        T_world_cam: ``(4, 4)`` camera-to-world pose of this frame.
        branch: ``"init"`` (first frame), ``"two-view"``, ``"pnp"``, ``"rotation"``
            (parallax too small, rotation only), ``"identity"`` (static camera) or
            ``"failed"`` (pose kept from the previous frame).
        reason: why that branch was taken (one short sentence, empty for two-view).
        image: ``(h, w, 3)`` uint8 BGR at working resolution.
        K: ``(3, 3)`` intrinsics at working resolution.
        ref_index: source index of the reference (key)frame the pose was solved from.
        depth: ``(h, w)`` float32 depth of the reference frame used for scale/PnP
            (0 = unknown), or None.
        flow: ``(h, w, 2)`` forward flow reference -> this frame, or None.
        pts_ref, pts_cur: ``(N, 2)`` inlier matches used for triangulation/PnP, or None.
        points_world: ``(M, 3)`` triangulated points in world coordinates, or None.
        point_colors: ``(M, 3)`` uint8 RGB colours of those points, or None.
        stats: scalars (``inliers``, ``scale``, ``mean_flow``, ``parallax``, ``ms`` ...).
    """

    line: int
    frame_index: int
    timestamp: float | None
    T_world_cam: np.ndarray
    branch: str
    reason: str = ""
    image: np.ndarray | None = None
    K: np.ndarray | None = None
    ref_index: int | None = None
    depth: np.ndarray | None = None
    flow: np.ndarray | None = None
    pts_ref: np.ndarray | None = None
    pts_cur: np.ndarray | None = None
    points_world: np.ndarray | None = None
    point_colors: np.ndarray | None = None
    stats: dict = field(default_factory=dict)


class Observer(Protocol):
    """Receives every processed frame, in order. ``close`` is called once at the end
    (also after an interruption, with ``interrupted=True``). An observer may also
    define ``on_start(n_frames)``: it is called once, before the first frame."""

    def on_frame(self, record: FrameRecord) -> None: ...

    def close(self, interrupted: bool = False) -> None: ...
