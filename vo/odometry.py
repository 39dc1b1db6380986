"""TrianFlow odometry, one frame at a time: flow -> matches -> [R|t] -> triangulation -> scale.

:class:`Odometry` holds the state (the current keyframe, its pose and depth) and
turns each new working-resolution image into a :class:`vo.observer.FrameRecord`.
It has no I/O; :mod:`vo.pipeline` feeds it frames and writes its results.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from trianflow_vo.depth.base import DepthSource
from trianflow_vo.depth.fusion import fuse_log_depth
from trianflow_vo.flow.base import FlowSource
from trianflow_vo.flow.masks import flow_scores
from trianflow_vo.geometry.epipolar import inlier_score
from trianflow_vo.geometry.pnp import backproject, solve_pnp
from trianflow_vo.geometry.relative_pose import estimate_relative_pose
from trianflow_vo.geometry.rotation import fit_rotation
from trianflow_vo.geometry.scale import align_scale
from trianflow_vo.geometry.se3 import invert_T, make_T
from trianflow_vo.geometry.triangulation import triangulate_midpoint
from trianflow_vo.observer import FrameRecord
from trianflow_vo.timing import StageTimer


@dataclass(frozen=True)
class OdometryParams:
    """Method parameters (defaults chosen by measurement, see benchmarks/README.md)."""

    n_samples: int = 6000
    top_ratio: float = 0.2
    ransac_method: str = "ransac"
    ransac_threshold_px: float = 0.25
    ransac_subset: int = 1000  # RANSAC on a subset, refinement on all matches
    refine: bool = True
    epi_inlier_px: float = 0.5  # M_r = (D_epi < 0.5) / (1 + D_epi)
    min_parallax_px: float = 3.0  # median parallax after removing rotation
    static_flow_px: float = 0.25  # median flow under this: the camera did not move
    min_inliers: int = 100
    min_scale_points: int = 20
    max_anchors: int = 6000
    min_angle_rad: float = 1e-3
    pnp_reproj_px: float = 1.0
    depth_fusion: bool = True  # fuse carried depth with new triangulation (weight-free source)
    depth_decay: float = 0.8  # carried depth loses this much weight per step
    pnp_check_ratio: float = 1.5  # two-view scale vs PnP disagreeing more than this: use PnP (0 = off)
    seed: int = 0


@dataclass
class _Keyframe:
    index: int
    image: np.ndarray
    prepared: object
    T_world_cam: np.ndarray


class Odometry:
    """Frame-to-keyframe TrianFlow odometry.

    Args:
        K: ``(3, 3)`` intrinsics at working resolution.
        size_hw: working ``(h, w)``.
        flow: a :class:`vo.flow.base.FlowSource`.
        depth: a :class:`vo.depth.base.DepthSource`.
        params: :class:`OdometryParams`.
    """

    def __init__(self, K: np.ndarray, size_hw: tuple[int, int], flow: FlowSource, depth: DepthSource,
                 params: OdometryParams = OdometryParams()):
        if K.shape != (3, 3):
            raise ValueError(f"K must be (3, 3), got {K.shape}")
        self.K = np.asarray(K, dtype=np.float64)
        self.h, self.w = size_hw
        self.flow = flow
        self.depth = depth
        self.p = params
        self.rng = np.random.default_rng(params.seed)
        self.kf: _Keyframe | None = None
        self.T_world_last = np.eye(4)
        self.last_step_norm: float | None = None  # |t| of the last keyframe-to-keyframe step
        gx, gy = np.meshgrid(np.arange(self.w, dtype=np.float32), np.arange(self.h, dtype=np.float32))
        self._grid = np.stack([gx.ravel(), gy.ravel()], 1)
        self.line = 0

    # -- sampling -------------------------------------------------------------
    def _draw(self, score: np.ndarray, n: int, extra: np.ndarray | None = None) -> np.ndarray:
        """Flat pixel indices: top ``top_ratio`` of positive ``score``, then ``n`` at random."""
        flat = score.ravel()
        pos = np.flatnonzero(flat > 0)
        if pos.size == 0:
            return np.zeros(0, dtype=np.int64)
        k = max(1, int(np.ceil(self.p.top_ratio * pos.size)))
        if k < pos.size:
            top = pos[np.argpartition(flat[pos], pos.size - k)[pos.size - k:]]
        else:
            top = pos
        if top.size > n:
            top = self.rng.choice(top, n, replace=False)
        if extra is not None and extra.size:
            top = np.union1d(top, extra)
        return top

    def _epipolar_distance_map(self, F: np.ndarray, fw: np.ndarray) -> np.ndarray:
        """D_epi ``(h, w)``: distance of ``x + flow(x)`` to the epipolar line ``F x``, every pixel."""
        F = F.astype(np.float32)
        gx = np.arange(self.w, dtype=np.float32)[None, :]
        gy = np.arange(self.h, dtype=np.float32)[:, None]
        a = F[0, 0] * gx + F[0, 1] * gy + F[0, 2]
        b = F[1, 0] * gx + F[1, 1] * gy + F[1, 2]
        c = F[2, 0] * gx + F[2, 1] * gy + F[2, 2]
        num = np.abs(a * (gx + fw[..., 0]) + b * (gy + fw[..., 1]) + c)
        return num / (np.sqrt(a * a + b * b) + 1e-12)

    # -- main step ------------------------------------------------------------
    def step(self, frame_index: int, timestamp: float | None, image: np.ndarray) -> FrameRecord:
        """Process one working-resolution frame ``(h, w, 3)`` uint8 BGR."""
        tm = StageTimer()
        t0 = time.perf_counter()
        prepared = self.flow.prepare(image)
        t0 = tm.add("prepare", t0)
        line = self.line
        self.line += 1
        if self.kf is None:
            self.kf = _Keyframe(frame_index, image, prepared, np.eye(4))
            self.T_world_last = np.eye(4)
            self.depth.predict(frame_index, image)
            tm.add("depth", t0)
            return FrameRecord(line, frame_index, timestamp, np.eye(4), "init", "first frame", image, self.K,
                               stats={"ms": tm.ms})
        kf = self.kf
        fw, bw = self.flow.flow_pair(kf.prepared, prepared)
        t0 = tm.add("flow", t0)
        _, m_s, m_o = flow_scores(fw, bw)
        t0 = tm.add("masks", t0)
        score = m_s * m_o
        idx = self._draw(score, self.p.n_samples)
        rec = FrameRecord(line, frame_index, timestamp, self.T_world_last, "failed", "", image, self.K,
                          ref_index=kf.index, flow=fw, stats={"ms": tm.ms})
        if idx.size < max(8, self.p.min_inliers):
            return self._fail(rec, f"only {idx.size} reliable flow matches", tm)
        flow_flat = fw.reshape(-1, 2)
        pts1 = self._grid[idx].astype(np.float64)
        pts2 = pts1 + flow_flat[idx]
        mag = np.linalg.norm(flow_flat[idx], axis=1)
        rec.stats["mean_flow"] = float(mag.mean())
        t0 = tm.add("sample", t0)
        if np.median(mag) < self.p.static_flow_px:
            rec.T_world_cam = kf.T_world_cam
            rec.branch, rec.reason = "identity", f"median flow {np.median(mag):.2f} px: camera static"
            return self._finish(rec, tm)
        R_rot, par = fit_rotation(pts1, pts2, self.K)
        parallax = float(np.median(par))
        rec.stats["parallax"] = parallax
        t0 = tm.add("rotation", t0)
        depth_ref = self.depth.predict(kf.index, kf.image)
        rec.depth = depth_ref
        t0 = tm.add("depth", t0)
        if parallax < self.p.min_parallax_px:
            why = f"parallax {parallax:.2f} px < {self.p.min_parallax_px} px"
            return self._small_motion(rec, why, R_rot, depth_ref, idx, fw, m_s * m_o, tm)
        rel, ok = estimate_relative_pose(pts1, pts2, self.K, threshold_px=self.p.ransac_threshold_px,
                                         method=self.p.ransac_method, refine=self.p.refine,
                                         inlier_px=self.p.epi_inlier_px, rng=self.rng,
                                         ransac_subset=self.p.ransac_subset)
        t0 = tm.add("pose", t0)
        if not ok or rel.inliers.sum() < self.p.min_inliers:
            n_in = 0 if rel is None else int(rel.inliers.sum())
            return self._small_motion(rec, f"two-view geometry degenerate ({n_in} inliers)", R_rot, depth_ref, idx,
                                      fw, m_s * m_o, tm)
        rec.stats["inliers"] = int(rel.inliers.sum())
        rec.stats["inlier_ratio"] = float(rel.inliers.mean())
        # inlier map over the whole image, matches re-drawn from M_r * M_s * M_o
        d_epi = self._epipolar_distance_map(rel.F, fw)
        score2 = inlier_score(d_epi, self.p.epi_inlier_px) * score
        anchors = None
        if depth_ref is not None and not self.depth.is_metric_prior:
            anchors = np.flatnonzero((depth_ref.ravel() > 0) & (score2.ravel() > 0))
            if anchors.size > self.p.max_anchors:
                anchors = self.rng.choice(anchors, self.p.max_anchors, replace=False)
        idx2 = self._draw(score2, self.p.n_samples, anchors)
        t0 = tm.add("redraw", t0)
        q1 = self._grid[idx2].astype(np.float64)
        q2 = q1 + flow_flat[idx2]
        R_use, t_unit = rel.R, rel.t
        X, valid, angle = triangulate_midpoint(q1, q2, self.K, R_use, t_unit, min_angle=self.p.min_angle_rad)
        t0 = tm.add("triangulate", t0)
        if valid.sum() < self.p.min_scale_points:
            return self._small_motion(rec, f"only {int(valid.sum())} points triangulated", R_rot, depth_ref, idx, fw,
                                      m_s * m_o, tm)
        # scale from the reference depth
        branch, how = "two-view", ""
        wmap = getattr(self.depth, "weight", lambda i: None)(kf.index) if depth_ref is not None else None

        def depths_at(valid, angle):
            """(reference depth, its weight, new-depth weight, scale weight) of the valid points."""
            w_new = angle[valid] ** 2  # information of a triangulated depth grows with parallax squared
            if depth_ref is None:
                return None, None, w_new, None
            d_ref = depth_ref.ravel()[idx2][valid]
            w_ref = wmap.ravel()[idx2][valid] * self.p.depth_decay if wmap is not None else np.full_like(w_new, np.inf)
            # a ratio is as reliable as the less reliable of its two depths
            w_scale = 1.0 / (1.0 / np.maximum(w_new, 1e-12) + 1.0 / np.maximum(w_ref, 1e-12))
            return d_ref, w_ref, w_new, w_scale

        d_ref, w_ref, w_new, w_scale = depths_at(valid, angle)
        scale, scale_ok = 1.0, False
        if depth_ref is not None:
            scale, scale_ok = align_scale(X[valid, 2], d_ref, weights=w_scale, min_points=self.p.min_scale_points)
            rec.stats["scale_points"] = int((d_ref > 0).sum())
        if scale_ok and self.p.pnp_check_ratio > 0:
            # guard: a two-view step on a short baseline can get the translation direction, and so
            # the scale, badly wrong; PnP on the same depth says how far the camera really moved
            (Rp, tp, _), okp, _, _ = self._pnp(depth_ref, idx, fw, score)
            tn = float(np.linalg.norm(tp))
            if okp and tn > 0:
                ratio = tn / scale
                rec.stats["pnp_ratio"] = ratio
                if abs(np.log(ratio)) > np.log(self.p.pnp_check_ratio):
                    R_use, t_unit, scale = Rp, tp / tn, tn
                    X, valid, angle = triangulate_midpoint(q1, q2, self.K, R_use, t_unit,
                                                           min_angle=self.p.min_angle_rad)
                    d_ref, w_ref, w_new, w_scale = depths_at(valid, angle)
                    branch = "pnp"
                    how = f"two-view scale disagreed with PnP by {ratio:.2f}x: PnP pose used"
        if not scale_ok:
            if self.last_step_norm is None:
                scale, how = 1.0, "first two-view step sets the unit of scale"
            else:
                scale, how = self.last_step_norm, "scale lost (too few points with depth): constant speed assumed"
                rec.stats["degraded"] = 1
        t0 = tm.add("scale", t0)
        rec.stats["scale"] = float(scale)
        t_s = t_unit * scale
        T_cur_kf = make_T(R_use, t_s)
        X_s = X[valid] * scale
        w_out = w_new
        if scale_ok and not self.depth.is_metric_prior and self.p.depth_fusion:
            # small depth filter: fuse carried and new depth along each ray (in log depth)
            d_new = X_s[:, 2]
            d_f, w_out = fuse_log_depth(d_ref, w_ref, d_new, w_new)
            X_s = X_s * (d_f / d_new)[:, None]
        X_cur = X_s @ R_use.T + t_s
        uv_cur = (X_cur @ self.K.T)[:, :2] / X_cur[:, 2:3]
        self.depth.observe(frame_index, uv_cur, X_cur[:, 2], w_out)
        self.depth.forget(kf.index)
        T_world_cur = kf.T_world_cam @ invert_T(T_cur_kf)
        rec.T_world_cam = T_world_cur
        rec.branch, rec.reason = branch, how
        rec.pts_ref, rec.pts_cur = q1[valid], q2[valid]
        rec.points_world = X_s @ kf.T_world_cam[:3, :3].T + kf.T_world_cam[:3, 3]
        gray = kf.image[np.rint(q1[valid, 1]).astype(int), np.rint(q1[valid, 0]).astype(int)]
        rec.point_colors = gray[:, ::-1].copy()
        self.last_step_norm = float(np.linalg.norm(t_s))
        self.kf = _Keyframe(frame_index, image, prepared, T_world_cur)
        tm.add("bookkeeping", t0)
        return self._finish(rec, tm)

    def _pnp(self, depth_ref, idx, fw, score):
        """PnP from keyframe depth to the flow matches: ``((R, t, inliers), ok, pts_ref, pts_cur)``.

        Dense (network) depth uses the sampled pixels ``idx``; carried depth uses
        every pixel that has depth and a positive match score (capped)."""
        dflat = depth_ref.ravel()
        cand = idx
        if not self.depth.is_metric_prior:
            cand = np.flatnonzero((dflat > 0) & (score.ravel() > 0))
            if cand.size > self.p.max_anchors:
                cand = self.rng.choice(cand, self.p.max_anchors, replace=False)
        cand = cand[dflat[cand] > 0]
        q1 = self._grid[cand].astype(np.float64)
        q2 = q1 + fw.reshape(-1, 2)[cand]
        X = backproject(q1, dflat[cand], self.K)
        res, ok = solve_pnp(X, q2, self.K, reproj_px=self.p.pnp_reproj_px, rng_seed=self.p.seed)
        return res, ok, q1, q2

    def _small_motion(self, rec, why, R_rot, depth_ref, idx, fw, score, tm):
        """PnP against the keyframe depth when there is some; else rotation only."""
        kf = self.kf
        t0 = time.perf_counter()
        if depth_ref is not None:
            (R, t, inl), ok, q1, q2 = self._pnp(depth_ref, idx, fw, score)
            tm.add("pnp", t0)
            if ok:
                rec.T_world_cam = kf.T_world_cam @ invert_T(make_T(R, t))
                rec.branch, rec.reason = "pnp", why
                rec.stats["inliers"] = int(inl.sum())
                rec.pts_ref, rec.pts_cur = q1[inl], q2[inl]
                return self._finish(rec, tm)
            why += "; PnP failed"
        rec.T_world_cam = kf.T_world_cam @ invert_T(make_T(R_rot, np.zeros(3)))
        rec.branch, rec.reason = "rotation", why + ("" if depth_ref is not None else "; no depth yet: rotation only")
        return self._finish(rec, tm)

    def _fail(self, rec, why, tm):
        rec.branch, rec.reason = "failed", why + "; pose kept from the previous frame"
        rec.T_world_cam = self.T_world_last
        return self._finish(rec, tm)

    def _finish(self, rec, tm):
        self.T_world_last = rec.T_world_cam
        rec.stats["ms"] = tm.ms
        return rec
