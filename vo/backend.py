"""The back-end seam: a pose graph of keyframes that may revise earlier poses.

The front-end solves each frame against its reference keyframe. A back-end sees
every new keyframe (its pose and its :class:`~trianflow_vo.keyframe.Tracks`) and
may answer with a :class:`PoseRevision`: new poses for some keyframes. The
pipeline then re-anchors every frame solved from a revised keyframe
(:class:`Trajectory`), tells the odometry (so chaining continues from the
revised pose) and the observers (``on_poses_revised``); the writers rewrite
``poses.txt`` with the final poses at the end.

The default back-end, :class:`NoBackend`, does nothing: the trajectory is the
front-end's frame-to-keyframe chain, as in the paper. To add one, implement
:class:`Backend` and register it in :func:`make_backend` (and in the choices of
``backend.kind`` in :mod:`trianflow_vo.config`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Mapping, Protocol

import numpy as np

from trianflow_vo.config import BackendConfig
from trianflow_vo.frame import FrameResult
from trianflow_vo.keyframe import Keyframe


@dataclass(frozen=True)
class DepthCorrection:
    """A keyframe's carried depth ``d`` becomes ``1 / (a / d + b)``: an affine map of inverse
    depth (``b = 0``: a rescale by ``1 / a``), fitted by the back-end to its adjusted points
    (:func:`~trianflow_vo.geometry.scale.fit_inverse_depth_affine`)."""

    a: float
    b: float = 0.0

    def __post_init__(self):
        if not (np.isfinite(self.a) and self.a > 0 and np.isfinite(self.b)):
            raise ValueError(f"a depth correction needs a finite a > 0 and a finite b, got a={self.a}, b={self.b}")
        object.__setattr__(self, "a", float(self.a))
        object.__setattr__(self, "b", float(self.b))

    def apply(self, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(corrected (N,), valid (N,))`` for depths ``(N,)`` > 0; not valid where the
        corrected inverse depth is not positive (the corrected value is then meaningless)."""
        depth = np.asarray(depth, dtype=np.float64)
        inv = self.a / depth + self.b
        valid = np.isfinite(inv) & (inv > 0)
        return np.where(valid, 1.0 / np.where(valid, inv, 1.0), 0.0), valid

    def median_factor(self, depth: np.ndarray) -> float:
        """The median of corrected / original depth over ``depth`` ``(N,)`` (its valid entries; 1 when none)."""
        new, valid = self.apply(depth)
        return float(np.median(new[valid] / np.asarray(depth, dtype=np.float64)[valid])) if valid.any() else 1.0

    def factors(self, depth: np.ndarray) -> np.ndarray:
        """Corrected / original depth ``(3,)`` at the 2nd, 50th and 98th percentile of ``depth``
        ``(N,)`` (N >= 1, > 0); inf where that depth would end (corrected inverse depth <= 0).
        The map is monotonic in depth, so the outer two bound it over that range."""
        d = np.percentile(np.asarray(depth, dtype=np.float64), [2, 50, 98])
        shrink = self.a + self.b * d  # original / corrected depth
        return np.where(shrink > 0, 1.0 / np.where(shrink > 0, shrink, 1.0), np.inf)

    def spread(self, depth: np.ndarray) -> float:
        """How unlike a rescale it is over ``depth`` ``(N,)``: the ratio of the largest to the
        smallest of :meth:`factors` (1 for a rescale; inf when a depth would end)."""
        f = self.factors(depth)
        return float(f.max() / f.min()) if np.all(np.isfinite(f)) else float("inf")

    def largest_change(self, depth: np.ndarray) -> float:
        """The largest ``|log(corrected / original)|`` of :meth:`factors` (inf when a depth would end)."""
        return float(np.max(np.abs(np.log(self.factors(depth)))))


@dataclass(frozen=True)
class PoseRevision:
    """New camera-to-world poses of some keyframes.

    Attributes:
        T_world_cam: keyframe source index -> ``(4, 4)`` revised pose.
        reason: one short sentence (e.g. "window bundle adjustment, 5 keyframes").
        ms: time the back-end spent on it.
        depth_correction: keyframe source index -> :class:`DepthCorrection` of the depth
            that keyframe carries, so that the frames solved from it next are scaled like
            the revised poses and points (the odometry applies it to its current keyframe's
            tracks). A revision may carry only a correction (no poses).
    """

    T_world_cam: Mapping[int, np.ndarray]
    reason: str = ""
    ms: float = 0.0
    depth_correction: Mapping[int, "DepthCorrection"] = field(default_factory=dict)

    def __post_init__(self):
        corrections = {}
        for k, c in dict(self.depth_correction).items():
            if not isinstance(c, DepthCorrection):
                raise ValueError(f"depth correction of keyframe {k} must be a DepthCorrection, got {c!r}")
            corrections[int(k)] = c
        object.__setattr__(self, "depth_correction", MappingProxyType(corrections))
        poses = {}
        for k, T in dict(self.T_world_cam).items():
            T = np.array(T, dtype=np.float64)
            if T.shape != (4, 4):
                raise ValueError(f"revised pose of keyframe {k} must be (4, 4), got {T.shape}")
            T.flags.writeable = False
            poses[int(k)] = T
        object.__setattr__(self, "T_world_cam", MappingProxyType(poses))


class Backend(Protocol):
    """What the pipeline asks of a back-end."""

    name: str

    def add_keyframe(self, keyframe: Keyframe, result: FrameResult) -> PoseRevision | None:
        """A new keyframe (``result`` is the frame that became it). Return revised poses, or None."""
        ...

    def finish(self) -> PoseRevision | None:
        """End of the sequence: a last revision, or None."""
        ...

    def describe(self) -> dict:
        ...

    def close(self) -> None:
        """Release what it holds (a worker process); called once at the end of every run, also a failed
        one. Optional: the pipeline skips a back-end without it."""
        ...


class NoBackend:
    """The default back-end: keeps the front-end's poses as they are."""

    name = "none"

    def add_keyframe(self, keyframe: Keyframe, result: FrameResult) -> PoseRevision | None:
        return None

    def finish(self) -> PoseRevision | None:
        return None

    def describe(self) -> dict:
        return {"name": self.name}

    def close(self) -> None:
        pass


def make_backend(config: BackendConfig, K: np.ndarray | None = None, size_hw: tuple[int, int] | None = None,
                 warn=None, blas_threads: int | None = None) -> Backend:
    """The back-end the ``backend`` section names: :class:`NoBackend` for ``kind: none`` or
    ``window: 0``, else the windowed bundle adjustment
    (:class:`~trianflow_vo.ba.backend.WindowBackend`, needs the working ``K`` and ``size_hw``;
    ``warn(kind, message)`` receives its failures; ``blas_threads``: NumPy's BLAS threads in its
    worker process, None = the library's own default)."""
    if config.kind == "none" or config.window == 0:
        return NoBackend()
    if config.kind == "window-ba":
        if K is None or size_hw is None:
            raise ValueError("the window-ba back-end needs the working intrinsics K and size")
        from trianflow_vo.ba.backend import WindowBackend

        return WindowBackend(config, K, size_hw, warn=warn, blas_threads=blas_threads)
    raise ValueError(f"unknown back-end {config.kind!r}; choose from: none, window-ba")


@dataclass(frozen=True)
class RevisedPoses:
    """What observers are told after a revision: the frames whose poses changed.

    Attributes:
        lines: ``(K,)`` output lines (positions in ``poses.txt``).
        frame_indices: ``(K,)`` source frame indices.
        T_world_cam: ``(K, 4, 4)`` their new camera-to-world poses.
        revision: 1 for the first revision of the run, 2 for the next, ...
        reason: the back-end's reason.
    """

    lines: np.ndarray
    frame_indices: np.ndarray
    T_world_cam: np.ndarray
    revision: int
    reason: str = ""


@dataclass
class _Entry:
    frame_index: int
    ref_index: int | None
    is_keyframe: bool
    T_ref_cam: np.ndarray
    T_world_cam: np.ndarray


@dataclass
class Trajectory:
    """Every processed frame's current pose, kept attached to its reference keyframe.

    A frame solved from keyframe ``k`` keeps ``T_ref_cam``; when ``k`` is revised
    the frame moves with it: ``T_world_cam = T_world_k @ T_ref_cam``. Keyframes in
    a revision take the revised pose. Small: two 4x4 matrices a frame.
    """

    entries: list[_Entry] = field(default_factory=list)
    revisions: int = 0
    _line_of_keyframe: dict[int, int] = field(default_factory=dict)

    def add(self, result: FrameResult) -> None:
        self.entries.append(_Entry(result.frame_index, result.ref_index, result.is_keyframe,
                                   np.array(result.T_ref_cam), np.array(result.T_world_cam)))
        if result.is_keyframe:
            self._line_of_keyframe[result.frame_index] = len(self.entries) - 1

    def poses(self) -> np.ndarray:
        """``(N, 4, 4)`` current poses, in line order."""
        return np.stack([e.T_world_cam for e in self.entries]) if self.entries else np.zeros((0, 4, 4))

    def frame_indices(self) -> np.ndarray:
        return np.array([e.frame_index for e in self.entries], dtype=np.int64)

    def revise(self, revision: PoseRevision) -> RevisedPoses:
        """Apply ``revision``; returns the frames that moved."""
        new = revision.T_world_cam
        unknown = [k for k in new if k not in self._line_of_keyframe]
        if unknown:
            raise ValueError(f"revision of frames that are not keyframes: {unknown}")
        changed = []
        for line, e in enumerate(self.entries):
            if e.is_keyframe and e.frame_index in new:
                e.T_world_cam = np.array(new[e.frame_index])
                changed.append(line)
            elif not e.is_keyframe and e.ref_index in new:
                e.T_world_cam = new[e.ref_index] @ e.T_ref_cam
                changed.append(line)
        self.revisions += 1
        lines = np.asarray(changed, dtype=np.int64)
        return RevisedPoses(lines, np.array([self.entries[i].frame_index for i in changed], dtype=np.int64),
                            np.stack([self.entries[i].T_world_cam for i in changed]) if changed
                            else np.zeros((0, 4, 4)), self.revisions, revision.reason)
