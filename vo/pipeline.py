"""Run TrianFlow odometry over a sequence and write the run folder.

Library entry point::

    from pathlib import Path
    from trianflow_vo.config import Config
    from trianflow_vo.pipeline import run
    summary = run(Path("SEQ"), Path("out"), Config())

One frame: read (background thread) -> resize to the working size ->
:meth:`Odometry.step` (front-end) -> :class:`~trianflow_vo.frame.FrameResult` ->
the back-end on each new keyframe (may revise poses) -> observers (writer,
progress, Rerun). See ARCHITECTURE.md.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import cv2
from trianflow_vo.backend import Backend, Trajectory, make_backend
from trianflow_vo.camera import PinholeCamera, working_size
from trianflow_vo.config import Config, resolve_scale_source, write_config_yaml
from trianflow_vo.depth.base import DepthPrior
from trianflow_vo.errors import InputError
from trianflow_vo.flow.base import FlowSource
from trianflow_vo.frame import Branch, FrameResult
from trianflow_vo.frames import FrameSkip
from trianflow_vo.io.run_writer import RunWriter
from trianflow_vo.io.sequence import Prefetcher, open_sequence
from trianflow_vo.observer import Observer
from trianflow_vo.odometry import Odometry
from trianflow_vo.runlog import RunLog

log = logging.getLogger("trianflow_vo.pipeline")

MakeOdometry = Callable[[PinholeCamera, Config], object]


def make_flow_source(config: Config) -> FlowSource:
    """OpenCV DIS (weight-free) or the ONNX flow network of ``flow.model``."""
    if config.flow.model is not None:
        from trianflow_vo.flow.onnx_flow import OnnxFlow

        return OnnxFlow(config.flow.model, threads=config.runtime.threads)
    from trianflow_vo.flow.dis import DisFlow

    return DisFlow(config.flow.dis_preset)


def make_depth_prior(config: Config, size_hw: tuple[int, int]) -> DepthPrior:
    """Depth carried by triangulation (weight-free) or the ONNX depth network of ``depth.model``,
    as ``scale.source`` says."""
    if resolve_scale_source(config) != "triangulation":
        from trianflow_vo.depth.network import NetworkDepth
        from trianflow_vo.depth.onnx_depth import OnnxDepthNet

        return NetworkDepth(OnnxDepthNet(config.depth.model, threads=config.runtime.threads))
    from trianflow_vo.depth.triangulated import TriangulatedDepth

    return TriangulatedDepth(size_hw)


def make_odometry(camera: PinholeCamera, config: Config) -> Odometry:
    """The TrianFlow odometry with the flow source and depth prior the config names."""
    return Odometry(camera, make_flow_source(config), make_depth_prior(config, camera.size_hw), config)


def run(
    seq: Path,
    out_dir: Path,
    config: Config = Config(),
    observers: Iterable[Observer] = (),
    odometry_factory: MakeOdometry | None = None,
    backend: Backend | None = None,
) -> dict:
    """Process the sequence ``seq`` and write the run folder ``out_dir``; returns the ``run.json`` summary.

    Frames are streamed (decoded one ahead in a background thread) and every pose
    is written as soon as it is known. ``observers`` get the hooks of
    :class:`~trianflow_vo.observer.Observer`. Degraded frames and skipped files
    are logged (logger ``trianflow_vo``) and grouped by kind in ``run.json``. On
    KeyboardInterrupt the outputs are closed with ``status: interrupted`` and the
    interrupt re-raised.

    ``odometry_factory(camera, config)`` replaces the TrianFlow odometry with another
    object whose ``step(frame_index, timestamp, image, timer)`` returns a
    :class:`~trianflow_vo.frame.FrameResult` (e.g. the sparse baseline,
    :mod:`trianflow_vo.baseline.sparse`) and that has ``describe()``. ``backend``
    replaces the one ``backend.kind`` names.
    """
    seq, out_dir = Path(seq), Path(out_dir)
    cv2.setNumThreads(config.runtime.threads)
    inp = config.input
    reader = open_sequence(seq, intrinsics=inp.intrinsics, calib=inp.calib, start=inp.start, end=inp.end,
                           stride=inp.stride)
    H, W = reader.image_size
    h, w = working_size(H, W, inp.size)
    if h <= 0 or w <= 0:
        raise InputError(f"bad working size {h}x{w}")
    camera = PinholeCamera(reader.K, (H, W)).resized((h, w))
    if resolve_scale_source(config) == "triangulation" and config.depth.model is not None:
        log.warning("depth.model is not used with scale.source=triangulation (scale from carried depth)")
    odo = (odometry_factory or make_odometry)(camera, config)
    backend = backend or make_backend(config.backend.kind)
    gt = None
    if config.output.gt is not None:
        from trianflow_vo.eval import load_ground_truth

        gt = load_ground_truth(config.output.gt)
    runlog = RunLog()
    info = {
        "command": "run",
        "sequence": {"path": str(seq), "kind": reader.kind, "frames_selected": len(reader),
                     "source_size_hw": [H, W], "K_source": reader.K.tolist()},
        "out_dir": str(out_dir),
        "config": config.to_dict(),
        "working_size_hw": [h, w],
        "K_working": camera.K.tolist(),
        **odo.describe(),
        "backend": backend.describe(),
        "pose_convention": "poses.txt: T_world_cam (camera-to-world), first frame identity, KITTI 3x4 row-major",
    }
    writer = RunWriter(out_dir, info, runlog)
    write_config_yaml(config, out_dir / "config.yaml")
    extra = list(observers)
    if config.output.rerun is not None or config.output.rerun_spawn:
        from trianflow_vo.viz.rerun_logger import RerunObserver

        extra.append(RerunObserver(path=config.output.rerun, spawn=config.output.rerun_spawn,
                                   gt_T_world_cam=None if gt is None else gt.poses,
                                   gt_frames=None if gt is None else gt.frames))
    all_obs: list[Observer] = [writer, *extra]
    for ob in all_obs:
        ob.on_start(len(reader))
    trajectory = Trajectory()
    interrupted, error = False, None
    try:
        with Prefetcher(reader, depth=2) as frames:
            t_prev = time.perf_counter()
            for item in frames:
                if isinstance(item, FrameSkip):
                    writer.skip(item.index, item.source, item.reason)
                    runlog.warn("skipped-frame", f"{item.source}: skipped ({item.reason})", frame=item.index)
                    continue
                result = _step(odo, item, (h, w), t_prev)
                t_prev = time.perf_counter()
                _report(result, runlog)
                trajectory.add(result)
                for ob in all_obs:
                    ob.on_frame(result)
                if result.is_keyframe:
                    _revise(backend.add_keyframe(odo.keyframe, result), trajectory, odo, all_obs)
        _revise(backend.finish(), trajectory, odo, all_obs)
        if writer.n_frames < 2:
            raise InputError(f"fewer than two usable frames ({writer.n_frames} processed, "
                             f"{len(writer.skipped)} skipped)", seq)
    except KeyboardInterrupt:
        interrupted = True
        raise
    except Exception as exc:  # keep what was written; say the run failed
        error = f"{type(exc).__name__}: {exc}"
        raise
    finally:
        for ob in extra:
            try:
                ob.close(interrupted=interrupted or error is not None)
            except Exception as exc:  # an observer failing must not lose the trajectory
                runlog.warn("observer", f"observer {type(ob).__name__} failed to close: {exc}")
        if config.output.plot and len(trajectory.entries) >= 2:
            _plot(trajectory, gt, out_dir / "trajectory.png", seq.name, runlog)
        runlog.log_summary()
        writer.close(interrupted=interrupted, error=error)
    return writer.summary()


def _step(odo, item, size_hw: tuple[int, int], t_prev: float) -> FrameResult:
    """Resize one decoded frame to the working size and run the odometry on it."""
    from trianflow_vo.timing import StageTimer

    timer = StageTimer(t_start=t_prev)  # frame time includes waiting for the decoder
    t0 = time.perf_counter()
    img = item.image
    if img.shape[:2] != size_hw:
        img = cv2.resize(img, (size_hw[1], size_hw[0]), interpolation=cv2.INTER_AREA)
    timer.add("resize", t0)
    return odo.step(item.index, item.timestamp, img, timer)


def _report(result: FrameResult, runlog: RunLog) -> None:
    """Routine branches are information; rotation-only, failed and fallback frames are warnings."""
    what = f"frame {result.frame_index}: {result.branch}" + (f" ({result.reason})" if result.reason else "")
    if result.branch is Branch.ROTATION:
        runlog.warn("rotation-only", what, frame=result.frame_index)
    elif result.branch is Branch.FAILED:
        runlog.warn("failed-frame", what, frame=result.frame_index)
    elif result.stats.degraded:
        runlog.warn("scale-fallback", what, frame=result.frame_index)
    elif result.branch is not Branch.TWO_VIEW and result.branch is not Branch.INIT:
        runlog.info(what)


def _revise(revision, trajectory: Trajectory, odo, observers: list[Observer]) -> None:
    if revision is None or not revision.T_world_cam:
        return
    revised = trajectory.revise(revision)
    odo.apply_revision(revision, trajectory.entries[-1].T_world_cam)
    for ob in observers:
        ob.on_poses_revised(revised)


def _plot(trajectory: Trajectory, gt, path: Path, title: str, runlog: RunLog) -> None:
    try:
        from trianflow_vo.viz.plot import plot_trajectory

        plot_trajectory(trajectory.poses(), path, gt_T_world_cam=None if gt is None else gt.poses,
                        frames=trajectory.frame_indices(), gt_frames=None if gt is None else gt.frames,
                        title=title)
    except Exception as exc:
        runlog.warn("plot", f"trajectory.png not written: {exc}")

