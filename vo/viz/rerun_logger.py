"""Rerun observer: writes a ``.rrd`` recording of a run and/or streams it to a live viewer.

``rerun`` is imported only when a ``RerunObserver`` is built, so runs without
``--rerun``/``--rerun-spawn`` never load it.

What is logged (entity paths; every per-frame row on timeline ``frame`` = source
frame index, and on ``time`` = seconds when the frame has a timestamp):

- ``world`` and ``world/camera``: ``ViewCoordinates.RDF`` (static).
- ``world/camera``: ``Transform3D`` camera-to-world (parent = world, child = camera).
- ``world/camera/image``: ``Pinhole`` at working resolution (re-logged only when
  ``K`` or the size changes) and the frame as a JPEG ``EncodedImage``.
- ``world/camera/image/matches``: inlier matches as 2D segments reference -> current
  position (at most ``max_matches``, evenly subsampled).
- ``world/points``: the triangulated points of this pair in world coordinates,
  coloured from the image (at most ``max_points``, evenly subsampled).
- ``world/trajectory``: the estimated camera path so far (one line strip).
- ``world/ground_truth``: with ground truth, its path up to the current frame,
  mapped into the estimate's world by the inverse of the alignment ``eval`` uses
  (re-base to the first common frame, 7-DoF Umeyama on positions). Since the
  alignment needs the estimate, it is re-computed from the frames known so far
  every ``gt_every`` frames and once more at ``close`` (no row before 3 common
  frames with motion exist).
- ``reference/depth``: ``DepthImage`` of the reference frame used for scale,
  subsampled by ``depth_stride`` (default 4: 64x208 at 256x832) and quantised to
  uint16 (``meter`` per row); logged only when the reference frame changes, since
  raw depth is the largest item (26 KB per row at the default stride).
- ``reference/flow``: forward flow reference -> current as a JPEG colour image
  (see ``vo.viz.flow_color``).
- ``stats/<name>``: ``Scalars`` for every measured number in ``FrameResult.stats``
  (inliers, scale, mean_flow_px, parallax_px ...; the stage times become
  ``stats/ms/<stage>``), and ``stats/branch`` as a code (see ``BRANCH_CODES``).
- When a back-end revises poses (``on_poses_revised``), ``world/trajectory`` is
  re-logged with the revised path.
- ``log``: ``TextLog`` per frame: branch and reason (WARN for ``failed``).

An entity that had data on the previous frame but has none on this one gets a
``Clear`` so the viewer never shows stale matches, depth or points.

A default blueprint (``default_blueprint``) lays the views out: the 3D world; the
image with matches, the flow and the depth; the plots and the log. Rows are
batched into chunks for ``FILE_FLUSH_S`` (file only) or ``LIVE_FLUSH_S`` (live
viewer) seconds, which keeps per-chunk overhead small at a few frames per second.

Size: about 75 KB per frame on the shipped KITTI sample at 256x832 (JPEG 35 KB,
depth 22 KB, 1000 points 15 KB, 500 matches 9 KB, flow 8 KB), so a 1000-frame
run is about 75 MB; measured by ``tests/test_rerun.py``. The trajectory strip is
re-logged whole every frame (12 bytes per pose so far): +6 KB per frame on average
over a 1000-frame run.
"""

from __future__ import annotations

import math
import os
import re
import sys
from pathlib import Path

import cv2
import numpy as np

from trianflow_vo.errors import ConfigError, DependencyError, InputError, VOError
from trianflow_vo.backend import RevisedPoses
from trianflow_vo.frame import Branch, FrameResult, FrameView
from trianflow_vo.observer import Observer
from trianflow_vo.viz.flow_color import flow_to_rgb
from trianflow_vo.viz.plot import align_estimate_to_gt

def rerun_install_hint() -> str:
    """How to install rerun-sdk, with the version range of the installed trianflow-vo's ``rerun`` extra
    (its requirement metadata); without the metadata just the extra."""
    fallback = "pip install 'trianflow-vo[rerun]'"
    try:
        from importlib.metadata import PackageNotFoundError, requires

        reqs = requires("trianflow-vo") or []
    except (ImportError, PackageNotFoundError, OSError, ValueError):
        return fallback
    for req in reqs:
        spec, _, marker = req.partition(";")
        name = spec.strip()
        base = name.split("[")[0]
        for ch in "<>=!~ (":
            base = base.split(ch)[0]
        if base.lower().replace("_", "-") == "rerun-sdk" and re.search(r"extra\s*==\s*['\"]rerun['\"]", marker):
            return f"{fallback} (or pip install '{name.replace(' ', '')}')"
    return fallback


RERUN_INSTALL_HINT = rerun_install_hint()

BRANCH_CODES = {"init": 0, "two-view": 1, "pnp": 2, "rotation": 3, "identity": 4, "failed": 5}

_TRAJ_COLOR = (40, 120, 255)
_GT_COLOR = (160, 160, 160)
_MATCH_COLOR = (0, 255, 80)


def no_display_reason() -> str | None:
    """Why a native viewer window cannot open here, or None when it probably can.

    Only Linux/BSD is checked: there a window needs ``DISPLAY`` (X11) or
    ``WAYLAND_DISPLAY`` (Wayland).
    """
    if sys.platform.startswith(("linux", "freebsd", "openbsd", "netbsd")):
        if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
            return "no display (neither DISPLAY nor WAYLAND_DISPLAY is set)"
    return None


def check_rerun_output(path: str | Path | None, spawn: bool, out_dir: str | Path | None = None) -> None:
    """Check a run's Rerun output before anything is written: raises, does not create anything.

    ``path`` must be a file whose folder exists (or is ``out_dir``, the run folder about
    to be created), not a folder; ``spawn`` needs a display; both need rerun-sdk.

    Raises:
        ConfigError: ``path`` is a folder or its folder does not exist (key ``output.rerun``).
        VOError: ``spawn`` without a display.
        DependencyError: rerun-sdk is not installed.
    """
    if path is not None:
        p = Path(path)
        if p.is_dir():
            raise ConfigError(f"{p} is a folder; give a recording file, e.g. {p / 'run.rrd'}", key="output.rerun")
        parent = p.parent
        is_run_dir = out_dir is not None and os.path.abspath(parent) == os.path.abspath(out_dir)
        if not parent.is_dir() and not is_run_dir:
            what = "is not a folder" if parent.exists() else "does not exist"
            raise ConfigError(f"{p}: the folder {parent} {what}; create it first or choose another path",
                              key="output.rerun")
    if spawn:
        reason = no_display_reason()
        if reason is not None:
            raise VOError(f"cannot open a live Rerun viewer: {reason}; write a recording with --rerun FILE.rrd instead")
    import_rerun()


def import_rerun():
    """The ``rerun`` module, or ``DependencyError`` with the install hint."""
    try:
        import rerun as rr
    except ImportError as exc:
        raise DependencyError(f"rerun-sdk is needed for Rerun recordings ({exc}): {rerun_install_hint()}") from None
    return rr


def _even_subsample(n: int, k: int) -> np.ndarray:
    """At most ``k`` indices spread evenly over ``range(n)`` (all when ``n <= k``)."""
    if n <= k:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, k).round().astype(np.int64))


def _jpeg(image: np.ndarray, quality: int) -> bytes:
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(image), [int(cv2.IMWRITE_JPEG_QUALITY), int(quality)])
    if not ok:
        raise VOError("could not JPEG-encode an image for the Rerun recording")
    return buf.tobytes()


def quantize_depth(depth: np.ndarray) -> tuple[np.ndarray, float]:
    """``(depth_u16 (h, w) uint16, meter)`` with ``depth ~ depth_u16 / meter``.

    The largest finite positive depth maps to 65535; 0, negative and non-finite
    depths (unknown) map to 0. ``meter`` is 1 when no depth is known.
    """
    d = np.asarray(depth, dtype=np.float32)
    known = np.isfinite(d) & (d > 0)
    dmax = float(d[known].max()) if known.any() else 0.0
    if dmax <= 0:
        return np.zeros(d.shape, dtype=np.uint16), 1.0
    meter = 65535.0 / dmax
    q = np.zeros(d.shape, dtype=np.uint16)
    q[known] = np.clip(np.rint(d[known] * meter), 1, 65535).astype(np.uint16)
    return q, meter


def _flat_scalars(stats: dict, escape, prefix: str = ""):
    """``(entity sub-path, value)`` of every finite number in ``stats``; nested dicts
    (e.g. ``{"ms": {"flow": 3.1}}``) become sub-paths (``ms/flow``)."""
    for key, value in stats.items():
        name = prefix + escape(str(key))
        if isinstance(value, dict):
            yield from _flat_scalars(value, escape, name + "/")
        elif isinstance(value, (bool, int, float, np.integer, np.floating)) and math.isfinite(float(value)):
            yield name, float(value)


def default_blueprint(rr):
    """Viewer layout: 3D world | image with matches, flow, depth | plots and the text log."""
    rrb = rr.blueprint

    def series(name, *keys):
        return rrb.TimeSeriesView(origin="stats", contents=[f"$origin/{k}" for k in keys], name=name)

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="world"),
            rrb.Vertical(
                rrb.Spatial2DView(origin="world/camera/image", name="image + inlier matches"),
                rrb.Spatial2DView(origin="reference/flow", name="flow (reference -> current)"),
                rrb.Spatial2DView(origin="reference/depth", name="reference depth"),
            ),
            rrb.Vertical(
                series("inliers", "inliers"),
                series("scale", "scale"),
                series("flow / parallax (px)", "mean_flow_px", "parallax_px"),
                series("ms", "frame_ms", "ms", "ms/**"),
                series("branch (0 init, 1 two-view, 2 pnp, 3 rotation, 4 identity, 5 failed)", "branch"),
                rrb.TextLogView(origin="log", name="log"),
            ),
            column_shares=[3, 2, 2],
        ),
        collapse_panels=False,
    )


class RerunObserver(Observer):
    """Observer logging every processed frame to Rerun (see the module docstring).

    Args:
        path: ``.rrd`` file to write (its folder is created), or None.
        spawn: also (or only) stream to a live viewer started with ``spawn()``.
            With both, the data goes to both sinks (file and viewer).
        gt_T_world_cam: ``(N, 4, 4)`` ground-truth camera-to-world poses, or None.
        gt_frames: ``(N,)`` source frame index of each ground-truth pose
            (default ``0..N-1``).
        app_id: Rerun application id.
        jpeg_quality: JPEG quality of the image and flow rows (1..100).
        gt_every: re-align and log the ground-truth path every this many frames.
        max_matches: most inlier matches drawn per frame.
        max_points: most triangulated points logged per frame.
        depth_stride: keep every ``depth_stride``-th depth pixel in each direction.

    Raises:
        DependencyError: rerun-sdk is not installed, or Rerun is disabled by the
            ``RERUN`` environment variable.
        VOError: ``spawn`` without a display.
        InputError: the recording file cannot be created.
    """

    LIVE_FLUSH_S = 0.5  # batching period with a live viewer (latency)
    FILE_FLUSH_S = 10.0  # batching period when only writing a file (rows lost on a hard kill)

    def __init__(
        self,
        path: str | Path | None = None,
        spawn: bool = False,
        gt_T_world_cam: np.ndarray | None = None,
        gt_frames: np.ndarray | None = None,
        app_id: str = "trianflow-vo",
        jpeg_quality: int = 75,
        *,
        gt_every: int = 10,
        max_matches: int = 500,
        max_points: int = 1000,
        depth_stride: int = 4,
    ):
        if path is None and not spawn:
            raise ValueError("RerunObserver needs a path, spawn=True, or both")
        if not 1 <= int(jpeg_quality) <= 100:
            raise ValueError(f"jpeg_quality must be in 1..100, got {jpeg_quality}")
        if gt_every < 1 or max_matches < 0 or max_points < 0 or depth_stride < 1:
            raise ValueError("gt_every and depth_stride must be >= 1, max_matches and max_points >= 0")
        self._gt = None
        self._gt_frames = None
        if gt_T_world_cam is not None:
            gt = np.asarray(gt_T_world_cam, dtype=np.float64)
            if gt.ndim != 3 or gt.shape[1:] != (4, 4):
                raise ValueError(f"gt_T_world_cam must be (N, 4, 4), got {gt.shape}")
            frames = np.arange(gt.shape[0]) if gt_frames is None else np.asarray(gt_frames, dtype=np.int64).reshape(-1)
            if frames.shape[0] != gt.shape[0]:
                raise ValueError(f"gt_frames must have {gt.shape[0]} entries, got {frames.shape[0]}")
            self._gt, self._gt_frames = gt, frames
        elif gt_frames is not None:
            raise ValueError("gt_frames given without gt_T_world_cam")

        self.path = None if path is None else Path(path)
        self.spawn = bool(spawn)
        self.jpeg_quality = int(jpeg_quality)
        self.gt_every = int(gt_every)
        self.max_matches = int(max_matches)
        self.max_points = int(max_points)
        self.depth_stride = int(depth_stride)

        if self.spawn:
            reason = no_display_reason()
            if reason is not None:
                raise VOError(f"cannot open a live Rerun viewer: {reason}; write a recording with --rerun FILE.rrd instead")
        rr = import_rerun()
        self._rr = rr
        # Batch rows into chunks for a while: a pipeline at a few frames per second would
        # otherwise write one chunk per entity per frame, ~0.7 KB of overhead each.
        batcher = rr.ChunkBatcherConfig(flush_tick=self.LIVE_FLUSH_S if self.spawn else self.FILE_FLUSH_S)
        rec = rr.RecordingStream(app_id, make_default=False, make_thread_default=False, batcher_config=batcher)
        if not rec.is_enabled():
            raise DependencyError("Rerun is disabled in this environment (RERUN=off?): unset RERUN to record")
        if self.path is not None:
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                with open(self.path, "wb"):
                    pass  # fail now, with the file name, if it cannot be written
            except OSError as exc:
                raise InputError(f"cannot write the Rerun recording: {exc.strerror or exc}", self.path) from None
        blueprint = default_blueprint(rr)
        try:
            if self.spawn and self.path is not None:
                rec.spawn(connect=False)
                rec.set_sinks(rr.GrpcSink(), rr.FileSink(str(self.path)), default_blueprint=blueprint)
            elif self.spawn:
                rec.spawn(default_blueprint=blueprint)
            else:
                rec.save(str(self.path), default_blueprint=blueprint)
        except Exception as exc:  # rerun raises RuntimeError/OSError variants
            what = "start the Rerun viewer" if self.spawn else f"write {self.path}"
            raise VOError(f"cannot {what}: {exc}") from None
        self._rec = rec

        self._closed = False
        self._n_frames = 0
        self._positions: list[np.ndarray] = []
        self._poses: list[np.ndarray] = []
        self._frames: list[int] = []
        self._last_pinhole: tuple | None = None
        self._had: set[str] = set()  # entities with data on the previous frame
        self._gt_logged_at = -1
        self._depth_ref: int | None = None  # reference frame whose depth is on screen

        rec.log("world", rr.ViewCoordinates.RDF, static=True)
        rec.log("world/camera", rr.ViewCoordinates.RDF, static=True)

    # -- helpers -----------------------------------------------------------------

    def _log_or_clear(self, entity: str, archetype) -> None:
        """Log ``archetype`` at ``entity``, or clear it when None and it had data last frame."""
        if archetype is not None:
            self._rec.log(entity, archetype)
            self._had.add(entity)
        elif entity in self._had:
            self._rec.log(entity, self._rr.Clear(recursive=False))
            self._had.discard(entity)

    def _matches(self, view: FrameView):
        rr = self._rr
        if view.pts_ref is None or view.pts_cur is None or self.max_matches == 0:
            return None
        a = np.asarray(view.pts_ref, dtype=np.float32).reshape(-1, 2)
        b = np.asarray(view.pts_cur, dtype=np.float32).reshape(-1, 2)
        if a.shape != b.shape:
            raise ValueError(f"pts_ref and pts_cur must have the same shape, got {a.shape} and {b.shape}")
        if a.shape[0] == 0:
            return None
        idx = _even_subsample(a.shape[0], self.max_matches)
        strips = np.stack([a[idx], b[idx]], axis=1)  # (K, 2, 2)
        return rr.LineStrips2D(strips, colors=_MATCH_COLOR, radii=rr.Radius.ui_points(1.0))

    def _points(self, view: FrameView):
        rr = self._rr
        if view.points_world is None or self.max_points == 0:
            return None
        p = np.asarray(view.points_world, dtype=np.float32).reshape(-1, 3)
        keep = np.isfinite(p).all(axis=1)
        colors = None
        if view.point_colors is not None:
            colors = np.asarray(view.point_colors, dtype=np.uint8).reshape(-1, 3)
            if colors.shape[0] != p.shape[0]:
                raise ValueError(f"point_colors must be ({p.shape[0]}, 3), got {colors.shape}")
            colors = colors[keep]
        p = p[keep]
        if p.shape[0] == 0:
            return None
        idx = _even_subsample(p.shape[0], self.max_points)
        return rr.Points3D(p[idx], colors=None if colors is None else colors[idx], radii=rr.Radius.ui_points(2.0))

    def _depth(self, view: FrameView):
        if view.depth is None:
            return None
        d = np.asarray(view.depth)
        if d.ndim != 2:
            raise ValueError(f"depth must be (h, w), got {d.shape}")
        s = self.depth_stride
        q, meter = quantize_depth(d[::s, ::s])
        return self._rr.DepthImage(q, meter=meter)

    def _flow(self, view: FrameView):
        if view.flow is None:
            return None
        rgb, _ = flow_to_rgb(view.flow)
        bgr = np.ascontiguousarray(rgb[..., ::-1])
        return self._rr.EncodedImage(contents=_jpeg(bgr, self.jpeg_quality), media_type="image/jpeg")

    def _log_gt(self) -> None:
        """Log the ground-truth path up to the last frame, aligned with the frames so far."""
        if self._gt is None or not self._poses or self._gt_logged_at == self._n_frames:
            return
        self._gt_logged_at = self._n_frames
        T = np.stack(self._poses)
        frames = np.asarray(self._frames, dtype=np.int64)
        (S_ref_est, T_ref_gt, _), valid = align_estimate_to_gt(T, self._gt, frames, self._gt_frames)
        if not valid:
            return
        upto = self._gt_frames <= frames.max()
        M = np.linalg.inv(S_ref_est) @ T_ref_gt  # ground-truth world -> estimate world
        p = self._gt[upto, :3, 3] @ M[:3, :3].T + M[:3, 3]
        self._rec.log(
            "world/ground_truth",
            self._rr.LineStrips3D([p.astype(np.float32)], colors=_GT_COLOR, radii=self._rr.Radius.ui_points(1.5)),
        )

    # -- Observer ----------------------------------------------------------------

    def on_frame(self, record: FrameResult) -> None:
        if self._closed:
            raise RuntimeError("RerunObserver.on_frame after close()")
        rr, rec = self._rr, self._rec
        T = np.asarray(record.T_world_cam, dtype=np.float64)
        if T.shape != (4, 4):
            raise ValueError(f"T_world_cam must be (4, 4), got {T.shape}")

        rec.set_time("frame", sequence=int(record.frame_index))
        if record.timestamp is not None and math.isfinite(record.timestamp):
            rec.set_time("time", duration=float(record.timestamp))

        rec.log(
            "world/camera",
            rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3], relation=rr.TransformRelation.ParentFromChild),
        )
        self._poses.append(T)
        self._frames.append(int(record.frame_index))
        self._positions.append(T[:3, 3].astype(np.float32))
        self._n_frames += 1
        view = record.view if record.view is not None else FrameView()

        if view.image is not None:
            img = np.asarray(view.image)
            if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
                raise ValueError(f"image must be (h, w, 3) uint8, got {img.shape} {img.dtype}")
            h, w = img.shape[:2]
            if record.K is not None:
                K = np.asarray(record.K, dtype=np.float64)
                if K.shape != (3, 3):
                    raise ValueError(f"K must be (3, 3), got {K.shape}")
                key = (h, w, *K.reshape(-1).round(9))
                if key != self._last_pinhole:
                    rec.log("world/camera/image", rr.Pinhole(image_from_camera=K, resolution=[w, h]))
                    self._last_pinhole = key
            rec.log(
                "world/camera/image",
                rr.EncodedImage(contents=_jpeg(img, self.jpeg_quality), media_type="image/jpeg"),
            )
        self._log_or_clear("world/camera/image/matches", self._matches(view))
        self._log_or_clear("world/points", self._points(view))
        if view.depth is None or record.ref_index is None or record.ref_index != self._depth_ref:
            self._log_or_clear("reference/depth", self._depth(view))
            self._depth_ref = None if view.depth is None else record.ref_index
        self._log_or_clear("reference/flow", self._flow(view))
        self._log_trajectory()
        if self._gt is not None and self._n_frames % self.gt_every == 0:
            self._log_gt()

        for name, value in _flat_scalars(record.stats.scalars(), rr.escape_entity_path_part):
            rec.log(f"stats/{name}", rr.Scalars(value))
        rec.log("stats/branch", rr.Scalars(float(BRANCH_CODES[record.branch.value])))
        text = f"frame {record.frame_index}: {record.branch}"
        if record.ref_index is not None:
            text += f" (reference {record.ref_index})"
        if record.reason:
            text += f": {record.reason}"
        rec.log("log", rr.TextLog(text, level="WARN" if record.branch is Branch.FAILED else "INFO"))

    def _log_trajectory(self) -> None:
        rr = self._rr
        self._rec.log(
            "world/trajectory",
            rr.LineStrips3D([np.stack(self._positions)], colors=_TRAJ_COLOR, radii=rr.Radius.ui_points(2.0)),
        )

    def on_poses_revised(self, revised: RevisedPoses) -> None:
        """Re-log the trajectory with the revised poses (at the current frame's time)."""
        for line, T in zip(revised.lines, revised.T_world_cam):
            self._poses[int(line)] = np.asarray(T, dtype=np.float64)
            self._positions[int(line)] = np.asarray(T[:3, 3], dtype=np.float32)
        if self._positions:
            self._log_trajectory()
            self._rec.log("log", self._rr.TextLog(f"poses revised ({len(revised.lines)} frames): {revised.reason}",
                                                  level="INFO"))

    def close(self, interrupted: bool = False) -> None:
        """Log the final ground-truth alignment, flush and close the sinks (idempotent)."""
        if self._closed:
            return
        self._closed = True
        rr, rec = self._rr, self._rec
        try:
            self._log_gt()
            if interrupted:
                rec.log("log", rr.TextLog(f"run interrupted after {self._n_frames} frames", level="WARN"))
            rec.flush()
        finally:
            rec.disconnect()
