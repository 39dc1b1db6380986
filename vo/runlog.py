"""The run's log: information and warnings, grouped by kind and kept for ``run.json``.

Messages go to the standard :mod:`logging` logger ``trianflow_vo`` (the CLI sets
its level with ``-v``/``-q``). Routine behaviour (a PnP step on small parallax, a
held keyframe, a static camera) is logged at INFO. A warning names its kind
(``skipped-frame``, ``rotation-only``, ``failed-frame``, ``scale-fallback``,
``backend-failed``, ``backend-rejected``, ``observer``, ``plot``); per-frame kinds are logged at INFO as they happen and
summarised once per kind at the end (WARNING), while a skipped frame is a
WARNING at once, naming its file. Every warning is kept, with its count, for
``run.json``.
"""

from __future__ import annotations

import logging

log = logging.getLogger("trianflow_vo")

# kinds that can happen on many frames: one summary line at the end instead of one line each
PER_FRAME_KINDS = {"rotation-only": "frames solved by rotation only",
                   "failed-frame": "frames failed (pose kept from the previous frame)",
                   "scale-fallback": "frames with a fallback scale (constant speed)",
                   "backend-failed": "keyframes whose bundle adjustment failed (front-end poses kept)",
                   "backend-rejected": "keyframes whose bundle adjustment was rejected as implausible"}


class RunLog:
    """Warnings of one run, grouped by kind (all kept), and the INFO log."""

    def __init__(self) -> None:
        self.groups: dict[str, list[dict]] = {}

    def warn(self, kind: str, message: str, frame: int | None = None) -> None:
        self.groups.setdefault(kind, []).append({"frame": frame, "message": message})
        if kind in PER_FRAME_KINDS:
            log.info(message)
        else:
            log.warning(message)

    def info(self, message: str) -> None:
        log.info(message)

    def count(self, kind: str) -> int:
        return len(self.groups.get(kind, ()))

    def log_summary(self, examples: int = 5) -> None:
        """One WARNING line per per-frame kind that occurred (count and the first frames)."""
        for kind, what in PER_FRAME_KINDS.items():
            items = self.groups.get(kind)
            if not items:
                continue
            frames = [str(i["frame"]) for i in items[:examples]]
            more = ", ..." if len(items) > examples else ""
            log.warning(f"{len(items)} {what}: frame {', '.join(frames)}{more} (all in run.json, frames.tsv)")

    def to_dict(self) -> dict:
        """``{kind: {"count": n, "items": [{"frame", "message"}, ...]}}`` for ``run.json``."""
        return {k: {"count": len(v), "items": list(v)} for k, v in self.groups.items()}
