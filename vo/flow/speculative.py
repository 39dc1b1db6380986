"""Flow computed ahead: the next frame's flow in a background thread (``flow.ahead``).

While the current frame's geometry is solved (NumPy and OpenCV on the main
thread), the flow the *next* frame will most likely need is computed in a thread
with its own flow source: OpenCV releases the interpreter lock while DIS runs, so
the two overlap. Which pair to compute is a guess made before the current frame is
solved (:class:`~trianflow_vo.odometry.Odometry` guesses that the current frame
ends like the previous one: becomes the keyframe, or keeps it). When the next frame
asks for exactly that pair (the same prepared arrays, by identity) it gets the
result; otherwise the guess is thrown away and the pair is computed as usual. The
flow is the same either way: a separate source of the same settings, on the same
inputs (``describe()`` counts hits and misses).
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np

from trianflow_vo.flow.base import FlowSource


class _Guess:
    """One pair computed in a background thread."""

    def __init__(self, source: FlowSource, a: Any, b: Any):
        self.a, self.b = a, b
        self.result: tuple[np.ndarray, np.ndarray] | None = None  # None: failed, the main thread tries itself
        self._thread = threading.Thread(target=self._run, args=(source,), name="flow-ahead", daemon=True)
        self._thread.start()

    def _run(self, source: FlowSource) -> None:
        try:
            self.result = source.flow_pair(self.a, self.b)
        except BaseException:  # the main thread computes the pair itself and meets the error there
            pass

    def join(self) -> None:
        self._thread.join()


class SpeculativeFlow:
    """A :class:`~trianflow_vo.flow.base.FlowSource` that can compute one pair ahead.

    Args:
        source: the flow source the frames ask.
        spare: a second source with the same settings, for the background thread (a DIS
            object must not be used by two threads at once).
    """

    def __init__(self, source: FlowSource, spare: FlowSource):
        self.source = source
        self.spare = spare
        self.name = source.name
        self._guess: _Guess | None = None
        self.hits = 0
        self.misses = 0

    def prepare(self, image: np.ndarray) -> Any:
        return self.source.prepare(image)

    def speculate(self, a: Any, b: Any) -> None:
        """Start computing ``flow_pair(a, b)`` in the background (after any guess still running)."""
        self._settle()
        self._guess = _Guess(self.spare, a, b)

    def flow_pair(self, a: Any, b: Any) -> tuple[np.ndarray, np.ndarray]:
        guess, self._guess = self._guess, None
        if guess is not None:
            guess.join()
            if guess.a is a and guess.b is b and guess.result is not None:
                self.hits += 1
                return guess.result
            self.misses += 1
        return self.source.flow_pair(a, b)

    def close(self) -> None:
        """Wait for a guess still running (nothing is left behind)."""
        self._settle()

    def _settle(self) -> None:
        guess, self._guess = self._guess, None
        if guess is not None:
            guess.join()
            self.misses += 1

    def describe(self) -> dict:
        return {**self.source.describe(), "computed_ahead": {"hits": self.hits, "misses": self.misses}}
