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
   (:class:`~trianflow_vo.backend.PoseRevision`);
4. at the next keyframe, the depth it carries is corrected to the adjusted points it
   sees (``depth_correction``, :class:`~trianflow_vo.backend.DepthCorrection`): an
   affine map of inverse depth fitted to those points' depths in it (by its pose chained
   from the revised poses) against the front-end's depths at the same pixels. A two-view
   step whose rotation is a little wrong gets every ray angle wrong by about the same
   amount, so its depth is off by an offset of inverse depth, not by one scale; when
   the camera later keeps only part of that depth (the far points of a turn), a rescale
   of the whole becomes a jump of scale. The window, seeing each point from several
   keyframes, measures the offset; the correction removes it before it is handed on.
   By default (``shape``) the median depth is kept (the front-end's scale), and a
   correction is made only when its offset is significant (``depth_correction_t``
   standard errors), it changes some depth by more than ``depth_correction_min`` and it
   changes the near and far depths by factors at most ``depth_correction_max`` apart.

With ``backend.concurrent`` (the default) step 2 runs in a worker process
(:mod:`~trianflow_vo.ba.worker`; GTSAM holds the interpreter lock, so a thread
would not overlap) while the next frames are solved, and steps 2-3 end at the
next keyframe (or at the end of the run): the revision then also carries the
newer keyframe, chained from its revised reference, and the points that keyframe's
step triangulated are moved with it. The front-end solves each frame relative to
its keyframe, so the final poses are those of an adjustment that blocks (to the
last printed digit); only the moment a revision reaches the outputs moves by one
keyframe. The depth correction is made at the next keyframe in both orders, from the
same points, so it keeps them equal. If the worker process dies, the run says so
and adjusts in its own process from then on.

With ``backend.anchors`` > 0 (the default), keyframes that leave the window go to a small archive
(:mod:`~trianflow_vo.ba.anchors`: image, adjusted pose, points and their track ids). When the
newest keyframe of a window sees what an archived keyframe saw (with ``anchor_revisit_ratio`` < 1
only when the camera came back to it), from a view no more than ``anchor_max_zoom`` nearer or
farther, and fewer than ``anchor_max_shared`` of its points are still tracked into the newest
keyframe (else the window's tracks already link the two), the oldest such keyframes join the
window as held poses and their points are linked into the newest keyframe: the old image is warped to the new view
by the flow the newest keyframe's points and the relative pose predict, DIS finds what is
left, and links that are forward-backward consistent, fit one fundamental matrix and lie
within ``anchor_gate_px`` of their predicted pixel (one per ``cell_px`` cell) become tracks
seen in the two keyframes only (not followed on). Counted in ``run.json``
(``anchor_tries``, ``anchored_windows``, ``anchor_links``).

A solve that fails (too few points, indeterminate system, error not reduced) or
that would move a keyframe implausibly far (more than ``max_shift`` keyframe steps
or ``max_rotation_deg``) keeps the front-end poses, is logged and counted; the run
goes on.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass

import numpy as np

from trianflow_vo.backend import DepthCorrection, PoseRevision
from trianflow_vo.ba.anchors import (AnchorArchive, Archived, invert_flow_at, link_points, predicted_flow,
                                     revisit_candidates, warp_to_new)
from trianflow_vo.ba.graph import project
from trianflow_vo.ba.tracks import TrackTable, follow_flow, grid_cell, texture_score
from trianflow_vo.ba.worker import init_worker, solve_timed, warm_up
from trianflow_vo.config import BackendConfig
from trianflow_vo.frame import Branch, FrameResult
from trianflow_vo.geometry.fundamental import fundamental_from_pose
from trianflow_vo.geometry.se3 import invert_T, rotation_angle
from trianflow_vo.keyframe import Keyframe

log = logging.getLogger("trianflow_vo.ba")

# the worker process could not be started or has died
_WORKER_ERRORS = (BrokenProcessPool, OSError)

Warn = Callable[..., None]  # warn(kind, message, frame=index), as RunLog.warn


def _depth_at(tracks, size_hw: tuple[int, int], uv: np.ndarray) -> np.ndarray:
    """Front-end depth of the keyframe's tracks at pixels ``uv`` ``(N, 2)`` (nearest track pixel; 0 = none)."""
    from trianflow_vo.depth.triangulated import splat_tracks

    dmap, _, _ = splat_tracks(tracks, size_hw)
    h, w = size_hw
    xi = np.clip(np.rint(uv[:, 0]).astype(np.int64), 0, w - 1)
    yi = np.clip(np.rint(uv[:, 1]).astype(np.int64), 0, h - 1)
    return dmap[yi, xi].astype(np.float64)


def _one_per_cell(uv: np.ndarray, ok: np.ndarray, cell_px: int, width: int) -> np.ndarray:
    """Indices of the valid pixels ``uv`` ``(N, 2)`` (``ok`` ``(N,)``), the first of each ``cell_px`` grid cell."""
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return idx
    _, first = np.unique(grid_cell(uv[idx], cell_px, width), return_index=True)
    return idx[np.sort(first)]


@dataclass(frozen=True)
class _Outcome:
    """A concluded adjustment: revised poses (empty when it failed or was rejected), the
    adjusted points kept (track id -> world point), the window's size and the solve's time (ms)."""

    poses: dict
    points: dict
    n_keyframes: int
    ms: float


class _Job:
    """One window adjustment: its inputs, and :func:`solve_window` run here or in the worker process."""

    def __init__(self, window: list[int], fixed: set[int], poses: dict, keyframe: Keyframe, args: tuple,
                 kwargs: dict, anchors: tuple[int, ...] = ()):
        self.window, self.fixed, self.poses, self.keyframe = window, fixed, poses, keyframe
        self.anchors = anchors  # held old keyframes that joined the window (not revised)
        self.args, self.kwargs = args, kwargs
        self.solution: tuple = (None, False)
        self.ms = 0.0
        self.worker_rss_mb: float | None = None  # the worker process's peak memory so far
        self.future = None

    def run(self) -> None:
        self.solution, self.ms, _ = solve_timed(self.args, self.kwargs)

    def submit(self, pool) -> None:
        self.future = pool.submit(solve_timed, self.args, self.kwargs)

    def join(self) -> None:
        """Wait for the worker's answer (raises what the worker raised, or BrokenProcessPool)."""
        if self.future is not None:
            self.solution, self.ms, self.worker_rss_mb = self.future.result()


class WindowBackend:
    """Sliding-window bundle adjustment of keyframes (see the module docstring).

    Args:
        config: the ``backend`` section.
        K: ``(3, 3)`` intrinsics at working resolution.
        size_hw: working image size.
        warn: ``warn(kind, message, frame=index)`` for failures (the run log); None: the module logger only.
        blas_threads: NumPy's BLAS threads in the worker process (``runtime.blas_threads``); None: the
            library's default.
    """

    name = "window-ba"

    def __init__(self, config: BackendConfig, K: np.ndarray, size_hw: tuple[int, int], warn: Warn | None = None,
                 blas_threads: int | None = None):
        self.cfg = config
        self.blas_threads = blas_threads
        self.K = np.asarray(K, dtype=np.float64)
        self.size_hw = (int(size_hw[0]), int(size_hw[1]))
        self.warn = warn
        self.tracks = self._new_tracks()
        self.keyframes: list[int] = []  # window order, oldest first (all keyframes seen, trimmed)
        self.poses: dict[int, np.ndarray] = {}  # keyframe -> current T_world_cam
        # keyframe -> (its reference, front-end T_ref_cam, solved by two-view geometry)
        self.steps: dict[int, tuple[int, np.ndarray, bool]] = {}
        self.stats = {"solves": 0, "failures": 0, "rejected": 0, "skipped": 0, "revisions": 0, "tracks_ended": 0,
                      "track_resets": 0, "depth_corrections": 0, "depth_corrections_refused": 0,
                      "depth_corrections_small": 0, "depth_corrections_insignificant": 0,
                      "unscored_births": 0, "anchored_windows": 0,
                      "anchor_links": 0, "anchor_tries": 0}
        self._ms: list[float] = []
        self._points: list[int] = []
        self._factors: list[int] = []
        self._depth_factors: list[float] = []  # median depth change of each correction
        self._depth_spread: list[float] = []  # its 98th / 2nd percentile factor (1 = a rescale)
        # the adjusted points of the last concluded window, for the next keyframe's depth correction
        self._fresh_points: dict | None = None
        self._since = 0  # keyframes since the last adjustment
        self._pending: _Job | None = None  # an adjustment running in the worker process
        self._pool = None  # the worker process (started at the first keyframe)
        self._worker_rss_mb: float | None = None
        self.concurrent = bool(config.concurrent)  # as planned (run.json)
        # revisit anchors (backend.anchors > 0): old keyframes, the window's grey images, the path travelled
        self.archive = AnchorArchive(config.anchor_keep) if config.anchors > 0 else None
        self._gray: dict[int, np.ndarray] = {}
        self._path: dict[int, float] = {}
        self._travelled = 0.0
        self._flow = None
        self._concurrent = self.concurrent  # false once the worker is lost

    # -- the Backend protocol ------------------------------------------------------------------------
    def add_keyframe(self, keyframe: Keyframe, result: FrameResult) -> PoseRevision | None:
        t0 = time.perf_counter()
        k = int(keyframe.index)
        if self._concurrent and self._pool is None and not self.keyframes:
            try:  # the first keyframe: the worker imports GTSAM while the next frames are solved
                self._worker()
            except _WORKER_ERRORS as exc:
                self._worker_lost(k, exc)
        # an adjustment started in a worker at an earlier keyframe ends here, before the tracks move on
        done = self._collect()
        revised = dict(done.poses) if done else {}
        T_world_k = np.array(keyframe.T_world_cam, dtype=np.float64)
        if revised and result.ref_index is not None and int(result.ref_index) in revised:
            # the front-end chained it from its reference's pose before the revision
            T_world_k = revised[int(result.ref_index)] @ np.asarray(result.T_ref_cam, dtype=np.float64)
            revised[k] = T_world_k
        self.poses[k] = T_world_k
        # the points of the last concluded window (here, or at the previous keyframe when blocking)
        points, self._fresh_points = self._fresh_points, None
        # the step's triangulated points are in the world of the unrevised chain too
        moved = T_world_k @ invert_T(np.asarray(keyframe.T_world_cam, dtype=np.float64)) if k in revised else None
        now = self._advance(k, keyframe, result, moved)  # an adjustment solved here (not concurrent), or None
        correction = {}
        if points and self.cfg.depth_correction != "none":
            c = self._depth_correction(keyframe, T_world_k, points)
            if c is not None:
                correction[k] = c
        if done is None and now is None and not correction:
            return None
        ms = (time.perf_counter() - t0) * 1000.0 + (done.ms if done else 0.0)
        self._ms.append(ms)
        if now is not None:
            revised.update(now.poses)
        if not revised and not correction:
            return None
        n = (now or done).n_keyframes if (now or done) else 0
        why = f"window bundle adjustment of {n} keyframes" if revised else "depth correction"
        return PoseRevision(revised, reason=why, ms=ms, depth_correction=correction)

    def finish(self) -> PoseRevision | None:
        done = self._collect()
        if done is None:
            return None
        self._ms.append(done.ms)
        if not done.poses:
            return None
        return PoseRevision(done.poses, reason=f"window bundle adjustment of {done.n_keyframes} keyframes",
                            ms=done.ms)

    def describe(self) -> dict:
        c = self.cfg
        med = (lambda v: float(np.median(v)) if v else None)
        return {
            "name": self.name, "window": c.window, "fixed": c.fixed,
            "concurrent": self.concurrent,
            "huber_px": c.huber_px, "max_iterations": c.max_iterations, "every": c.every,
            "anchors": c.anchors,
            "max_tracks": c.max_tracks, "cell_px": c.cell_px, "track_texture_px": c.track_texture_px,
            "track_fb_px": c.track_fb_px, "track_epi_px": c.track_epi_px, "outlier_px": c.outlier_px,
            **self.stats,
            "ms_total": float(np.sum(self._ms)) if self._ms else 0.0, "ms_median": med(self._ms),
            "points_median": med(self._points), "factors_median": med(self._factors),
            "depth_correction": c.depth_correction, "depth_correction_max": c.depth_correction_max,
            "depth_correction_t": c.depth_correction_t, "depth_correction_min": c.depth_correction_min,
            "depth_factor_median": med(self._depth_factors),
            "depth_spread_median": med(self._depth_spread), "depth_spread_max": max(self._depth_spread, default=None),
            "worker_peak_rss_mb": self._worker_rss_mb,
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
        if self.archive is not None:
            for k in [k for k in self.keyframes if k not in window]:
                self._archive(k)
            for k in [k for k in self._gray if k not in window]:  # keyframes lost in a track reset
                del self._gray[k]
            for k in [k for k in self._path if k not in window]:
                del self._path[k]
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

    def _advance(self, k: int, keyframe: Keyframe, result: FrameResult,
                 moved: np.ndarray | None = None) -> "_Outcome | None":
        """Move the tracks into keyframe ``k`` (its pose already in ``self.poses``) and, when one
        is due, start an adjustment: solved here (returns its outcome) or in the worker process
        (``backend.concurrent``; returns None, :meth:`_collect` ends it). ``moved`` ``(4, 4)``: the
        world correction a revision of the reference applied, to apply to the step's points too."""
        view = result.view
        if result.ref_index is None or view is None or view.flow is None or view.flow_bw is None:
            self._restart(k)  # the first frame (or a result without flow): tracks start at the next step
            return None
        if result.ref_index != self.tracks.newest or result.ref_index not in self.poses:
            self.stats["track_resets"] += 1
            self._restart(int(result.ref_index))
            self.poses.setdefault(int(result.ref_index), self.poses[k] @ invert_T(result.T_ref_cam))
        T_cur_ref = invert_T(np.asarray(result.T_ref_cam, dtype=np.float64))
        step = float(np.linalg.norm(T_cur_ref[:3, 3]))
        F = fundamental_from_pose(T_cur_ref[:3, :3], T_cur_ref[:3, 3] / step, self.K) if step > 1e-12 else None
        cand_ref, cand_cur, cand_world = view.pts_ref, view.pts_cur, view.points_world
        if cand_ref is None or cand_world is None or cand_world.shape[0] != cand_ref.shape[0]:
            cand_ref = cand_cur = np.zeros((0, 2))
            cand_world = np.zeros((0, 3))
        elif moved is not None:
            cand_world = np.asarray(cand_world, dtype=np.float64) @ moved[:3, :3].T + moved[:3, 3]
        self.steps[k] = (int(result.ref_index), np.array(result.T_ref_cam, dtype=np.float64),
                         result.branch == Branch.TWO_VIEW)
        if self.archive is not None:
            self._remember(k, keyframe, int(result.ref_index))
        score = None
        if self.cfg.track_texture_px > 0 and cand_cur.shape[0]:
            if view.image is None:
                self.stats["unscored_births"] += 1
            else:
                score = texture_score(view.image, cand_cur, self.cfg.track_texture_px)
        self.tracks.advance(int(result.ref_index), k, np.asarray(view.flow), np.asarray(view.flow_bw), F,
                            cand_ref, cand_cur, cand_world, cand_score=score)
        self.keyframes.append(k)
        window = self.keyframes[-self.cfg.window:]
        self._trim(window)
        n_fixed = min(self.cfg.fixed, len(window) - 2)
        self._since += 1
        if n_fixed < 1 or len(window) < 3 or self._since < self.cfg.every:
            self.stats["skipped"] += 1
            return None
        self._since = 0
        c = self.cfg
        fixed = set(window[:n_fixed])
        poses = {j: self.poses[j] for j in window}
        anchors = self._anchor(k) if self.archive is not None else []
        for a in anchors:
            poses[a] = self.archive.items[a].T_world_cam
            fixed.add(a)
        # copies (pickled for the worker later), observations in window order: the order the
        # factors enter the graph in (a plain copy of tracks.obs changes the poses in the 9th digit)
        order = anchors + window
        seen = {t for j in order for t in self.tracks.obs.get(j, (np.zeros(0, np.int64),))[0].tolist()}
        args = (self.K, poses, fixed, {j: self.tracks.obs[j] for j in order if j in self.tracks.obs},
                {t: X for t, X in self.tracks.landmarks.items() if t in seen})
        kwargs = dict(huber_px=c.huber_px, max_iterations=c.max_iterations, min_points=c.min_points,
                      steps=self._step_factors() if c.step_factors else None,
                      step_rot_sigma=np.radians(c.step_rot_deg), step_trans_sigma=c.step_trans)
        job = _Job(window, fixed, poses, keyframe, args, kwargs, tuple(anchors))
        if self._concurrent:
            try:
                job.submit(self._worker())
                self._pending = job
                return None
            except _WORKER_ERRORS as exc:
                self._worker_lost(window[-1], exc)
        job.run()
        return self._conclude(job)

    # -- revisit anchors ----------------------------------------------------------------------------
    def _remember(self, k: int, keyframe: Keyframe, ref: int) -> None:
        """Keep keyframe ``k``'s grey image and the path travelled up to it (for the archive)."""
        import cv2

        img = np.asarray(keyframe.image)
        self._gray[k] = np.ascontiguousarray(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img)
        if ref in self.poses:
            self._travelled += float(np.linalg.norm(self.poses[k][:3, 3] - self.poses[ref][:3, 3]))
        self._path[k] = self._travelled

    def _archive(self, k: int) -> None:
        """Keyframe ``k`` leaves the window: archive it with the adjusted points it observed."""
        gray, path = self._gray.pop(k, None), self._path.pop(k, None)
        if gray is None or path is None or k not in self.poses:
            return
        ids, uv = self.tracks.obs.get(k, (np.zeros(0, np.int64), np.zeros((0, 2))))
        has = np.array([t in self.tracks.landmarks for t in ids.tolist()], dtype=bool)
        X = np.stack([self.tracks.landmarks[t] for t in ids[has].tolist()]) if has.any() else np.zeros((0, 3))
        self.archive.add(Archived(k, gray, np.array(self.poses[k]), np.array(uv[has]), X, path, np.array(ids[has])))

    def _anchor(self, k: int) -> list[int]:
        """Old keyframes the newest keyframe ``k`` revisits, linked into it as new tracks (their ids
        observed in the anchor and in ``k``); at most ``backend.anchors``."""
        c = self.cfg
        if k not in self._gray or k not in self._path or not len(self.archive):
            return []
        cands = revisit_candidates(self.archive, self.poses[k], self._path[k], self.K, self.size_hw,
                                   c.anchor_max_angle_deg, c.anchor_revisit_ratio, c.anchor_min_links,
                                   c.anchor_max_parallax_px, c.anchor_max_zoom,
                                   live_ids=self.tracks.obs.get(k, (np.zeros(0, np.int64),))[0],
                                   max_shared=c.anchor_max_shared)
        if not cands:
            return []
        if self._flow is None:
            from trianflow_vo.flow.dis import DisFlow

            self._flow = DisFlow("medium")  # "fast" is 5x cheaper, but its links lost the gain on 7-Scenes
        out = []
        for a, _ in cands[:c.anchors]:
            item = self.archive.items[a]
            self.stats["anchor_tries"] += 1
            T_new_old = invert_T(self.poses[k]) @ item.T_world_cam
            # the newest keyframe's points, with the links of an anchor taken before this one (they
            # predict the flow back to this old keyframe)
            ids_k, uv_k = self.tracks.obs.get(k, (np.zeros(0, np.int64), np.zeros((0, 2))))
            has = np.array([t in self.tracks.landmarks for t in ids_k.tolist()], dtype=bool)
            if has.sum() < c.anchor_min_links:
                continue
            X_k = np.stack([self.tracks.landmarks[t] for t in ids_k[has].tolist()])
            z_k = ((X_k - self.poses[k][:3, 3]) @ self.poses[k][:3, :3])[:, 2]
            # the old image seen from the newest keyframe (through its points and the relative pose);
            # the flow from it then only has to find what the poses got wrong
            bw0 = predicted_flow(self.K, invert_T(T_new_old), uv_k[has], z_k, self.size_hw)
            warped = warp_to_new(item.gray, bw0)
            uv_pred, _ = project(self.K, self.poses[k], item.X_world)
            start = invert_flow_at(bw0, item.uv, uv_pred)  # where the old pixels lie in the warped image
            r_fw, r_bw = self._flow.flow_pair(warped, self._gray[k])
            uv_new, inside, fb = follow_flow(r_fw, r_bw, start)
            followed = inside & (fb < c.track_fb_px)
            ok = link_points(item.uv, uv_new, followed, uv_pred, c.track_epi_px, c.anchor_gate_px, seed=k)
            sel = _one_per_cell(uv_new, ok, c.cell_px, self.size_hw[1])
            if sel.size < c.anchor_min_links:
                continue
            self.tracks.attach(a, item.uv[sel], k, uv_new[sel], item.X_world[sel])
            self.stats["anchor_links"] += int(sel.size)
            out.append(a)
        return out

    def _worker(self):
        """The worker process's pool (started on first use)."""
        if self._pool is None:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            # spawn: the run has threads (frame prefetch, OpenCV) that a fork would copy mid-work
            self._pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"),
                                             initializer=init_worker, initargs=(os.getpid(), 1.0, self.blas_threads))
            self._pool.submit(warm_up)
        return self._pool

    def close(self) -> None:
        """Stop the worker process (an adjustment still running is abandoned)."""
        self._pending = None
        pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)

    def _collect(self) -> "_Outcome | None":
        """Wait for the adjustment running in the worker, if any, and conclude it."""
        job, self._pending = self._pending, None
        if job is None:
            return None
        try:
            job.join()
            self._worker_rss_mb = max(self._worker_rss_mb or 0.0, job.worker_rss_mb or 0.0) or None
        except BrokenProcessPool as exc:
            self._worker_lost(job.window[-1], exc)
            job.run()
        return self._conclude(job)

    def _worker_lost(self, frame: int, exc: BaseException) -> None:
        """The worker process could not start or died (killed, out of memory): say so, and adjust
        here from now on."""
        self._fail("backend-worker", f"keyframe {frame}: the bundle adjustment's worker process failed "
                                     f"({exc or type(exc).__name__}); adjusting in this process from now on", frame)
        self.close()
        self._concurrent = False

    def _conclude(self, job: "_Job") -> "_Outcome":
        """Check a solved window and take it: revised poses, landmarks, outlier tracks ended."""
        c = self.cfg
        window, fixed, poses = job.window, job.fixed, job.poses
        sol, ok = job.solution
        self.stats["solves"] += 1
        newest = window[-1]
        nothing = _Outcome({}, {}, len(window), job.ms)
        if not ok:
            self.stats["failures"] += 1
            self._fail("backend-failed", f"keyframe {newest}: bundle adjustment failed (too few points or no "
                                         "convergence); front-end poses kept", newest)
            return nothing
        self._points.append(sol.n_points)
        self._factors.append(sol.n_factors)
        why = self._implausible(poses, sol.poses, window)
        if why:
            self.stats["rejected"] += 1
            self._fail("backend-rejected", f"keyframe {newest}: bundle adjustment rejected ({why}); front-end "
                                           "poses kept", newest)
            return nothing
        bad = [t for t, e in sol.residual_px.items() if e > c.outlier_px]
        good = {t: X for t, X in sol.landmarks.items() if sol.residual_px[t] <= c.outlier_px}
        self.tracks.landmarks.update(good)
        self.tracks.end(np.asarray(bad, dtype=np.int64))
        self.stats["tracks_ended"] += len(bad)
        revised = {k: T for k, T in sol.poses.items() if k not in fixed}
        if job.anchors:
            self.stats["anchored_windows"] += 1
        self.poses.update(revised)
        self.stats["revisions"] += 1
        self._fresh_points = good
        return _Outcome(revised, good, len(window), job.ms)

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

    def _depth_correction(self, keyframe: Keyframe, T_world_k: np.ndarray, points: dict) -> DepthCorrection | None:
        """The correction of keyframe ``k``'s carried depth (its tracks just followed into it):
        the adjusted ``points`` (track id -> world point) seen in it, put in its camera by
        ``T_world_k`` ``(4, 4)``, against the front-end's depth at their pixels. An affine
        correction that would change the depths of the keyframe's tracks (2nd to 98th
        percentile) by factors more than ``depth_correction_max`` apart is refused for a
        scale-only one (``shape``: for none), and so is one whose offset of inverse depth lies fewer than
        ``depth_correction_t`` standard errors from zero (:func:`~trianflow_vo.geometry.scale.inverse_depth_offset_t`);
        None with fewer than ``min_points`` points, or when the correction would
        change none of those depths (2nd, 50th, 98th percentile) by more than ``depth_correction_min``."""
        from trianflow_vo.geometry.scale import fit_inverse_depth_affine, inverse_depth_offset_t

        c = self.cfg
        ids, uv = self.tracks.obs.get(keyframe.index, (np.zeros(0, np.int64), np.zeros((0, 2))))
        if ids.size == 0 or len(keyframe.tracks) == 0:
            return None
        has = np.array([t in points for t in ids.tolist()], dtype=bool)
        if has.sum() < c.min_points:
            return None
        X = np.stack([points[t] for t in ids[has].tolist()])
        z_ba = ((X - T_world_k[:3, 3]) @ T_world_k[:3, :3])[:, 2]
        z_fe = _depth_at(keyframe.tracks, self.size_hw, uv[has])
        ok = (z_fe > 0) & (z_ba > 0)
        if ok.sum() < c.min_points:
            return None
        depth = keyframe.tracks.depth
        if c.depth_correction in ("affine", "shape"):
            (a, b), valid = fit_inverse_depth_affine(z_fe[ok], z_ba[ok], min_points=c.min_points)
            if valid and b != 0.0 and not DepthCorrection(a, b).spread(depth) <= c.depth_correction_max:
                self.stats["depth_corrections_refused"] += 1  # affine: a rescale instead; shape: nothing
                valid = False
            if valid and b != 0.0 and c.depth_correction_t > 0:
                t, t_ok = inverse_depth_offset_t(z_fe[ok], z_ba[ok], a, b)
                if not (t_ok and abs(t) >= c.depth_correction_t):
                    self.stats["depth_corrections_insignificant"] += 1  # as refused: a rescale / nothing
                    valid = False
        else:
            valid = False
        if c.depth_correction == "shape":
            if not valid or b == 0.0:
                return None
            # the front-end's scale kept: the correction's median change of depth over the tracks is 1
            m = DepthCorrection(a, b).median_factor(depth)
            a, b = a * m, b * m
        elif not valid:
            s = float(np.median(z_ba[ok] / z_fe[ok]))
            if not (np.isfinite(s) and s > 0):
                return None
            a, b = 1.0 / s, 0.0
        corr = DepthCorrection(a, b)
        if corr.largest_change(depth) < np.log1p(c.depth_correction_min):
            self.stats["depth_corrections_small"] += 1
            return None
        self.stats["depth_corrections"] += 1
        self._depth_factors.append(corr.median_factor(depth))
        self._depth_spread.append(corr.spread(depth))
        return corr
