"""Weight-free depth: what earlier two-view steps triangulated, in the trajectory's scale."""

from __future__ import annotations

import numpy as np


class TriangulatedDepth:
    """:class:`vo.depth.base.DepthSource` carrying triangulated depth from frame to frame.

    Each two-view step triangulates points of its reference frame, scales them to
    the trajectory and hands their depth in the *current* frame to :meth:`observe`;
    the next step reads them back with :meth:`predict` as a sparse map (0 where
    unknown) to fix its scale. Only the most recent ``keep`` frames are stored, so
    memory does not grow with the sequence.
    """

    name = "triangulated"
    is_metric_prior = False

    def __init__(self, size_hw: tuple[int, int], keep: int = 3):
        self.size_hw = (int(size_hw[0]), int(size_hw[1]))
        self.keep = keep
        self._maps: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def predict(self, frame_index: int, image: np.ndarray | None = None) -> np.ndarray | None:
        entry = self._maps.get(frame_index)
        return None if entry is None else entry[0]

    def weight(self, frame_index: int) -> np.ndarray | None:
        """``(h, w)`` float32 confidence of the stored depth (0 where unknown), or None."""
        entry = self._maps.get(frame_index)
        return None if entry is None else entry[1]

    def observe(self, frame_index: int, pts: np.ndarray, depth: np.ndarray, weight: np.ndarray) -> None:
        """Splat depths ``(N,)`` at pixels ``pts`` ``(N, 2)`` (nearest pixel; the
        highest weight wins where several land on one pixel)."""
        h, w = self.size_hw
        pts = np.asarray(pts, dtype=np.float64)
        xi = np.rint(pts[:, 0]).astype(np.int64)
        yi = np.rint(pts[:, 1]).astype(np.int64)
        ok = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h) & np.isfinite(depth) & (depth > 0)
        xi, yi = xi[ok], yi[ok]
        d = np.asarray(depth, dtype=np.float32)[ok]
        wt = np.asarray(weight, dtype=np.float32)[ok]
        order = np.argsort(wt)  # ascending: the last write (highest weight) wins
        dmap = np.zeros((h, w), dtype=np.float32)
        wmap = np.zeros((h, w), dtype=np.float32)
        dmap[yi[order], xi[order]] = d[order]
        wmap[yi[order], xi[order]] = wt[order]
        self._maps[frame_index] = (dmap, wmap)
        while len(self._maps) > self.keep:
            self._maps.pop(next(iter(self._maps)))

    def forget(self, frame_index: int) -> None:
        self._maps.pop(frame_index, None)

    def describe(self) -> dict:
        return {"name": self.name, "keep": self.keep}
