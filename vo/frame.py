"""The per-frame contract: what the odometry says about each processed frame.

:class:`FrameResult` is built once, when a frame is done, and never changed. The
writers (``poses.txt``, ``frames.tsv``, ``run.json``), the progress bar, the Rerun
recording and the plot all read it. A back-end that later revises poses says so
with a :class:`PoseRevision` (see :mod:`trianflow_vo.backend`), not by editing results.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field, fields
from types import MappingProxyType
from typing import Mapping

import numpy as np


class Branch(str, enum.Enum):
    """How a frame's pose was obtained.

    The value is the word written to ``frames.tsv`` and ``run.json``.
    """

    INIT = "init"  # first frame: identity
    TWO_VIEW = "two-view"  # relative pose from the flow matches, scale from the reference depth
    PNP = "pnp"  # PnP against the reference keyframe's depth
    ROTATION = "rotation"  # rotation only (parallax too small and no depth yet, or PnP failed)
    IDENTITY = "identity"  # the camera did not move: the reference keyframe's pose
    FAILED = "failed"  # nothing usable: the previous frame's pose is kept

    def __str__(self) -> str:  # "two-view", not "Branch.TWO_VIEW"
        return self.value

    @property
    def is_routine(self) -> bool:
        """True for the branches of normal operation (logged as information, not warnings)."""
        return self in (Branch.INIT, Branch.TWO_VIEW, Branch.IDENTITY, Branch.PNP)


def _frozen_copy(a: np.ndarray | None, dtype=None) -> np.ndarray | None:
    if a is None:
        return None
    out = np.array(a, dtype=dtype, copy=True)
    out.flags.writeable = False
    return out


def _read_only(a: np.ndarray | None) -> np.ndarray | None:
    """A read-only view of ``a`` (no copy: the producer hands the array over)."""
    if a is None:
        return None
    out = np.asarray(a).view()
    out.flags.writeable = False
    return out


@dataclass(frozen=True)
class FrameStats:
    """Typed per-frame statistics. ``None`` = not measured for this frame's branch.

    Attributes:
        inliers: matches consistent with the pose (two-view: Sampson < epi_inlier_px;
            PnP: RANSAC inliers).
        inlier_ratio: ``inliers`` / matches (two-view), or / points with depth (PnP).
        parallax_px: median parallax after removing the best rotation (pixels).
        mean_flow_px: mean flow magnitude of the sampled matches (pixels).
        scale: length of the step from the reference keyframe, in trajectory units.
        scale_points: points that had a reference depth for the scale fit.
        pnp_ratio: PnP step length / two-view step length (the PnP cross-check).
        tracks: number of tracks (sparse baseline) or tracked points handed on.
        degraded: the pose was obtained by a fallback (e.g. constant speed).
        ms: milliseconds per stage (read-only mapping).
        frame_ms: wall time of the whole frame, decoding included.
    """

    inliers: int | None = None
    inlier_ratio: float | None = None
    parallax_px: float | None = None
    mean_flow_px: float | None = None
    scale: float | None = None
    scale_points: int | None = None
    pnp_ratio: float | None = None
    tracks: int | None = None
    degraded: bool = False
    ms: Mapping[str, float] = field(default_factory=lambda: MappingProxyType({}))
    frame_ms: float | None = None

    def __post_init__(self):
        if not isinstance(self.ms, MappingProxyType):
            object.__setattr__(self, "ms", MappingProxyType(dict(self.ms)))

    def scalars(self) -> dict:
        """The measured statistics as ``{name: number}`` (``ms`` as a nested dict), None left out."""
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "ms":
                out["ms"] = dict(v)
            elif v is not None:
                out[f.name] = v
        return out


@dataclass(frozen=True)
class FrameView:
    """What a viewer may draw of one frame (all arrays read-only; any may be None).

    Attributes:
        image: ``(h, w, 3)`` uint8 BGR at working resolution.
        depth: ``(h, w)`` float32 depth of the reference keyframe used for scale/PnP (0 = unknown).
        flow: ``(h, w, 2)`` float32 forward flow reference -> this frame (pixels).
        flow_bw: ``(h, w, 2)`` float32 backward flow this frame -> reference (pixels).
        pts_ref, pts_cur: ``(N, 2)`` matches used for triangulation or PnP (reference, this frame).
        points_world: ``(M, 3)`` triangulated points in world coordinates.
        point_colors: ``(M, 3)`` uint8 RGB colours of those points.
    """

    image: np.ndarray | None = None
    depth: np.ndarray | None = None
    flow: np.ndarray | None = None
    flow_bw: np.ndarray | None = None
    pts_ref: np.ndarray | None = None
    pts_cur: np.ndarray | None = None
    points_world: np.ndarray | None = None
    point_colors: np.ndarray | None = None

    @classmethod
    def of(cls, **arrays) -> FrameView:
        """A view holding read-only views of the given arrays (not copies: the
        producer must not change them afterwards)."""
        return cls(**{k: _read_only(v) for k, v in arrays.items()})


@dataclass(frozen=True)
class FrameResult:
    """The outcome of one processed frame.

    Attributes:
        line: 0-based output line (position in ``poses.txt``).
        frame_index: source frame index (as in ``frames.txt``).
        timestamp: seconds, or None.
        T_world_cam: ``(4, 4)`` camera-to-world pose (read-only), as first estimated.
        branch: a :class:`Branch`.
        reason: why that branch was taken (one short sentence; empty for a plain two-view step).
        ref_index: source index of the reference keyframe the pose was solved from
            (None for the first frame).
        T_ref_cam: ``(4, 4)`` pose of this frame in its reference keyframe (read-only):
            what keeps the frame attached to its keyframe when a back-end moves it.
        is_keyframe: this frame became the new reference keyframe.
        K: ``(3, 3)`` intrinsics at working resolution.
        stats: :class:`FrameStats`.
        view: :class:`FrameView`, or None when nothing is kept for viewers.
    """

    line: int
    frame_index: int
    timestamp: float | None
    T_world_cam: np.ndarray
    branch: Branch
    reason: str
    ref_index: int | None
    T_ref_cam: np.ndarray
    is_keyframe: bool
    K: np.ndarray
    stats: FrameStats
    view: FrameView | None = None

    def __post_init__(self):
        if not isinstance(self.branch, Branch):
            object.__setattr__(self, "branch", Branch(self.branch))
        for name in ("T_world_cam", "T_ref_cam"):
            T = np.asarray(getattr(self, name), dtype=np.float64)
            if T.shape != (4, 4):
                raise ValueError(f"{name} must be (4, 4), got {T.shape}")
            object.__setattr__(self, name, _frozen_copy(T))
        object.__setattr__(self, "K", _frozen_copy(self.K, np.float64))

    @property
    def is_degraded(self) -> bool:
        """The pose came from a fallback, not from the normal two-view path."""
        return self.branch in (Branch.ROTATION, Branch.FAILED) or self.stats.degraded
