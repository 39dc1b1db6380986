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
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from trianflow_vo.backend import PoseRevision
from trianflow_vo.camera import PinholeCamera, unproject
from trianflow_vo.config import Config
from trianflow_vo.depth.fusion import fuse_log_depth
from trianflow_vo.frame import Branch, FrameResult, FrameStats, FrameView
from trianflow_vo.frontend import Solution, failed_solution, identity_solution, small_motion_solution, step_scale
from trianflow_vo.geometry.relative_pose import estimate_relative_pose
from trianflow_vo.geometry.rotation import fit_rotation
from trianflow_vo.geometry.scale import align_scale
from trianflow_vo.geometry.se3 import invert_T, make_T
from trianflow_vo.geometry.triangulation import triangulate_midpoint
from trianflow_vo.keyframe import Keyframe, TrackIds, Tracks
from trianflow_vo.odometry import result_from_solution
from trianflow_vo.timing import StageTimer


@dataclass(frozen=True)
class SparseParams:
    """Tracker parameters; the geometry is the dense pipeline's (the run's :class:`Config`)."""

    max_corners: int = 2000
    quality_level: float = 0.01
    min_distance_px: int = 7
    block_size: int = 7
    redetect_ratio: float = 0.7  # top up when fewer tracks than this fraction of max_corners
    lk_window: int = 31  # 21 lost most tracks on KITTI 00 at stride 3
    lk_levels: int = 3
    fb_max_px: float = 0.5  # forward-backward distance above which a track is dropped


class SparseOdometry:
    """Shi-Tomasi + pyramidal LK odometry with the dense pipeline's geometry.

    Args:
        camera: working-resolution :class:`~trianflow_vo.camera.PinholeCamera`.
        config: the run's :class:`~trianflow_vo.config.Config` (geometry, scale,
            keyframes, depth and sampling.seed are used; LK tracks are less precise
            than dense flow, and 0.25 px RANSAC beat 0.1 and 0.5 px on KITTI 00 stride 3).
        params: :class:`SparseParams`.

    :meth:`step` has the signature of :meth:`trianflow_vo.odometry.Odometry.step`.
    """

    def __init__(self, camera: PinholeCamera, config: Config = Config(), params: SparseParams = SparseParams()):
        self.camera = camera
        self.K = camera.K
        self.h, self.w = camera.size_hw
        self.cfg = config
        self.p = params
        self.rng = np.random.default_rng(config.sampling.seed)
        self.ids = TrackIds()
        self.line = 0
        self.prev_gray: np.ndarray | None = None
        self.kf_index: int | None = None
        self.kf_T_world_cam = np.eye(4)
        self.T_world_last = np.eye(4)
        self.last_step_norm: float | None = None
        # tracks: id, pixel in the keyframe, pixel in the previous frame, keyframe depth and weight
        self.track_ids = np.zeros(0, np.int64)
        self.kf_pts = np.zeros((0, 2), np.float32)
        self.cur_pts = np.zeros((0, 2), np.float32)
        self.depth = np.zeros(0)
        self.weight = np.zeros(0)

    @property
    def keyframe(self) -> Keyframe:
        """The keyframe state (tracks with depth), for a back-end."""
        has = (self.depth > 0) & (self.weight > 0)
        return Keyframe(self.kf_index, None, None, self.kf_T_world_cam,
                        Tracks(self.track_ids[has], self.kf_pts[has], self.depth[has], self.weight[has]))

    def apply_revision(self, revision: PoseRevision, T_world_last: np.ndarray) -> None:
        if self.kf_index in revision.T_world_cam:
            self.kf_T_world_cam = np.array(revision.T_world_cam[self.kf_index])
        self.T_world_last = np.array(T_world_last, dtype=np.float64)

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
        self.track_ids = self.track_ids[ok]
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
            self.track_ids = np.concatenate([self.track_ids, self.ids.new(len(new))])
            self.cur_pts = np.concatenate([self.cur_pts, new])
            self.kf_pts = self.cur_pts.copy()
            self.depth = np.concatenate([self.depth, np.zeros(len(new))])
            self.weight = np.concatenate([self.weight, np.zeros(len(new))])

    # -- main step ------------------------------------------------------------
    def step(self, frame_index: int, timestamp: float | None, image: np.ndarray,
             timer: StageTimer | None = None) -> FrameResult:
        """Process one working-resolution frame ``(h, w, 3)`` uint8 BGR (or ``(h, w)`` gray)."""
        tm = timer if timer is not None else StageTimer()
        t0 = time.perf_counter()
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        t0 = tm.add("prepare", t0)
        if self.prev_gray is None:
            self.prev_gray = gray
            self._new_keyframe(frame_index, gray, np.eye(4), np.zeros(0), np.zeros(0))
            tm.add("detect", t0)
            sol = Solution(Branch.INIT, "first frame", np.eye(4), np.eye(4), tracks=Tracks.empty())
            return self._result(frame_index, timestamp, image, None, sol, {}, tm)
        new_pts, ok = self._track(self.prev_gray, gray, self.cur_pts)
        self.cur_pts = new_pts.astype(np.float32)
        self._keep(ok)
        self.prev_gray = gray
        tm.add("track", t0)
        kf_index, stats = self.kf_index, {"tracks": int(len(self.cur_pts))}
        sol = self._solve(frame_index, gray, stats, tm)
        return self._result(frame_index, timestamp, image, kf_index, sol, stats, tm)

    def _solve(self, frame_index: int, gray: np.ndarray, stats: dict, tm: StageTimer) -> Solution:
        """The branch of this frame: failed, identity, small motion or two-view."""
        g, n = self.cfg.geometry, len(self.cur_pts)
        if n < max(8, g.min_inliers):
            # too few tracks to solve anything: restart from this frame (the scale chain is broken)
            sol = failed_solution(self.kf_T_world_cam, self.T_world_last, f"only {n} tracks survived")
            self._new_keyframe(frame_index, gray, self.T_world_last, np.zeros(n), np.zeros(n))
            return replace(sol, tracks=self.keyframe.tracks)  # this frame is the new (depth-less) keyframe
        pts1, pts2 = self.kf_pts.astype(np.float64), self.cur_pts.astype(np.float64)
        mag = np.linalg.norm(pts2 - pts1, axis=1)
        stats["mean_flow_px"] = float(mag.mean())
        if np.median(mag) < self.cfg.keyframes.static_flow_px:
            return identity_solution(self.kf_T_world_cam, f"median flow {np.median(mag):.2f} px: camera static")
        t0 = time.perf_counter()
        R_rot, par = fit_rotation(pts1, pts2, self.K)
        stats["parallax_px"] = parallax = float(np.median(par))
        tm.add("rotation", t0)
        if parallax < self.cfg.keyframes.min_parallax_px:
            return self._small_motion(f"parallax {parallax:.2f} px < {self.cfg.keyframes.min_parallax_px} px",
                                      R_rot, tm)
        return self._two_view(frame_index, gray, pts1, pts2, R_rot, tm)

    def _small_motion(self, why: str, R_rot: np.ndarray, tm: StageTimer) -> Solution:
        """PnP from the keyframe depth of the tracks (at least 20), else rotation only."""
        t0 = time.perf_counter()
        has = (self.depth > 0) & (self.weight > 0)
        X = unproject(self.kf_pts[has], self.depth[has], self.K) if has.sum() >= 20 else None
        sol = small_motion_solution(X, self.kf_pts[has].astype(np.float64), self.cur_pts[has].astype(np.float64),
                                    R_rot, self.K, self.kf_T_world_cam, why, self.cfg.geometry.pnp_reproj_px,
                                    self.cfg.sampling.seed)
        if X is not None:
            tm.add("pnp", t0)
        return sol

    def _two_view(self, frame_index: int, gray: np.ndarray, pts1: np.ndarray, pts2: np.ndarray,
                  R_rot: np.ndarray, tm: StageTimer) -> Solution:
        """Two-view pose of the tracks, scale from their carried depth; the frame becomes the keyframe."""
        g, K = self.cfg.geometry, self.K
        t0 = time.perf_counter()
        rel, ok = estimate_relative_pose(pts1, pts2, K, threshold_px=g.ransac_threshold_px, method=g.ransac_method,
                                         refine=g.refine, inlier_px=g.epi_inlier_px, rng=self.rng)
        t0 = tm.add("pose", t0)
        if not ok or rel.inliers.sum() < g.min_inliers:
            n_in = 0 if rel is None else int(rel.inliers.sum())
            return self._small_motion(f"two-view geometry degenerate ({n_in} inliers)", R_rot, tm)
        inl = rel.inliers
        stats = {"inliers": int(inl.sum()), "inlier_ratio": float(inl.mean())}
        X, valid, angle = triangulate_midpoint(pts1, pts2, K, rel.R, rel.t, min_angle=g.min_angle_rad)
        valid &= inl
        t0 = tm.add("triangulate", t0)
        min_points = self.cfg.scale.min_points
        if valid.sum() < min_points:
            return self._small_motion(f"only {int(valid.sum())} points triangulated", R_rot, tm)
        # scale from the depth carried at the tracked points (parallax-weighted, as the dense pipeline)
        w_new = angle[valid] ** 2
        d_ref = self.depth[valid]
        w_ref = self.weight[valid] * self.cfg.depth.decay
        w_scale = 1.0 / (1.0 / np.maximum(w_new, 1e-12) + 1.0 / np.maximum(w_ref, 1e-12))
        scale, scale_ok = align_scale(X[valid, 2], d_ref, weights=np.where(w_ref > 0, w_scale, 0.0),
                                      min_points=min_points)
        stats["scale_points"] = int(((d_ref > 0) & (w_ref > 0)).sum())
        scale, how, degraded = step_scale(scale, scale_ok, self.last_step_norm)
        stats["degraded"] = degraded
        t0 = tm.add("scale", t0)
        stats["scale"] = float(scale)
        t_s = rel.t * scale
        X_s = X[valid] * scale
        w_out = w_new
        if scale_ok and self.cfg.depth.fusion:
            d_f, w_out = fuse_log_depth(d_ref, w_ref, X_s[:, 2], w_new, max_log_gap=self.cfg.depth.max_log_gap)
            X_s = X_s * (d_f / X_s[:, 2])[:, None]
        X_cur = X_s @ rel.R.T + t_s
        T_ref_cam = invert_T(make_T(rel.R, t_s))
        T_world_cur = self.kf_T_world_cam @ T_ref_cam
        points_world = X_s @ self.kf_T_world_cam[:3, :3].T + self.kf_T_world_cam[:3, 3]
        self.last_step_norm = float(np.linalg.norm(t_s))
        n = len(self.cur_pts)
        depth_cur, weight_cur = np.zeros(n), np.zeros(n)
        depth_cur[valid] = X_cur[:, 2]
        weight_cur[valid] = w_out
        behind = np.flatnonzero(valid)[~(X_cur[:, 2] > 0)]
        depth_cur[behind] = 0.0
        weight_cur[behind] = 0.0
        self._new_keyframe(frame_index, gray, T_world_cur, depth_cur, weight_cur)
        tm.add("bookkeeping", t0)
        return Solution(Branch.TWO_VIEW, how, T_world_cur, T_ref_cam, stats, pts_ref=pts1[valid], pts_cur=pts2[valid],
                        points_world=points_world, tracks=self.keyframe.tracks,
                        step_norm=self.last_step_norm)

    def _result(self, frame_index: int, timestamp: float | None, image: np.ndarray, kf_index: int | None,
                sol: Solution, stats: dict, tm: StageTimer) -> FrameResult:
        self.T_world_last = sol.T_world_cam
        line, self.line = self.line, self.line + 1
        view = FrameView.of(image=image, pts_ref=sol.pts_ref, pts_cur=sol.pts_cur, points_world=sol.points_world)
        return result_from_solution(line, frame_index, timestamp, kf_index, sol, stats, self.K, tm, view)

    def describe(self) -> dict:
        return {"odometry": "sparse", "tracker": "shi-tomasi + pyramidal lucas-kanade", "params": asdict(self.p)}


def run_sparse(seq_path, out_dir, *, start: int = 0, end: int | None = None, stride: int = 1, size=None,
               params: SparseParams = SparseParams(), config: Config = Config()) -> dict:
    """Run :class:`SparseOdometry` over a sequence through :func:`trianflow_vo.pipeline.run`, so it
    writes the same run folder (``poses.txt``, ``frames.txt``, ``run.json``, ...) to
    ``out_dir``. Returns the ``run.json`` summary."""
    from trianflow_vo.pipeline import run

    config = replace(config, input=replace(config.input, start=start, end=end, stride=stride, size=size),
                     output=replace(config.output, plot=False))
    return run(Path(seq_path), Path(out_dir), config,
               odometry_factory=lambda camera, cfg: SparseOdometry(camera, cfg, params))
