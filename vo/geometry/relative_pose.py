"""Relative pose of two calibrated views from matches: robust estimation + refinement.

Estimators:
    ``"ransac"``  OpenCV's five-point essential-matrix RANSAC on normalised points.
    ``"magsac"``  OpenCV's USAC MAGSAC++ (local optimisation included).
    ``"8point"``  our normalised eight-point fundamental matrix in a RANSAC loop,
                  converted to E with K (the paper's choice).
Every estimator is followed (``refine=True``) by a robust Gauss-Newton-style
refinement of ``(R, t)`` minimising the Sampson error (pixels) with a Cauchy loss,
because RANSAC returns its best sampled hypothesis unrefined.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from trianflow_vo.camera import focal_px
from trianflow_vo.geometry.epipolar import sampson_distance
from trianflow_vo.geometry.essential import choose_pose_cheirality
from trianflow_vo.geometry.fundamental import eight_point, essential_from_fundamental, fundamental_from_pose
from trianflow_vo.geometry.se3 import rodrigues, skew
from trianflow_vo.geometry.triangulation import bearings


@dataclass
class RelativePose:
    """``X2 = R @ X1 + t`` with ``|t| = 1``; ``inliers`` ``(N,)`` bool; ``F`` ``(3, 3)``."""

    R: np.ndarray
    t: np.ndarray
    inliers: np.ndarray
    F: np.ndarray
    n_cheirality: int


def _ransac_8point(pts1, pts2, threshold_px, rng, prob=0.999, max_iters=2000):
    n = pts1.shape[0]
    best_inl = None
    best_count = -1
    iters = max_iters
    i = 0
    while i < iters:
        idx = rng.choice(n, 8, replace=False)
        F, ok = eight_point(pts1[idx], pts2[idx])
        i += 1
        if not ok:
            continue
        inl = sampson_distance(F, pts1, pts2) < threshold_px
        c = int(inl.sum())
        if c > best_count:
            best_count, best_inl = c, inl
            w = c / n
            denom = np.log(max(1e-12, 1.0 - w ** 8))
            if denom < 0:
                iters = min(max_iters, int(np.ceil(np.log(1 - prob) / denom)))
    if best_inl is None or best_count < 8:
        return None, None
    F, ok = eight_point(pts1[best_inl], pts2[best_inl])
    if not ok:
        return None, None
    return F, best_inl


def normalised_columns(pts: np.ndarray, K: np.ndarray) -> np.ndarray:
    """``(3, N)`` contiguous normalised homogeneous coordinates (one column a pixel of ``pts``
    ``(N, 2)``): :func:`~trianflow_vo.geometry.triangulation.bearings` as columns, whose rows are
    contiguous, which keeps every per-match operation of the Sampson residual a contiguous one."""
    return np.ascontiguousarray(bearings(pts, K).T)


def _sampson_parts(E, x1c, x2c):
    """``(E x1, E^T x2, x2^T E x1, Sampson denominator)`` of the columns ``x1c``, ``x2c`` ``(3, N)``."""
    Ex1 = E @ x1c
    Etx2 = E.T @ x2c
    num = np.einsum("in,in->n", x2c, Ex1)
    den = Ex1[0] ** 2 + Ex1[1] ** 2 + Etx2[0] ** 2 + Etx2[1] ** 2 + 1e-18
    return Ex1, Etx2, num, den


def _signed_sampson(R, t, x1c, x2c, f):
    """Signed Sampson residuals ``(N,)`` in pixels of the pose ``(R, t)``.

    ``x1c``, ``x2c``: ``(3, N)`` normalised homogeneous coordinates as columns
    (:func:`normalised_columns`); f: focal length.
    """
    _, _, num, den = _sampson_parts(skew(t) @ R, x1c, x2c)
    return f * num / np.sqrt(den)


def sampson_jacobian(R, t, B, x1c, x2c, f):
    """Signed Sampson residuals (pixels) and their Jacobian in the 5 pose parameters.

    The parameters are those of :func:`_perturb_pose` at ``dx = 0``: a rotation vector
    applied on the left of ``R`` (3), then a step of the unit direction ``t`` in the
    tangent basis ``B`` (2). Analytic: ``dE = [t]x [e_k]x R`` for the rotation and
    ``[B_j]x R`` for the direction (the renormalisation has no first-order term).

    Args:
        R: ``(3, 3)``, t: ``(3,)`` unit, B: ``(3, 2)`` tangent basis at ``t``.
        x1c, x2c: ``(3, N)`` normalised homogeneous coordinates as columns. f: focal length (pixels).

    Returns:
        ``(r, J)``: ``(N,)`` residuals and ``(N, 5)`` Jacobian.
    """
    G = np.stack([skew(t) @ skew(e) @ R for e in np.eye(3)] + [skew(B[:, j]) @ R for j in range(2)])
    Ex1, Etx2, num, den = _sampson_parts(skew(t) @ R, x1c, x2c)
    sd = np.sqrt(den)
    # both derivatives are linear in G_k: dnum_k = (x2 x1^T) : G_k and dden_k / 2 =
    # sum_c Ex1_0 x1_c G_k[0, c] + Ex1_1 x1_c G_k[1, c] + Etx2_0 x2_c G_k[c, 0] + Etx2_1 x2_c G_k[c, 1],
    # so J is one (5, 21) x (21, N) product
    a = f / sd
    b = -f * num / (den * sd)
    M = np.empty((21, x1c.shape[1]))
    M[:9] = ((a * x2c)[:, None, :] * x1c[None, :, :]).reshape(9, -1)
    M[9:12] = (b * Ex1[0]) * x1c
    M[12:15] = (b * Ex1[1]) * x1c
    M[15:18] = (b * Etx2[0]) * x2c
    M[18:21] = (b * Etx2[1]) * x2c
    C = np.concatenate([G.reshape(5, 9), G[:, 0, :], G[:, 1, :], G[:, :, 0], G[:, :, 1]], 1)
    return f * num / sd, (C @ M).T


def _tangent_basis(t):
    """``(3, 2)`` orthonormal basis of the tangent plane of the unit sphere at the direction ``t``."""
    a = np.array([1.0, 0.0, 0.0]) if abs(t[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    b1 = np.cross(t, a)
    b1 /= np.linalg.norm(b1)
    return np.stack([b1, np.cross(t, b1)], 1)


def _perturb_pose(R, t, B, dx):
    """``(R, t)`` moved by ``dx`` ``(5,)``: a rotation vector (3) and a step of the direction in basis ``B`` (2)."""
    Rn = rodrigues(dx[:3]) @ R
    tn = t + B @ dx[3:]
    return Rn, tn / np.linalg.norm(tn)


def _robust_cost(r, scale):
    # truncated Cauchy: constant beyond 3 scales
    return np.sum(np.log1p(np.minimum(np.abs(r) / scale, 3.0) ** 2))


def refine_pose_sampson(
    R0: np.ndarray, t0: np.ndarray, pts1: np.ndarray, pts2: np.ndarray, K: np.ndarray, scale_px: float = 0.5,
    iters: int = 15,
) -> tuple[tuple[np.ndarray, np.ndarray], bool]:
    """Robust refinement of ``(R, t)`` minimising the Sampson error (truncated Cauchy loss).

    Args:
        R0: ``(3, 3)``, t0: ``(3,)`` initial pose (``X2 = R X1 + t``).
        pts1, pts2: ``(N, 2)`` pixel matches.
        K: ``(3, 3)`` intrinsics.
        scale_px: Cauchy scale in pixels.
        iters: Gauss-Newton (IRLS) iterations.

    Returns:
        ``((R, t), valid)``, ``|t| = 1``.
    """
    x1c, x2c = normalised_columns(pts1, K), normalised_columns(pts2, K)
    f = focal_px(K)
    R = R0.copy()
    t = np.asarray(t0, dtype=np.float64) / np.linalg.norm(t0)
    # matches far from the initial model have no weight under the truncated loss and
    # rarely come back within a few steps: refine on the rest (much cheaper)
    near = np.abs(_signed_sampson(R, t, x1c, x2c, f)) < 6.0 * scale_px
    if near.sum() >= 8:
        x1c, x2c = np.ascontiguousarray(x1c[:, near]), np.ascontiguousarray(x2c[:, near])
    r = _signed_sampson(R, t, x1c, x2c, f)
    lam = 1e-3
    for _ in range(iters):
        B = _tangent_basis(t)
        _, J = sampson_jacobian(R, t, B, x1c, x2c, f)
        # Cauchy IRLS weights, zero beyond 3 scales (gross outliers have no say)
        w = (np.abs(r) < 3.0 * scale_px) / (1.0 + (r / scale_px) ** 2)
        JW = J * w[:, None]
        H = JW.T @ J
        g = JW.T @ r
        cost = _robust_cost(r, scale_px)
        improved = False
        for _ in range(8):  # Levenberg-Marquardt damping
            try:
                dx = -np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), g)
            except np.linalg.LinAlgError:
                return (R0, t0), False
            Rn, tn = _perturb_pose(R, t, B, dx)
            rn = _signed_sampson(Rn, tn, x1c, x2c, f)
            cost_n = _robust_cost(rn, scale_px)
            if np.isfinite(cost_n) and cost_n <= cost:
                R, t, r = Rn, tn, rn
                lam = max(lam / 10.0, 1e-7)
                improved = True
                break
            lam *= 10.0
        if not improved or np.linalg.norm(dx) < 1e-10 or cost - cost_n < 1e-6 * cost:
            break
    return (R, t), bool(np.all(np.isfinite(R)) and np.all(np.isfinite(t)))


def estimate_relative_pose(
    pts1: np.ndarray,
    pts2: np.ndarray,
    K: np.ndarray,
    threshold_px: float = 0.1,
    method: str = "ransac",
    refine: bool = True,
    inlier_px: float = 0.5,
    rng: np.random.Generator | None = None,
    ransac_subset: int | None = None,
) -> tuple[RelativePose | None, bool]:
    """Relative pose from pixel matches of two views with the same intrinsics.

    Args:
        pts1, pts2: ``(N, 2)`` matching pixels, ``N >= 8``.
        K: ``(3, 3)`` intrinsics.
        threshold_px: RANSAC inlier threshold (pixels).
        method: ``"ransac"``, ``"magsac"`` or ``"8point"`` (see module docstring).
        refine: robust Sampson refinement after the estimator.
        inlier_px: Sampson distance under which a match counts as an inlier of the
            final pose.
        rng: random generator for the ``"8point"`` RANSAC and the subset.
        ransac_subset: run the estimator on this many matches drawn at random
            (the refinement then uses all of them): with refinement the answer is
            the same and the RANSAC stage several times cheaper.

    Returns:
        ``(RelativePose or None, valid)``; invalid when the estimator finds no
        model or the cheirality check is ambiguous.
    """
    pts1 = np.asarray(pts1, dtype=np.float64)
    pts2 = np.asarray(pts2, dtype=np.float64)
    if pts1.ndim != 2 or pts1.shape[1] != 2 or pts1.shape != pts2.shape:
        raise ValueError(f"pts1 and pts2 must both be (N, 2), got {pts1.shape} and {pts2.shape}")
    if K.shape != (3, 3):
        raise ValueError(f"K must be (3, 3), got {K.shape}")
    if pts1.shape[0] < 8:
        return None, False
    f = focal_px(K)
    all1, all2 = pts1, pts2
    rng = np.random.default_rng(0) if rng is None else rng
    if ransac_subset is not None and refine and pts1.shape[0] > ransac_subset:
        sub = rng.choice(pts1.shape[0], ransac_subset, replace=False)
        pts1, pts2 = pts1[sub], pts2[sub]
    if method in ("ransac", "magsac"):
        x1 = bearings(pts1, K)[:, :2]
        x2 = bearings(pts2, K)[:, :2]
        flag = cv2.RANSAC if method == "ransac" else cv2.USAC_MAGSAC
        try:
            E, mask = cv2.findEssentialMat(
                np.ascontiguousarray(x1), np.ascontiguousarray(x2), np.eye(3), method=flag, prob=0.999,
                threshold=threshold_px / f,
            )
        except cv2.error:  # OpenCV >= 5.1 asserts inside its 5-point solver on degenerate samples
            return None, False  # (no motion, pure rotation): no model, as older versions reported
        if E is None or E.shape != (3, 3):
            return None, False  # none, or several stacked solutions from a degenerate sample
        inl = mask.ravel().astype(bool)
    elif method == "8point":
        F, inl = _ransac_8point(pts1, pts2, threshold_px, rng)
        if F is None:
            return None, False
        E = essential_from_fundamental(F, K)
    else:
        raise ValueError(f"unknown method {method!r}")
    if inl.sum() < 8:
        return None, False
    (R, t), n_front, ok = choose_pose_cheirality(E, pts1[inl], pts2[inl], K)
    if not ok:
        return None, False
    pts1, pts2 = all1, all2
    if refine:
        (R, t), ok = refine_pose_sampson(R, t, pts1, pts2, K, scale_px=max(threshold_px, 0.25))
        if not ok:
            return None, False
    F = fundamental_from_pose(R, t, K)
    d = sampson_distance(F, pts1, pts2)
    inliers = d < inlier_px
    return RelativePose(R=R, t=t, inliers=inliers, F=F, n_cheirality=n_front), True
