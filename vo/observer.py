"""Observers: what the pipeline tells the writers, the progress bar and the viewers.

An observer implements some of the hooks of :class:`Observer`; subclassing it
gives the others as no-ops. The pipeline calls, in order:

1. ``on_start(n_frames)`` once, with the number of frames selected;
2. ``on_frame(result)`` for every processed frame (a :class:`~trianflow_vo.frame.FrameResult`);
3. ``on_poses_revised(revised)`` whenever a back-end moved earlier poses
   (a :class:`~trianflow_vo.backend.RevisedPoses`);
4. ``close(interrupted)`` once at the end, also after an error or Ctrl-C
   (``interrupted=True`` then).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol, runtime_checkable

if TYPE_CHECKING:
    from trianflow_vo.backend import RevisedPoses
    from trianflow_vo.frame import FrameResult


@runtime_checkable
class Observer(Protocol):
    """Receives the run as it goes. Every hook defaults to doing nothing."""

    def on_start(self, n_frames: int) -> None:
        """Called once, before the first frame, with the number of frames selected."""

    def on_frame(self, result: FrameResult) -> None:
        """Called for every processed frame, in order."""

    def on_poses_revised(self, revised: RevisedPoses) -> None:
        """Called when a back-end revised the poses of earlier frames."""

    def close(self, interrupted: bool = False) -> None:
        """Called once at the end (``interrupted``: Ctrl-C or an error)."""
