"""The front-end: one frame pair, from flow to a scaled relative pose.

``flow -> matches -> relative pose -> triangulation -> scale``, as in TrianFlow.
Every function here solves the current frame against the reference keyframe and
returns a :class:`Solution`; none of them changes any state (the one exception is the
pair's rolling-shutter motion, which :meth:`FrontEnd.set_shutter` sets before a pair
is solved). The order of the
branches, and the state they update, is :class:`trianflow_vo.odometry.Odometry`'s.

Frames: ``T_world_ref`` is the keyframe's camera-to-world pose, a relative pose
``(R, t)`` maps keyframe points into the current camera (``X_cur = R X_ref + t``,
i.e. ``T_cur_ref``), and a solution's ``T_ref_cam`` is the current camera in the
keyframe (``T_ref_cur = T_cur_ref^-1``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from trianflow_vo.camera import PinholeCamera, project, unproject
from trianflow_vo.config import Config
from trianflow_vo.depth.base import ReferenceDepth
from trianflow_vo.depth.fusion import fuse_log_depth
from trianflow_vo.flow.base import FlowSource
from trianflow_vo.flow.masks import flow_scores
from trianflow_vo.frame import Branch
from trianflow_vo.geometry.epipolar import (epipolar_distance, epipolar_distance_map, inlier_score,
                                            project_to_epipolar_line, sampson_distance)
from trianflow_vo.geometry.fundamental import fundamental_from_pose
from trianflow_vo.geometry.model_selection import direction_sigma, select_motion_model
from trianflow_vo.geometry.parallax import local_angle_floor
from trianflow_vo.geometry.pnp import solve_pnp
from trianflow_vo.geometry.relative_pose import estimate_relative_pose
from trianflow_vo.geometry.rolling_shutter import dense_inverse_depth, to_global_shutter
from trianflow_vo.geometry.rotation import fit_rotation
from trianflow_vo.geometry.scale import align_scale, fit_scale_ransac
from trianflow_vo.geometry.se3 import invert_T, make_T
from trianflow_vo.geometry.triangulation import triangulate_midpoint
from trianflow_vo.keyframe import Keyframe, TrackIds, Tracks
from trianflow_vo.timing import StageTimer


@dataclass(frozen=True)
class Matches:
    """Dense flow between the keyframe and the current frame, and the matches drawn from it.

    Attributes:
        fw, bw: ``(h, w, 2)`` float32 forward (keyframe -> current) and backward flow.
        score: ``(h, w)`` float32 ``M_s * M_o`` (forward-backward score times visibility).
        idx: ``(N,)`` flat pixel indices of the drawn matches.
        pts_ref, pts_cur: ``(N, 2)`` float64 matching pixels (``pts_cur = pts_ref + flow``).
        flow_mag: ``(N,)`` float32 flow magnitude of each match (pixels).
    """

    fw: np.ndarray
    bw: np.ndarray
    score: np.ndarray
    idx: np.ndarray
    pts_ref: np.ndarray
    pts_cur: np.ndarray
    flow_mag: np.ndarray


@dataclass(frozen=True)
class Solution:
    """The current frame solved against its keyframe.

    Attributes:
        branch: the :class:`~trianflow_vo.frame.Branch` taken.
        reason: why (empty for a plain two-view step).
        T_world_cam: ``(4, 4)`` camera-to-world pose of the current frame.
        T_ref_cam: ``(4, 4)`` the current frame in the keyframe (``T_ref_cur``).
        stats: :class:`~trianflow_vo.frame.FrameStats` fields measured here.
        pts_ref, pts_cur: ``(N, 2)`` matches the pose was solved from (inliers), or None.
        points_world: ``(M, 3)`` triangulated points, world frame, or None.
        point_colors: ``(M, 3)`` uint8 RGB colours of those points, or None.
        tracks: the new keyframe's tracks when this frame becomes the keyframe, else None.
        step_norm: length of the step from the keyframe (two-view steps), else None.
    """

    branch: Branch
    reason: str
    T_world_cam: np.ndarray
    T_ref_cam: np.ndarray
    stats: dict = field(default_factory=dict)
    pts_ref: np.ndarray | None = None
    pts_cur: np.ndarray | None = None
    points_world: np.ndarray | None = None
    point_colors: np.ndarray | None = None
    tracks: Tracks | None = None
    step_norm: float | None = None


def identity_solution(T_world_ref: np.ndarray, why: str) -> Solution:
    """The camera did not move: the keyframe's pose ``T_world_ref`` ``(4, 4)``."""
    return Solution(Branch.IDENTITY, why, T_world_ref, np.eye(4))


def failed_solution(T_world_ref: np.ndarray, T_world_last: np.ndarray, why: str) -> Solution:
    """Nothing usable: keep the previous frame's pose ``T_world_last`` ``(4, 4)``."""
    return Solution(Branch.FAILED, why + "; pose kept from the previous frame", T_world_last,
                    invert_T(T_world_ref) @ T_world_last)


def small_motion_solution(X_ref: np.ndarray | None, pts_ref: np.ndarray, pts_cur: np.ndarray,
                          R_rot: np.ndarray, K: np.ndarray, T_world_ref: np.ndarray, why: str,
                          reproj_px: float, seed: int) -> Solution:
    """Too little parallax for two-view geometry: PnP on the keyframe's depth, else rotation only.

    Args:
        X_ref: ``(N, 3)`` keyframe-camera points of the matches that have depth, or
            None when the keyframe has no depth yet.
        pts_ref, pts_cur: ``(N, 2)`` their pixels in the keyframe and the current frame.
        R_rot: ``(3, 3)`` best rotation-only fit (``X_cur ~ R_rot X_ref``), the fallback.
        K: ``(3, 3)`` intrinsics. T_world_ref: ``(4, 4)`` keyframe pose.
        why: the reason the two-view step was not taken.
        reproj_px, seed: PnP RANSAC threshold and seed.

    Returns:
        A :class:`Solution` with branch PNP (``T_cur_ref`` from PnP) or ROTATION.
    """
    if X_ref is not None:
        (R, t, inl), ok = solve_pnp(X_ref, pts_cur, K, reproj_px=reproj_px, rng_seed=seed)
        if ok:
            T_ref_cam = invert_T(make_T(R, t))
            n_in = int(inl.sum())
            return Solution(Branch.PNP, why, T_world_ref @ T_ref_cam, T_ref_cam,
                            {"inliers": n_in, "inlier_ratio": n_in / len(X_ref)},
                            pts_ref=pts_ref[inl], pts_cur=pts_cur[inl])
        why += "; PnP failed"
    else:
        why += "; no depth yet: rotation only"
    T_ref_cam = invert_T(make_T(R_rot, np.zeros(3)))
    return Solution(Branch.ROTATION, why, T_world_ref @ T_ref_cam, T_ref_cam)


def step_scale(scale: float, scale_ok: bool, last_step_norm: float | None) -> tuple[float, str, bool]:
    """The step length when the depth could not fix it: ``(scale, reason, degraded)``.

    The first two-view step of a run sets the unit of scale (1); later ones assume
    constant speed (the last step's length) and are marked degraded.
    """
    if scale_ok:
        return scale, "", False
    if last_step_norm is None:
        return 1.0, "first two-view step sets the unit of scale", False
    return last_step_norm, "scale lost (too few points with depth): constant speed assumed", True


def pnp_check_limit(parallax_px: float | None, ratio: float, ratio_low: float, low_parallax_px: float) -> float:
    """The factor by which a two-view step's length may differ from PnP's on the same keyframe
    depth before PnP replaces it (``scale.pnp_check_*``); 0 = the step is not checked.

    A two-view step's scale comes from triangulating its own matches, whose error grows as
    the parallax (rotation removed) shrinks; PnP's comes from the carried depth alone. Under
    ``low_parallax_px`` of median parallax ``parallax_px`` the tighter ``ratio_low`` applies,
    else ``ratio`` (also when the parallax is not known: None). ``ratio`` 0 turns the
    check off for every step.
    """
    if ratio <= 0:
        return 0.0
    if parallax_px is not None and parallax_px < low_parallax_px:
        return ratio_low
    return ratio


class FrontEnd:
    """Solves one frame against the reference keyframe (TrianFlow's per-pair recipe).

    Args:
        camera: working-resolution :class:`~trianflow_vo.camera.PinholeCamera`.
        flow: a :class:`~trianflow_vo.flow.base.FlowSource`.
        config: the run's :class:`~trianflow_vo.config.Config`.
        rng: the run's random generator (match sampling, RANSAC subsets).
    """

    def __init__(self, camera: PinholeCamera, flow: FlowSource, config: Config, rng: np.random.Generator):
        self.camera = camera
        self.K = camera.K
        self.flow = flow
        self.cfg = config
        self.rng = rng
        self.track_ids = TrackIds()
        h, w = camera.size_hw
        gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
        self._grid = np.stack([gx.ravel(), gy.ravel()], 1)
        # rolling shutter (input.readout) of the pair being solved: (twist of the keyframe, twist of
        # the current frame, (h w,) inverse depth of the keyframe or None), each twist (omega, v) or None
        self.shutter: tuple | None = None

    def set_shutter(self, twist_ref, twist_cur, depth: np.ndarray | None) -> None:
        """The camera's motion while the rows of the keyframe and of the current frame were read,
        for ``input.readout``: each twist ``(omega (3,), v (3,))`` per source frame interval, or
        None (that frame's pixels are left as they are). ``depth``: ``(h, w)`` keyframe depth
        (0 = none), made dense by :func:`~trianflow_vo.geometry.rolling_shutter.dense_inverse_depth`
        for the translation part (also for the current frame's pixels); None: rotation only.
        Until the next call :meth:`pixels` returns matches moved to each frame's middle-row instant."""
        self.shutter = None
        if self.cfg.input.readout == 0 or (twist_ref is None and twist_cur is None):
            return
        inv = None
        if depth is not None and np.any(depth > 0):
            inv = dense_inverse_depth(depth).ravel()
        self.shutter = (twist_ref, twist_cur, inv)

    def _global_shutter(self, pts: np.ndarray, twist, inv_depth: np.ndarray | None) -> np.ndarray:
        if twist is None:
            return pts
        omega, v = twist
        return to_global_shutter(pts, self.K, self.camera.size_hw[0], self.cfg.input.readout, omega,
                                 None if inv_depth is None else v, inv_depth)

    # -- matches ------------------------------------------------------------------------
    def draw(self, score: np.ndarray, n: int, extra: np.ndarray | None = None) -> np.ndarray:
        """Flat pixel indices: the top ``sampling.top_ratio`` of positive ``score`` ``(h, w)``,
        then ``n`` of them at random, plus the indices ``extra`` ``(M,)``."""
        flat = score.ravel()
        pos = np.flatnonzero(flat > 0)
        if pos.size == 0:
            return np.zeros(0, dtype=np.int64)
        k = max(1, int(np.ceil(self.cfg.sampling.top_ratio * pos.size)))
        top = pos[np.argpartition(flat[pos], pos.size - k)[pos.size - k:]] if k < pos.size else pos
        if top.size > n:
            top = self.rng.choice(top, n, replace=False)
        if extra is not None and extra.size:
            top = np.union1d(top, extra)
        return top

    def pixels(self, idx: np.ndarray, fw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(pts_ref, pts_cur)`` ``(N, 2)`` float64 of flat indices ``idx`` under flow ``fw``."""
        q1 = self._grid[idx].astype(np.float64)
        q2 = q1 + fw.reshape(-1, 2)[idx]
        if self.shutter is None:
            return q1, q2
        tw_ref, tw_cur, inv = self.shutter
        inv = None if inv is None else inv[idx]
        return self._global_shutter(q1, tw_ref, inv), self._global_shutter(q2, tw_cur, inv)

    def epipolar_map(self, F: np.ndarray, fw: np.ndarray) -> np.ndarray:
        """``(h, w)`` float32 distance of every pixel's match under flow ``fw`` to its epipolar line
        ``F x`` (:func:`~trianflow_vo.geometry.epipolar.epipolar_distance_map`), with the pair's
        rolling-shutter correction when there is one."""
        if self.shutter is None:
            return epipolar_distance_map(F, fw)
        p1, p2 = self.pixels(np.arange(self._grid.shape[0]), fw)
        return epipolar_distance(F, p1, p2).reshape(fw.shape[:2]).astype(np.float32)

    def match(self, keyframe: Keyframe, prepared, tm: StageTimer) -> Matches:
        """Flow both ways between ``keyframe`` and the current frame, masks, and drawn matches."""
        t0 = time.perf_counter()
        fw, bw = self.flow.flow_pair(keyframe.prepared, prepared)
        t0 = tm.add("flow", t0)
        _, m_s, m_o = flow_scores(fw, bw)
        t0 = tm.add("masks", t0)
        score = m_s * m_o
        idx = self.draw(score, self.cfg.sampling.n_samples)
        pts_ref, pts_cur = self.pixels(idx, fw)
        mag = np.linalg.norm(fw.reshape(-1, 2)[idx], axis=1)
        tm.add("sample", t0)
        return Matches(fw, bw, score, idx, pts_ref, pts_cur, mag)

    def _capped(self, idx: np.ndarray) -> np.ndarray:
        cap = self.cfg.sampling.max_anchors
        return self.rng.choice(idx, cap, replace=False) if idx.size > cap else idx

    # -- branches -----------------------------------------------------------------------
    def rotation(self, m: Matches, tm: StageTimer) -> tuple[np.ndarray, float, np.ndarray]:
        """``(R_rot (3, 3), median parallax px, parallax (N,) px)``: the rotation-only fit and what
        it leaves of every match."""
        t0 = time.perf_counter()
        R_rot, par = fit_rotation(m.pts_ref, m.pts_cur, self.K)
        tm.add("rotation", t0)
        return R_rot, float(np.median(par)), par

    def motion_test(self, m: Matches, rotation_px: np.ndarray, tm: StageTimer):
        """Which motion the matches show (``keyframes.policy`` gric).

        Estimates the relative pose, then compares general motion with rotation only by
        GRIC (:func:`~trianflow_vo.geometry.model_selection.select_motion_model`) and,
        when general motion wins, how well the translation direction is determined
        (:func:`~trianflow_vo.geometry.model_selection.direction_sigma`, degrees).

        Returns:
            ``(rel or None, n_inliers, MotionTest or None, direction sigma deg)``.
        """
        rel, n_in = self._relative_pose(m, tm)
        if rel is None:
            return None, n_in, None, float("inf")
        t0 = time.perf_counter()
        d = sampson_distance(rel.F, m.pts_ref, m.pts_cur)
        test = select_motion_model(d, rotation_px, floor_px=self.cfg.keyframes.noise_floor_px)
        sig = float("inf")
        if test.general:
            inl = rel.inliers
            sig_rad, ok = direction_sigma(rel.R, rel.t, m.pts_ref[inl], m.pts_cur[inl], self.K, test.sigma_px,
                                          n_independent=self.cfg.keyframes.independent_matches)
            sig = float(np.degrees(sig_rad)) if ok else float("inf")
        tm.add("model", t0)
        return rel, n_in, test, sig

    def pnp_inputs(self, ref: ReferenceDepth, m: Matches, score: np.ndarray):
        """``(X_ref (N, 3), pts_ref, pts_cur)`` for PnP against the keyframe depth.

        A dense depth uses the drawn matches; a sparse one every pixel that has
        depth and a positive match score (capped at ``sampling.max_anchors``)."""
        dflat = ref.depth.ravel()
        cand = m.idx
        if ref.sparse:
            cand = self._capped(np.flatnonzero((dflat > 0) & (score.ravel() > 0)))
        cand = cand[dflat[cand] > 0]
        q1, q2 = self.pixels(cand, m.fw)
        return unproject(q1, dflat[cand], self.K), q1, q2

    def small_motion(self, keyframe: Keyframe, ref: ReferenceDepth | None, m: Matches, R_rot: np.ndarray,
                     why: str, tm: StageTimer) -> Solution:
        """PnP against the keyframe's depth, or rotation only while there is none (keyframe kept)."""
        t0 = time.perf_counter()
        g = self.cfg.geometry
        if ref is None:
            sol = small_motion_solution(None, m.pts_ref, m.pts_cur, R_rot, self.K, keyframe.T_world_cam, why,
                                        g.pnp_reproj_px, self.cfg.sampling.seed)
        else:
            X, q1, q2 = self.pnp_inputs(ref, m, m.score)
            sol = small_motion_solution(X, q1, q2, R_rot, self.K, keyframe.T_world_cam, why, g.pnp_reproj_px,
                                        self.cfg.sampling.seed)
            tm.add("pnp", t0)
        return sol

    def transfer_keyframe(self, keyframe: Keyframe, sol: Solution, note: str, extra: Tracks | None = None) -> Solution:
        """Make the frame of a PnP / rotation-only solution the new keyframe: the keyframe's
        tracks are moved into it by the solved pose (``T_cur_ref``), keeping their ids and
        weights; those that leave the image or fall behind the camera are dropped. ``extra``:
        tracks already in the current frame (:meth:`handon_points`) that join them."""
        T_cur_ref = invert_T(sol.T_ref_cam)
        tr = keyframe.tracks
        if len(tr):
            X = unproject(tr.pts, tr.depth, self.K) @ T_cur_ref[:3, :3].T + T_cur_ref[:3, 3]
            uv, keep = self.camera.project(X)
            tracks = Tracks(tr.ids[keep], uv[keep], X[keep, 2], tr.weight[keep])
        else:
            tracks = Tracks.empty()
        if extra is not None and len(extra):
            tracks = Tracks(np.concatenate([tracks.ids, extra.ids]), np.concatenate([tracks.pts, extra.pts]),
                            np.concatenate([tracks.depth, extra.depth]), np.concatenate([tracks.weight, extra.weight]))
        return replace(sol, reason=sol.reason + note, tracks=tracks, step_norm=None)

    def handon_points(self, ref: ReferenceDepth | None, m: Matches, sol: Solution,
                      min_angle_rad: float) -> tuple[Tracks, float | None]:
        """New depth for a keyframe handed on after PnP: the drawn matches ``m`` whose keyframe
        pixel carries no depth in ``ref``, triangulated along the solved pose of ``sol``, as tracks
        of the current frame (new ids, weight = ray angle squared). ``(tracks, scale)``.

        A match is used when its Sampson distance under that pose is at most
        ``geometry.epi_inlier_px`` (the pose explains it), its rays meet at more than
        ``min_angle_rad``, and it passes the two-view step's own triangulation checks
        (:meth:`_triangulate_rays`: in front of both cameras, ``geometry``'s angle floors and
        epipolar correction). The length of the step comes from
        the keyframe's depth, as for a two-view step: the matches that do carry depth fix the
        scale (:func:`~trianflow_vo.geometry.scale.align_scale`, at least ``scale.min_points``),
        so an error of PnP's translation length does not enter the new depth. Without enough of
        them (or without ``ref``) no tracks are made and the scale is None."""
        T_cur_ref = invert_T(sol.T_ref_cam)
        R, t = T_cur_ref[:3, :3], T_cur_ref[:3, 3]
        base = float(np.linalg.norm(t))
        if ref is None or base <= 0 or m.idx.size == 0:
            return Tracks.empty(), None
        t_unit = t / base
        q1, q2 = m.pts_ref, m.pts_cur
        near = sampson_distance(fundamental_from_pose(R, t_unit, self.K), q1, q2) <= self.cfg.geometry.epi_inlier_px
        X, valid, angle = self._triangulate_rays(q1, q2, R, t_unit)
        valid &= near & (angle > min_angle_rad)
        d_ref = ref.depth.ravel()[m.idx]
        carried = valid & (d_ref > 0)
        scale, ok = align_scale(X[carried, 2], d_ref[carried], min_points=self.cfg.scale.min_points)
        if not ok:
            return Tracks.empty(), None
        free = valid & (d_ref <= 0)
        X_cur = (X[free] @ R.T + t_unit) * scale
        uv, keep = self.camera.project(X_cur)
        n = int(keep.sum())
        return Tracks(self.track_ids.new(n), uv[keep], X_cur[keep, 2], angle[free][keep] ** 2), scale / base

    def _relative_pose(self, m: Matches, tm: StageTimer):
        """``(RelativePose, n_inliers)`` of the matches, or ``(None, n)`` when degenerate."""
        g = self.cfg.geometry
        t0 = time.perf_counter()
        rel, ok = estimate_relative_pose(m.pts_ref, m.pts_cur, self.K, threshold_px=g.ransac_threshold_px,
                                         method=g.ransac_method, refine=g.refine, inlier_px=g.epi_inlier_px,
                                         rng=self.rng, ransac_subset=g.ransac_subset)
        tm.add("pose", t0)
        n_in = 0 if rel is None else int(rel.inliers.sum())
        return (rel if ok and n_in >= g.min_inliers else None), n_in

    def _triangulate(self, rel, m: Matches, ref: ReferenceDepth | None, tm: StageTimer):
        """Re-draw matches from ``M_r * M_s * M_o`` (plus every pixel that carries depth) and
        triangulate them: ``(idx2 (N,), q1 (N, 2), q2 (N, 2), X (N, 3) keyframe camera, valid, angle)``."""
        g = self.cfg.geometry
        t0 = time.perf_counter()
        score2 = inlier_score(self.epipolar_map(rel.F, m.fw), g.epi_inlier_px) * m.score
        anchors = None
        if ref is not None and ref.sparse:
            anchors = self._capped(np.flatnonzero((ref.depth.ravel() > 0) & (score2.ravel() > 0)))
        idx2 = self.draw(score2, self.cfg.sampling.n_samples, anchors)
        t0 = tm.add("redraw", t0)
        q1, q2 = self.pixels(idx2, m.fw)
        X, valid, angle = self._triangulate_rays(q1, q2, rel.R, rel.t)
        tm.add("triangulate", t0)
        return idx2, q1, q2, X, valid, angle

    def _triangulate_rays(self, q1: np.ndarray, q2: np.ndarray, R: np.ndarray, t_unit: np.ndarray):
        """Mid-point triangulation of matches ``q1``, ``q2`` ``(N, 2)`` under ``X2 = R X1 + t_unit``,
        with the optional epipolar correction and cell floor of ``geometry`` (both off by default):
        ``(X (N, 3), valid (N,), angle (N,))``."""
        g = self.cfg.geometry
        if g.epipolar_correction:
            q2 = project_to_epipolar_line(fundamental_from_pose(R, t_unit, self.K), q1, q2)
        X, valid, angle = triangulate_midpoint(q1, q2, self.K, R, t_unit, min_angle=g.min_angle_rad)
        if g.min_local_angle_rad > 0:
            valid, _ = local_angle_floor(angle, q1, valid, g.min_local_angle_rad, g.local_angle_keep,
                                         g.local_angle_cell_px)
        return X, valid, angle

    def _solution(self, keyframe: Keyframe, branch: Branch, how: str, R: np.ndarray, t_s: np.ndarray,
                  X_s: np.ndarray, idx: np.ndarray, q1: np.ndarray, q2: np.ndarray, weight: np.ndarray,
                  stats: dict, ref: ReferenceDepth | None) -> Solution:
        """A scaled step ``X_cur = R X_ref + t_s`` from the keyframe; the frame becomes the keyframe,
        with the triangulated points ``X_s`` ``(N, 3)`` (keyframe camera, at pixels ``idx``) as its tracks."""
        T_ref_cam = invert_T(make_T(R, t_s))
        tracks = self._new_tracks(ref, idx, X_s @ R.T + t_s, weight)
        Tw = keyframe.T_world_cam
        h, w = keyframe.image.shape[:2]  # q1 may lie off the grid (rolling-shutter correction)
        gray = keyframe.image[np.clip(np.rint(q1[:, 1]).astype(int), 0, h - 1),
                              np.clip(np.rint(q1[:, 0]).astype(int), 0, w - 1)]
        return Solution(branch, how, Tw @ T_ref_cam, T_ref_cam, stats, pts_ref=q1, pts_cur=q2,
                        points_world=X_s @ Tw[:3, :3].T + Tw[:3, 3], point_colors=gray[:, ::-1].copy(),
                        tracks=tracks, step_norm=float(np.linalg.norm(t_s)))

    def two_view(self, keyframe: Keyframe, ref: ReferenceDepth | None, m: Matches, R_rot: np.ndarray,
                 last_step_norm: float | None, tm: StageTimer, estimated=None,
                 parallax_px: float | None = None) -> Solution:
        """Relative pose from the matches, mid-point triangulation, scale from the keyframe depth.

        Falls back to :meth:`small_motion` when the geometry is degenerate. On
        success the current frame becomes the keyframe: the solution carries its
        :class:`~trianflow_vo.keyframe.Tracks` (the triangulated points, with the
        ids of the tracks they continue). ``parallax_px``: the matches' median parallax
        with rotation removed, which sets how far the step's scale may differ from PnP's
        (:func:`pnp_check_limit`)."""
        g, K = self.cfg.geometry, self.K
        rel, n_in = estimated if estimated is not None else self._relative_pose(m, tm)
        if rel is None:
            return self.small_motion(keyframe, ref, m, R_rot, f"two-view geometry degenerate ({n_in} inliers)", tm)
        stats = {"inliers": n_in, "inlier_ratio": float(rel.inliers.mean())}
        idx2, q1, q2, X, valid, angle = self._triangulate(rel, m, ref, tm)
        t0 = time.perf_counter()
        if valid.sum() < self.cfg.scale.min_points or valid.mean() < g.min_valid_fraction:
            # few points in front of both cameras: an ambiguous or wrong pose, not a step to build on
            return self.small_motion(keyframe, ref, m, R_rot, f"only {int(valid.sum())} of {valid.size} points "
                                     "triangulated", tm)
        branch, how = Branch.TWO_VIEW, ""
        R, t_unit = rel.R, rel.t
        d_ref, w_ref, w_new, w_scale = self._depths_at(ref, idx2, valid, angle)
        scale, scale_ok = 1.0, False
        if ref is not None:
            scale, scale_ok = align_scale(X[valid, 2], d_ref, weights=w_scale, min_points=self.cfg.scale.min_points)
            stats["scale_points"] = int((d_ref > 0).sum())
        sc = self.cfg.scale
        limit = pnp_check_limit(parallax_px, sc.pnp_check_ratio, sc.pnp_check_ratio_low, sc.pnp_check_low_parallax_px)
        if scale_ok and limit > 0:
            # a two-view step on a short baseline can get the translation direction, and so the
            # scale, badly wrong; PnP on the same depth says how far the camera really moved
            Xp, _, q2p = self.pnp_inputs(ref, m, m.score)
            (Rp, tp, _), okp = solve_pnp(Xp, q2p, K, reproj_px=g.pnp_reproj_px, rng_seed=self.cfg.sampling.seed)
            tn = float(np.linalg.norm(tp))
            if okp and tn > 0:
                ratio = tn / scale
                stats["pnp_ratio"] = ratio
                disagrees = abs(np.log(ratio)) > np.log(limit)
                why = f"two-view scale disagreed with PnP by {ratio:.2f}x (limit {limit:g}x"
                why += ")" if parallax_px is None else f" at {parallax_px:.2f} px of parallax)"
                if disagrees and self.cfg.keyframes.policy == "gric":
                    # the two-view step is not to be trusted: PnP on the held keyframe, no new keyframe
                    T_ref_cam = invert_T(make_T(Rp, tp))
                    return Solution(Branch.PNP, f"{why}: PnP pose, keyframe kept", keyframe.T_world_cam @ T_ref_cam,
                                    T_ref_cam, {"inliers": n_in, "pnp_ratio": ratio})
                if disagrees:
                    R, t_unit, scale = Rp, tp / tn, tn
                    X, valid, angle = self._triangulate_rays(q1, q2, R, t_unit)
                    d_ref, w_ref, w_new, w_scale = self._depths_at(ref, idx2, valid, angle)
                    branch = Branch.PNP
                    how = f"{why}: PnP pose used"
        if ref is not None and not scale_ok:
            # the keyframe has depth but too little of it under this step's matches to fix the
            # step's length: PnP on that depth keeps the keyframe and its scale; constant speed
            # (below) only when PnP fails too
            sol = self.small_motion(keyframe, ref, m, R_rot, "scale lost (too few points with depth under the "
                                    "two-view matches)", tm)
            if sol.branch == Branch.PNP:
                return sol
        scale, lost, degraded = step_scale(scale, scale_ok, last_step_norm)
        how = how or lost
        if degraded:
            stats["degraded"] = True
        t0 = tm.add("scale", t0)
        stats["scale"] = float(scale)
        X_s = X[valid] * scale
        w_out = w_new
        if scale_ok and self.cfg.depth.fusion and w_ref is not None:
            # small depth filter: fuse carried and new depth along each ray (in log depth)
            d_f, w_out = fuse_log_depth(d_ref, w_ref, X_s[:, 2], w_new, max_log_gap=self.cfg.depth.max_log_gap)
            X_s = X_s * (d_f / X_s[:, 2])[:, None]
        sol = self._solution(keyframe, branch, how, R, t_unit * scale, X_s, idx2[valid], q1[valid], q2[valid],
                             w_out, stats, ref)
        tm.add("bookkeeping", t0)
        return sol

    def two_view_to_depth(self, keyframe: Keyframe, ref: ReferenceDepth, cur: ReferenceDepth, m: Matches,
                          R_rot: np.ndarray, tm: StageTimer) -> Solution:
        """The authors' per-pair recipe (reference §5): the scale of each pair from the network.

        Two-view pose when the mean flow exceeds ``scale.depth_min_flow_px``; the
        triangulated depth of the current frame is fitted to the network's depth of
        the current frame ``cur`` (RANSAC line through the origin). When the flow is
        small, the geometry degenerate or the fit fails: PnP of the keyframe's
        network depth ``ref`` (below ``scale.depth_max``) against the matches."""
        sc = self.cfg.scale
        mean_flow = float(m.flow_mag.mean())
        if mean_flow <= sc.depth_min_flow_px:
            return self._pnp_on_depth(keyframe, ref, m, R_rot, f"mean flow {mean_flow:.2f} px <= "
                                      f"{sc.depth_min_flow_px} px", tm)
        rel, n_in = self._relative_pose(m, tm)
        if rel is None:
            return self._pnp_on_depth(keyframe, ref, m, R_rot, f"two-view geometry degenerate ({n_in} inliers)", tm)
        stats = {"inliers": n_in, "inlier_ratio": float(rel.inliers.mean())}
        idx2, q1, q2, X, valid, angle = self._triangulate(rel, m, ref, tm)
        t0 = time.perf_counter()
        X_cur = X[valid] @ rel.R.T + rel.t
        uv, inside = self.camera.project(X_cur)  # inside: rounds to a pixel of the image
        d_net = np.zeros(X_cur.shape[0])
        px = np.rint(uv[inside]).astype(int)
        d_net[inside] = cur.depth[px[:, 1], px[:, 0]]
        scale, fit_ok = fit_scale_ransac(X_cur[:, 2], d_net, threshold=sc.depth_fit_threshold,
                                         trials=sc.depth_fit_trials, min_points=sc.depth_fit_min_points,
                                         rng=self.rng)
        stats["scale_points"] = int((d_net > 0).sum())
        tm.add("scale", t0)
        if not fit_ok:
            return self._pnp_on_depth(keyframe, ref, m, R_rot, f"scale fit to the network depth failed "
                                      f"({stats['scale_points']} points)", tm)
        stats["scale"] = float(scale)
        return self._solution(keyframe, Branch.TWO_VIEW, "", rel.R, rel.t * scale, X[valid] * scale, idx2[valid],
                              q1[valid], q2[valid], angle[valid] ** 2, stats, None)

    def _pnp_on_depth(self, keyframe: Keyframe, ref: ReferenceDepth, m: Matches, R_rot: np.ndarray, why: str,
                      tm: StageTimer) -> Solution:
        """PnP of the keyframe's network depth (0 < d < ``scale.depth_max``) against the drawn matches."""
        t0 = time.perf_counter()
        d = ref.depth.ravel()[m.idx]
        keep = (d > 0) & (d < self.cfg.scale.depth_max)
        X = unproject(m.pts_ref[keep], d[keep], self.K)
        sol = small_motion_solution(X, m.pts_ref[keep], m.pts_cur[keep], R_rot, self.K, keyframe.T_world_cam,
                                    why, self.cfg.geometry.pnp_reproj_px, self.cfg.sampling.seed)
        tm.add("pnp", t0)
        return sol

    def _depths_at(self, ref: ReferenceDepth | None, idx: np.ndarray, valid: np.ndarray, angle: np.ndarray):
        """``(d_ref, w_ref, w_new, w_scale)`` at the valid triangulated pixels ``idx[valid]``.

        ``w_new``: information of a new depth (parallax angle squared); ``w_ref``: the
        keyframe depth's, decayed by ``depth.decay`` (None for a prior without
        confidence, which is then trusted fully); ``w_scale``: a ratio is as reliable
        as the less reliable of its two depths. None entries when there is no depth."""
        w_new = angle[valid] ** 2
        if ref is None:
            return None, None, w_new, None
        d_ref = ref.depth.ravel()[idx][valid]
        if ref.weight is None:
            w_ref = None
            w_scale = 1.0 / (1.0 / np.maximum(w_new, 1e-12))
        else:
            w_ref = ref.weight.ravel()[idx][valid] * self.cfg.depth.decay
            w_scale = 1.0 / (1.0 / np.maximum(w_new, 1e-12) + 1.0 / np.maximum(w_ref, 1e-12))
        return d_ref, w_ref, w_new, w_scale

    def _new_tracks(self, ref: ReferenceDepth | None, idx: np.ndarray, X_cur: np.ndarray,
                    weight: np.ndarray) -> Tracks:
        """Tracks of the new keyframe: points ``X_cur`` ``(N, 3)`` (current camera) triangulated
        at keyframe pixels ``idx`` ``(N,)``; a pixel that carried a track continues it."""
        ids = np.full(idx.shape[0], -1, dtype=np.int64)
        if ref is not None and ref.track_ids is not None:
            ids = ref.track_ids.ravel()[idx].copy()
        born = ids < 0
        ids[born] = self.track_ids.new(int(born.sum()))
        uv = project(X_cur, self.K)
        d = X_cur[:, 2]
        h, w = self.camera.size_hw
        xi, yi = np.rint(uv[:, 0]), np.rint(uv[:, 1])
        keep = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h) & np.isfinite(d) & (d > 0)
        return Tracks(ids[keep], uv[keep], d[keep], np.asarray(weight, dtype=np.float64)[keep])
