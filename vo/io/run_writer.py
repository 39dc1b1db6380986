"""Streaming run outputs: poses.txt, frames.txt, trajectory.tum, frames.tsv, run.json.

Every line is written whole as soon as the frame is done (the full line built first,
then one ``os.write`` on an unbuffered file), so an interrupted or crashed run leaves
a valid trajectory of what was processed. If a write fails (disk full, file too
large), the frame's lines are taken back from all four files (truncated to where the
frame began), so the files keep the same number of complete lines, and the error
names the file. ``run.json`` is rewritten every few frames and at the end, and says
whether the run completed; if the disk is too full to write it beside the old one,
the final status is written over the old one in place.

While the run goes, ``poses.txt`` and ``trajectory.tum`` hold each pose as first
estimated (append-only). When a back-end revised poses, both are rewritten once
at the end with the final trajectory (atomically), and ``run.json`` counts the
revisions; ``frames.tsv`` stays the per-frame log of the front-end.

Frame rate (``fps`` in ``run.json``, the progress line and the closing summary, all
from one :class:`RunClock`): frames processed / wall time from the first frame read
to the last frame done, decoding included (skipped frames count in neither).
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from trianflow_vo import __version__
from trianflow_vo.io.trajectory import format_kitti_line, format_tum_line
from trianflow_vo.backend import RevisedPoses
from trianflow_vo.frame import Branch, FrameResult
from trianflow_vo.observer import Observer
from trianflow_vo.runlog import RunLog
from trianflow_vo.resources import peak_rss_mb

FPS_DEFINITION = ("frames processed / wall time from the first frame read to the last frame done "
                  "(decoding included)")

BRANCHES = tuple(b.value for b in Branch)
# frames.tsv: one row per processed frame, which branch it took and why
LOG_COLUMNS = ("line", "frame", "ref_frame", "branch", "inliers", "scale", "parallax_px", "mean_flow_px",
               "pnp_ratio", "frame_ms", "reason")


def _fmt(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def _versions() -> dict:
    """Versions of what computes the poses; ``blas``: NumPy's BLAS libraries as the run uses them (name,
    version, the CPU kernels chosen, threads), since the last bits of their sums can change a run."""
    import cv2
    from threadpoolctl import threadpool_info

    blas = [f"{i['internal_api']} {i.get('version')} ({i.get('architecture')}), {i['num_threads']} thread(s)"
            for i in threadpool_info() if i["user_api"] == "blas"]
    return {"trianflow-vo": __version__, "python": platform.python_version(), "numpy": np.__version__,
            "opencv": cv2.__version__, "blas": blas}


class RunClock:
    """The run's frame counts and its one frame-rate definition (:data:`FPS_DEFINITION`).

    The pipeline calls :meth:`start` just before the first frame is read,
    :meth:`frame_done` after each processed frame and :meth:`frame_skipped` for each
    file that could not be used; the writer (``run.json``), the progress line and the
    closing summary all read :attr:`fps` from here.
    """

    def __init__(self, clock=time.perf_counter):
        self._now = clock
        self.total = 0
        self.processed = 0
        self.skipped = 0
        self.t_first: float | None = None
        self.t_last: float | None = None

    def start(self, total: int | None = None) -> None:
        if total is not None:
            self.total = int(total)
        self.t_first = self._now()
        self.t_last = self.t_first

    def frame_done(self) -> None:
        self.processed += 1
        self.t_last = self._now()

    def frame_skipped(self) -> None:
        self.skipped += 1

    @property
    def done(self) -> int:
        """Frames read so far, processed or skipped."""
        return self.processed + self.skipped

    @property
    def elapsed_s(self) -> float:
        """Wall time from the first frame read to the last frame done (0 before any frame)."""
        if self.t_first is None or self.t_last is None:
            return 0.0
        return max(self.t_last - self.t_first, 0.0)

    @property
    def fps(self) -> float | None:
        e = self.elapsed_s
        return self.processed / e if self.processed and e > 0 else None

    def eta_s(self) -> float | None:
        """Seconds left at the rate so far (processed and skipped frames alike), None if unknown."""
        if self.t_first is None or not self.done or not self.total:
            return None
        left = max(self.total - self.done, 0)
        per = (self._now() - self.t_first) / self.done
        return left * per


def _write_all(fd: int, data: bytes, path: Path) -> None:
    """Write ``data`` to ``fd`` entirely (retrying short writes); errors name ``path``."""
    view = memoryview(data)
    while view:
        try:
            n = os.write(fd, view)
        except OSError as exc:
            raise OSError(exc.errno, exc.strerror or os.strerror(exc.errno or 0), str(path)) from None
        if n <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        view = view[n:]


class _LineFile:
    """An unbuffered output file written in whole lines; knows its size so a frame can be taken back."""

    def __init__(self, path: Path):
        self.path = Path(path)
        try:
            self.fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        except OSError as exc:
            raise OSError(exc.errno, exc.strerror, str(self.path)) from None
        self.size = 0

    def write(self, text: str) -> None:
        data = text.encode()
        _write_all(self.fd, data, self.path)
        self.size += len(data)

    def truncate(self, size: int) -> None:
        """Take back everything after ``size`` bytes (best effort)."""
        with contextlib.suppress(OSError):
            os.ftruncate(self.fd, size)
            os.lseek(self.fd, size, os.SEEK_SET)
            self.size = size

    def close(self) -> None:
        if self.fd >= 0:
            with contextlib.suppress(OSError):
                os.close(self.fd)
            self.fd = -1


def _write_file_atomic(path: Path, text: str) -> None:
    """Write ``path`` through ``path.tmp`` and ``os.replace``; on failure the old file stays, the temporary goes."""
    tmp = path.with_name(path.name + ".tmp")
    f = _LineFile(tmp)
    try:
        f.write(text)
    except BaseException:
        f.close()
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    f.close()
    os.replace(tmp, path)


class RunWriter(Observer):
    """Observer that writes the run folder as the run goes.

    Args:
        out_dir: output folder (created).
        info: static facts for ``run.json`` (config, sequence, sources).
        runlog: the run's :class:`~trianflow_vo.runlog.RunLog` (its warnings go to ``run.json``).
        json_every: rewrite ``run.json`` every this many frames.
        clock: the run's :class:`RunClock` (frame rate, counts); its own when None.
    """

    FILES = ("poses.txt", "frames.txt", "trajectory.tum", "frames.tsv")

    def __init__(self, out_dir: Path, info: dict, runlog: RunLog | None = None, json_every: int = 25,
                 clock: RunClock | None = None):
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.info = info
        self.runlog = runlog or RunLog()
        self.json_every = json_every
        self.clock = clock or RunClock()
        self._own_clock = clock is None
        self.revisions = 0
        self.frames_revised = 0
        self.counts = {b: 0 for b in BRANCHES}
        self.skipped: list[dict] = []
        self.degraded: list[dict] = []
        self.stage_ms: dict[str, list[float]] = {}
        self.frame_ms: list[float] = []
        self.inliers: list[int] = []
        self.n_frames = 0
        self.t_start = time.perf_counter()
        self.status = "running"
        self.error: str | None = None
        self.signal: str | None = None
        self.poses: list[np.ndarray] = []  # small: 16 floats a frame
        self.frame_indices: list[int] = []
        self.timestamps: list[float | None] = []
        self._files: list[_LineFile] = []
        self._versions = _versions()  # as the run starts: what computes its poses
        try:
            for name in self.FILES:
                self._files.append(_LineFile(self.out_dir / name))
            self._poses, self._frames, self._tum, self._log = self._files
            self._log.write("\t".join(LOG_COLUMNS) + "\n")
            self._write_json()
        except BaseException:
            for f in self._files:
                f.close()
            raise

    @staticmethod
    def _timestamp(ts: float | None, frame_index: int) -> float:
        return ts if ts is not None else float(frame_index)

    def on_start(self, n_frames: int) -> None:
        if self._own_clock:
            self.clock.start(n_frames)

    def on_poses_revised(self, revised: RevisedPoses) -> None:
        """Hold the revised poses; the files are rewritten with them in :meth:`close`."""
        for line, T in zip(revised.lines, revised.T_world_cam):
            self.poses[int(line)] = np.array(T, dtype=np.float64)
        self.revisions = revised.revision
        self.frames_revised += len(revised.lines)

    def skip(self, index: int, source: str, reason: str) -> None:
        self.skipped.append({"frame": index, "source": source, "reason": reason})
        if self._own_clock:
            self.clock.frame_skipped()

    def on_frame(self, rec: FrameResult) -> None:
        st = rec.stats
        row = (rec.line, rec.frame_index, rec.ref_index, rec.branch.value, st.inliers, st.scale, st.parallax_px,
               st.mean_flow_px, st.pnp_ratio, st.frame_ms, rec.reason.replace("\t", " "))
        lines = (format_kitti_line(rec.T_world_cam) + "\n",
                 f"{rec.frame_index}\n",
                 format_tum_line(self._timestamp(rec.timestamp, rec.frame_index), rec.T_world_cam) + "\n",
                 "\t".join(_fmt(v) for v in row) + "\n")
        sizes = [f.size for f in self._files]
        try:
            for f, line in zip(self._files, lines):
                f.write(line)
        except BaseException:  # disk full, Ctrl-C mid-frame: take the frame back from every file
            for f, size in zip(self._files, sizes):
                f.truncate(size)
            raise
        self.poses.append(np.asarray(rec.T_world_cam, dtype=np.float64).copy())
        self.frame_indices.append(rec.frame_index)
        self.timestamps.append(rec.timestamp)
        self.counts[rec.branch.value] += 1
        if rec.branch not in (Branch.INIT, Branch.TWO_VIEW) or st.degraded:
            self.degraded.append({"frame": rec.frame_index, "branch": rec.branch.value, "reason": rec.reason})
        if st.inliers is not None:
            self.inliers.append(int(st.inliers))
        for k, v in st.ms.items():
            self.stage_ms.setdefault(k, []).append(v)
        if st.frame_ms is not None:
            self.frame_ms.append(st.frame_ms)
        self.n_frames += 1
        if self._own_clock:
            self.clock.frame_done()
        if self.n_frames % self.json_every == 0:
            self._write_json()

    def summary(self) -> dict:
        inl = np.asarray(self.inliers) if self.inliers else np.zeros(0)
        return {
            "status": self.status,
            "error": self.error,
            "signal": self.signal,
            "frames_processed": self.n_frames,
            "frames_skipped": len(self.skipped),
            "branch_counts": self.counts,
            "skipped": self.skipped,
            "degraded": self.degraded,
            "warnings": self.runlog.to_dict(),
            "revisions": {"count": self.revisions, "frames_revised": self.frames_revised},
            "inliers": {
                "median": float(np.median(inl)) if inl.size else None,
                "min": int(inl.min()) if inl.size else None,
                "max": int(inl.max()) if inl.size else None,
            },
            "timing_ms_median": {k: float(np.median(v)) for k, v in self.stage_ms.items()},
            "frame_ms_median": float(np.median(self.frame_ms)) if self.frame_ms else None,
            "elapsed_s": self.clock.elapsed_s,
            "fps": self.clock.fps,
            "fps_definition": FPS_DEFINITION,
            "wall_s": time.perf_counter() - self.t_start,
            "peak_rss_mb": peak_rss_mb(),
        }

    def _write_json(self, final: bool = False) -> None:
        doc = {**self.info, "versions": self._versions, **self.summary()}
        path = self.out_dir / "run.json"
        try:
            _write_file_atomic(path, json.dumps(doc, indent=2, default=str))
        except OSError as exc:
            if not final or not path.exists():
                raise OSError(exc.errno, exc.strerror, str(path)) from None
            # no room for a second copy: write the final status over the old file, compact
            try:
                _write_in_place(path, json.dumps(doc, separators=(",", ":"), default=str))
            except OSError:
                small = {k: doc.get(k) for k in ("command", "out_dir", "status", "error", "signal",
                                                 "frames_processed", "frames_skipped", "elapsed_s", "fps")}
                small["note"] = f"run.json cut short: {exc.strerror or exc}"
                try:
                    _write_in_place(path, json.dumps(small, separators=(",", ":"), default=str))
                except OSError:
                    raise OSError(exc.errno, exc.strerror, str(path)) from None

    def close(self, interrupted: bool = False, error: str | None = None, signal: str | None = None) -> None:
        """Close the files; rewrite the trajectory files when poses were revised; write the final run.json.

        Raises the first ``OSError`` (naming its file) after run.json has been written, if possible,
        with ``status: failed``.
        """
        for f in self._files:
            f.close()
        problem = None
        if self.revisions:
            try:
                self._rewrite_trajectory()
            except OSError as exc:
                problem = exc
                error = error or f"OSError: {exc.filename}: {exc.strerror}"
        self.status = "failed" if error else ("interrupted" if interrupted else "completed")
        self.error = error
        self.signal = signal if interrupted and not error else None
        self._write_json(final=True)
        if problem is not None:
            raise problem

    def _rewrite_trajectory(self) -> None:
        """Write poses.txt and trajectory.tum anew with the final (revised) poses, atomically."""
        lines = {"poses.txt": [format_kitti_line(T) for T in self.poses],
                 "trajectory.tum": [format_tum_line(self._timestamp(ts, i), T)
                                    for T, ts, i in zip(self.poses, self.timestamps, self.frame_indices)]}
        for name, rows in lines.items():
            _write_file_atomic(self.out_dir / name, "".join(r + "\n" for r in rows))


def _write_in_place(path: Path, text: str) -> None:
    """Overwrite ``path`` from its start and cut it to ``text`` (reuses the file's blocks)."""
    data = text.encode()
    fd = os.open(path, os.O_WRONLY)
    try:
        _write_all(fd, data, path)
        os.ftruncate(fd, len(data))
    finally:
        os.close(fd)


def write_failed_status(out_dir: Path, info: dict, error: str | None, signal: str | None = None) -> None:
    """``run.json`` for a run that stopped before its writer existed (best effort, never raises)."""
    doc = {**info, "status": "failed" if error else "interrupted", "error": error, "signal": signal,
           "frames_processed": 0, "frames_skipped": 0}
    with contextlib.suppress(Exception):
        _write_file_atomic(Path(out_dir) / "run.json", json.dumps(doc, indent=2, default=str))
