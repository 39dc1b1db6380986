"""KITTI odometry segment metric (t_err %, r_err deg/100 m), as the KITTI devkit defines it.

For each first frame (every ``step`` frames) and each segment length L, the end frame is
the first frame whose cumulative ground-truth path length exceeds the first frame's by
more than L. The error of the segment is ``E = inv(inv(P_a) P_b) @ inv(G_a) G_b`` (P
predicted, G ground truth); its translation norm divided by L and its rotation angle
divided by L are averaged over all segments.

Two rules choose the segments (``protocol``):

- ``"kept-frames"`` (default): distances along the ground truth of the kept (common)
  frames, first frames every ``step`` kept frames (:func:`segment_errors`);
- ``"kitti-odom-eval"``: the rule of the common kitti-odom-eval script: distances along
  *every* ground-truth frame, first frames the ground-truth frames at positions 0,
  ``step``, ``2 step``, ... (frames 0, 10, 20, ... of a KITTI file), end frames found on
  the whole ground truth, and a segment dropped when its first or end frame has no
  prediction (:func:`segment_errors_all_gt`).

Both are the same when every ground-truth frame is predicted (the published numbers).

The rotations are used as read (not orthonormalised) here, on purpose: see
:func:`rotation_angle` and :func:`nearest_rotation`.

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
PROTOCOLS = ("kept-frames", "kitti-odom-eval")


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


def nearest_rotation(T: np.ndarray) -> np.ndarray:
    """A copy of ``(N, 4, 4)`` poses (or ``(N, 3, 3)`` matrices) with each rotation replaced by
    the nearest proper rotation in the Frobenius norm (SVD: ``U diag(1, 1, det(U V^T)) V^T``).

    Rotations read from files are orthonormal to ~1e-7 only (KITTI prints 6-7 digits); the
    trace of a product of such matrices is off by as much, and ``acos((trace - 1) / 2)``
    turns that into an angle error of ~1e-7 / sin(angle): large for the small angles of
    consecutive frames (RPE). Translations are left unchanged.
    """
    A = np.array(T, dtype=np.float64)
    R = A[..., :3, :3]
    U, _, Vt = np.linalg.svd(R)
    d = np.sign(np.linalg.det(U @ Vt))
    U[..., :, 2] *= d[..., None]
    A[..., :3, :3] = U @ Vt
    return A


def _check_segment_args(lengths, step: int) -> np.ndarray:
    lengths = np.asarray(list(lengths), dtype=np.float64)
    if lengths.ndim != 1 or lengths.size == 0 or np.any(~np.isfinite(lengths)) or np.any(lengths <= 0):
        raise ValueError(f"lengths must be positive numbers, got {lengths}")
    if step < 1:
        raise ValueError(f"step must be >= 1, got {step}")
    return lengths


def _errors(G_a, G_b, P_a, P_b, L) -> tuple[np.ndarray, np.ndarray]:
    """Per segment ``|t(E)| / L`` and ``angle(E) / L`` of ``E = inv(inv(P_a) P_b) inv(G_a) G_b``."""
    delta_gt = np.linalg.inv(G_a) @ G_b
    delta_pred = np.linalg.inv(P_a) @ P_b
    E = np.linalg.inv(delta_pred) @ delta_gt
    return np.linalg.norm(E[:, :3, 3], axis=1) / L, rotation_angle(E[:, :3, :3]) / L


def segment_errors(
    gt_poses: np.ndarray,
    pred_poses: np.ndarray,
    lengths=DEFAULT_LENGTHS,
    step: int = DEFAULT_STEP,
    orthonormalize: bool = False,
) -> SegmentErrors:
    """Errors of every (first frame, length) segment whose end frame exists.

    Args:
        gt_poses: ``(N, 4, 4)`` ground-truth camera-to-world poses of the kept frames.
        pred_poses: ``(N, 4, 4)`` predicted poses of the same frames (aligned).
        lengths: positive segment lengths in metres.
        step: first frames are positions ``0, step, 2 step, ...``.
        orthonormalize: replace every rotation by its nearest rotation first
            (:func:`nearest_rotation`). Off by default: on KITTI 09 it moves the
            published r_err 0.287707222 to 0.287702744 and t_err 2.527535077 to
            2.527535279 (the devkit's numbers are defined on the rotations as read).

    Returns:
        :class:`SegmentErrors`, rows ordered by first frame then by length.
    """
    G = np.asarray(gt_poses, dtype=np.float64)
    P = np.asarray(pred_poses, dtype=np.float64)
    if G.ndim != 3 or G.shape[1:] != (4, 4) or P.shape != G.shape:
        raise ValueError(f"gt_poses and pred_poses must both be (N, 4, 4), got {G.shape} and {P.shape}")
    lengths = _check_segment_args(lengths, step)
    if orthonormalize:
        G, P = nearest_rotation(G), nearest_rotation(P)
    dist = path_distances(G[:, :3, 3])
    n = G.shape[0]
    firsts = np.arange(0, n, step)
    a = np.repeat(firsts, lengths.size)
    L = np.tile(lengths, firsts.size)
    # first position whose distance is strictly greater than dist[a] + L
    b = np.searchsorted(dist, dist[a] + L, side="right")
    keep = b < n
    a, b, L = a[keep], b[keep], L[keep]
    t, r = _errors(G[a], G[b], P[a], P[b], L)
    return SegmentErrors(a.astype(np.int64), b.astype(np.int64), L, t, r)


def segment_errors_all_gt(
    gt_all: np.ndarray,
    pred_poses: np.ndarray,
    pred_gt_pos: np.ndarray,
    lengths=DEFAULT_LENGTHS,
    step: int = DEFAULT_STEP,
) -> SegmentErrors:
    """The segments of the kitti-odom-eval rule (``--protocol kitti-odom-eval``).

    Cumulative distances along all M ground-truth poses; first frames the ground-truth
    positions ``0, step, 2 step, ...``; for each length L the end frame is the first
    ground-truth position whose distance exceeds the first one's by more than L; the
    segment is kept only when both its first and end frames are predicted (no other
    frame is tried instead). Then the same error as :func:`segment_errors`.

    This follows kitti-odom-eval's ``calc_sequence_errors`` except one of its quirks: it
    re-bases only the predicted ground-truth frames, so its distances across a missing
    frame mix two world frames when the first predicted ground-truth pose is not the
    identity; here the ground truth stays in one frame (the same numbers when the
    prediction starts at a KITTI file's frame 0, whose pose is the identity).

    Args:
        gt_all: ``(M, 4, 4)`` every ground-truth pose, in frame order.
        pred_poses: ``(K, 4, 4)`` predicted poses of the K common frames (aligned; any
            world frame: only their relative motion is used).
        pred_gt_pos: ``(K,)`` increasing positions in ``gt_all`` of those K frames.
        lengths, step: as :func:`segment_errors`.

    Returns:
        :class:`SegmentErrors` whose ``first``/``last`` are positions in the K common
        frames, like :func:`segment_errors`.
    """
    G = np.asarray(gt_all, dtype=np.float64)
    P = np.asarray(pred_poses, dtype=np.float64)
    pos = np.asarray(pred_gt_pos, dtype=np.int64)
    if G.ndim != 3 or G.shape[1:] != (4, 4) or P.ndim != 3 or P.shape[1:] != (4, 4):
        raise ValueError(f"gt_all and pred_poses must be (M, 4, 4) and (K, 4, 4), got {G.shape} and {P.shape}")
    if pos.shape != (P.shape[0],) or (pos.size and (pos.min() < 0 or pos.max() >= G.shape[0])) \
            or np.any(np.diff(pos) <= 0):
        raise ValueError("pred_gt_pos must be (K,) increasing positions into gt_all")
    lengths = _check_segment_args(lengths, step)
    dist = path_distances(G[:, :3, 3])
    m = G.shape[0]
    firsts = np.arange(0, m, step)
    a = np.repeat(firsts, lengths.size)
    L = np.tile(lengths, firsts.size)
    b = np.searchsorted(dist, dist[a] + L, side="right")
    keep = b < m
    a, b, L = a[keep], b[keep], L[keep]
    k_of = np.full(m, -1, dtype=np.int64)  # ground-truth position -> position among the common frames
    k_of[pos] = np.arange(pos.size)
    keep = (k_of[a] >= 0) & (k_of[b] >= 0)
    a, b, L = a[keep], b[keep], L[keep]
    ka, kb = k_of[a], k_of[b]
    t, r = _errors(G[a], G[b], P[ka], P[kb], L)
    return SegmentErrors(ka, kb, L, t, r)


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
