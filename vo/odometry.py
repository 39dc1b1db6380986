"""TrianFlow odometry, one frame at a time, frame to keyframe.

:class:`Odometry` holds the state (the reference :class:`~trianflow_vo.keyframe.Keyframe`,
the last pose, the random generator) and turns each new working-resolution image
into a :class:`~trianflow_vo.frame.FrameResult`. The per-pair work is the
:class:`~trianflow_vo.frontend.FrontEnd`'s; which branch a frame takes is decided
here, in :meth:`Odometry.step`. No I/O: :mod:`trianflow_vo.pipeline` feeds it frames.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from trianflow_vo.backend import PoseRevision
from trianflow_vo.camera import PinholeCamera, focal_px
from trianflow_vo.config import Config, resolve_scale_source
from trianflow_vo.depth.base import DepthPrior, ReferenceDepth
from trianflow_vo.flow.base import FlowSource
from trianflow_vo.frame import Branch, FrameResult, FrameStats, FrameView
from trianflow_vo.frontend import FrontEnd, Matches, Solution, failed_solution, identity_solution
from trianflow_vo.geometry.rolling_shutter import twist_per_frame
from trianflow_vo.geometry.se3 import invert_T
from trianflow_vo.keyframe import Keyframe, Tracks
from trianflow_vo.timing import StageTimer


def result_from_solution(line: int, frame_index: int, timestamp: float | None, ref_index: int, sol: Solution,
                         stats: dict, K: np.ndarray, tm: StageTimer, view: FrameView | None) -> FrameResult:
    """The frame's :class:`~trianflow_vo.frame.FrameResult`, built once from the branch's
    :class:`~trianflow_vo.frontend.Solution`, the statistics measured before it and the timer."""
    fs = FrameStats(**{"tracks": None if sol.tracks is None else len(sol.tracks), **stats, **sol.stats},
                    ms=tm.ms, frame_ms=tm.elapsed_ms())
    return FrameResult(line, frame_index, timestamp, sol.T_world_cam, sol.branch, sol.reason, ref_index,
                       sol.T_ref_cam, sol.tracks is not None, K, fs, view)


class Odometry:
    """Frame-to-keyframe TrianFlow odometry.

    Args:
        camera: working-resolution :class:`~trianflow_vo.camera.PinholeCamera`.
        flow: a :class:`~trianflow_vo.flow.base.FlowSource`.
        depth: a :class:`~trianflow_vo.depth.base.DepthPrior`.
        config: the run's :class:`~trianflow_vo.config.Config` (sampling, geometry,
            scale, keyframes and depth sections are used).
    """

    def __init__(self, camera: PinholeCamera, flow: FlowSource, depth: DepthPrior, config: Config = Config()):
        self.camera = camera
        self.flow = flow
        self.depth = depth
        self.cfg = config
        self.front = FrontEnd(camera, flow, config, np.random.default_rng(config.sampling.seed))
        self.scale_source = resolve_scale_source(config)
        self._solve = self._solve_pairwise if self.scale_source == "depth" else self._solve_to_keyframe
        self.keyframe: Keyframe | None = None
        self.T_world_last = np.eye(4)
        self.last_step_norm: float | None = None  # |t| of the last keyframe-to-keyframe step
        self.line = 0
        self._kf_line = 0  # line of the current keyframe
        self._ahead: tuple[np.ndarray, object] | None = None  # (next image, its prepared input) when speculating
        self._new_keyframe_last = True  # did the last frame become the keyframe (the guess for the next)
        # the last frame when it was solved against the held keyframe and kept it: (index, image, prepared,
        # Solution), the way round a keyframe whose flow is lost
        self._held_last: tuple[int, np.ndarray, object, Solution] | None = None
        # PnP inlier ratio of the first frame kept on the current keyframe (keyframes.min_inlier_share)
        self._kf_ratio0: float | None = None
        # rolling shutter (input.readout): the camera twist per source frame interval at the last
        # frame and at the keyframe, from the poses solved so far (constant velocity), and the
        # last frame's source index
        self._twist_last: tuple[np.ndarray, np.ndarray] | None = None
        self._twist_kf: tuple[np.ndarray, np.ndarray] | None = None
        self._index_last: int | None = None

    def describe(self) -> dict:
        return {"odometry": "trianflow", "scale_source": self.scale_source, "flow_source": self.flow.describe(),
                "depth_source": self.depth.describe()}

    def step(self, frame_index: int, timestamp: float | None, image: np.ndarray,
             timer: StageTimer | None = None, next_image: np.ndarray | None = None) -> FrameResult:
        """Process one working-resolution frame ``(h, w, 3)`` uint8 BGR.

        Branches: first frame (INIT); too few reliable matches (FAILED); otherwise
        the policy of ``scale.source`` (:meth:`_solve_to_keyframe` or
        :meth:`_solve_pairwise`).
        ``timer`` may hold stages timed before the call. ``next_image``: the frame that
        comes next, when known; a flow source that can compute ahead
        (:class:`~trianflow_vo.flow.speculative.SpeculativeFlow`) starts on its flow
        while this frame is solved. The results do not depend on it.
        """
        tm = timer if timer is not None else StageTimer()
        t0 = time.perf_counter()
        ahead, self._ahead = self._ahead, None
        prepared = ahead[1] if ahead is not None and ahead[0] is image else self.flow.prepare(image)
        tm.add("prepare", t0)
        if self.keyframe is None:
            self._compute_ahead(prepared, next_image)
            return self._start(frame_index, timestamp, image, prepared, tm)
        kf = self.keyframe
        self._shutter(self._twist_kf, kf, tm)
        m = self.front.match(kf, prepared, tm)
        # guess: this frame ends like the last one (becomes the keyframe, or keeps it)
        self._compute_ahead(prepared if self._new_keyframe_last else kf.prepared, next_image)
        ref, stats = None, {}
        cur = Keyframe(frame_index, image, prepared, np.eye(4), Tracks.empty())
        keeps_keyframe = self.scale_source != "depth"  # "depth" solves every pair: no keyframe is held
        if self._too_few(m):
            why = f"only {m.idx.size} reliable flow matches"
            sol = failed_solution(kf.T_world_cam, self.T_world_last, why)
            if keeps_keyframe:
                again = self._through_last_frame(kf, cur, f"flow against keyframe {kf.index} lost ({why})", tm)
                if again is not None:
                    sol, m, ref, stats = again
        else:
            stats["mean_flow_px"] = float(m.flow_mag.mean())
            sol, ref = self._solve(kf, m, cur, stats, tm)
            if keeps_keyframe and self._flow_lost(sol):
                lost = (f"flow against keyframe {kf.index} lost (PnP {sol.stats['inliers']} inliers, "
                        f"{100 * sol.stats['inlier_ratio']:.1f}% of its points)")
                again = self._through_last_frame(kf, cur, lost, tm)
                if again is None:
                    sol = replace(sol, reason=f"{sol.reason}; {lost}: PnP pose kept")
                    stats = {**stats, "degraded": True}
                else:
                    sol, m, ref, stats = again
        return self._commit(frame_index, timestamp, image, prepared, m, ref, sol, stats, tm)

    def _shutter(self, twist_ref, kf: Keyframe, tm: StageTimer) -> None:
        """Tell the front-end how the camera moved while the reference ``kf``'s rows and the current
        frame's were read (the current frame: the last frame's twist, constant velocity)."""
        if self.cfg.input.readout == 0:
            return
        ref = self._reference(kf, tm)
        self.front.set_shutter(twist_ref, self._twist_last, None if ref is None else ref.depth)

    def _too_few(self, m: Matches) -> bool:
        """Too few reliable matches to solve a frame pair."""
        return m.idx.size < max(8, self.cfg.geometry.min_inliers)

    def _flow_lost(self, sol: Solution) -> bool:
        """A PnP that explains too small a share of its points: the flow against the keyframe is lost."""
        ratio = sol.stats.get("inlier_ratio")
        return (sol.branch == Branch.PNP and ratio is not None
                and ratio < self.cfg.geometry.pnp_min_inlier_ratio)

    def _through_last_frame(self, kf: Keyframe, cur: Keyframe, lost: str, tm: StageTimer):
        """Solve the frame ``cur`` again against the last frame, when that one held the keyframe ``kf``
        whose flow is ``lost`` (the reason's first words): the keyframe's depth is moved into the last
        frame by its pose, the frame is solved against it and becomes the keyframe; its pose stays
        expressed in ``kf``. ``(Solution, Matches, reference depth, stats)``, or None without such a
        frame or when that fails too."""
        if self._held_last is None:
            return None
        index, image, prepared, last_sol = self._held_last
        moved = self.front.transfer_keyframe(kf, last_sol, "")
        via = Keyframe(index, image, prepared, kf.T_world_cam @ last_sol.T_ref_cam, moved.tracks)
        self._shutter(self._twist_last, via, tm)
        m = self.front.match(via, cur.prepared, tm)
        if self._too_few(m):
            return None
        stats = {"mean_flow_px": float(m.flow_mag.mean())}
        sol, ref = self._solve(via, m, cur, stats, tm)
        if sol.branch not in (Branch.TWO_VIEW, Branch.PNP, Branch.ROTATION) or self._flow_lost(sol):
            return None
        if sol.tracks is None:
            sol = self.front.transfer_keyframe(via, sol, "")
        reason = f"{lost}: solved through frame {index}" + (f"; {sol.reason}" if sol.reason else "")
        return replace(sol, reason=reason, T_ref_cam=invert_T(kf.T_world_cam) @ sol.T_world_cam), m, ref, stats

    def _solve_to_keyframe(self, kf: Keyframe, m: Matches, cur: Keyframe, stats: dict, tm: StageTimer):
        """Our policy (``scale.source`` triangulation / keyframe-depth): ``(Solution, reference depth)``.

        Static camera (median flow under ``keyframes.static_flow_px``): IDENTITY. Then, by
        ``keyframes.policy``: ``gric`` (rotation only preferred by GRIC, or the translation
        direction's sigma over ``max_direction_deg``, or, while the keyframe has no depth, the
        median parallax under ``init_min_parallax_px``; while it has depth, its angle under
        ``depth_min_parallax_deg``) or ``parallax`` (median parallax under
        ``min_parallax_px``) give PnP/rotation with the keyframe kept (handed on under
        ``gric`` when its flow exceeds ``max_flow_fraction`` of the width, or the next
        frame's is expected past ``max_next_flow_fraction``, or a PnP's inlier ratio falls
        under ``min_inlier_share`` of the first one's on this keyframe; :meth:`_hand_on`); else
        the two-view step, after which the frame is the new keyframe."""
        kc = self.cfg.keyframes
        median_flow = float(np.median(m.flow_mag))
        if median_flow < kc.static_flow_px:
            return identity_solution(kf.T_world_cam, f"median flow {median_flow:.2f} px: camera static"), None
        R_rot, parallax, par = self.front.rotation(m, tm)
        stats["parallax_px"] = parallax
        ref = self._reference(kf, tm)
        if kc.policy == "parallax":
            if parallax < kc.min_parallax_px:
                why = f"parallax {parallax:.2f} px < {kc.min_parallax_px} px"
                return self.front.small_motion(kf, ref, m, R_rot, why, tm), ref
            return self.front.two_view(kf, ref, m, R_rot, self.last_step_norm, tm, parallax_px=parallax), ref
        rel, n_in, test, dir_sigma = self.front.motion_test(m, par, tm)
        parallax_deg = self._parallax_deg(parallax)
        why = ""
        if rel is None:
            why = f"two-view geometry degenerate ({n_in} inliers)"
        elif not test.general:
            why = (f"rotation-only motion (GRIC {test.gric_rotation:.2f} <= {test.gric_general:.2f} per match, "
                   f"noise {test.sigma_px:.2f} px, parallax {parallax:.2f} px)")
        elif dir_sigma > kc.max_direction_deg:
            why = f"translation direction uncertain ({dir_sigma:.2f} deg > {kc.max_direction_deg} deg)"
        elif ref is None and parallax < kc.init_min_parallax_px:
            # with no depth to align to, this step's triangulation becomes the first depth and its
            # length the unit: on too little parallax that depth is mostly noise, and every later
            # step's scale would be aligned to it
            why = f"parallax {parallax:.2f} px < {kc.init_min_parallax_px} px for a step without keyframe depth"
        elif ref is not None and parallax_deg < kc.depth_min_parallax_deg:
            # on a short baseline a small error of the rotation tilts the triangulated depth across
            # the image; fused into the keyframe's depth, the tilt becomes the scale of later steps.
            # An angle, not pixels: the same floor holds at any image size and focal length
            why = (f"parallax {parallax:.2f} px = {parallax_deg:.3f} deg < "
                   f"{kc.depth_min_parallax_deg} deg for a step on keyframe depth")
        if why:
            sol = self.front.small_motion(kf, ref, m, R_rot, why, tm)
        else:
            sol = self.front.two_view(kf, ref, m, R_rot, self.last_step_norm, tm, estimated=(rel, n_in),
                                      parallax_px=parallax)
        mean_flow = float(m.flow_mag.mean())
        # the flow against a held keyframe grows with every frame: hand the keyframe's depth on to
        # this frame once the flow passes max_flow_fraction of the width, or when the next frame's
        # (this one's times (n + 1) / n after n frames held) would pass max_next_flow_fraction,
        # the range the flow can follow: in a fast turn one frame's flow is already 63 px
        width = self.camera.size_hw[1]
        held = max(1, self.line - self._kf_line)
        next_flow = mean_flow * (held + 1) / held
        if sol.tracks is None and sol.branch in (Branch.PNP, Branch.ROTATION):
            ratio = sol.stats.get("inlier_ratio") if sol.branch == Branch.PNP else None
            note = ""
            if mean_flow > kc.max_flow_fraction * width:
                note = f"; keyframe handed on at mean flow {mean_flow:.1f} px"
            elif next_flow > kc.max_next_flow_fraction * width:
                note = (f"; keyframe handed on at mean flow {mean_flow:.1f} px, "
                        f"{next_flow:.1f} px expected at the next frame")
            elif (kc.min_inlier_share > 0 and ratio is not None and self._kf_ratio0 is not None
                  and ratio < kc.min_inlier_share * self._kf_ratio0):
                # the keyframe's points are leaving the view (an orbit, an occluder): its depth still
                # fits the frames that see them, but PnP on a shrinking, one-sided set drifts in rotation
                note = (f"; keyframe handed on at a PnP inlier share of {ratio:.2f} < "
                        f"{kc.min_inlier_share} x {self._kf_ratio0:.2f} (the first frame on it)")
            if note:
                sol = self._hand_on(kf, ref, m, sol, note, tm)
        return sol, ref

    def _hand_on(self, kf: Keyframe, ref: ReferenceDepth | None, m: Matches, sol: Solution, note: str,
                 tm: StageTimer) -> Solution:
        """The PnP / rotation-only frame ``sol`` becomes the keyframe: ``kf``'s depth moved into it
        and, with ``keyframes.handon_min_angle_deg``, after PnP the matches without depth
        triangulated along its pose and scaled by ``kf``'s depth
        (:meth:`~trianflow_vo.frontend.FrontEnd.handon_points`; the view turns towards parts of
        the scene the held depth does not cover). ``note`` (the rule that handed it on) and what
        was added go into the reason."""
        min_deg = self.cfg.keyframes.handon_min_angle_deg
        extra = None
        if min_deg > 0 and sol.branch == Branch.PNP:
            t0 = time.perf_counter()
            extra, ratio = self.front.handon_points(ref, m, sol, np.radians(min_deg))
            tm.add("triangulate", t0)
            if ratio is None:
                note += " (too few points with depth to scale new ones)"
            else:
                note += (f" with {len(extra)} new points triangulated along its PnP pose, "
                         f"step length {ratio:.3f} x PnP's from the keyframe depth")
        return self.front.transfer_keyframe(kf, sol, note, extra)

    def _parallax_deg(self, parallax_px: float) -> float:
        """A parallax in pixels as an angle in degrees (over :func:`~trianflow_vo.camera.focal_px`)."""
        return float(np.degrees(parallax_px / focal_px(self.camera.K)))

    def _solve_pairwise(self, kf: Keyframe, m: Matches, cur: Keyframe, stats: dict, tm: StageTimer):
        """The authors' policy (``scale.source`` depth): every pair scaled by the network depth of
        the new frame; every frame becomes the next reference."""
        R_rot, parallax, _ = self.front.rotation(m, tm)
        stats["parallax_px"] = parallax
        ref = self._reference(kf, tm)
        sol = self.front.two_view_to_depth(kf, ref, self._reference(cur, tm), m, R_rot, tm)
        return (sol if sol.tracks is not None else replace(sol, tracks=Tracks.empty())), ref

    def _compute_ahead(self, ref_prepared, next_image: np.ndarray | None) -> None:
        """Start the flow ``ref_prepared -> next frame`` in the background, if the source can."""
        speculate = getattr(self.flow, "speculate", None)
        if speculate is None or next_image is None:
            return
        nxt = self.flow.prepare(next_image)
        self._ahead = (next_image, nxt)
        speculate(ref_prepared, nxt)

    def _reference(self, kf: Keyframe, tm: StageTimer) -> ReferenceDepth | None:
        t0 = time.perf_counter()
        ref = self.depth.reference(kf)
        tm.add("depth", t0)
        return ref

    def _start(self, frame_index: int, timestamp: float | None, image: np.ndarray, prepared,
               tm: StageTimer) -> FrameResult:
        """The first frame: identity pose, the first keyframe (no depth yet)."""
        self.keyframe = Keyframe(frame_index, image, prepared, np.eye(4), Tracks.empty())
        self._kf_line = self.line
        self.T_world_last = np.eye(4)
        self._index_last, self._twist_last, self._twist_kf = frame_index, None, None
        self._reference(self.keyframe, tm)  # a network computes the first keyframe's depth now
        line, self.line = self.line, self.line + 1
        return FrameResult(line, frame_index, timestamp, np.eye(4), Branch.INIT, "first frame", None, np.eye(4),
                           True, self.camera.K, FrameStats(ms=tm.ms, frame_ms=tm.elapsed_ms()),
                           FrameView.of(image=image))

    def _commit(self, frame_index: int, timestamp: float | None, image: np.ndarray, prepared, m: Matches,
                ref: ReferenceDepth | None, sol: Solution, stats: dict, tm: StageTimer) -> FrameResult:
        """Build the frame's result once, then move the state on (new keyframe after a two-view step)."""
        kf = self.keyframe
        is_keyframe = sol.tracks is not None
        self._new_keyframe_last = is_keyframe
        kept_keyframe = not is_keyframe and sol.branch in (Branch.PNP, Branch.ROTATION) and not self._flow_lost(sol)
        self._held_last = (frame_index, image, prepared, sol) if kept_keyframe else None
        if kept_keyframe and sol.branch == Branch.PNP and self._kf_ratio0 is None:
            self._kf_ratio0 = sol.stats.get("inlier_ratio")
        if is_keyframe:
            self._kf_ratio0 = None
            if sol.step_norm is not None:  # a handed-on keyframe (PnP / rotation) keeps the last step length
                self.last_step_norm = sol.step_norm
            self.keyframe = Keyframe(frame_index, image, prepared, sol.T_world_cam, sol.tracks)
            self._kf_line = self.line
        if self.cfg.input.readout != 0 and self._index_last is not None and frame_index > self._index_last:
            self._twist_last = twist_per_frame(invert_T(self.T_world_last) @ sol.T_world_cam,
                                               frame_index - self._index_last)
        self._index_last = frame_index
        if is_keyframe:
            self._twist_kf = self._twist_last
        self.T_world_last = sol.T_world_cam
        line, self.line = self.line, self.line + 1
        view = FrameView.of(image=image, depth=None if ref is None else ref.depth, flow=m.fw, flow_bw=m.bw,
                            pts_ref=sol.pts_ref,
                            pts_cur=sol.pts_cur, points_world=sol.points_world, point_colors=sol.point_colors)
        return result_from_solution(line, frame_index, timestamp, kf.index, sol, stats, self.camera.K, tm, view)

    def apply_revision(self, revision: PoseRevision, T_world_last: np.ndarray) -> None:
        """A back-end moved keyframes: chain on from the revised pose of the current keyframe,
        with its carried depth corrected by ``revision.depth_correction`` when the back-end
        gives one (tracks whose corrected depth would not be positive end; the last step
        length follows the median change of depth).

        ``T_world_last`` is the last frame's pose after the revision (from the
        pipeline's :class:`~trianflow_vo.backend.Trajectory`)."""
        kf = self.keyframe
        if kf is not None and kf.index in revision.T_world_cam:
            kf = kf.with_pose(revision.T_world_cam[kf.index])
        c = None if kf is None else revision.depth_correction.get(kf.index)
        if c is not None and len(kf.tracks):
            tr = kf.tracks
            depth, valid = c.apply(tr.depth)
            kf = kf.with_tracks(Tracks(tr.ids[valid], tr.pts[valid], depth[valid], tr.weight[valid]))
            if self.last_step_norm is not None:
                self.last_step_norm *= c.median_factor(tr.depth)
        self.keyframe = kf
        self.T_world_last = np.array(T_world_last, dtype=np.float64)
