"""Frames as the readers stream them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Frame:
    """One decoded frame.

    Attributes:
        index: source frame index (0-based position in the whole sequence, before
            ``--start``/``--stride`` selection); this is what ``frames.txt`` records.
        timestamp: seconds, from ``times.txt``/``rgb.txt``/the video, or None.
        image: ``(H, W, 3)`` uint8, BGR (grayscale sources are expanded to 3 channels).
        source: file path, or ``"video.mp4#123"`` for video frames.
    """

    index: int
    timestamp: float | None
    image: np.ndarray
    source: str


@dataclass(frozen=True)
class FrameSkip:
    """A frame that could not be used (unreadable, truncated, wrong size)."""

    index: int
    source: str
    reason: str
