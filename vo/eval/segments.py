"""KITTI odometry segment metric (t_err %, r_err deg/100 m), as the KITTI devkit defines it.

For each first frame (every ``step`` frames) and each segment length L, the end frame is
the first frame whose cumulative ground-truth path length exceeds the first frame's by
more than L. The error of the segment is ``E = inv(inv(P_a) P_b) @ inv(G_a) G_b`` (P
predicted, G ground truth); its translation norm divided by L and its rotation angle
divided by L are averaged over all segments.

evo has no such metric (its RPE with a delta in metres pairs poses by distance along
either trajectory and does not divide by a nominal length), so it is implemented here;
the cumulative distances are evo's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from evo.core.geometry import accumulated_distances

DEFAULT_LENGTHS = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
DEFAULT_STEP = 10


@dataclass(frozen=True)
class SegmentErrors:
    """One row per evaluated segment.

    Attributes:
        first: ``(M,)`` int, position of the first frame (index into the kept frames).
        last: ``(M,)`` int, position of the end frame.
        length: ``(M,)`` segment length L (m).
        t_err: ``(M,)`` translation error / L (unitless; x100 for %).
        r_err: ``(M,)`` rotation angle / L (rad/m; x 180/pi x 100 for deg/100 m).
    """

    first: np.ndarray
    last: np.ndarray
    length: np.ndarray
    t_err: np.ndarray
    r_err: np.ndarray

    def __len__(self) -> int:
        return int(self.first.shape[0])


def path_distances(positions: np.ndarray) -> np.ndarray:
    """``(N,)`` cumulative path length along ``(N, 3)`` positions (0 at the first): evo's
    ``accumulated_distances`` (what ``PosePath3D.distances`` gives)."""
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"positions must be (N, 3), got {p.shape}")
    return np.asarray(accumulated_distances(p), dtype=np.float64)


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Angle (rad) of ``(..., 3, 3)`` rotations, from the trace, clipped to ``[0, pi]``.

    This is the KITTI devkit's ``acos((trace - 1) / 2)`` on purpose: the ground-truth and
    predicted rotations read from files are not exactly orthonormal, and an
    ``atan2``-based angle changes the published r_err in the 5th digit. Its price is a
    ~1e-8 rad floor near zero (a perfect prediction gives r_err ~1e-6 deg/100 m).
    """
    R = np.asarray(R, dtype=np.float64)
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    return np.arccos(np.clip(c, -1.0, 1.0))


def segment_errors(
    gt_poses: np.ndarray,
    pred_poses: np.ndarray,
    lengths=DEFAULT_LENGTHS,
    step: int = DEFAULT_STEP,
) -> SegmentErrors:
    """Errors of every (first frame, length) segment whose end frame exists.

    Args:
        gt_poses: ``(N, 4, 4)`` ground-truth camera-to-world poses of the kept frames.
        pred_poses: ``(N, 4, 4)`` predicted poses of the same frames (aligned).
        lengths: positive segment lengths in metres.
        step: first frames are positions ``0, step, 2 step, ...``.

    Returns:
        :class:`SegmentErrors`, rows ordered by first frame then by length.
    """
    G = np.asarray(gt_poses, dtype=np.float64)
    P = np.asarray(pred_poses, dtype=np.float64)
    if G.ndim != 3 or G.shape[1:] != (4, 4) or P.shape != G.shape:
        raise ValueError(f"gt_poses and pred_poses must both be (N, 4, 4), got {G.shape} and {P.shape}")
    lengths = np.asarray(list(lengths), dtype=np.float64)
    if lengths.ndim != 1 or lengths.size == 0 or np.any(~np.isfinite(lengths)) or np.any(lengths <= 0):
        raise ValueError(f"lengths must be positive numbers, got {lengths}")
    if step < 1:
        raise ValueError(f"step must be >= 1, got {step}")
    dist = path_distances(G[:, :3, 3])
    n = G.shape[0]
    firsts = np.arange(0, n, step)
    a = np.repeat(firsts, lengths.size)
    L = np.tile(lengths, firsts.size)
    # first position whose distance is strictly greater than dist[a] + L
    b = np.searchsorted(dist, dist[a] + L, side="right")
    keep = b < n
    a, b, L = a[keep], b[keep], L[keep]
    G_inv = np.linalg.inv(G)
    P_inv = np.linalg.inv(P)
    delta_gt = G_inv[a] @ G[b]
    delta_pred = P_inv[a] @ P[b]
    E = np.linalg.inv(delta_pred) @ delta_gt
    t = np.linalg.norm(E[:, :3, 3], axis=1)
    r = rotation_angle(E[:, :3, :3])
    return SegmentErrors(a.astype(np.int64), b.astype(np.int64), L, t / L, r / L)


def summarize_segments(seg: SegmentErrors, lengths=DEFAULT_LENGTHS) -> dict:
    """Averages in the published units.

    Returns:
        ``{"t_err": % or None, "r_err": deg/100 m or None, "num_segments": M,
        "per_length": [{"length", "t_err", "r_err", "num_segments"}, ...]}``; the
        averages are None when there is no segment (never NaN).
    """
    to_pct = 100.0
    to_deg100 = 180.0 / np.pi * 100.0

    def mean_or_none(x: np.ndarray, factor: float):
        return float(np.mean(x) * factor) if x.size else None

    per_length = []
    for length in lengths:
        m = seg.length == float(length)
        per_length.append(
            {
                "length": float(length),
                "t_err": mean_or_none(seg.t_err[m], to_pct),
                "r_err": mean_or_none(seg.r_err[m], to_deg100),
                "num_segments": int(m.sum()),
            }
        )
    return {
        "t_err": mean_or_none(seg.t_err, to_pct),
        "r_err": mean_or_none(seg.r_err, to_deg100),
        "num_segments": len(seg),
        "per_length": per_length,
    }
