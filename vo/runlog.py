"""The run's log: information and warnings, grouped by kind and kept for ``run.json``.

Messages go to the standard :mod:`logging` logger ``trianflow_vo`` (the CLI sets
its level with ``-v``/``-q``). Routine behaviour (a PnP step on small parallax, a
held keyframe, a static camera) is logged at INFO. A warning names its kind
(``skipped-frame``, ``rotation-only``, ``failed-frame``, ``scale-fallback``,
``backend-failed``, ``backend-rejected``, ``backend-worker``, ``depth-contradicted``,
``observer``, ``close``, ``plot``); per-frame kinds are logged at INFO as they happen
and summarised once per kind at the end (WARNING), while a skipped frame is a
WARNING at once, naming its file. Every warning is kept, with its count, for ``run.json``.
"""

from __future__ import annotations

import logging
import math

from trianflow_vo.frame import Branch

log = logging.getLogger("trianflow_vo")

# kinds that can happen on many frames: one summary line at the end instead of one line each
PER_FRAME_KINDS = {"rotation-only": "frames solved by rotation only",
                   "failed-frame": "frames failed (pose kept from the previous frame)",
                   "scale-fallback": "frames with a fallback scale (constant speed)",
                   "backend-failed": "keyframes whose bundle adjustment failed (front-end poses kept)",
                   "backend-rejected": "keyframes whose bundle adjustment was rejected as implausible",
                   "depth-contradicted": "keyframes whose carried depth PnP trusted against many two-view steps "
                                         "in a row"}


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


class OverruleWatch:
    """Notices a keyframe whose carried depth keeps contradicting the two-view geometry.

    A two-view step whose length PnP on the keyframe's depth contradicts (the
    ``scale.pnp_check_ratio`` guard, or ``scale.pnp_check_ratio_low`` under
    ``scale.pnp_check_low_parallax_px`` of parallax) is replaced by the PnP pose: a
    frame of branch ``pnp`` with a ``pnp_ratio``. A few in a row are routine on short
    indoor baselines; many in a row mean the depth itself has probably gone wrong
    (seen: 34 frames at 2-19 px of parallax, PnP saying 0.03-0.3x the two-view
    length, after which the scale collapsed), and every pose solved from it is
    suspect. Only an overrule beyond ``ratio`` (the guard's limit for every step)
    counts towards the streak: inside it, a low-parallax step's own scale is the
    doubtful one, so such an overrule says nothing against the depth and neither
    counts nor ends the streak. Counting those too, a streak of 10 came in 3 of the 66
    runs of the robustness table with the default settings, runs that ended at 2.06,
    0.60 and 0.70 % ATE; counting only the gross ones, in 1 (the last)
    (``benchmarks/ROBUSTNESS.md``, 2026-12-05). ``update`` returns a warning once per
    keyframe when its streak reaches ``min_streak``.

    Args:
        min_streak: overrules in a row against one keyframe that make a warning (>= 1).
        ratio: the factor (> 1) an overrule's PnP / two-view ratio must pass to count;
            0 = every overrule counts.
    """

    def __init__(self, min_streak: int = 10, ratio: float = 1.5):
        if min_streak < 1:
            raise ValueError(f"min_streak must be >= 1, got {min_streak}")
        if not (ratio == 0 or ratio > 1):
            raise ValueError(f"ratio must be 0 or > 1, got {ratio}")
        self.min_streak = int(min_streak)
        self._log_ratio = math.log(ratio) if ratio > 0 else 0.0
        self._ref: int | None = None
        self._first: int | None = None
        self._ratios: list[float] = []

    def update(self, result) -> str | None:
        """Feed one :class:`~trianflow_vo.frame.FrameResult`; the warning text when a streak reaches the limit."""
        ratio = result.stats.pnp_ratio
        overruled = result.branch is Branch.PNP and ratio is not None and abs(math.log(ratio)) > self._log_ratio
        if result.branch is Branch.TWO_VIEW or result.ref_index != self._ref:
            self._ref, self._first, self._ratios = result.ref_index, None, []
        if not overruled:
            return None
        if self._first is None:
            self._first = result.frame_index
        self._ratios.append(float(ratio))
        if len(self._ratios) != self.min_streak:  # once per streak; a streak belongs to one keyframe
            return None
        return (f"frames {self._first}-{result.frame_index}: PnP on keyframe {self._ref}'s depth overruled "
                f"{len(self._ratios)} two-view steps in a row (PnP / two-view step length "
                f"{min(self._ratios):.2f}-{max(self._ratios):.2f}x); the keyframe's carried depth has probably "
                "gone wrong and the poses solved from it are suspect")

