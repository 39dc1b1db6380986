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


@dataclass(frozen=True)
class Shortfall:
    """The source ended before the frame count it states (e.g. a truncated video file).

    A reader sets it (``Sequence.shortfall``) when iteration ends early; the pipeline
    logs it as a ``truncated-input`` warning.

    Attributes:
        source: the file.
        decoded: source frames read before the source ended.
        stated: frames the container states (``CAP_PROP_FRAME_COUNT``).
        missing: selected frames that were never delivered.
    """

    source: str
    decoded: int
    stated: int
    missing: int

    @property
    def message(self) -> str:
        return (
            f"{self.source}: truncated or corrupt: {self.decoded} of the {self.stated} frames the "
            f"container states could be decoded; {self.missing} selected frame(s) missing at the end"
        )
