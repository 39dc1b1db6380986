"""The windowed bundle-adjustment back-end (``backend.window`` > 0).

On every new keyframe:

1. the tracks are followed from the previous keyframe into the new one through the
   step's flow (:class:`~trianflow_vo.ba.tracks.TrackTable`), and new tracks start
   at the step's triangulated matches;
2. the last ``window`` keyframes and the points of their tracks are bundle-adjusted
   (:func:`~trianflow_vo.ba.window.solve_window`), the oldest ``fixed`` keyframes
   held (gauge and scale); tracks with a reprojection error above ``outlier_px``
   after the solve end;
3. the revised keyframe poses go back through the back-end seam
   (:class:`~trianflow_vo.backend.PoseRevision`), with the factor by which the new
   keyframe's carried depth must be rescaled so that the next frames are scaled like
   the adjusted window (``depth_scale``): the median ratio of the adjusted points'
   depths to the front-end's depths at the same pixels.

A solve that fails (too few points, indeterminate system, error not reduced) or
that would move a keyframe implausibly far (more than ``max_shift`` keyframe steps
or ``max_rotation_deg``) keeps the front-end poses, is logged and counted; the run
goes on.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np

from trianflow_vo.backend import PoseRevision
from trianflow_vo.ba.tracks import TrackTable
from trianflow_vo.ba.window import solve_window
from trianflow_vo.config import BackendConfig
from trianflow_vo.frame import Branch, FrameResult
from trianflow_vo.geometry.fundamental import fundamental_from_pose
from trianflow_vo.geometry.se3 import invert_T, rotation_angle
from trianflow_vo.keyframe import Keyframe

log = logging.getLogger("trianflow_vo.ba")

Warn = Callable[..., None]  # warn(kind, message, frame=index), as RunLog.warn


def _depth_at(tracks, size_hw: tuple[int, int], uv: np.ndarray) -> np.ndarray:
    """Front-end depth of the keyframe's tracks at pixels ``uv`` ``(N, 2)`` (nearest track pixel; 0 = none)."""
    from trianflow_vo.depth.triangulated import splat_tracks

    dmap, _, _ = splat_tracks(tracks, size_hw)
    h, w = size_hw
    xi = np.clip(np.rint(uv[:, 0]).astype(np.int64), 0, w - 1)
    yi = np.clip(np.rint(uv[:, 1]).astype(np.int64), 0, h - 1)
    return dmap[yi, xi].astype(np.float64)


class WindowBackend:
    """Sliding-window bundle adjustment of keyframes (see the module docstring).

    Args:
        config: the ``backend`` section.
        K: ``(3, 3)`` intrinsics at working resolution.
        size_hw: working image size.
        warn: ``warn(kind, message, frame=index)`` for failures (the run log); None: the module logger only.
    """

    name = "window-ba"

    def __init__(self, config: BackendConfig, K: np.ndarray, size_hw: tuple[int, int], warn: Warn | None = None):
        self.cfg = config
        self.K = np.asarray(K, dtype=np.float64)
        self.size_hw = (int(size_hw[0]), int(size_hw[1]))
        self.warn = warn
        self.tracks = self._new_tracks()
        self.keyframes: list[int] = []  # window order, oldest first (all keyframes seen, trimmed)
        self.poses: dict[int, np.ndarray] = {}  # keyframe -> current T_world_cam
        # keyframe -> (its reference, front-end T_ref_cam, solved by two-view geometry)
        self.steps: dict[int, tuple[int, np.ndarray, bool]] = {}
        self.stats = {"solves": 0, "failures": 0, "rejected": 0, "skipped": 0, "revisions": 0, "tracks_ended": 0,
                      "track_resets": 0, "depth_rescales": 0}
        self._ms: list[float] = []
        self._points: list[int] = []
        self._factors: list[int] = []
        self._depth_scales: list[float] = []
        self._since = 0  # keyframes since the last adjustment

    # -- the Backend protocol ------------------------------------------------------------------------
    def add_keyframe(self, keyframe: Keyframe, result: FrameResult) -> PoseRevision | None:
        t0 = time.perf_counter()
        k = int(keyframe.index)
        self.poses[k] = np.array(keyframe.T_world_cam, dtype=np.float64)
        view = result.view
        if result.ref_index is None or view is None or view.flow is None or view.flow_bw is None:
            self._restart(k)  # the first frame (or a result without flow): tracks start at the next step
            return None
        if result.ref_index != self.tracks.newest or result.ref_index not in self.poses:
            self.stats["track_resets"] += 1
            self._restart(int(result.ref_index))
            self.poses.setdefault(int(result.ref_index), keyframe.T_world_cam @ invert_T(result.T_ref_cam))
        T_cur_ref = invert_T(np.asarray(result.T_ref_cam, dtype=np.float64))
        step = float(np.linalg.norm(T_cur_ref[:3, 3]))
        F = fundamental_from_pose(T_cur_ref[:3, :3], T_cur_ref[:3, 3] / step, self.K) if step > 1e-12 else None
        cand_ref, cand_cur, cand_world = view.pts_ref, view.pts_cur, view.points_world
        if cand_ref is None or cand_world is None or cand_world.shape[0] != cand_ref.shape[0]:
            cand_ref = cand_cur = np.zeros((0, 2))
            cand_world = np.zeros((0, 3))
        self.steps[k] = (int(result.ref_index), np.array(result.T_ref_cam, dtype=np.float64),
                         result.branch == Branch.TWO_VIEW)
        self.tracks.advance(int(result.ref_index), k, np.asarray(view.flow), np.asarray(view.flow_bw), F,
                            cand_ref, cand_cur, cand_world)
        self.keyframes.append(k)
        window = self.keyframes[-self.cfg.window:]
        self._trim(window)
        n_fixed = min(self.cfg.fixed, len(window) - 2)
        self._since += 1
        if n_fixed < 1 or len(window) < 3 or self._since < self.cfg.every:
            self.stats["skipped"] += 1
            return None
        self._since = 0
        revision = self._solve(window, n_fixed, keyframe)
        ms = (time.perf_counter() - t0) * 1000.0
        self._ms.append(ms)
        if revision is None:
            return None
        return PoseRevision(revision[0], reason=f"window bundle adjustment of {len(window)} keyframes", ms=ms,
                            depth_scale=revision[1])

    def finish(self) -> PoseRevision | None:
        return None

    def describe(self) -> dict:
        c = self.cfg
        med = (lambda v: float(np.median(v)) if v else None)
        return {
            "name": self.name, "window": c.window, "fixed": c.fixed, "huber_px": c.huber_px,
            "max_iterations": c.max_iterations, "every": c.every, "max_tracks": c.max_tracks, "cell_px": c.cell_px,
            "track_fb_px": c.track_fb_px, "track_epi_px": c.track_epi_px, "outlier_px": c.outlier_px,
            **self.stats,
            "ms_total": float(np.sum(self._ms)) if self._ms else 0.0, "ms_median": med(self._ms),
            "points_median": med(self._points), "factors_median": med(self._factors),
            "depth_scale_median": med(self._depth_scales),
        }

    # -- internals --------------------------------------------------------------------------------------
    def _new_tracks(self) -> TrackTable:
        c = self.cfg
        return TrackTable(self.size_hw, cell_px=c.cell_px, max_tracks=c.max_tracks, fb_px=c.track_fb_px,
                          epi_px=c.track_epi_px)

    def _restart(self, k: int) -> None:
        self.tracks = self._new_tracks()
        self.tracks.newest = k
        self.keyframes = [k]

    def _trim(self, window: list[int]) -> None:
        self.keyframes = list(window)
        for k in [k for k in self.poses if k not in window]:
            del self.poses[k]
        for k in [k for k in self.steps if k not in window]:
            del self.steps[k]
        self.tracks.forget(window)

    def _fail(self, kind: str, message: str, frame: int) -> None:
        if self.warn is not None:
            self.warn(kind, message, frame=frame)
        else:
            log.info(message)

    def _solve(self, window: list[int], n_fixed: int, keyframe: Keyframe):
        """Adjust ``window``; returns ``(revised poses, {newest: depth scale})`` or None."""
        c = self.cfg
        fixed = set(window[:n_fixed])
        poses = {k: self.poses[k] for k in window}
        sol, ok = solve_window(self.K, poses, fixed, self.tracks.obs, self.tracks.landmarks, huber_px=c.huber_px,
                               max_iterations=c.max_iterations, min_points=c.min_points,
                               steps=self._step_factors() if c.step_factors else None,
                               step_rot_sigma=np.radians(c.step_rot_deg), step_trans_sigma=c.step_trans)
        self.stats["solves"] += 1
        newest = window[-1]
        if not ok:
            self.stats["failures"] += 1
            self._fail("backend-failed", f"keyframe {newest}: bundle adjustment failed (too few points or no "
                                         "convergence); front-end poses kept", newest)
            return None
        self._points.append(sol.n_points)
        self._factors.append(sol.n_factors)
        why = self._implausible(poses, sol.poses, window)
        if why:
            self.stats["rejected"] += 1
            self._fail("backend-rejected", f"keyframe {newest}: bundle adjustment rejected ({why}); front-end "
                                           "poses kept", newest)
            return None
        bad = [t for t, e in sol.residual_px.items() if e > c.outlier_px]
        good = {t: X for t, X in sol.landmarks.items() if sol.residual_px[t] <= c.outlier_px}
        self.tracks.landmarks.update(good)
        self.tracks.end(np.asarray(bad, dtype=np.int64))
        self.stats["tracks_ended"] += len(bad)
        revised = {k: T for k, T in sol.poses.items() if k not in fixed}
        self.poses.update(revised)
        self.stats["revisions"] += 1
        scale = self._depth_scale(keyframe, sol.poses[newest], good) if c.rescale_depth else None
        return revised, ({newest: scale} if scale is not None else {})

    def _step_factors(self) -> dict[int, tuple[int, np.ndarray, float]]:
        """The window's steps with their translation sigmas: a two-view step ``step_trans`` x its
        length; a PnP / rotation-only step (a handed-on keyframe, whose translation direction
        is poorly determined) ``step_trans_pnp`` x the larger of its length and the median
        two-view step of the window."""
        c = self.cfg
        lengths = {k: float(np.linalg.norm(T[:3, 3])) for k, (_, T, _) in self.steps.items()}
        two_view = [lengths[k] for k, (_, _, tv) in self.steps.items() if tv]
        typical = float(np.median(two_view)) if two_view else 0.0
        return {k: (ref, T, c.step_trans * lengths[k] if tv else c.step_trans_pnp * max(lengths[k], typical))
                for k, (ref, T, tv) in self.steps.items()}

    def _implausible(self, before: dict, after: dict, window: list[int]) -> str:
        steps = [np.linalg.norm(before[b][:3, 3] - before[a][:3, 3]) for a, b in zip(window[:-1], window[1:])]
        step = float(np.median(steps)) if steps else 0.0
        for k in window:
            shift = float(np.linalg.norm(after[k][:3, 3] - before[k][:3, 3]))
            if step > 0 and shift > self.cfg.max_shift * step:
                return f"keyframe {k} would move {shift / step:.2f} keyframe steps"
            rot = np.degrees(rotation_angle(before[k][:3, :3].T @ after[k][:3, :3]))
            if rot > self.cfg.max_rotation_deg:
                return f"keyframe {k} would rotate {rot:.2f} deg"
        return ""

    def _depth_scale(self, keyframe: Keyframe, T_world_new: np.ndarray, points: dict) -> float | None:
        """Median ratio adjusted depth / front-end depth of the newest keyframe's tracked points."""
        ids, uv = self.tracks.obs.get(keyframe.index, (np.zeros(0, np.int64), np.zeros((0, 2))))
        if ids.size == 0 or len(keyframe.tracks) == 0:
            return None
        has = np.array([t in points for t in ids.tolist()], dtype=bool)
        if has.sum() < self.cfg.min_points:
            return None
        X = np.stack([points[t] for t in ids[has].tolist()])
        z_ba = ((X - T_world_new[:3, 3]) @ T_world_new[:3, :3])[:, 2]
        z_fe = _depth_at(keyframe.tracks, self.size_hw, uv[has])
        ok = (z_fe > 0) & (z_ba > 0)
        if ok.sum() < self.cfg.min_points:
            return None
        from trianflow_vo.geometry.scale import weighted_median

        # near points fix the ratio best (depth noise grows with depth squared)
        s = float(np.exp(weighted_median(np.log(z_ba[ok] / z_fe[ok]), 1.0 / z_fe[ok] ** 2)))
        if not np.isfinite(s) or s <= 0:
            return None
        self.stats["depth_rescales"] += 1
        self._depth_scales.append(s)
        return s
