"""Run TrianFlow odometry over a sequence and write the run folder.

Library entry point::

    from trianflow_vo.config import RunConfig
    from trianflow_vo.pipeline import run
    summary = run(RunConfig(seq=Path("SEQ"), out_dir=Path("out")))
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from pathlib import Path

import cv2
import numpy as np

from trianflow_vo.camera import scale_intrinsics, working_size
from trianflow_vo.config import RunConfig
from trianflow_vo.errors import InputError
from trianflow_vo.frames import FrameSkip
from trianflow_vo.io.run_writer import RunWriter
from trianflow_vo.io.sequence import Prefetcher, open_sequence
from trianflow_vo.observer import FrameRecord, Observer
from trianflow_vo.odometry import Odometry, OdometryParams


def make_flow_source(config: RunConfig, size_hw: tuple[int, int]):
    """OpenCV DIS (weight-free) or the ONNX flow network of ``config.flow_model``."""
    if config.flow_model is not None:
        from trianflow_vo.flow.onnx_flow import OnnxFlow

        return OnnxFlow(config.flow_model, threads=config.threads)
    from trianflow_vo.flow.dis import DisFlow

    return DisFlow(config.dis_preset)


def make_depth_source(config: RunConfig, size_hw: tuple[int, int]):
    """Depth carried by triangulation (weight-free) or the ONNX depth network."""
    if config.depth_model is not None:
        from trianflow_vo.depth.onnx_depth import OnnxDepth

        return OnnxDepth(config.depth_model, threads=config.threads)
    from trianflow_vo.depth.triangulated import TriangulatedDepth

    return TriangulatedDepth(size_hw)


def odometry_params(config: RunConfig) -> OdometryParams:
    return OdometryParams(
        n_samples=config.n_samples,
        top_ratio=config.top_ratio,
        ransac_threshold_px=config.ransac_threshold_px,
        refine=config.refine,
        min_parallax_px=config.min_parallax_px,
        min_inliers=config.min_inliers,
        seed=config.seed,
        ransac_method=config.ransac_method,
        depth_fusion=config.depth_fusion,
        depth_decay=config.depth_decay,
        pnp_check_ratio=config.pnp_check_ratio,
    )


def load_ground_truth(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(poses (N, 4, 4), frames (N,))`` of a ground-truth file (frame i = line i for KITTI)."""
    from trianflow_vo.io.trajectory import read_trajectory

    gt = read_trajectory(path)
    frames = gt.frames if gt.frames is not None else np.arange(len(gt.poses))
    return gt.poses, frames


def run(
    config: RunConfig,
    observers: Iterable[Observer] = (),
    on_warning: Callable[[str], None] | None = None,
    make_odometry: Callable[[np.ndarray, tuple[int, int], RunConfig], object] | None = None,
) -> dict:
    """Process ``config.seq`` and write ``config.out_dir``; returns the ``run.json`` summary.

    Frames are streamed (decoded one ahead in a background thread) and every pose
    is written as soon as it is known. ``observers`` receive each
    :class:`vo.observer.FrameRecord` (and, if they have ``on_start(n)``, the number of
    frames selected before the first one); ``on_warning`` receives one-line messages
    about degraded frames (skipped, PnP, rotation only). On KeyboardInterrupt the
    outputs are closed with ``status: interrupted`` and the interrupt re-raised.

    ``make_odometry(K, (h, w), config)`` replaces the TrianFlow odometry with another
    object whose ``step(frame_index, timestamp, image)`` returns a FrameRecord (e.g.
    the sparse baseline, :mod:`vo.baseline.sparse`); it should have ``describe()``.
    """
    warn = on_warning or (lambda msg: None)
    seq = open_sequence(config.seq, intrinsics=config.intrinsics, calib=config.calib, start=config.start,
                        end=config.end, stride=config.stride)
    H, W = seq.image_size
    h, w = working_size(H, W, config.size)
    if h <= 0 or w <= 0:
        raise InputError(f"bad working size {h}x{w}")
    K = scale_intrinsics(seq.K, (H, W), (h, w))
    if make_odometry is None:
        flow = make_flow_source(config, (h, w))
        depth = make_depth_source(config, (h, w))
        params = odometry_params(config)
        odo = Odometry(K, (h, w), flow, depth, params)
        method = {"odometry": "trianflow", "flow_source": flow.describe(), "depth_source": depth.describe(),
                  "params": params.__dict__}
    else:
        odo = make_odometry(K, (h, w), config)
        method = {"odometry": getattr(odo, "describe", lambda: {"name": type(odo).__name__})()}
    gt = None
    if config.gt is not None:
        gt = load_ground_truth(config.gt)
    info = {
        "command": "run",
        "config": config.to_dict(),
        "sequence": {"path": str(seq.path), "kind": seq.kind, "frames_selected": len(seq),
                     "source_size_hw": [H, W], "K_source": seq.K.tolist()},
        "working_size_hw": [h, w],
        "K_working": K.tolist(),
        **method,
        "pose_convention": "poses.txt: T_world_cam (camera-to-world), first frame identity, KITTI 3x4 row-major",
    }
    writer = RunWriter(config.out_dir, info)
    all_obs: list[Observer] = [writer]
    extra = list(observers)
    if config.rerun is not None or config.rerun_spawn:
        from trianflow_vo.viz.rerun_logger import RerunObserver

        extra.append(RerunObserver(path=config.rerun, spawn=config.rerun_spawn,
                                   gt_T_world_cam=None if gt is None else gt[0],
                                   gt_frames=None if gt is None else gt[1]))
    all_obs += extra
    for ob in all_obs:  # observers that want the number of selected frames (a progress bar)
        start = getattr(ob, "on_start", None)
        if start is not None:
            start(len(seq))
    interrupted = False
    error = None
    try:
        with Prefetcher(seq, depth=2) as frames:
            t_prev = time.perf_counter()
            for item in frames:
                if isinstance(item, FrameSkip):
                    writer.skip(item.index, item.source, item.reason)
                    warn(f"{item.source}: skipped ({item.reason})")
                    continue
                t0 = time.perf_counter()
                img = item.image
                if img.shape[:2] != (h, w):
                    img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
                resize_ms = (time.perf_counter() - t0) * 1000.0
                rec: FrameRecord = odo.step(item.index, item.timestamp, img)
                rec.stats["ms"]["resize"] = resize_ms
                now = time.perf_counter()
                rec.stats["frame_ms"] = (now - t_prev) * 1000.0  # wall time per frame, decoding included
                t_prev = now
                if rec.branch not in ("init", "two-view") or rec.stats.get("degraded"):
                    warn(f"frame {item.index}: {rec.branch} ({rec.reason})")
                for ob in all_obs:
                    ob.on_frame(rec)
        if writer.n_frames < 2:
            raise InputError(f"fewer than two usable frames ({writer.n_frames} processed, "
                             f"{len(writer.skipped)} skipped)", config.seq)
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
                warn(f"observer {type(ob).__name__} failed to close: {exc}")
        writer.close(interrupted=interrupted, error=error)
        if config.plot and writer.n_frames >= 2:
            try:
                from trianflow_vo.viz.plot import plot_trajectory

                plot_trajectory(np.stack(writer.poses), config.out_dir / "trajectory.png",
                                gt_T_world_cam=None if gt is None else gt[0],
                                frames=np.asarray(writer.frame_indices),
                                gt_frames=None if gt is None else gt[1], title=str(seq.path.name))
            except Exception as exc:
                warn(f"trajectory.png not written: {exc}")
    return writer.summary()
