"""How well a trajectory's relative poses explain the images: a check of ground truth.

Ground truth from GPS/INS or motion capture has errors of its own. This module measures
them with evidence that does not come from the pipeline: sparse SIFT matches (not the
pipeline's dense optical flow). The same measurement is made for a run, so the two can be
compared frame pair by frame pair:

* **epipolar residual** of frames ``a -> b``: the median Sampson distance (pixels) of the
  matches under the fundamental matrix of the trajectory's relative pose. It tests the
  relative rotation and the translation direction. A pose that explains the images
  leaves the matching noise (about 0.1 px for SIFT). Matches above ``cap_px`` are left out
  (mismatches and moving objects).
* **step-scale consistency** of frames ``a, b, c``: points matched in all three are
  triangulated from ``(a, b)`` and from ``(b, c)`` with the trajectory's poses. The result is
  the median ``log(z_ab / z_bc)`` of their depths in ``b``. It is 0 when the lengths of the
  two steps agree with the scene. At +0.01, step ``b -> c`` is 1 % too short relative to
  step ``a -> b``. Errors of this kind accumulate into the scale drift that ATE measures.

If a ground truth's values sit well above a run's, its local errors are larger than the
run's. Differences between runs at that level cannot be ranked against it.

Poses are ``T_world_cam`` ``(4, 4)`` (camera to world); pixels ``(u, v)`` at the images'
resolution, with ``K`` the intrinsics at that resolution.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trianflow_vo.geometry.epipolar import sampson_distance
from trianflow_vo.geometry.fundamental import fundamental_from_pose
from trianflow_vo.geometry.se3 import invert_T
from trianflow_vo.geometry.triangulation import triangulate_midpoint

MIN_MATCHES = 20  # fewer usable matches / triangulated points: no value


def _check_T(name: str, T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"{name} must be a finite (4, 4) pose, got shape {T.shape}")
    return T


def _check_pts(**pts: np.ndarray) -> list[np.ndarray]:
    out = [np.asarray(p, dtype=np.float64) for p in pts.values()]
    n = out[0].shape[0] if out[0].ndim == 2 else -1
    for name, p in zip(pts, out):
        if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] != n:
            raise ValueError(f"{', '.join(pts)} must all be (N, 2) with the same N; {name} is {p.shape}")
    return out


def _relative(T_world_a: np.ndarray, T_world_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` with ``X_b = R X_a + t``."""
    T_b_a = invert_T(T_world_b) @ T_world_a
    return T_b_a[:3, :3], T_b_a[:3, 3]


def sampson_under_poses(K: np.ndarray, T_world_a: np.ndarray, T_world_b: np.ndarray, pts_a: np.ndarray,
                        pts_b: np.ndarray) -> tuple[np.ndarray, bool]:
    """Sampson distances (pixels) of matches ``a -> b`` under the fundamental matrix of the poses.

    Args:
        K: ``(3, 3)`` intrinsics.
        T_world_a, T_world_b: ``(4, 4)`` poses of the two frames.
        pts_a, pts_b: ``(N, 2)`` matched pixels.

    Returns:
        ``(d (N,), valid)``; ``valid`` is False (``d`` all NaN) when the frames do not move apart.
    """
    R, t = _relative(_check_T("T_world_a", T_world_a), _check_T("T_world_b", T_world_b))
    n = float(np.linalg.norm(t))
    if n < 1e-12:
        return np.full(np.asarray(pts_a).shape[0], np.nan), False
    return sampson_distance(fundamental_from_pose(R, t / n, np.asarray(K, dtype=np.float64)), pts_a, pts_b), True


def epipolar_residual(K: np.ndarray, T_world_a: np.ndarray, T_world_b: np.ndarray, pts_a: np.ndarray,
                      pts_b: np.ndarray, cap_px: float = 3.0) -> tuple[float, bool]:
    """Median Sampson distance (pixels) of matches ``a -> b`` under the poses' fundamental matrix.

    Args:
        K: ``(3, 3)`` intrinsics.
        T_world_a, T_world_b: ``(4, 4)`` poses of the two frames.
        pts_a, pts_b: ``(N, 2)`` matched pixels.
        cap_px: matches farther than this are left out (outliers).

    Returns:
        ``(median_px, valid)``. ``valid`` is False when the frames do not move apart
        (no epipolar geometry) or fewer than ``MIN_MATCHES`` matches are under the cap.
    """
    pts_a, pts_b = _check_pts(pts_a=pts_a, pts_b=pts_b)
    d, moved = sampson_under_poses(K, T_world_a, T_world_b, pts_a, pts_b)
    if not moved:
        return float("nan"), False
    d = d[d < cap_px]
    if d.size < MIN_MATCHES:
        return float("nan"), False
    return float(np.median(d)), True


def step_scale_log_ratio(K: np.ndarray, T_world_a: np.ndarray, T_world_b: np.ndarray, T_world_c: np.ndarray,
                         pts_a: np.ndarray, pts_b: np.ndarray, pts_c: np.ndarray,
                         min_angle: float = 2e-3) -> tuple[float, bool]:
    """Median ``log(z_ab / z_bc)`` of points seen in frames ``a``, ``b`` and ``c`` (depths in ``b``).

    Args:
        K: ``(3, 3)`` intrinsics.
        T_world_a, T_world_b, T_world_c: ``(4, 4)`` poses of the three frames.
        pts_a, pts_b, pts_c: ``(N, 2)`` pixels of the same N points in each frame.
        min_angle: rays meeting at a smaller angle (radians) are not triangulated.

    Returns:
        ``(log_ratio, valid)``. 0 means the two steps' lengths agree with the scene; ``log(s)``
        means the step ``b -> c`` must be multiplied by ``s`` to agree with step ``a -> b``.
        ``valid`` is False when fewer than ``MIN_MATCHES`` points triangulate in both pairs.
    """
    pts_a, pts_b, pts_c = _check_pts(pts_a=pts_a, pts_b=pts_b, pts_c=pts_c)
    K = np.asarray(K, dtype=np.float64)
    Ta, Tb, Tc = (_check_T(n, T) for n, T in (("T_world_a", T_world_a), ("T_world_b", T_world_b),
                                               ("T_world_c", T_world_c)))
    R_ba, t_ba = _relative(Ta, Tb)
    R_cb, t_cb = _relative(Tb, Tc)
    if np.linalg.norm(t_ba) < 1e-12 or np.linalg.norm(t_cb) < 1e-12:
        return float("nan"), False
    X_a, ok_ab, _ = triangulate_midpoint(pts_a, pts_b, K, R_ba, t_ba, min_angle=min_angle)
    z_ab = (X_a @ R_ba.T + t_ba)[:, 2]
    X_b, ok_bc, _ = triangulate_midpoint(pts_b, pts_c, K, R_cb, t_cb, min_angle=min_angle)
    z_bc = X_b[:, 2]
    ok = ok_ab & ok_bc & (z_ab > 0) & (z_bc > 0)
    if ok.sum() < MIN_MATCHES:
        return float("nan"), False
    return float(np.median(np.log(z_ab[ok] / z_bc[ok]))), True


class SiftMatcher:
    """SIFT keypoints of grey images (cached by key) and ratio-test matches between them.

    Args:
        n_features: keypoints kept per image.
        ratio: Lowe's ratio test threshold.
    """

    def __init__(self, n_features: int = 4000, ratio: float = 0.7):
        import cv2

        self._sift = cv2.SIFT_create(int(n_features))
        self._bf = cv2.BFMatcher()
        self.ratio = float(ratio)
        self._cache: dict = {}

    def features(self, key, read_gray) -> tuple[np.ndarray, np.ndarray | None]:
        """``(pixels (N, 2), descriptors)`` of the image ``read_gray() -> (h, w) uint8``, computed once
        per ``key`` (the image is read only when ``key`` is not cached)."""
        if key not in self._cache:
            kps, desc = self._sift.detectAndCompute(np.ascontiguousarray(read_gray()), None)
            self._cache[key] = (np.array([k.pt for k in kps], dtype=np.float64).reshape(-1, 2), desc)
        return self._cache[key]

    def forget(self, keep) -> None:
        """Drop the cached features of keys not in ``keep``."""
        for k in [k for k in self._cache if k not in keep]:
            del self._cache[k]

    def match(self, desc_a: np.ndarray | None, desc_b: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Indices ``(ia, ib)`` of the matches ``a -> b`` that pass the ratio test."""
        if desc_a is None or desc_b is None or len(desc_a) < 2 or len(desc_b) < 2:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        pairs = [p for p in self._bf.knnMatch(desc_a, desc_b, k=2) if len(p) == 2]
        good = [(m.queryIdx, m.trainIdx) for m, n in pairs if m.distance < self.ratio * n.distance]
        if not good:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        ia, ib = np.array(good, dtype=np.int64).T
        return ia, ib


@dataclass(frozen=True)
class ConsistencyTable:
    """Per frame pair / triple values of each trajectory (NaN = no value).

    Attributes:
        pairs: ``(P, 2)`` positions ``(a, b)`` in the trajectories of consecutive frames.
        epipolar_px: trajectory name -> ``(P,)`` epipolar residuals (pixels).
        triples: ``(Q,)`` position of the middle frame ``b`` of each triple ``(b-1, b, b+1)``.
        scale_log_ratio: trajectory name -> ``(Q,)`` step-scale log ratios.
    """

    pairs: np.ndarray
    epipolar_px: dict
    triples: np.ndarray
    scale_log_ratio: dict

    def summary(self) -> dict:
        """Per trajectory: median epipolar residual, median |scale log ratio| and its spread."""
        out = {}
        for name in self.epipolar_px:
            e, s = self.epipolar_px[name], self.scale_log_ratio[name]
            out[name] = {
                "epipolar_px_median": float(np.nanmedian(e)) if np.isfinite(e).any() else None,
                "scale_abs_log_median": float(np.nanmedian(np.abs(s))) if np.isfinite(s).any() else None,
                "scale_log_std": float(np.nanstd(s)) if np.isfinite(s).any() else None,
                "pairs": int(np.isfinite(e).sum()), "triples": int(np.isfinite(s).sum()),
            }
        return out


def consistency_table(read_gray, K: np.ndarray, trajectories: dict, matcher: SiftMatcher | None = None,
                      cap_px: float = 3.0) -> ConsistencyTable:
    """Epipolar residuals and step-scale ratios of consecutive frames for several trajectories.

    Args:
        read_gray: ``read_gray(position) -> (h, w) uint8`` image of the trajectories' frame
            at that position (the same frames for all trajectories).
        K: ``(3, 3)`` intrinsics at the images' resolution.
        trajectories: name -> ``(N, 4, 4)`` ``T_world_cam`` (all the same N >= 2).
        matcher: a :class:`SiftMatcher` (default: 4000 features, ratio 0.7).
        cap_px: see :func:`epipolar_residual`.
    """
    if not trajectories:
        raise ValueError("trajectories is empty")
    arrs = {k: np.asarray(v, dtype=np.float64) for k, v in trajectories.items()}
    n = next(iter(arrs.values())).shape[0]
    for k, v in arrs.items():
        if v.ndim != 3 or v.shape[1:] != (4, 4) or v.shape[0] != n or n < 2:
            raise ValueError(f"trajectory {k!r} must be (N, 4, 4) with the same N >= 2 as the others, got {v.shape}")
    matcher = matcher or SiftMatcher()
    feats = lambda i: matcher.features(i, lambda: read_gray(i))  # noqa: E731
    epi = {k: np.full(n - 1, np.nan) for k in arrs}
    scl = {k: np.full(max(n - 2, 0), np.nan) for k in arrs}
    prev = None  # matches (b-1 -> b) as a dict b-keypoint -> (b-1)-keypoint
    for b in range(1, n):
        (pa, da), (pb, db) = feats(b - 1), feats(b)
        ia, ib = matcher.match(da, db)
        for k, T in arrs.items():
            epi[k][b - 1], _ = epipolar_residual(K, T[b - 1], T[b], pa[ia], pb[ib], cap_px=cap_px)
        if prev is not None:  # the triple (b-2, b-1, b): keypoints of b-1 matched both ways
            common = [(prev[j], j, i) for j, i in zip(ia.tolist(), ib.tolist()) if j in prev]
            if len(common) >= MIN_MATCHES:
                i0, i1, i2 = (np.array(c, dtype=np.int64) for c in zip(*common))
                p0 = feats(b - 2)[0]
                for k, T in arrs.items():
                    scl[k][b - 2], _ = step_scale_log_ratio(K, T[b - 2], T[b - 1], T[b], p0[i0], pa[i1], pb[i2])
        # keypoint of b -> keypoint of b-1, for the next triple
        prev = dict(zip(ib.tolist(), ia.tolist()))
        matcher.forget({b - 1, b})
    return ConsistencyTable(np.stack([np.arange(n - 1), np.arange(1, n)], axis=1), epi, np.arange(1, n - 1), scl)
