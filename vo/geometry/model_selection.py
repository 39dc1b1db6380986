"""Which motion explains a set of matches: general two-view motion or a rotation only.

GRIC (Torr's Geometric Robust Information Criterion) compares models of
different dimension on the same matches. For a model with manifold dimension
``d`` and ``k`` parameters, fitted to ``n`` matches in an ``r = 4``-dimensional
data space (two image points) with residuals ``e`` and noise ``sigma``::

    GRIC = sum_i min(e_i^2 / sigma^2, lambda3 * (r - d)) + lambda1 * d * n + lambda2 * k
    lambda1 = ln r,  lambda2 = ln(r n),  lambda3 = 2

The lower GRIC wins. Here the two models are

* general motion, the essential matrix (``d = 3``, ``k = 5``), residual = Sampson distance;
* rotation only, the infinite homography ``K R K^-1`` (``d = 2``, ``k = 3``), residual =
  the rotation fit's transfer error divided by sqrt(2) (the error is shared by both images,
  as the Sampson distance is).

A pure rotation, or a translation too small against the noise to be seen, makes the
rotation model win: the translation direction of a two-view step would be noise.
The noise ``sigma`` is measured on the matches themselves (robust spread of the
general model's residuals), so the test adapts to the flow's accuracy, the image
size and the scene, with no pixel threshold.

:func:`direction_sigma` gives the standard deviation of the estimated translation
direction (radians) from the Sampson residuals' Jacobian: a second test for steps
that are not degenerate but too short for the direction to be reliable.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trianflow_vo.camera import focal_px
from trianflow_vo.geometry.relative_pose import _tangent_basis, normalised_columns, sampson_jacobian

R_DATA = 4  # two image points per match


def gric(residuals: np.ndarray, sigma: float, d: int, k: int, r: int = R_DATA) -> float:
    """GRIC score of a model (lower is better).

    Args:
        residuals: ``(N,)`` geometric residuals in pixels.
        sigma: noise standard deviation in pixels (> 0).
        d: dimension of the model's manifold; k: number of its parameters; r: data dimension.
    """
    e = np.asarray(residuals, dtype=np.float64)
    if sigma <= 0:
        raise ValueError(f"sigma must be > 0, got {sigma}")
    n = e.size
    if n == 0:
        return 0.0
    rho = np.minimum((e / sigma) ** 2, 2.0 * (r - d)).sum()
    return float(rho + np.log(r) * d * n + np.log(r * n) * k)


@dataclass(frozen=True)
class MotionTest:
    """The verdict of :func:`select_motion_model`.

    Attributes:
        general: True when general motion (essential matrix) wins over rotation only.
        gric_general, gric_rotation: the two scores per match (lower wins).
        sigma_px: the noise used (pixels).
    """

    general: bool
    gric_general: float
    gric_rotation: float
    sigma_px: float


def noise_sigma(residuals: np.ndarray, floor_px: float = 0.05) -> float:
    """Robust noise estimate ``1.4826 * median(|residuals|)`` (pixels), at least ``floor_px``."""
    e = np.abs(np.asarray(residuals, dtype=np.float64))
    return float(max(1.4826 * np.median(e), floor_px)) if e.size else float(floor_px)


def select_motion_model(sampson_px: np.ndarray, rotation_px: np.ndarray, floor_px: float = 0.05) -> MotionTest:
    """General motion or rotation only, by GRIC (see the module docstring).

    Args:
        sampson_px: ``(N,)`` Sampson distances of the matches under the estimated essential matrix.
        rotation_px: ``(N,)`` transfer errors of the same matches under the best rotation (pixels).
        floor_px: smallest noise assumed (pixels).
    """
    s = np.asarray(sampson_px, dtype=np.float64)
    q = np.asarray(rotation_px, dtype=np.float64) / np.sqrt(2.0)
    if s.shape != q.shape or s.ndim != 1:
        raise ValueError(f"sampson_px and rotation_px must be (N,) alike, got {s.shape} and {q.shape}")
    n = max(s.size, 1)
    sigma = noise_sigma(s, floor_px)
    g_e = gric(s, sigma, d=3, k=5) / n
    g_r = gric(q, sigma, d=2, k=3) / n
    return MotionTest(bool(g_e < g_r), g_e, g_r, sigma)


def direction_sigma(R: np.ndarray, t: np.ndarray, pts1: np.ndarray, pts2: np.ndarray, K: np.ndarray,
                    sigma_px: float, n_independent: int | None = None) -> tuple[float, bool]:
    """Standard deviation (radians) of the translation direction of a relative pose.

    First-order propagation of ``sigma_px`` through the Sampson residuals of the
    matches: ``cov = sigma^2 (J^T J)^-1`` over the 5 parameters (rotation, direction on
    the sphere); the larger axis of the direction block. Dense flow matches are not
    independent: ``n_independent`` (if given and smaller than N) scales the information
    down to that many matches.

    Args:
        R: ``(3, 3)``, t: ``(3,)`` the pose (``X2 = R X1 + t``).
        pts1, pts2: ``(N, 2)`` inlier matches (pixels). K: ``(3, 3)``.
        sigma_px: noise of a match (pixels).

    Returns:
        ``(sigma_rad, valid)``; invalid (``inf``) when the information is singular.
    """
    pts1 = np.asarray(pts1, dtype=np.float64)
    pts2 = np.asarray(pts2, dtype=np.float64)
    n = pts1.shape[0]
    if n < 6:
        return float("inf"), False
    t = np.asarray(t, dtype=np.float64)
    t = t / np.linalg.norm(t)
    x1c, x2c = normalised_columns(pts1, K), normalised_columns(pts2, K)
    f = focal_px(K)
    B = _tangent_basis(t)  # the parametrisation of refine_pose_sampson: its Jacobian, at the solution
    _, J = sampson_jacobian(R, t, B, x1c, x2c, f)
    info = J.T @ J
    if n_independent is not None and n_independent < n:
        info *= n_independent / n
    try:
        cov = np.linalg.inv(info) * sigma_px ** 2
    except np.linalg.LinAlgError:
        return float("inf"), False
    ev = np.linalg.eigvalsh(0.5 * (cov[3:, 3:] + cov[3:, 3:].T))
    if not np.all(np.isfinite(ev)) or ev.max() < 0:
        return float("inf"), False
    return float(np.sqrt(ev.max())), True
