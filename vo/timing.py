"""Per-stage wall-clock timing of one frame."""

from __future__ import annotations

import time
from dataclasses import dataclass, field


@dataclass
class StageTimer:
    """Accumulates milliseconds per named stage: ``t0 = timer.add("flow", t0)``."""

    ms: dict = field(default_factory=dict)

    def add(self, name: str, t0: float) -> float:
        t1 = time.perf_counter()
        self.ms[name] = self.ms.get(name, 0.0) + (t1 - t0) * 1000.0
        return t1
