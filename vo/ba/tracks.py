"""Tracks for the bundle adjustment: keyframe pixels followed through the flow.

A track is one scene point seen in several keyframes. It is born at a match of a
two-view step (a pixel of the older keyframe and its flow end point in the newer
one, both observations, with the triangulated point as the landmark's first
estimate). At each new keyframe every live track is moved by the forward flow
between the two keyframes, sampled bilinearly at its sub-pixel position, and
ends when

* it leaves the image (``margin_px`` from the border),
* the flow there is not forward-backward consistent
  (``|fw(p) + bw(p + fw(p))| >= fb_px``), or
* the new pixel is an epipolar outlier of the step (Sampson distance ``>= epi_px``).

Empty cells of a grid over the newer keyframe (``cell_px``) are then filled with
new tracks, up to ``max_tracks`` alive: in each cell the candidate with the best
score (:func:`texture_score`: flow is most accurate where the image is textured), or
without scores the first candidate drawn. A track also ends when the bundle
adjustment finds it an outlier (:meth:`TrackTable.end`).

Pixels are ``(u, v)``; flows are ``flow[y, x] = (dx, dy)`` at working resolution.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from trianflow_vo.geometry.epipolar import sampson_distance


def sample_bilinear(field: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear samples of ``field`` at sub-pixel points.

    Args:
        field: ``(h, w, C)`` or ``(h, w)`` array (converted to float32).
        pts: ``(N, 2)`` pixels ``(u, v)``.

    Returns:
        ``(values (N, C) float64, inside (N,) bool)``; ``inside`` is False for points
        outside ``[0, w-1] x [0, h-1]`` (their values are 0).
    """
    pts = np.asarray(pts, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"pts must be (N, 2), got {pts.shape}")
    f = np.asarray(field, dtype=np.float32)
    if f.ndim == 2:
        f = f[..., None]
    h, w, c = f.shape
    n = pts.shape[0]
    inside = (pts[:, 0] >= 0) & (pts[:, 0] <= w - 1) & (pts[:, 1] >= 0) & (pts[:, 1] <= h - 1)
    if n == 0:
        return np.zeros((0, c)), inside
    map_x = np.ascontiguousarray(pts[:, 0].reshape(1, n), dtype=np.float32)
    map_y = np.ascontiguousarray(pts[:, 1].reshape(1, n), dtype=np.float32)
    out = np.zeros((n, c))
    for k in range(0, c, 4):  # cv2.remap takes up to 4 channels at once
        chunk = np.ascontiguousarray(f[..., k:k + 4])
        s = cv2.remap(chunk, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        out[:, k:k + 4] = np.asarray(s, dtype=np.float64).reshape(n, -1)
    out[~inside] = 0.0
    return out, inside


def follow_flow(fw: np.ndarray, bw: np.ndarray, pts: np.ndarray,
                margin_px: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels followed through a dense flow, with their forward-backward distance.

    Args:
        fw, bw: ``(h, w, 2)`` flow from the image of ``pts`` to the other and back.
        pts: ``(N, 2)`` pixels (non-finite rows are not followed).
        margin_px: a followed pixel must land at least this far inside the other image.

    Returns:
        ``(moved (N, 2), inside (N,) bool, fb (N,))``: where each pixel lands (``nan`` for
        non-finite rows), whether it started in the image and landed inside the margin, and
        ``|fw(p) + bw(p + fw(p))|`` in pixels (``inf`` where not inside).
    """
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    h, w = fw.shape[:2]
    finite = np.isfinite(pts).all(axis=1)
    f, inside = sample_bilinear(fw, np.where(finite[:, None], pts, -1.0))
    moved = np.where(finite[:, None], pts + f, np.nan)
    m = margin_px
    with np.errstate(invalid="ignore"):
        inside &= (moved[:, 0] >= m) & (moved[:, 0] <= w - 1 - m) & (moved[:, 1] >= m) & (moved[:, 1] <= h - 1 - m)
    b, _ = sample_bilinear(bw, np.where(inside[:, None], moved, 0.0))
    fb = np.where(inside, np.linalg.norm(f + b, axis=1), np.inf)
    return moved, inside, fb


def texture_score(image: np.ndarray, pts: np.ndarray, block_px: int) -> np.ndarray:
    """How well the image pins down a small patch at each point: the smaller eigenvalue of the
    covariance of the image gradients over a ``block_px`` square (Shi-Tomasi's corner measure).
    Flat areas and straight edges score low: there a patch matcher such as DIS can slide.

    Args:
        image: ``(h, w)`` grey or ``(h, w, 3)`` BGR image (any numeric type).
        pts: ``(N, 2)`` pixels ``(u, v)`` (rounded to the nearest pixel, clamped to the image).
        block_px: side of the block in pixels (>= 1).

    Returns:
        ``(N,)`` float64 scores (units: squared intensity gradients; only their order matters).
    """
    if block_px < 1:
        raise ValueError(f"block_px must be >= 1, got {block_px}")
    pts = np.asarray(pts, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"pts must be (N, 2), got {pts.shape}")
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_BGR2GRAY)
    if img.ndim != 2:
        raise ValueError(f"image must be (h, w) or (h, w, 3), got {np.asarray(image).shape}")
    score = cv2.cornerMinEigenVal(np.ascontiguousarray(img, dtype=np.float32), int(block_px), 3)
    h, w = score.shape
    xi = np.clip(np.rint(pts[:, 0]), 0, w - 1).astype(np.int64)
    yi = np.clip(np.rint(pts[:, 1]), 0, h - 1).astype(np.int64)
    return score[yi, xi].astype(np.float64)


def grid_cell(pts: np.ndarray, cell_px: int, width: int) -> np.ndarray:
    """``(N,)`` int64 index of the ``cell_px`` grid cell of each pixel ``pts`` ``(N, 2)`` of an image
    ``width`` pixels wide (row-major)."""
    n_cols = (int(width) + cell_px - 1) // cell_px
    return (pts[:, 1] // cell_px).astype(np.int64) * n_cols + (pts[:, 0] // cell_px).astype(np.int64)


@dataclass(frozen=True)
class TrackUpdate:
    """What one keyframe step did to the tracks (counts)."""

    continued: int
    left_image: int
    inconsistent: int
    epipolar_outliers: int
    born: int


class TrackTable:
    """Live tracks, their observations in recent keyframes, and landmark estimates.

    Args:
        size_hw: working image size ``(h, w)``.
        cell_px: side of the grid cells new tracks are spread over (pixels).
        max_tracks: most tracks alive at once.
        fb_px: forward-backward distance (pixels) from which a track ends.
        epi_px: Sampson distance (pixels) to the step's epipolar geometry from which a track ends.
        margin_px: a track closer than this to the border ends.
    """

    def __init__(self, size_hw: tuple[int, int], cell_px: int = 24, max_tracks: int = 400, fb_px: float = 1.0,
                 epi_px: float = 1.0, margin_px: float = 2.0):
        if cell_px < 1 or max_tracks < 1:
            raise ValueError(f"cell_px and max_tracks must be >= 1, got {cell_px}, {max_tracks}")
        self.size_hw = (int(size_hw[0]), int(size_hw[1]))
        self.cell_px = int(cell_px)
        self.max_tracks = int(max_tracks)
        self.fb_px = float(fb_px)
        self.epi_px = float(epi_px)
        self.margin_px = float(margin_px)
        self.ids = np.zeros(0, dtype=np.int64)  # live tracks, seen in the newest keyframe
        self.pts = np.zeros((0, 2))  # their pixel there
        self.newest: int | None = None  # the newest keyframe's index
        self.obs: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # keyframe -> (ids (M,), pixels (M, 2))
        self.landmarks: dict[int, np.ndarray] = {}  # track id -> (3,) world point
        self._next_id = 0

    def __len__(self) -> int:
        return int(self.ids.size)

    # -- one keyframe step ----------------------------------------------------------------------------
    def advance(self, kf_old: int, kf_new: int, fw: np.ndarray, bw: np.ndarray, F: np.ndarray,
                cand_old: np.ndarray, cand_new: np.ndarray, cand_world: np.ndarray,
                cand_score: np.ndarray | None = None) -> TrackUpdate:
        """Follow the live tracks from keyframe ``kf_old`` into ``kf_new`` and add new ones.

        Args:
            kf_old, kf_new: source indices of the two keyframes (``kf_old`` must be the
                newest keyframe so far, or the first call).
            fw, bw: ``(h, w, 2)`` flow ``kf_old -> kf_new`` and back.
            F: ``(3, 3)`` fundamental matrix of the step (``x_new^T F x_old = 0``), or None for a
                step without translation (no epipolar test).
            cand_old, cand_new: ``(M, 2)`` matches of the step that new tracks may start from.
            cand_world: ``(M, 3)`` their triangulated world points (first landmark estimates).
            cand_score: ``(M,)`` preference of each candidate (higher is better, e.g. :func:`texture_score`
                at ``cand_new``); None: the first candidate of a cell is taken.
        """
        if self.newest is not None and kf_old != self.newest:
            raise ValueError(f"tracks are in keyframe {self.newest}, not {kf_old}")
        h, w = self.size_hw
        if fw.shape != (h, w, 2) or bw.shape != (h, w, 2):
            raise ValueError(f"fw and bw must be ({h}, {w}, 2), got {fw.shape} and {bw.shape}")
        n = self.ids.size
        left = inconsistent = epi_out = 0
        if n:
            moved, inside, fb = follow_flow(fw, bw, self.pts, self.margin_px)
            fb_ok = fb < self.fb_px
            epi_ok = (np.ones(n, dtype=bool) if F is None
                      else sampson_distance(F, self.pts, moved) < self.epi_px)
            keep = inside & fb_ok & epi_ok
            left = int((~inside).sum())
            inconsistent = int((inside & ~fb_ok).sum())
            epi_out = int((inside & fb_ok & ~epi_ok).sum())
            self.ids, self.pts = self.ids[keep], moved[keep]
        self.obs[kf_new] = (self.ids.copy(), self.pts.copy())
        born = self._spawn(kf_old, kf_new, cand_old, cand_new, cand_world, cand_score)
        self.newest = kf_new
        return TrackUpdate(int(self.ids.size) - born, left, inconsistent, epi_out, born)

    def _spawn(self, kf_old: int, kf_new: int, cand_old: np.ndarray, cand_new: np.ndarray,
               cand_world: np.ndarray, cand_score: np.ndarray | None = None) -> int:
        """New tracks in the empty grid cells of ``kf_new``; returns how many."""
        room = self.max_tracks - self.ids.size
        cand_new = np.asarray(cand_new, dtype=np.float64).reshape(-1, 2)
        if room <= 0 or cand_new.shape[0] == 0:
            return 0
        h, w = self.size_hw
        m, c = self.margin_px, self.cell_px
        ok = ((cand_new[:, 0] >= m) & (cand_new[:, 0] <= w - 1 - m) & (cand_new[:, 1] >= m)
              & (cand_new[:, 1] <= h - 1 - m) & np.isfinite(cand_world).all(axis=1))
        idx = np.flatnonzero(ok)
        cell = grid_cell(cand_new[idx], c, w)
        taken = set(grid_cell(self.pts, c, w).tolist())
        free = np.array([cl not in taken for cl in cell.tolist()], dtype=bool)
        idx, cell = idx[free], cell[free]
        if cand_score is None:
            _, first = np.unique(cell, return_index=True)  # one candidate per cell: the first drawn
            pick = idx[np.sort(first)][:room]
        else:  # one per cell: the best-scored (ties: the first drawn); the best cells first when room is short
            sc = np.asarray(cand_score, dtype=np.float64).reshape(-1)[idx]
            order = np.lexsort((np.arange(idx.size), -sc, cell))
            _, first = np.unique(cell[order], return_index=True)
            best = order[first]
            pick = idx[best[np.argsort(-sc[best], kind="stable")]][:room]
        if pick.size == 0:
            return 0
        new_ids = np.arange(self._next_id, self._next_id + pick.size, dtype=np.int64)
        self._next_id += pick.size
        for tid, X in zip(new_ids.tolist(), np.asarray(cand_world, dtype=np.float64)[pick]):
            self.landmarks[tid] = X.copy()
        old_ids, old_pts = self.obs.get(kf_old, (np.zeros(0, np.int64), np.zeros((0, 2))))
        self.obs[kf_old] = (np.concatenate([old_ids, new_ids]),
                            np.concatenate([old_pts, np.asarray(cand_old, dtype=np.float64)[pick]]))
        self.ids = np.concatenate([self.ids, new_ids])
        self.pts = np.concatenate([self.pts, cand_new[pick]])
        self.obs[kf_new] = (self.ids.copy(), self.pts.copy())
        return int(pick.size)

    def attach(self, kf_old: int, uv_old: np.ndarray, kf_new: int, uv_new: np.ndarray,
               X_world: np.ndarray) -> np.ndarray:
        """New tracks linking an older keyframe (e.g. a revisit anchor, no longer in the table) to
        the newest one: each observed at ``uv_old`` in ``kf_old`` and ``uv_new`` in ``kf_new``,
        with the landmark ``X_world``. They are not followed into later keyframes (they do not
        count against ``max_tracks``); when ``kf_old``'s observations are forgotten they drop out
        of the adjustments.

        Args:
            kf_old: the older keyframe; kf_new: the newest keyframe (the table's).
            uv_old, uv_new: ``(M, 2)`` pixels; X_world: ``(M, 3)`` landmarks.

        Returns:
            ``(M,)`` the new track ids.
        """
        if kf_new != self.newest:
            raise ValueError(f"tracks are in keyframe {self.newest}, not {kf_new}")
        uv_old = np.asarray(uv_old, dtype=np.float64).reshape(-1, 2)
        uv_new = np.asarray(uv_new, dtype=np.float64).reshape(-1, 2)
        X_world = np.asarray(X_world, dtype=np.float64).reshape(-1, 3)
        if not uv_old.shape[0] == uv_new.shape[0] == X_world.shape[0]:
            raise ValueError(f"uv_old, uv_new and X_world must have one row per track, got {uv_old.shape[0]}, "
                             f"{uv_new.shape[0]}, {X_world.shape[0]}")
        new_ids = np.arange(self._next_id, self._next_id + uv_old.shape[0], dtype=np.int64)
        self._next_id += new_ids.size
        for tid, X in zip(new_ids.tolist(), X_world):
            self.landmarks[tid] = X.copy()
        for kf, uv in ((kf_old, uv_old), (kf_new, uv_new)):
            ids, pts = self.obs.get(kf, (np.zeros(0, np.int64), np.zeros((0, 2))))
            self.obs[kf] = (np.concatenate([ids, new_ids]), np.concatenate([pts, uv]))
        return new_ids

    # -- what the bundle adjustment says ------------------------------------------------------------
    def end(self, track_ids: np.ndarray) -> None:
        """End these tracks everywhere (outliers): observations, landmark and live entry."""
        gone = np.asarray(track_ids, dtype=np.int64)
        if gone.size == 0:
            return
        live = ~np.isin(self.ids, gone)
        self.ids, self.pts = self.ids[live], self.pts[live]
        for kf, (ids, pts) in list(self.obs.items()):
            keep = ~np.isin(ids, gone)
            self.obs[kf] = (ids[keep], pts[keep])
        for t in gone.tolist():
            self.landmarks.pop(t, None)

    def forget(self, keep_keyframes) -> None:
        """Drop the observations of keyframes outside ``keep_keyframes`` and the landmarks
        of tracks no longer seen in any kept keyframe (memory stays bounded)."""
        keep = set(int(k) for k in keep_keyframes)
        for kf in [k for k in self.obs if k not in keep]:
            del self.obs[kf]
        seen = set()
        for ids, _ in self.obs.values():
            seen.update(ids.tolist())
        for t in [t for t in self.landmarks if t not in seen]:
            del self.landmarks[t]
