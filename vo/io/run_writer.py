"""Streaming run outputs: poses.txt, frames.txt, trajectory.tum and run.json.

Every pose line is flushed as soon as the frame is done, so an interrupted or
crashed run leaves a valid trajectory of what was processed; ``run.json`` is
rewritten every few frames and at the end, and says whether the run completed.
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
from trianflow_vo.observer import FrameRecord

BRANCHES = ("init", "two-view", "pnp", "rotation", "identity", "failed")
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


class RunWriter:
    """Observer that writes the run folder as the run goes.

    Args:
        out_dir: output folder (created).
        info: static facts for ``run.json`` (config, sequence, sources).
        json_every: rewrite ``run.json`` every this many frames.
    """

    def __init__(self, out_dir: Path, info: dict, json_every: int = 25):
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.info = info
        self.json_every = json_every
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
        self._write_json()

    def skip(self, index: int, source: str, reason: str) -> None:
        self.skipped.append({"frame": index, "source": source, "reason": reason})

    def on_frame(self, rec: FrameRecord) -> None:
        self._poses.write(format_kitti_line(rec.T_world_cam) + "\n")
        self._frames.write(f"{rec.frame_index}\n")
        ts = rec.timestamp if rec.timestamp is not None else float(rec.frame_index)
        self._tum.write(format_tum_line(ts, rec.T_world_cam) + "\n")
        st = rec.stats
        row = (rec.line, rec.frame_index, rec.ref_index, rec.branch, st.get("inliers"), st.get("scale"),
               st.get("parallax"), st.get("mean_flow"), st.get("pnp_ratio"), st.get("frame_ms"),
               rec.reason.replace("\t", " "))
        self._log.write("\t".join(_fmt(v) for v in row) + "\n")
        for f in (self._poses, self._frames, self._tum, self._log):
            f.flush()
        self.poses.append(np.asarray(rec.T_world_cam, dtype=np.float64).copy())
        self.frame_indices.append(rec.frame_index)
        self.counts[rec.branch] = self.counts.get(rec.branch, 0) + 1
        if rec.branch not in ("init", "two-view") or rec.stats.get("degraded"):
            self.degraded.append({"frame": rec.frame_index, "branch": rec.branch, "reason": rec.reason})
        if "inliers" in rec.stats:
            self.inliers.append(int(rec.stats["inliers"]))
        for k, v in rec.stats.get("ms", {}).items():
            self.stage_ms.setdefault(k, []).append(v)
        if "frame_ms" in rec.stats:
            self.frame_ms.append(rec.stats["frame_ms"])
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
        self.status = "failed" if error else ("interrupted" if interrupted else "completed")
        self.error = error
        for f in (self._poses, self._frames, self._tum, self._log):
            f.close()
        self._write_json()
