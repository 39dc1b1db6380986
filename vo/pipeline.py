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
import os
import signal
import time
from collections.abc import Callable, Iterable
from dataclasses import replace
from pathlib import Path

import cv2
from threadpoolctl import threadpool_limits
from trianflow_vo.backend import Backend, Trajectory, make_backend
from trianflow_vo.camera import PinholeCamera, intrinsics_problem, working_size
from trianflow_vo.config import Config, resolve_scale_source, write_config_yaml
from trianflow_vo.depth.base import DepthPrior
from trianflow_vo.errors import ConfigError, InputError
from trianflow_vo.flow.base import FlowSource
from trianflow_vo.frame import Branch, FrameResult
from trianflow_vo.frames import Frame, FrameSkip
from trianflow_vo.io.calib import how_to_give_intrinsics
from trianflow_vo.io.run_dir import Interrupted, InterruptSignals, open_run_dir, signal_name
from trianflow_vo.io.run_writer import RunClock, RunWriter, write_failed_status
from trianflow_vo.io.sequence import Prefetcher, open_sequence
from trianflow_vo.observer import Observer
from trianflow_vo.odometry import Odometry
from trianflow_vo.runlog import OverruleWatch, RunLog
from trianflow_vo.timing import StageTimer

log = logging.getLogger("trianflow_vo.pipeline")

MakeOdometry = Callable[[PinholeCamera, Config], object]


def make_flow_source(config: Config) -> FlowSource:
    """OpenCV DIS (weight-free; computed one frame ahead with ``flow.ahead``) or the ONNX flow
    network of ``flow.model``."""
    if config.flow.model is not None:
        from trianflow_vo.flow.onnx_flow import OnnxFlow

        return OnnxFlow(config.flow.model, threads=config.runtime.threads)
    from trianflow_vo.flow.dis import DisFlow

    dis = DisFlow(config.flow.dis_preset)
    if not config.flow.ahead:
        return dis
    from trianflow_vo.flow.speculative import SpeculativeFlow

    return SpeculativeFlow(dis, dis.clone())


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
    *,
    overwrite: bool = False,
    clock: RunClock | None = None,
) -> dict:
    """Process the sequence ``seq`` and write the run folder ``out_dir``; returns the ``run.json`` summary.

    Frames are streamed (decoded one ahead in a background thread) and every pose
    is written as soon as it is known. ``observers`` get the hooks of
    :class:`~trianflow_vo.observer.Observer`. Degraded frames and skipped files
    are logged (logger ``trianflow_vo``) and grouped by kind in ``run.json``.

    Everything that can be checked is checked before ``out_dir`` is touched (the
    sequence, intrinsics, working size and its memory, the Rerun path). Then the
    folder is created and locked (:func:`~trianflow_vo.io.run_dir.open_run_dir`: a
    folder held by a live run is refused, one with an earlier run's files too unless
    ``overwrite``). From there on every exit writes the final ``status`` of
    ``run.json``: ``completed``; ``interrupted`` on Ctrl-C or SIGTERM (both raise
    :class:`~trianflow_vo.io.run_dir.Interrupted`, a ``KeyboardInterrupt``, re-raised
    after closing); ``failed`` with a one-line ``error`` otherwise (re-raised).

    ``odometry_factory(camera, config)`` replaces the TrianFlow odometry with another
    object whose ``step(frame_index, timestamp, image, timer)`` returns a
    :class:`~trianflow_vo.frame.FrameResult` (e.g. the sparse baseline,
    :mod:`trianflow_vo.baseline.sparse`) and that has ``describe()``. ``backend``
    replaces the one ``backend.kind`` names. ``clock`` (a
    :class:`~trianflow_vo.io.run_writer.RunClock`) is the run's frame counter and
    frame rate, shared with e.g. a progress display.
    """
    # BLAS threads spin-wait between NumPy's (small) products on the cores the flow thread and the
    # back-end process need; held to runtime.blas_threads for the run, restored after it
    with InterruptSignals() as signals, threadpool_limits(limits=config.runtime.blas_threads, user_api="blas"):
        return _run(Path(seq), Path(out_dir), config, list(observers), odometry_factory, backend, overwrite,
                    clock or RunClock(), signals)


def _run(seq: Path, out_dir: Path, config: Config, observers: list[Observer], odometry_factory, backend,
         overwrite: bool, clock: RunClock, signals: InterruptSignals) -> dict:
    cv2.setNumThreads(config.runtime.threads)
    inp = config.input
    # -- checks before the folder is touched ------------------------------------------------------------
    rerun_wanted = config.output.rerun is not None or config.output.rerun_spawn
    if rerun_wanted:
        from trianflow_vo.viz.rerun_logger import check_rerun_output

        check_rerun_output(config.output.rerun, config.output.rerun_spawn, out_dir)
    reader = open_sequence(seq, intrinsics=inp.intrinsics, calib=inp.calib, start=inp.start, end=inp.end,
                           stride=inp.stride)
    H, W = reader.image_size
    problem = intrinsics_problem(reader.K, (H, W))
    if problem is not None:
        raise InputError(f"implausible intrinsics from {reader.K_source}: {problem}; "
                         f"{how_to_give_intrinsics()}", seq)
    h, w = working_size(H, W, inp.size)
    if h <= 0 or w <= 0:
        raise InputError(f"bad working size {h}x{w}")
    check_memory((h, w), (H, W))
    camera = PinholeCamera(reader.K, (H, W)).resized((h, w))
    if resolve_scale_source(config) == "triangulation" and config.depth.model is not None:
        log.warning("depth.model is not used with scale.source=triangulation (scale from carried depth)")
    odo = (odometry_factory or make_odometry)(camera, config)
    runlog = RunLog()
    backend = backend or make_backend(config.backend, camera.K, camera.size_hw, warn=runlog.warn,
                                      blas_threads=config.runtime.blas_threads)
    gt = None
    if config.output.gt is not None:
        from trianflow_vo.eval import load_ground_truth

        gt = load_ground_truth(config.output.gt)
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
    # -- the folder: from here on every exit writes run.json's final status -----------------------------
    lock = open_run_dir(out_dir, overwrite=overwrite)
    writer: RunWriter | None = None
    extra: list[Observer] = list(observers)
    all_obs: list[Observer] = []
    trajectory = Trajectory()
    watch = OverruleWatch(ratio=config.scale.pnp_check_ratio)
    interrupted, error, signame = False, None, None
    try:
        writer = RunWriter(out_dir, info, runlog, clock=clock)
        try:
            write_config_yaml(config, out_dir / "config.yaml")
        except OSError as exc:  # a full disk fails at close, without the file name
            if exc.filename:
                raise
            raise OSError(exc.errno, exc.strerror, str(out_dir / "config.yaml")) from None
        if rerun_wanted:
            from trianflow_vo.viz.rerun_logger import RerunObserver

            extra.append(RerunObserver(path=config.output.rerun, spawn=config.output.rerun_spawn,
                                       gt_T_world_cam=None if gt is None else gt.poses,
                                       gt_frames=None if gt is None else gt.frames))
        all_obs = [writer, *extra]
        for ob in all_obs:
            ob.on_start(len(reader))
        clock.start(len(reader))  # the frame rate counts from the first frame read
        ahead = isinstance(odo, Odometry)  # it may start on the next frame's flow while solving this one
        with Prefetcher(_at_working_size(reader, (h, w)), depth=2) as frames:
            t_prev = time.perf_counter()
            for item, nxt in _with_next(frames):
                if isinstance(item, FrameSkip):
                    clock.frame_skipped()
                    writer.skip(item.index, item.source, item.reason)
                    runlog.warn("skipped-frame", f"{item.source}: skipped ({item.reason})", frame=item.index)
                    continue
                result = _step(odo, item, t_prev, nxt.image if ahead and isinstance(nxt, Frame) else None)
                t_prev = time.perf_counter()
                _report(result, runlog)
                contradicted = watch.update(result)
                if contradicted:
                    runlog.warn("depth-contradicted", contradicted, frame=result.frame_index)
                trajectory.add(result)
                clock.frame_done()
                # a frame's outputs are written whole: a Ctrl-C / SIGTERM that comes while they are is held
                # until every observer has it (else frames.tsv could hold a row that run.json does not count)
                with signals.deferred():
                    for ob in all_obs:
                        ob.on_frame(result)
                if signals.pending is not None:
                    raise Interrupted(signals.pending)
                if result.is_keyframe:
                    _revise(backend.add_keyframe(odo.keyframe, result), trajectory, odo, all_obs)
        if reader.shortfall is not None:  # the video ended before the frame count its container states
            runlog.warn("truncated-input", reader.shortfall.message)
        _revise(backend.finish(), trajectory, odo, all_obs)
        if writer.n_frames < 2:
            raise InputError(f"fewer than two usable frames ({writer.n_frames} processed, "
                             f"{len(writer.skipped)} skipped)", seq)
    except KeyboardInterrupt as exc:
        interrupted, signame = True, signal_name(exc)
        raise
    except BaseException as exc:  # keep what was written; say the run failed
        error = failure_reason(exc)
        raise
    finally:
        with signals.deferred():  # a second Ctrl-C must not lose the final status
            try:
                _close(backend, runlog)
                _close(getattr(odo, "flow", None), runlog)  # a flow computed ahead still running
                info["backend"] = backend.describe()  # its counts and time, in the final run.json
                info.update(odo.describe())  # and the flow source's
                _finish(writer, extra, trajectory, gt, config, out_dir, seq, runlog, info, interrupted, error,
                        signame)
            finally:
                lock.release()
        if signals.pending is not None and not interrupted:
            log.warning(f"{signal.Signals(signals.pending).name} received while the outputs were being "
                        "closed; they were closed first")
    return writer.summary()


def _finish(writer, extra, trajectory, gt, config, out_dir, seq, runlog, info, interrupted, error, signame):
    """Close observers, plot, write the final run.json; a failure here never hides the run's own error."""
    stopped = interrupted or error is not None
    for ob in extra:
        try:
            ob.close(interrupted=stopped)
        except Exception as exc:  # an observer failing must not lose the trajectory
            runlog.warn("observer", f"observer {type(ob).__name__} failed to close: {exc}")
    if config.output.plot and len(trajectory.entries) >= 2:
        _plot(trajectory, gt, out_dir / "trajectory.png", seq.name, runlog)
    runlog.log_summary()
    if writer is None:  # the writer itself could not start: still leave a final status
        write_failed_status(out_dir, info, error, signame)
        return
    try:
        writer.close(interrupted=interrupted, error=error, signal=signame)
    except Exception as exc:
        if error is None and not interrupted:
            raise
        log.error(f"could not write the final run.json: {failure_reason(exc)}")


def failure_reason(exc: BaseException) -> str:
    """One line for ``run.json``'s ``error``: the exception type and message, an OSError with its file."""
    if isinstance(exc, OSError) and exc.filename:
        msg = f"{exc.filename}: {exc.strerror or exc}"
    else:
        msg = str(exc)
    line = " ".join(msg.split()) or type(exc).__name__
    return f"{type(exc).__name__}: {line}"


# bytes of per-frame buffers per working pixel: flow fw/bw (float32, 2 channels: 16 B), prepared
# images, masks, carried depth and weight, DIS pyramids; measured ~150 B/px on the KITTI sample
# (peak RSS 108 MB at 256x832, 207 MB at 512x1664, 602 MB at 1024x3328), rounded up
BYTES_PER_WORKING_PIXEL = 160
FRAMES_IN_FLIGHT = 3  # decoded source frames held at once: the one processed and two prefetched


def memory_needed(size_hw: tuple[int, int], source_hw: tuple[int, int]) -> int:
    """Rough bytes the per-frame buffers need: ``160 * h * w`` for the working size plus
    ``3 * H * W * 3`` for the decoded colour source frames in flight."""
    h, w = size_hw
    H, W = source_hw
    return BYTES_PER_WORKING_PIXEL * h * w + FRAMES_IN_FLIGHT * H * W * 3


def available_memory() -> int | None:
    """Bytes of memory available to this process (``MemAvailable``, capped by a cgroup v2/v1 limit),
    or None when unknown."""
    avail = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                avail = int(line.split()[1]) * 1024
                break
    except (OSError, ValueError, IndexError):
        pass
    if avail is None:
        try:
            avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (AttributeError, ValueError, OSError):
            avail = None
    for limit_f, used_f in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                            ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
                             "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        try:
            limit = Path(limit_f).read_text().strip()
            used = int(Path(used_f).read_text().strip())
        except (OSError, ValueError):
            continue
        if limit.isdigit() and int(limit) < (1 << 60):
            left = max(int(limit) - used, 0)
            avail = left if avail is None else min(avail, left)
        break
    return avail


def check_memory(size_hw: tuple[int, int], source_hw: tuple[int, int]) -> None:
    """ConfigError (``input.size``) when :func:`memory_needed` exceeds :func:`available_memory`."""
    need = memory_needed(size_hw, source_hw)
    have = available_memory()
    if have is not None and need > have:
        gb = 1024.0 ** 3
        raise ConfigError(
            f"working size {size_hw[0]}x{size_hw[1]} (source {source_hw[0]}x{source_hw[1]}) needs about "
            f"{need / gb:.1f} GiB for the per-frame buffers ({BYTES_PER_WORKING_PIXEL} bytes per working pixel "
            f"+ {FRAMES_IN_FLIGHT} decoded source frames), only {have / gb:.1f} GiB available; "
            "choose a smaller --size", key="input.size")


def _at_working_size(items, size_hw: tuple[int, int]):
    """The decoded frames resized to the working size, as they come. Iterated in the prefetch
    thread, so the resize (``cv2.resize`` releases the GIL) overlaps the previous frame's work."""
    it = iter(items)
    try:
        for item in it:
            if isinstance(item, Frame) and item.image.shape[:2] != size_hw:
                item = replace(item, image=cv2.resize(item.image, (size_hw[1], size_hw[0]),
                                                      interpolation=cv2.INTER_AREA))
            yield item
    finally:
        close = getattr(it, "close", None)
        if close is not None:
            close()  # e.g. release a video capture when stopped early


def _with_next(items):
    """``(item, the item after it or None)``. An error reading the next item is raised after the
    current one has been handed out (no frame is lost to it)."""
    it = iter(items)
    try:
        cur = next(it)
    except StopIteration:
        return
    while True:
        try:
            nxt = next(it)
        except StopIteration:
            yield cur, None
            return
        except BaseException:
            yield cur, None
            raise
        yield cur, nxt
        cur = nxt


def _step(odo, item, t_prev: float, next_image=None) -> FrameResult:
    """Run the odometry on one frame (already at the working size: :func:`_at_working_size`);
    ``next_image``: the next frame's image, for an odometry that computes ahead."""
    timer = StageTimer(t_start=t_prev)  # frame time includes waiting for the decoder (and the resize)
    if next_image is None:
        return odo.step(item.index, item.timestamp, item.image, timer)
    return odo.step(item.index, item.timestamp, item.image, timer, next_image=next_image)


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


def _close(part, runlog: RunLog) -> None:
    """Let the back-end (or the flow source) release its worker; a failure there is logged, never
    lost outputs."""
    close = getattr(part, "close", None)
    if close is None:
        return
    try:
        close()
    except Exception as exc:
        runlog.warn("close", f"{type(part).__name__} did not close cleanly: {exc}")


def _revise(revision, trajectory: Trajectory, odo, observers: list[Observer]) -> None:
    if revision is None:
        return
    if not revision.T_world_cam:
        if revision.depth_correction:  # the keyframe's depth only, no pose moved
            odo.apply_revision(revision, trajectory.entries[-1].T_world_cam)
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

