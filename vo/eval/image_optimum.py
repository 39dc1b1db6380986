"""The trajectory that best explains the images, and how far a reference is from it.

:mod:`~trianflow_vo.eval.consistency` scores each frame pair and triple on its own. This
module looks at the whole clip. It bundle-adjusts all frames at once with sparse SIFT
tracks (evidence that does not come from the pipeline's flow). Only the reprojection error
counts: there is no motion prior. The adjustment starts from a given trajectory, for
example the ground truth. Its result is the nearby trajectory that the images support best.

Starting from the ground truth answers one question: how far does it move? If the
ground truth explained the images to their noise, it would stay put. If it moves by
``d`` % of the path (ATE after a Sim(3) alignment), a run can be ranked against that
ground truth only at differences well above ``d``.

Pieces:

* :func:`link_tracks`: union-find of pairwise keypoint matches into tracks (a track with
  two keypoints in one frame is dropped);
* :func:`sift_tracks`: SIFT matches of each frame with the next ``overlap`` frames
  (:func:`sift_matches`, independent of any trajectory) that fit the trajectory's epipolar
  geometry (Sampson distance < ``epi_px``), linked (:func:`tracks_from_matches`);
* :func:`triangulate_tracks`: linear triangulation of each track from all its
  observations; observations that reproject worse than ``max_px`` are dropped;
* :func:`image_optimum`: ``rounds`` times triangulate, then Levenberg-Marquardt on all
  poses and points (Huber kernel, pixels). The gauge: the first pose is held, and so is
  the distance from the first camera centre to the one farthest from it (the scale). Rounds repeat until the gate keeps the same observations.

Poses are ``T_world_cam`` ``(4, 4)``; pixels ``(u, v)`` at the images' resolution, with ``K``
the intrinsics at that resolution (held fixed).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trianflow_vo.ba.graph import add_reprojection_factors, levenberg_marquardt, project
from trianflow_vo.eval.consistency import SiftMatcher, sampson_under_poses

HOLD_SIGMA = 1e-4  # the gauge's priors (radians; a fraction of the held distance): effectively constants


@dataclass(frozen=True)
class Observations:
    """Track observations, one row each.

    Attributes:
        frame: ``(M,)`` int64 position of the frame in the trajectory.
        track: ``(M,)`` int64 track id (``0 .. n_tracks - 1``).
        uv: ``(M, 2)`` float64 pixels.
    """

    frame: np.ndarray
    track: np.ndarray
    uv: np.ndarray

    @property
    def n_tracks(self) -> int:
        return int(self.track.max()) + 1 if self.track.size else 0

    def subset(self, keep: np.ndarray) -> "Observations":
        """The rows ``keep`` (bool ``(M,)``), track ids renumbered ``0 ..``."""
        track = self.track[keep]
        _, new = np.unique(track, return_inverse=True)
        return Observations(self.frame[keep], new.astype(np.int64).reshape(-1), self.uv[keep])


def link_tracks(n_keypoints: list[int], matches: list[tuple[int, int, np.ndarray, np.ndarray]]):
    """Tracks from pairwise matches.

    Args:
        n_keypoints: keypoints of each frame.
        matches: ``(frame_a, frame_b, ia (P,), ib (P,))``: keypoint ``ia[p]`` of ``frame_a`` is
            keypoint ``ib[p]`` of ``frame_b``.

    Returns:
        ``(frame (M,), keypoint (M,), track (M,))`` int64 arrays: every keypoint of a track with
        at least two frames and at most one keypoint per frame.
    """
    offset = np.concatenate([[0], np.cumsum(n_keypoints)]).astype(np.int64)
    parent = np.arange(int(offset[-1]), dtype=np.int64)

    def find(x: int) -> int:
        root = x
        while parent[root] != root:
            root = parent[root]
        while parent[x] != root:  # path compression
            parent[x], x = root, parent[x]
        return root

    for fa, fb, ia, ib in matches:
        for a, b in zip((offset[fa] + np.asarray(ia, dtype=np.int64)).tolist(),
                        (offset[fb] + np.asarray(ib, dtype=np.int64)).tolist()):
            ra, rb = find(a), find(b)
            if ra != rb:
                parent[ra] = rb
    roots = np.array([find(x) for x in range(parent.size)], dtype=np.int64)
    frame_of = np.repeat(np.arange(len(n_keypoints), dtype=np.int64), np.asarray(n_keypoints, dtype=np.int64))
    kp_of = np.arange(parent.size, dtype=np.int64) - offset[frame_of]
    _, inv, size = np.unique(roots, return_inverse=True, return_counts=True)
    # a track's frames must be distinct: count (root, frame) pairs
    pair = inv.astype(np.int64) * len(n_keypoints) + frame_of
    _, pinv, pcount = np.unique(pair, return_inverse=True, return_counts=True)
    dup = np.zeros(size.size, dtype=bool)
    dup[inv[pcount[pinv] > 1]] = True
    keep = (size[inv] >= 2) & ~dup[inv]
    _, track = np.unique(inv[keep], return_inverse=True)
    return frame_of[keep], kp_of[keep], track.astype(np.int64).reshape(-1)


@dataclass(frozen=True)
class SiftMatches:
    """Ratio-test SIFT matches of each frame with the next ``overlap`` frames, before any geometry.

    Attributes:
        pts: per frame, ``(K_i, 2)`` keypoint pixels.
        pairs: ``(a, b, ia (P,), ib (P,))``: keypoint ``ia[p]`` of frame ``a`` matches ``ib[p]`` of ``b``.
    """

    pts: list
    pairs: list


def sift_matches(read_gray, n_frames: int, overlap: int = 5, matcher=None) -> SiftMatches:
    """SIFT keypoints of ``n_frames`` frames and the matches of each with the next ``overlap``.

    Args:
        read_gray: ``read_gray(position) -> (h, w) uint8`` image of the frame at that position.
        overlap: each frame is matched with the next ``overlap`` frames.
        matcher: a :class:`~trianflow_vo.eval.consistency.SiftMatcher` (default: 4000 features, ratio 0.75).
            Descriptors are kept only for the frames still to be matched.
    """
    if overlap < 1:
        raise ValueError(f"overlap must be >= 1, got {overlap}")
    matcher = matcher or SiftMatcher(ratio=0.75)
    feats = (lambda i: matcher.features(i, lambda: read_gray(i)))  # noqa: E731
    pts, pairs = [], []
    for a in range(int(n_frames)):
        pa, da = feats(a)
        pts.append(pa)
        for b in range(a + 1, min(int(n_frames), a + overlap + 1)):
            ia, ib = matcher.match(da, feats(b)[1])
            if ia.size:
                pairs.append((a, b, ia, ib))
        matcher.forget(set(range(a + 1, a + overlap + 1)))
    return SiftMatches(pts, pairs)


def tracks_from_matches(K: np.ndarray, T_world_cam: np.ndarray, matches: SiftMatches,
                        epi_px: float = 1.5) -> Observations:
    """Tracks of the matches that fit the trajectory's epipolar geometry (Sampson distance below
    ``epi_px`` under each pair's relative pose), linked by :func:`link_tracks`.

    Args:
        K: ``(3, 3)`` intrinsics at the images' resolution.
        T_world_cam: ``(N, 4, 4)`` poses of the frames of ``matches``.
    """
    T = _check_poses(T_world_cam)
    if T.shape[0] != len(matches.pts):
        raise ValueError(f"T_world_cam has {T.shape[0]} poses for {len(matches.pts)} frames of matches")
    fitting = []
    for a, b, ia, ib in matches.pairs:
        d, moved = sampson_under_poses(K, T[a], T[b], matches.pts[a][ia], matches.pts[b][ib])
        if moved:
            ok = d < epi_px
            fitting.append((a, b, ia[ok], ib[ok]))
    frame, kp, track = link_tracks([p.shape[0] for p in matches.pts], fitting)
    uv = np.zeros((frame.size, 2))
    for i, p in enumerate(matches.pts):
        sel = frame == i
        uv[sel] = p[kp[sel]]
    return Observations(frame, track, uv)


def sift_tracks(read_gray, K: np.ndarray, T_world_cam: np.ndarray, overlap: int = 5, epi_px: float = 1.5,
                matcher=None) -> Observations:
    """SIFT tracks over a trajectory's frames: :func:`sift_matches` then :func:`tracks_from_matches`.

    Args:
        read_gray: ``read_gray(position) -> (h, w) uint8`` image of the frame at that position.
        K: ``(3, 3)`` intrinsics at the images' resolution.
        T_world_cam: ``(N, 4, 4)`` poses of the frames; they pick the matches that fit (its
            epipolar geometry, Sampson distance below ``epi_px``).
        overlap, matcher: see :func:`sift_matches`.
    """
    T = _check_poses(T_world_cam)
    return tracks_from_matches(K, T, sift_matches(read_gray, T.shape[0], overlap, matcher), epi_px)


def _check_poses(T_world_cam: np.ndarray) -> np.ndarray:
    T = np.asarray(T_world_cam, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or T.shape[0] < 2 or not np.isfinite(T).all():
        raise ValueError(f"T_world_cam must be finite (N, 4, 4) with N >= 2, got {T.shape}")
    return T


def triangulate_tracks(K: np.ndarray, T_world_cam: np.ndarray, obs: Observations,
                       max_px: float = 2.0, min_angle_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Linear (DLT) triangulation of each track from all its observations.

    Returns:
        ``(X (n_tracks, 3), keep (M,) bool)``: an observation is kept when its point is in
        front of its camera and reprojects within ``max_px``, and its track keeps at least two,
        whose rays (from the first and the last of them, in frame order) meet at
        ``min_angle_deg`` or more.
    """
    T = _check_poses(T_world_cam)
    P = np.einsum("ij,njk->nik", K, np.linalg.inv(T)[:, :3, :])  # (N, 3, 4) projection matrices
    Pm = P[obs.frame]
    rows = np.concatenate([obs.uv[:, :1] * Pm[:, 2] - Pm[:, 0], obs.uv[:, 1:2] * Pm[:, 2] - Pm[:, 1]], axis=0)
    tid = np.concatenate([obs.track, obs.track])
    n_tracks = obs.n_tracks
    # normal equations per track: A^T A (4 x 4), smallest eigenvector
    AtA = np.zeros((n_tracks, 4, 4))
    np.add.at(AtA, tid, np.einsum("mi,mj->mij", rows, rows))
    _, vecs = np.linalg.eigh(AtA)
    Xh = vecs[:, :, 0]
    w = Xh[:, 3]
    good = np.abs(w) > 1e-12
    X = np.zeros((n_tracks, 3))
    X[good] = Xh[good, :3] / w[good, None]
    uv, front = project(K, T[obs.frame], X[obs.track])
    keep = good[obs.track] & front & (np.linalg.norm(uv - obs.uv, axis=1) < max_px)
    count = np.bincount(obs.track[keep], minlength=n_tracks)
    keep &= count[obs.track] >= 2
    if min_angle_deg > 0 and keep.any():
        ray = X[obs.track] - T[obs.frame, :3, 3]
        ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-300)
        idx = np.flatnonzero(keep)
        idx = idx[np.lexsort((obs.frame[idx], obs.track[idx]))]
        tr = obs.track[idx]
        starts = np.r_[True, tr[1:] != tr[:-1]]
        first, last = idx[starts], idx[np.r_[starts[1:], True]]
        wide = np.zeros(n_tracks, dtype=bool)
        wide[obs.track[first]] = np.sum(ray[first] * ray[last], axis=1) < np.cos(np.radians(min_angle_deg))
        keep &= wide[obs.track]
    return X, keep


@dataclass(frozen=True)
class ImageOptimum:
    """The adjusted trajectory.

    Attributes:
        T_world_cam: ``(N, 4, 4)`` adjusted poses.
        error_before, error_after: per round, the graph's total (robust) error at the start and the end.
        n_points, n_observations: of the last round.
        residual_px_median: median reprojection error of the last round's observations after it.
    """

    T_world_cam: np.ndarray
    error_before: list
    error_after: list
    n_points: int
    n_observations: int
    residual_px_median: float


def image_optimum(K: np.ndarray, T_world_cam: np.ndarray, obs: Observations, rounds: int = 6,
                  huber_px: float = 1.0, max_iterations: int = 100, max_px: float = 2.0,
                  min_angle_deg: float = 0.0, min_points: int = 20) -> tuple[ImageOptimum | None, bool]:
    """Bundle-adjust all frames and tracks, starting from ``T_world_cam``.

    Args:
        K: ``(3, 3)`` intrinsics (held).
        T_world_cam: ``(N, 4, 4)`` starting poses.
        obs: the tracks' observations (frames are positions ``0 .. N-1``).
        rounds: most triangulate-then-adjust rounds. Each re-triangulates with the adjusted
            poses, so observations the gate dropped at a poor start come back; the rounds
            stop when a round keeps the same observations as the one before.
        huber_px: Huber threshold (noise sigma 1 px).
        max_iterations: Levenberg-Marquardt iterations per round.
        max_px, min_angle_deg: the gates of :func:`triangulate_tracks`.
        min_points: fewer triangulated points gives ``valid = False``.

    Returns:
        ``(ImageOptimum, True)``, or ``(None, False)`` with too few points, a failed solve
        (indeterminate system) or a non-finite result.
    """
    import gtsam

    T = _check_poses(T_world_cam).copy()
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must be (3, 3), got {K.shape}")
    if obs.frame.size and (obs.frame.min() < 0 or obs.frame.max() >= T.shape[0]):
        raise ValueError(f"observations name frames outside 0..{T.shape[0] - 1}")
    if rounds < 1:
        raise ValueError(f"rounds must be >= 1, got {rounds}")
    dist = np.linalg.norm(T[:, :3, 3] - T[0, :3, 3], axis=1)
    j = int(np.argmax(dist))  # the frame farthest from the first: the distance to it holds the scale
    step = float(dist[j])
    if not step > 0:
        raise ValueError("all poses have the same camera centre: nothing can hold the scale")
    # the gauge: the first pose (radians, trajectory units) and the distance to frame j
    hold_pose = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, HOLD_SIGMA), np.full(3, HOLD_SIGMA * step)])
    hold_range = gtsam.noiseModel.Isotropic.Sigma(1, HOLD_SIGMA * step)
    Xk, Lk = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.L
    before, after = [], []
    kept = None
    for _ in range(int(rounds)):
        X, keep = triangulate_tracks(K, T, obs, max_px=max_px, min_angle_deg=min_angle_deg)
        if kept is not None and np.array_equal(keep, kept):
            break
        kept = keep
        sub = obs.subset(keep)
        pts = X[np.unique(obs.track[keep])] if keep.any() else np.zeros((0, 3))
        if pts.shape[0] < min_points:
            return None, False
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        for i in range(T.shape[0]):
            values.insert(Xk(i), gtsam.Pose3(T[i]))
        graph.add(gtsam.PriorFactorPose3(Xk(0), gtsam.Pose3(T[0]), hold_pose))
        graph.add(gtsam.RangeFactorPose3(Xk(0), Xk(j), step, hold_range))
        for q in range(pts.shape[0]):
            values.insert(Lk(q), pts[q])
        add_reprojection_factors(graph, K, sub.frame, sub.track, sub.uv, huber_px, Xk, Lk)
        solved, ok = levenberg_marquardt(graph, values, max_iterations)
        if not ok:
            return None, False
        result, e0, e1, _ = solved
        T_new = np.stack([result.atPose3(Xk(i)).matrix() for i in range(T.shape[0])])
        if not np.isfinite(T_new).all():
            return None, False
        T = T_new
        before.append(float(e0))
        after.append(float(e1))
        pts = np.stack([result.atPoint3(Lk(q)) for q in range(pts.shape[0])])
    uv, _ = project(K, T[sub.frame], pts[sub.track])
    res = np.linalg.norm(uv - sub.uv, axis=1)
    return ImageOptimum(T, before, after, int(pts.shape[0]), int(sub.frame.size), float(np.median(res))), True
