"""Keyframe state: the reference frame, its pose and the points tracked into it.

One object that the front-end (which solves every new frame against it) and the
back-end (which may revise its pose) both read. A keyframe is immutable; a new
keyframe, or a revised pose, is a new object (``dataclasses.replace``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Tracks:
    """3-D points followed from keyframe to keyframe, as seen in one keyframe.

    A track is born when a pixel of a keyframe is triangulated and keeps its id
    while the next keyframes re-triangulate it from the flow (the pixel carries
    depth there). It ends when it leaves the image, falls behind the camera, or
    loses its pixel to a stronger track.

    Attributes:
        ids: ``(N,)`` int64 track ids, unique within one keyframe.
        pts: ``(N, 2)`` float64 pixel of each track in this keyframe (sub-pixel).
        depth: ``(N,)`` float64 depth (camera z) in trajectory units, > 0.
        weight: ``(N,)`` float64 confidence of that depth (information, grows with parallax squared).
    """

    ids: np.ndarray
    pts: np.ndarray
    depth: np.ndarray
    weight: np.ndarray

    def __post_init__(self):
        n = np.asarray(self.ids).shape[0]
        for name, shape in (("ids", (n,)), ("pts", (n, 2)), ("depth", (n,)), ("weight", (n,))):
            a = np.array(getattr(self, name), dtype=np.int64 if name == "ids" else np.float64)
            if a.shape != shape:
                raise ValueError(f"Tracks.{name} must be {shape}, got {a.shape}")
            a.flags.writeable = False
            object.__setattr__(self, name, a)

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    @classmethod
    def empty(cls) -> Tracks:
        return cls(np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0), np.zeros(0))


class TrackIds:
    """Hands out new track ids (one counter per run; no global state)."""

    def __init__(self) -> None:
        self._next = 0

    def new(self, n: int) -> np.ndarray:
        ids = np.arange(self._next, self._next + n, dtype=np.int64)
        self._next += n
        return ids


@dataclass(frozen=True)
class Keyframe:
    """The current reference frame.

    Attributes:
        index: source frame index.
        image: ``(h, w, 3)`` uint8 BGR at working resolution.
        prepared: what the flow source made of the image (:meth:`FlowSource.prepare`).
        T_world_cam: ``(4, 4)`` camera-to-world pose.
        tracks: points with depth in this keyframe (:class:`Tracks`); empty for the first.
    """

    index: int
    image: np.ndarray
    prepared: Any
    T_world_cam: np.ndarray
    tracks: Tracks

    def with_pose(self, T_world_cam: np.ndarray) -> Keyframe:
        """The same keyframe at a revised pose."""
        return replace(self, T_world_cam=np.asarray(T_world_cam, dtype=np.float64).copy())

    def with_tracks(self, tracks: Tracks) -> Keyframe:
        """The same keyframe with revised tracks (e.g. corrected depth)."""
        return replace(self, tracks=tracks)
