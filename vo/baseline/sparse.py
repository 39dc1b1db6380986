"""Classical sparse visual odometry: the reference point of the benchmark.

Shi-Tomasi corners tracked by pyramidal Lucas-Kanade (forward and backward, with
a forward-backward check) replace the dense flow; everything after the matches is
the dense pipeline's: the same relative-pose estimator
(:func:`vo.geometry.relative_pose.estimate_relative_pose`), mid-point
triangulation, a parallax-weighted scale from the depth carried by the previous
triangulation (:func:`vo.geometry.scale.align_scale`), the same small depth
filter fusing carried and new depth along each track, and the same
frame-to-keyframe structure with its identity / PnP / rotation-only fallbacks.

Tracks live from keyframe to keyframe: each holds its pixel in the keyframe,
its pixel in the latest frame and the keyframe depth (0 = unknown) with its
weight. Tracking runs between consecutive frames; the pose is solved between the
keyframe and the current frame. When a two-view step succeeds the current frame
becomes the keyframe, and corners are re-detected when the tracked count has
fallen below ``redetect_ratio * max_corners``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from trianflow_vo.depth.fusion import fuse_log_depth  # noqa: F401  (re-exported)

from trianflow_vo.geometry.pnp import backproject, solve_pnp
from trianflow_vo.geometry.relative_pose import estimate_relative_pose
from trianflow_vo.geometry.rotation import fit_rotation
from trianflow_vo.geometry.scale import align_scale
from trianflow_vo.geometry.se3 import invert_T, make_T
from trianflow_vo.geometry.triangulation import triangulate_midpoint
from trianflow_vo.observer import FrameRecord
from trianflow_vo.timing import StageTimer
from trianflow_vo.odometry import OdometryParams


@dataclass(frozen=True)
class SparseParams:
    """Tracker parameters; the geometry parameters are the dense pipeline's :class:`OdometryParams`."""

    max_corners: int = 2000
    quality_level: float = 0.01
    min_distance_px: int = 7
    block_size: int = 7
    redetect_ratio: float = 0.7  # top up when fewer tracks than this fraction of max_corners
    lk_window: int = 31  # 21 lost most tracks on KITTI 00 at stride 3
    lk_levels: int = 3
    fb_max_px: float = 0.5  # forward-backward distance above which a track is dropped
    # LK tracks are less precise than the dense flow's: 0.25 px beat 0.1 and 0.5 px on KITTI 00 stride 3
    geometry: OdometryParams = OdometryParams(ransac_threshold_px=0.25)


class SparseOdometry:
    """Shi-Tomasi + pyramidal LK odometry with the dense pipeline's geometry.

    Args:
        K: ``(3, 3)`` intrinsics at working resolution.
        size_hw: working ``(h, w)``.
        params: :class:`SparseParams`.

    :meth:`step` has the signature of :meth:`vo.odometry.Odometry.step`.
    """

    def __init__(self, K: np.ndarray, size_hw: tuple[int, int], params: SparseParams = SparseParams()):
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"K must be (3, 3), got {K.shape}")
        self.K = K
        self.h, self.w = int(size_hw[0]), int(size_hw[1])
        self.p = params
        self.g = params.geometry
        self.rng = np.random.default_rng(self.g.seed)
        self.line = 0
        self.prev_gray: np.ndarray | None = None
        self.kf_index: int | None = None
        self.kf_T_world_cam = np.eye(4)
        self.T_world_last = np.eye(4)
        self.last_step_norm: float | None = None
        # tracks: pixel in the keyframe, pixel in the previous frame, keyframe depth and weight
        self.kf_pts = np.zeros((0, 2), np.float32)
        self.cur_pts = np.zeros((0, 2), np.float32)
        self.depth = np.zeros(0)
        self.weight = np.zeros(0)

    # -- tracks ---------------------------------------------------------------
    def _detect(self, gray: np.ndarray, existing: np.ndarray, n: int) -> np.ndarray:
        """Up to ``n`` new corners ``(M, 2)`` float32 away from ``existing`` ``(E, 2)``."""
        if n <= 0:
            return np.zeros((0, 2), np.float32)
        mask = np.full(gray.shape, 255, np.uint8)
        for x, y in np.rint(existing).astype(int):
            cv2.circle(mask, (int(x), int(y)), self.p.min_distance_px, 0, -1)
        c = cv2.goodFeaturesToTrack(gray, maxCorners=n, qualityLevel=self.p.quality_level,
                                    minDistance=self.p.min_distance_px, mask=mask, blockSize=self.p.block_size)
        return np.zeros((0, 2), np.float32) if c is None else c.reshape(-1, 2).astype(np.float32)

    def _track(self, prev: np.ndarray, cur: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """LK forward and backward; ``(new_pts (N, 2), ok (N,))`` with the forward-backward check."""
        if len(pts) == 0:
            return pts, np.zeros(0, bool)
        win = (self.p.lk_window, self.p.lk_window)
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
        p0 = pts.reshape(-1, 1, 2)
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev, cur, p0, None, winSize=win, maxLevel=self.p.lk_levels,
                                              criteria=crit)
        p0b, st2, _ = cv2.calcOpticalFlowPyrLK(cur, prev, p1, None, winSize=win, maxLevel=self.p.lk_levels,
                                               criteria=crit)
        p1 = p1.reshape(-1, 2)
        fb = np.linalg.norm(p0b.reshape(-1, 2) - pts, axis=1)
        inside = (p1[:, 0] >= 0) & (p1[:, 0] <= self.w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= self.h - 1)
        ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < self.p.fb_max_px) & inside
        return p1, ok

    def _keep(self, ok: np.ndarray) -> None:
        self.kf_pts, self.cur_pts = self.kf_pts[ok], self.cur_pts[ok]
        self.depth, self.weight = self.depth[ok], self.weight[ok]

    def _new_keyframe(self, frame_index: int, gray: np.ndarray, T_world_cam: np.ndarray,
                      depth: np.ndarray, weight: np.ndarray) -> None:
        """Current tracks become the keyframe's; top up with fresh corners (no depth)."""
        self.kf_index = frame_index
        self.kf_T_world_cam = T_world_cam
        self.kf_pts = self.cur_pts.copy()
        self.depth, self.weight = depth, weight
        if len(self.cur_pts) < self.p.redetect_ratio * self.p.max_corners:
            new = self._detect(gray, self.cur_pts, self.p.max_corners - len(self.cur_pts))
            self.cur_pts = np.concatenate([self.cur_pts, new])
            self.kf_pts = self.cur_pts.copy()
            self.depth = np.concatenate([self.depth, np.zeros(len(new))])
            self.weight = np.concatenate([self.weight, np.zeros(len(new))])

    # -- main step ------------------------------------------------------------
    def step(self, frame_index: int, timestamp: float | None, image: np.ndarray) -> FrameRecord:
        """Process one working-resolution frame ``(h, w, 3)`` uint8 BGR (or ``(h, w)`` gray)."""
        tm = StageTimer()
        t0 = time.perf_counter()
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        t0 = tm.add("prepare", t0)
        line = self.line
        self.line += 1
        if self.prev_gray is None:
            self.prev_gray = gray
            self._new_keyframe(frame_index, gray, np.eye(4), np.zeros(0), np.zeros(0))
            tm.add("detect", t0)
            return FrameRecord(line, frame_index, timestamp, np.eye(4), "init", "first frame", image, self.K,
                               stats={"ms": tm.ms})
        new_pts, ok = self._track(self.prev_gray, gray, self.cur_pts)
        self.cur_pts = new_pts.astype(np.float32)
        self._keep(ok)
        self.prev_gray = gray
        t0 = tm.add("track", t0)
        rec = FrameRecord(line, frame_index, timestamp, self.T_world_last, "failed", "", image, self.K,
                          ref_index=self.kf_index, stats={"ms": tm.ms, "tracks": int(len(self.cur_pts))})
        g = self.g
        n = len(self.cur_pts)
        if n < max(8, g.min_inliers):
            # too few tracks to solve anything: restart from this frame (the scale chain is broken)
            self._new_keyframe(frame_index, gray, self.T_world_last, np.zeros(n), np.zeros(n))
            return self._fail(rec, f"only {n} tracks survived", tm)
        pts1 = self.kf_pts.astype(np.float64)
        pts2 = self.cur_pts.astype(np.float64)
        mag = np.linalg.norm(pts2 - pts1, axis=1)
        rec.stats["mean_flow"] = float(mag.mean())
        if np.median(mag) < g.static_flow_px:
            rec.T_world_cam = self.kf_T_world_cam
            rec.branch, rec.reason = "identity", f"median flow {np.median(mag):.2f} px: camera static"
            return self._finish(rec, tm)
        R_rot, par = fit_rotation(pts1, pts2, self.K)
        parallax = float(np.median(par))
        rec.stats["parallax"] = parallax
        t0 = tm.add("rotation", t0)
        if parallax < g.min_parallax_px:
            return self._small_motion(rec, f"parallax {parallax:.2f} px < {g.min_parallax_px} px", R_rot, tm)
        rel, ok = estimate_relative_pose(pts1, pts2, self.K, threshold_px=g.ransac_threshold_px,
                                         method=g.ransac_method, refine=g.refine, inlier_px=g.epi_inlier_px,
                                         rng=self.rng)
        t0 = tm.add("pose", t0)
        if not ok or rel.inliers.sum() < g.min_inliers:
            n_in = 0 if rel is None else int(rel.inliers.sum())
            return self._small_motion(rec, f"two-view geometry degenerate ({n_in} inliers)", R_rot, tm)
        inl = rel.inliers
        rec.stats["inliers"] = int(inl.sum())
        rec.stats["inlier_ratio"] = float(inl.mean())
        X, valid, angle = triangulate_midpoint(pts1, pts2, self.K, rel.R, rel.t, min_angle=g.min_angle_rad)
        valid &= inl
        t0 = tm.add("triangulate", t0)
        if valid.sum() < g.min_scale_points:
            return self._small_motion(rec, f"only {int(valid.sum())} points triangulated", R_rot, tm)
        # scale from the depth carried at the tracked points (parallax-weighted, as the dense pipeline)
        d_tri = X[valid, 2]
        w_new = angle[valid] ** 2
        d_ref = self.depth[valid]
        w_ref = self.weight[valid] * g.depth_decay
        w_scale = 1.0 / (1.0 / np.maximum(w_new, 1e-12) + 1.0 / np.maximum(w_ref, 1e-12))
        scale, scale_ok = align_scale(d_tri, d_ref, weights=np.where(w_ref > 0, w_scale, 0.0),
                                      min_points=g.min_scale_points)
        rec.stats["scale_points"] = int(((d_ref > 0) & (w_ref > 0)).sum())
        how = ""
        if not scale_ok:
            if self.last_step_norm is None:
                scale, how = 1.0, "first two-view step sets the unit of scale"
            else:
                scale, how = self.last_step_norm, "scale lost (too few points with depth): constant speed assumed"
        t0 = tm.add("scale", t0)
        rec.stats["scale"] = float(scale)
        t_s = rel.t * scale
        X_s = X[valid] * scale
        w_out = w_new
        if scale_ok and g.depth_fusion:
            d_f, w_out = fuse_log_depth(d_ref, w_ref, X_s[:, 2], w_new)
            X_s = X_s * (d_f / X_s[:, 2])[:, None]
        X_cur = X_s @ rel.R.T + t_s
        T_world_cur = self.kf_T_world_cam @ invert_T(make_T(rel.R, t_s))
        rec.T_world_cam = T_world_cur
        rec.branch, rec.reason = "two-view", how
        rec.pts_ref, rec.pts_cur = pts1[valid], pts2[valid]
        rec.points_world = X_s @ self.kf_T_world_cam[:3, :3].T + self.kf_T_world_cam[:3, 3]
        self.last_step_norm = float(np.linalg.norm(t_s))
        depth_cur = np.zeros(n)
        weight_cur = np.zeros(n)
        depth_cur[valid] = X_cur[:, 2]
        weight_cur[valid] = w_out
        keep = X_cur[:, 2] > 0
        depth_cur[np.flatnonzero(valid)[~keep]] = 0.0
        weight_cur[np.flatnonzero(valid)[~keep]] = 0.0
        self._new_keyframe(frame_index, gray, T_world_cur, depth_cur, weight_cur)
        tm.add("bookkeeping", t0)
        return self._finish(rec, tm)

    def _small_motion(self, rec: FrameRecord, why: str, R_rot: np.ndarray, tm: StageTimer) -> FrameRecord:
        """PnP from the keyframe depth of the tracks when there is some; else rotation only."""
        t0 = time.perf_counter()
        has = (self.depth > 0) & (self.weight > 0)
        if has.sum() >= 20:
            X = backproject(self.kf_pts[has].astype(np.float64), self.depth[has], self.K)
            q2 = self.cur_pts[has].astype(np.float64)
            (R, t, inl), ok = solve_pnp(X, q2, self.K, reproj_px=self.g.pnp_reproj_px, rng_seed=self.g.seed)
            tm.add("pnp", t0)
            if ok:
                rec.T_world_cam = self.kf_T_world_cam @ invert_T(make_T(R, t))
                rec.branch, rec.reason = "pnp", why
                rec.stats["inliers"] = int(inl.sum())
                rec.pts_ref, rec.pts_cur = self.kf_pts[has][inl], q2[inl]
                return self._finish(rec, tm)
            why += "; PnP failed"
        else:
            why += "; no depth yet: rotation only"
        rec.T_world_cam = self.kf_T_world_cam @ invert_T(make_T(R_rot, np.zeros(3)))
        rec.branch, rec.reason = "rotation", why
        return self._finish(rec, tm)

    def _fail(self, rec: FrameRecord, why: str, tm: StageTimer) -> FrameRecord:
        rec.branch, rec.reason = "failed", why + "; pose kept from the previous frame"
        rec.T_world_cam = self.T_world_last
        return self._finish(rec, tm)

    def describe(self) -> dict:
        from dataclasses import asdict

        return {"name": "sparse", "tracker": "shi-tomasi + pyramidal lucas-kanade", "params": asdict(self.p)}

    def _finish(self, rec: FrameRecord, tm: StageTimer) -> FrameRecord:
        self.T_world_last = rec.T_world_cam
        rec.stats["ms"] = tm.ms
        return rec


def run_sparse(seq_path, out_dir, *, start: int = 0, end: int | None = None, stride: int = 1, size=None,
               params: SparseParams = SparseParams()) -> dict:
    """Run :class:`SparseOdometry` over a sequence through :func:`vo.pipeline.run`, so it
    writes the same run folder (``poses.txt``, ``frames.txt``, ``run.json``, ...) to
    ``out_dir``. Returns the ``run.json`` summary."""
    from trianflow_vo.config import RunConfig
    from trianflow_vo.pipeline import run

    config = RunConfig(seq=Path(seq_path), out_dir=Path(out_dir), start=start, end=end, stride=stride, size=size,
                       seed=params.geometry.seed, plot=False, quiet=True)
    return run(config, make_odometry=lambda K, size_hw, cfg: SparseOdometry(K, size_hw, params))
