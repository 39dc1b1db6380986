"""The depth-prior seam: where the depth of a reference keyframe comes from.

The odometry needs the depth of its reference keyframe to fix the scale of each
two-view step and to solve PnP when the motion is small. Two priors exist:

- :class:`trianflow_vo.depth.triangulated.TriangulatedDepth` (weight-free): the
  depth that earlier steps triangulated and carried into the keyframe (its
  :class:`~trianflow_vo.keyframe.Tracks`), sparse, with a confidence per pixel.
- :class:`trianflow_vo.depth.network.NetworkDepth`: a depth network's prediction
  for the keyframe image, dense, taken as it is (the paper's inference).

The odometry only calls :meth:`DepthPrior.reference` and reads the
:class:`ReferenceDepth` it returns; it never asks which prior it holds.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:
    from trianflow_vo.keyframe import Keyframe


@dataclass(frozen=True)
class ReferenceDepth:
    """Depth of a keyframe at working resolution.

    Attributes:
        depth: ``(h, w)`` float32 depth (camera z), 0 where unknown.
        weight: ``(h, w)`` float32 confidence of each depth (0 where unknown), or
            None for a prior without per-pixel confidence, which is trusted as it is
            (new triangulation is aligned to it, never fused with it).
        sparse: True when only some pixels have depth (those are then worth
            sampling on purpose, and PnP uses all of them); False for a dense map.
        track_ids: ``(h, w)`` int64 id of the track each pixel's depth belongs to
            (-1 = none), or None.
    """

    depth: np.ndarray
    weight: np.ndarray | None = None
    sparse: bool = False
    track_ids: np.ndarray | None = None


class DepthPrior(Protocol):
    """Depth of the reference keyframe (see the module docstring)."""

    name: str

    def reference(self, keyframe: Keyframe) -> ReferenceDepth | None:
        """The keyframe's depth, or None when there is none yet. Computed once per keyframe."""
        ...

    def describe(self) -> dict:
        """JSON-ready description for ``run.json``."""
        ...
