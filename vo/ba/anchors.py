"""Revisit anchors: keyframes that left the window, linked again when the camera comes back.

A sliding window forgets: when a hand-held camera returns to a place it filmed many
keyframes ago, the window holds only the recent keyframes, so the scale and the
pose drift that built up since are not corrected. An *anchor* is an old keyframe
(its image, its adjusted pose and the adjusted points it observed) kept in a small
archive. When the newest keyframe of a window sees what an archived keyframe saw,
the archived keyframe joins that window as a held pose, and its points are linked
into the newest keyframe through a dense flow between the two images:

1. :func:`revisit_candidates`: an archived keyframe qualifies when it looks the same
   way (optical axes within ``max_angle_deg``), enough of its points project into the
   newest keyframe, their parallax (rotation removed) is small enough for a flow to
   find, their depths in the two views differ by at most ``max_zoom`` (a much nearer or
   farther view is not linked by the flow), fewer than ``max_shared`` of its points are
   still tracked into the newest keyframe (else the window's own tracks link the two
   already), and, with ``max_revisit_ratio`` < 1, when the camera came *back* to it (its
   centre nearer than that ratio x the path travelled since: a straight drive never
   qualifies). With the ratio at 1 any old keyframe in view qualifies: a long link past
   the window along the path;
2. the old image is warped into the newest keyframe's view by the flow the newest
   keyframe's points and the relative pose predict (:func:`predicted_flow`,
   :func:`warp_to_new`), a dense flow finds what the poses got wrong (followed by
   :func:`~trianflow_vo.ba.tracks.follow_flow`, forward-backward consistent; a dense flow,
   not sparse Lucas-Kanade at the points: they are flow-track pixels, many on edges or weak
   texture, where a window alone slides), and :func:`link_points` keeps a
   link when the pair fits one fundamental matrix (RANSAC) and the pixel lies within
   ``gate_px`` of where the current pose projects the point (the drift an anchor may
   correct is bounded).

:class:`AnchorArchive` holds at most ``keep`` keyframes; when full it drops the one
nearest another archived keyframe (the most redundant view), so memory does not
grow with the length of the run.

Poses are ``T_world_cam`` ``(4, 4)``; pixels ``(u, v)``; flows ``flow[y, x] = (dx, dy)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from trianflow_vo.ba.graph import project
from trianflow_vo.ba.tracks import sample_bilinear


@dataclass(frozen=True)
class Archived:
    """A keyframe that left the window.

    Attributes:
        index: source frame index.
        gray: ``(h, w)`` uint8 image at working resolution (what the flow is computed on).
        T_world_cam: ``(4, 4)`` its last adjusted pose.
        uv: ``(N, 2)`` pixels of the points it observed.
        X_world: ``(N, 3)`` those points, as last adjusted.
        path: distance travelled from the first keyframe to this one (trajectory units).
        track_ids: ``(N,)`` int64 the points' track ids (None: unknown).
    """

    index: int
    gray: np.ndarray
    T_world_cam: np.ndarray
    uv: np.ndarray
    X_world: np.ndarray
    path: float
    track_ids: np.ndarray | None = None


class AnchorArchive:
    """Old keyframes that may anchor a later window (at most ``keep``)."""

    def __init__(self, keep: int):
        if keep < 1:
            raise ValueError(f"keep must be >= 1, got {keep}")
        self.keep = int(keep)
        self.items: dict[int, Archived] = {}

    def __len__(self) -> int:
        return len(self.items)

    def add(self, item: Archived) -> None:
        """Archive ``item``; when over ``keep``, drop the archived keyframe nearest another one
        (the older of the closest pair)."""
        self.items[item.index] = item
        if len(self.items) <= self.keep:
            return
        keys = sorted(self.items)
        C = np.stack([self.items[k].T_world_cam[:3, 3] for k in keys])
        d = np.linalg.norm(C[:, None] - C[None], axis=2)
        np.fill_diagonal(d, np.inf)
        i, j = np.unravel_index(int(np.argmin(d)), d.shape)
        del self.items[keys[min(i, j)]]


def rotation_homography(K: np.ndarray, T_world_old: np.ndarray, T_world_new: np.ndarray) -> np.ndarray:
    """``(3, 3)`` homography ``K R_new_old K^-1`` that turns the old view to the new one's
    orientation (exact for points at infinity; what remains is the parallax of the translation)."""
    R_new_old = T_world_new[:3, :3].T @ T_world_old[:3, :3]
    return K @ R_new_old @ np.linalg.inv(K)


def apply_homography(H: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """``(N, 2)`` pixels mapped by ``H`` ``(3, 3)`` (``inf`` where they go to infinity)."""
    p = np.c_[np.asarray(uv, dtype=np.float64).reshape(-1, 2), np.ones(len(uv))] @ H.T
    with np.errstate(divide="ignore", invalid="ignore"):
        out = p[:, :2] / p[:, 2:3]
    out[~np.isfinite(out).all(axis=1) | (p[:, 2] <= 0)] = np.inf
    return out


def revisit_candidates(archive: AnchorArchive, T_world_cam: np.ndarray, path: float, K: np.ndarray,
                       size_hw: tuple[int, int], max_angle_deg: float, max_revisit_ratio: float,
                       min_points: int, max_parallax_px: float = np.inf,
                       max_zoom: float = np.inf, live_ids: np.ndarray | None = None,
                       max_shared: int | None = None) -> list[tuple[int, float]]:
    """Archived keyframes the camera at ``T_world_cam`` has come back to, best first.

    Args:
        archive: the old keyframes.
        T_world_cam: ``(4, 4)`` pose of the newest keyframe.
        path: distance travelled up to the newest keyframe (same origin as :attr:`Archived.path`).
        K: ``(3, 3)`` intrinsics; size_hw: ``(h, w)`` image size.
        max_angle_deg: largest angle between the two optical axes.
        max_revisit_ratio: the centres must be nearer than this x the path travelled between them;
            1: any old keyframe (a chord is never longer than its path).
        min_points: fewest of the archived keyframe's points that must project into the image.
        max_parallax_px: largest median distance between the points' projections and their old
            pixels turned by :func:`rotation_homography` (what the flow must find; pixels).
        max_zoom: largest ratio (either way) of the points' depths in the archived and the newest
            view (median): a patch seen this much nearer or farther is not found by the flow, even
            after the warp.
        live_ids: ``(M,)`` track ids observed in the newest keyframe; max_shared: an archived
            keyframe with at least this many of its points' tracks among them is skipped (the
            window's own tracks already link it to the newest keyframe; None: no limit).

    Returns:
        ``[(index, median parallax px), ...]``, the oldest first (the longest link).
    """
    T = np.asarray(T_world_cam, dtype=np.float64)
    h, w = size_hw
    cos_max = np.cos(np.radians(max_angle_deg))
    live = None  # live[track id]: observed in the newest keyframe
    if max_shared is not None and live_ids is not None:
        ids = np.asarray(live_ids, dtype=np.int64).reshape(-1)
        ids = ids[ids >= 0]
        live = np.zeros(int(ids.max()) + 1 if ids.size else 0, dtype=bool)
        live[ids] = True
    out = []
    for k, a in archive.items.items():
        travelled = path - a.path
        if travelled <= 0:
            continue
        if max_revisit_ratio < 1 and np.linalg.norm(T[:3, 3] - a.T_world_cam[:3, 3]) >= max_revisit_ratio * travelled:
            continue
        if float(T[:3, 2] @ a.T_world_cam[:3, 2]) < cos_max:
            continue
        if a.X_world.shape[0] < min_points:
            continue
        if live is not None and a.track_ids is not None:
            ids = a.track_ids[(a.track_ids >= 0) & (a.track_ids < live.size)]
            if int(live[ids].sum()) >= max_shared:
                continue
        uv, front = project(K, T, a.X_world)
        inside = front & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
        if int(inside.sum()) < min_points:
            continue
        if np.isfinite(max_zoom):
            X = a.X_world[inside]
            z_old = ((X - a.T_world_cam[:3, 3]) @ a.T_world_cam[:3, :3])[:, 2]
            z_new = ((X - T[:3, 3]) @ T[:3, :3])[:, 2]
            pos = (z_old > 0) & (z_new > 0)
            if not pos.any() or abs(float(np.median(np.log(z_old[pos] / z_new[pos])))) > np.log(max_zoom):
                continue
        turned = apply_homography(rotation_homography(K, a.T_world_cam, T), a.uv[inside])
        parallax = float(np.median(np.linalg.norm(uv[inside] - turned, axis=1)))
        if parallax <= max_parallax_px:
            out.append((k, parallax))
    out.sort(key=lambda kp: kp[0])
    return out


def predicted_flow(K: np.ndarray, T_new_old: np.ndarray, uv: np.ndarray, depth: np.ndarray,
                   size_hw: tuple[int, int], cell_px: int = 32, step: int = 4) -> np.ndarray:
    """Dense flow old -> new that the old view's points and the relative pose predict
    (a start for the flow between two distant views).

    The points' depths are spread over the old image (:func:`dense_inverse_depth` on a
    ``cell_px`` grid); the flow is computed every ``step`` pixels (each pixel moved into
    the new camera and projected) and interpolated bilinearly in between (a smooth
    field; exact to a few 1e-3 px for a plane, a fraction of a pixel where the depth jumps).

    Args:
        K: ``(3, 3)`` intrinsics; T_new_old: ``(4, 4)`` old camera -> new camera.
        uv: ``(N, 2)`` pixels of the old view's points; depth: ``(N,)`` their depths (> 0).
        size_hw: ``(h, w)``; cell_px: the depth grid's cell; step: the flow's sampling step (pixels).

    Returns:
        ``(h, w, 2)`` float32 flow (0 where the predicted point is behind the new camera).
    """
    from trianflow_vo.geometry.rolling_shutter import dense_inverse_depth

    h, w = size_hw
    step = max(1, int(step))
    hc, wc = -(-(h - 1) // step) + 1, -(-(w - 1) // step) + 1  # samples at 0, step, ... up to >= the last pixel
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    depth = np.asarray(depth, dtype=np.float64).reshape(-1)
    good = (depth > 0) & np.isfinite(depth) & np.isfinite(uv).all(axis=1)
    sparse = np.zeros((hc, wc))
    xi = np.clip(np.floor(uv[good, 0] / step).astype(np.int64), 0, wc - 1)
    yi = np.clip(np.floor(uv[good, 1] / step).astype(np.int64), 0, hc - 1)
    sparse[yi, xi] = depth[good]
    inv = dense_inverse_depth(sparse, max(1, cell_px // step))
    # the new pixel of old pixel (u, v) with inverse depth q: K (R K^-1 [u, v, 1] + q t)
    M = K @ T_new_old[:3, :3] @ np.linalg.inv(K)
    b = K @ T_new_old[:3, 3]
    u = (np.arange(wc, dtype=np.float64) * step)[None, :]
    v = (np.arange(hc, dtype=np.float64) * step)[:, None]
    x, y, z = (M[i, 0] * u + M[i, 1] * v + M[i, 2] + inv * b[i] for i in range(3))
    ok = z > 1e-9
    zs = np.where(ok, z, 1.0)
    coarse = np.zeros((hc, wc, 2), dtype=np.float32)
    coarse[..., 0] = np.where(ok, x / zs - u, 0.0)
    coarse[..., 1] = np.where(ok, y / zs - v, 0.0)
    if step == 1:
        return coarse
    mx = np.broadcast_to(np.arange(w, dtype=np.float32) / step, (h, w))
    my = np.broadcast_to(np.arange(h, dtype=np.float32)[:, None] / step, (h, w))
    return cv2.remap(coarse, np.ascontiguousarray(mx), np.ascontiguousarray(my), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)


def warp_to_new(gray_old: np.ndarray, bw: np.ndarray) -> np.ndarray:
    """The old image as the new view would see it, given a flow new -> old ``bw`` ``(h, w, 2)``:
    ``out[y] = gray_old[y + bw(y)]`` (bilinear; 0 outside)."""
    h, w = bw.shape[:2]
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    mx = np.ascontiguousarray(u + bw[..., 0].astype(np.float32))
    my = np.ascontiguousarray(v + bw[..., 1].astype(np.float32))
    return np.ascontiguousarray(cv2.remap(gray_old, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                                          borderValue=0))


def invert_flow_at(bw: np.ndarray, uv_old: np.ndarray, start: np.ndarray, iterations: int = 8) -> np.ndarray:
    """Pixels ``y`` of the new view with ``y + bw(y) = uv_old`` (fixed-point iteration from ``start``).

    Args:
        bw: ``(h, w, 2)`` flow new -> old (smooth, e.g. :func:`predicted_flow`).
        uv_old: ``(N, 2)`` old pixels; start: ``(N, 2)`` first guesses in the new view.

    Returns:
        ``(N, 2)`` new-view pixels (``nan`` where the iteration left the image).
    """
    h, w = bw.shape[:2]
    y = np.asarray(start, dtype=np.float64).reshape(-1, 2).copy()
    uv_old = np.asarray(uv_old, dtype=np.float64).reshape(-1, 2)
    for _ in range(iterations):
        ok = np.isfinite(y).all(axis=1)
        f, inside = sample_bilinear(bw, np.where(ok[:, None], y, -1.0))
        y = np.where((ok & inside)[:, None], uv_old - f, np.nan)
    return y


def link_points(uv_old: np.ndarray, uv_new: np.ndarray, followed: np.ndarray, uv_pred: np.ndarray,
                ransac_px: float, gate_px: float, seed: int = 0) -> np.ndarray:
    """Which followed pixels of an archived keyframe become links into the newest keyframe.

    Args:
        uv_old: ``(N, 2)`` pixels in the old keyframe.
        uv_new: ``(N, 2)`` where they were followed to in the newest keyframe
            (:func:`~trianflow_vo.ba.tracks.follow_flow`).
        followed: ``(N,)`` bool, the follow succeeded.
        uv_pred: ``(N, 2)`` where the newest keyframe's current pose projects the same points
            (``inf`` behind it).
        ransac_px: RANSAC threshold of the fundamental matrix fit (pixels).
        gate_px: largest distance between the linked pixel and ``uv_pred`` (pixels).
        seed: OpenCV's RNG seed for the RANSAC (a run is reproducible).

    Returns:
        ``(N,)`` bool: within the gate and an inlier of one fundamental matrix (none when fewer
        than 8 pass the gate).
    """
    uv_old = np.asarray(uv_old, dtype=np.float64).reshape(-1, 2)
    uv_new = np.asarray(uv_new, dtype=np.float64).reshape(-1, 2)
    n = uv_old.shape[0]
    ok = np.asarray(followed, dtype=bool).copy()
    with np.errstate(invalid="ignore"):
        ok &= np.linalg.norm(uv_new - uv_pred, axis=1) < gate_px
    idx = np.flatnonzero(ok)
    valid = np.zeros(n, dtype=bool)
    if idx.size < 8:
        return valid
    cv2.setRNGSeed(int(seed))
    _, mask = cv2.findFundamentalMat(np.ascontiguousarray(uv_old[idx], dtype=np.float64),
                                     np.ascontiguousarray(uv_new[idx], dtype=np.float64),
                                     cv2.FM_RANSAC, float(ransac_px), 0.999)
    if mask is not None:
        valid[idx[mask.ravel().astype(bool)]] = True
    return valid
