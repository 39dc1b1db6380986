"""Streaming run outputs: poses.txt, frames.txt, trajectory.tum, frames.tsv, run.json.

Every line is flushed as soon as the frame is done, so an interrupted or crashed
run leaves a valid trajectory of what was processed; ``run.json`` is rewritten
every few frames and at the end, and says whether the run completed.

While the run goes, ``poses.txt`` and ``trajectory.tum`` hold each pose as first
estimated (append-only). When a back-end revised poses, both are rewritten once
at the end with the final trajectory (atomically), and ``run.json`` counts the
revisions; ``frames.tsv`` stays the per-frame log of the front-end.
"""

from __future__ import annotations

import json
import os
import platform
import resource
import sys
import time
from pathlib import Path

import numpy as np

from trianflow_vo import __version__
from trianflow_vo.io.trajectory import format_kitti_line, format_tum_line
from trianflow_vo.backend import RevisedPoses
from trianflow_vo.frame import Branch, FrameResult
from trianflow_vo.observer import Observer
from trianflow_vo.runlog import RunLog

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


def peak_rss_mb() -> float:
    """Peak resident set size of this process in MiB."""
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / 1024.0 if sys.platform != "darwin" else r / (1024.0 * 1024.0)


def _versions() -> dict:
    import cv2

    return {"trianflow-vo": __version__, "python": platform.python_version(), "numpy": np.__version__,
            "opencv": cv2.__version__}


class RunWriter(Observer):
    """Observer that writes the run folder as the run goes.

    Args:
        out_dir: output folder (created).
        info: static facts for ``run.json`` (config, sequence, sources).
        runlog: the run's :class:`~trianflow_vo.runlog.RunLog` (its warnings go to ``run.json``).
        json_every: rewrite ``run.json`` every this many frames.
    """

    def __init__(self, out_dir: Path, info: dict, runlog: RunLog | None = None, json_every: int = 25):
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.info = info
        self.runlog = runlog or RunLog()
        self.json_every = json_every
        self.revisions = 0
        self.frames_revised = 0
        self._poses = open(self.out_dir / "poses.txt", "w")
        self._frames = open(self.out_dir / "frames.txt", "w")
        self._tum = open(self.out_dir / "trajectory.tum", "w")
        self._log = open(self.out_dir / "frames.tsv", "w")
        self._log.write("\t".join(LOG_COLUMNS) + "\n")
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
        self.poses: list[np.ndarray] = []  # small: 16 floats a frame
        self.frame_indices: list[int] = []
        self.timestamps: list[float | None] = []
        self._write_json()

    @staticmethod
    def _timestamp(ts: float | None, frame_index: int) -> float:
        return ts if ts is not None else float(frame_index)

    def on_poses_revised(self, revised: RevisedPoses) -> None:
        """Hold the revised poses; the files are rewritten with them in :meth:`close`."""
        for line, T in zip(revised.lines, revised.T_world_cam):
            self.poses[int(line)] = np.array(T, dtype=np.float64)
        self.revisions = revised.revision
        self.frames_revised += len(revised.lines)

    def skip(self, index: int, source: str, reason: str) -> None:
        self.skipped.append({"frame": index, "source": source, "reason": reason})

    def on_frame(self, rec: FrameResult) -> None:
        self._poses.write(format_kitti_line(rec.T_world_cam) + "\n")
        self._frames.write(f"{rec.frame_index}\n")
        self._tum.write(format_tum_line(self._timestamp(rec.timestamp, rec.frame_index), rec.T_world_cam) + "\n")
        st = rec.stats
        row = (rec.line, rec.frame_index, rec.ref_index, rec.branch.value, st.inliers, st.scale, st.parallax_px,
               st.mean_flow_px, st.pnp_ratio, st.frame_ms, rec.reason.replace("\t", " "))
        self._log.write("\t".join(_fmt(v) for v in row) + "\n")
        for f in (self._poses, self._frames, self._tum, self._log):
            f.flush()
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
        if self.n_frames % self.json_every == 0:
            self._write_json()

    def summary(self) -> dict:
        elapsed = time.perf_counter() - self.t_start
        inl = np.asarray(self.inliers) if self.inliers else np.zeros(0)
        return {
            "status": self.status,
            "error": self.error,
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
            "elapsed_s": elapsed,
            "fps": self.n_frames / elapsed if elapsed > 0 else None,
            "peak_rss_mb": peak_rss_mb(),
        }

    def _write_json(self) -> None:
        doc = {**self.info, "versions": _versions(), **self.summary()}
        tmp = self.out_dir / "run.json.tmp"
        tmp.write_text(json.dumps(doc, indent=2, default=str))
        os.replace(tmp, self.out_dir / "run.json")

    def close(self, interrupted: bool = False, error: str | None = None) -> None:
        """Close the files; rewrite the trajectory files when poses were revised."""
        self.status = "failed" if error else ("interrupted" if interrupted else "completed")
        self.error = error
        for f in (self._poses, self._frames, self._tum, self._log):
            f.close()
        if self.revisions:
            self._rewrite_trajectory()
        self._write_json()

    def _rewrite_trajectory(self) -> None:
        """Write poses.txt and trajectory.tum anew with the final (revised) poses, atomically."""
        lines = {"poses.txt": [format_kitti_line(T) for T in self.poses],
                 "trajectory.tum": [format_tum_line(self._timestamp(ts, i), T)
                                    for T, ts, i in zip(self.poses, self.timestamps, self.frame_indices)]}
        for name, rows in lines.items():
            tmp = self.out_dir / (name + ".tmp")
            tmp.write_text("".join(r + "\n" for r in rows))
            os.replace(tmp, self.out_dir / name)
