"""Per-stage wall-clock timing of one frame."""

from __future__ import annotations

import time
from dataclasses import dataclass, field


@dataclass
class StageTimer:
    """Accumulates milliseconds per named stage: ``t0 = timer.add("flow", t0)``.

    ``t_start`` is when the frame began (by default, when the timer was made); the
    pipeline starts it when the previous frame ended, so :meth:`elapsed_ms` is the
    wall time per frame with decoding included.
    """

    ms: dict = field(default_factory=dict)
    t_start: float = field(default_factory=time.perf_counter)

    def add(self, name: str, t0: float) -> float:
        t1 = time.perf_counter()
        self.ms[name] = self.ms.get(name, 0.0) + (t1 - t0) * 1000.0
        return t1

    def elapsed_ms(self) -> float:
        return (time.perf_counter() - self.t_start) * 1000.0
