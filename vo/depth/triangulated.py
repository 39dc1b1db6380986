"""Weight-free depth: what earlier two-view steps triangulated, carried into the keyframe."""

from __future__ import annotations

import numpy as np

from trianflow_vo.depth.base import ReferenceDepth
from trianflow_vo.keyframe import Keyframe, Tracks


def splat_tracks(tracks: Tracks, size_hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tracks as maps: ``(depth (h, w) float32, weight (h, w) float32, ids (h, w) int64)``.

    Each track goes to its nearest pixel; where several land on one pixel the
    highest weight wins. Pixels without a track have depth 0, weight 0, id -1.
    Tracks outside the image or without positive finite depth are ignored.
    """
    h, w = size_hw
    xi = np.rint(tracks.pts[:, 0]).astype(np.int64)
    yi = np.rint(tracks.pts[:, 1]).astype(np.int64)
    ok = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h) & np.isfinite(tracks.depth) & (tracks.depth > 0)
    xi, yi = xi[ok], yi[ok]
    d = tracks.depth.astype(np.float32)[ok]
    wt = tracks.weight.astype(np.float32)[ok]
    ids = tracks.ids[ok]
    order = np.argsort(wt)  # ascending: the last write (highest weight) wins
    dmap = np.zeros((h, w), dtype=np.float32)
    wmap = np.zeros((h, w), dtype=np.float32)
    imap = np.full((h, w), -1, dtype=np.int64)
    dmap[yi[order], xi[order]] = d[order]
    wmap[yi[order], xi[order]] = wt[order]
    imap[yi[order], xi[order]] = ids[order]
    return dmap, wmap, imap


class TriangulatedDepth:
    """:class:`~trianflow_vo.depth.base.DepthPrior` of the weight-free path.

    Each two-view step triangulates points of its reference keyframe, scales them
    to the trajectory and hands them to the new keyframe as its
    :class:`~trianflow_vo.keyframe.Tracks`; this prior turns them into a sparse
    depth map with a confidence per pixel. The map is made once per keyframe.
    """

    name = "triangulated"

    def __init__(self, size_hw: tuple[int, int]):
        self.size_hw = (int(size_hw[0]), int(size_hw[1]))
        self._cached: tuple[int, Tracks, ReferenceDepth | None] | None = None  # (index, tracks, ref)

    def reference(self, keyframe: Keyframe) -> ReferenceDepth | None:
        if self._cached is not None and self._cached[0] == keyframe.index and self._cached[1] is keyframe.tracks:
            return self._cached[2]
        ref = None
        if len(keyframe.tracks):
            dmap, wmap, imap = splat_tracks(keyframe.tracks, self.size_hw)
            ref = ReferenceDepth(depth=dmap, weight=wmap, sparse=True, track_ids=imap)
        self._cached = (keyframe.index, keyframe.tracks, ref)  # holding the tracks: identity stays meaningful
        return ref

    def describe(self) -> dict:
        return {"name": self.name}
