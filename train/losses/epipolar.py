"""Two-view geometry inside training: F from the flow, epipolar distances, geometric loss, pose.

TrianFlow has no pose network: each training pair's relative pose comes from the flow.

* :func:`fundamental_from_flow`: the top 20 % of image-1 pixels by score, 6000 of them
  drawn with replacement, OpenCV's RANSAC (0.1 px, confidence 0.99); no gradient.
* :func:`epipolar_distance`: ``D_epi`` of every pixel's match ``x -> x + flow12(x)``, the
  distance of the match to the epipolar line ``F x`` in image 2 (gradient of the flow kept).
* :func:`geometric_loss`: mean ``D_epi`` over the band ``0.1 <= D_epi < 0.5`` (pixels
  already near-perfect or far off, e.g. moving objects, are left alone).
* :func:`rigid_mask`: ``(D_epi < 0.5) / (1 + D_epi)``.
* :func:`pose_from_fundamental`: ``E = K^T F K``, its SVD, the four ``(R, t)``
  candidates; the one putting most mid-point-triangulated matches in front of both
  cameras wins. ``X2 = R X1 + t`` (``T_cam2_cam1``), ``|t| = 1``.

Flows are ``(N, 2, H, W)`` in pixels, channel 0 = x. ``F`` maps pixels: ``x2^T F x1 = 0``.
"""

from __future__ import annotations

import numpy as np
import torch

from trianflow_vo.errors import InputError
from trianflow_vo.train.losses.triangulation import midpoint_points, pixel_grid, sample_matches

RANSAC_THRESHOLD_PX = 0.1
RANSAC_CONFIDENCE = 0.99
LINE_EPS = 1e-6  # added to the line-normal length, as the authors
MIN_POINTS = 8  # distinct matches the RANSAC needs (fewer: the item fails)


def _check_flow(flow12: torch.Tensor) -> None:
    if flow12.dim() != 4 or flow12.shape[1] != 2:
        raise InputError(f"flow12: expected (N, 2, H, W), got {tuple(flow12.shape)}")


def _check_F(F: torch.Tensor, n: int) -> None:
    if tuple(F.shape) != (n, 3, 3):
        raise InputError(f"F: expected ({n}, 3, 3), got {tuple(F.shape)}")


def fundamental_from_flow(flow12: torch.Tensor, score: torch.Tensor, top_ratio: float = 0.2,
                          n_samples: int = 6000, generator: torch.Generator | None = None,
                          threshold: float = RANSAC_THRESHOLD_PX, confidence: float = RANSAC_CONFIDENCE
                          ) -> tuple[torch.Tensor, torch.Tensor]:
    """The fundamental matrix of each pair from its flow, as the authors fit it. No gradient.

    Args:
        flow12: ``(N, 2, H, W)`` flow from image 1 to image 2.
        score: ``(N, 1, H, W)`` match score of image-1 pixels (``valid / (0.1 + |fb|)``).
        top_ratio: share of the pixels, by score, the matches are drawn from.
        n_samples: matches drawn (with replacement) for the RANSAC.
        generator: torch generator of the draw; ``None`` = torch's global one.
        threshold: RANSAC inlier distance in pixels; confidence: RANSAC confidence.

    Returns:
        ``F`` ``(N, 3, 3)`` (dtype and device of ``flow12``; zeros where it failed) and
        ``valid`` ``(N,)`` bool: False when fewer than 8 distinct matches had a positive
        score or OpenCV returned no finite ``3 x 3`` matrix.
    """
    import cv2

    _check_flow(flow12)
    with torch.no_grad():
        pts1, pts2, ok = sample_matches(flow12.detach(), score, top_ratio, n_samples, generator)
        p1 = pts1.double().cpu().numpy()
        p2 = pts2.double().cpu().numpy()
    n = flow12.shape[0]
    out = np.zeros((n, 3, 3))
    valid = np.zeros(n, dtype=bool)
    for i in range(n):
        if not ok[i] or not np.isfinite(p2[i]).all():
            continue
        if len(np.unique(np.round(p1[i], 3), axis=0)) < MIN_POINTS:
            continue
        try:
            f, _ = cv2.findFundamentalMat(p1[i], p2[i], cv2.FM_RANSAC, threshold, confidence)
        except cv2.error:
            f = None
        if f is None or f.shape != (3, 3) or not np.isfinite(f).all() or not np.abs(f).max() > 0:
            continue
        out[i] = f
        valid[i] = True
    return (torch.from_numpy(out).to(device=flow12.device, dtype=flow12.dtype),
            torch.from_numpy(valid).to(flow12.device))


def epipolar_distance(F: torch.Tensor, flow12: torch.Tensor) -> torch.Tensor:
    """``D_epi``: distance in pixels of each match ``x + flow12(x)`` to the line ``F x``.

    ``|l . x2| / (sqrt(l_0^2 + l_1^2) + 1e-6)`` with ``l = F x1`` (homogeneous pixels).
    Differentiable in ``flow12`` (and ``F``).

    Args:
        F: ``(N, 3, 3)`` with ``x2^T F x1 = 0``.
        flow12: ``(N, 2, H, W)``.

    Returns:
        ``(N, 1, H, W)``.
    """
    _check_flow(flow12)
    n, _, h, w = flow12.shape
    _check_F(F, n)
    grid = pixel_grid(h, w, flow12.dtype, flow12.device).reshape(1, 2, h * w)
    ones = torch.ones(1, 1, h * w, dtype=flow12.dtype, device=flow12.device)
    x1 = torch.cat((grid, ones), dim=1).expand(n, 3, h * w)
    x2 = torch.cat((grid + flow12.reshape(n, 2, h * w), ones.expand(n, 1, h * w)), dim=1)
    lines = F.to(flow12.dtype) @ x1  # (N, 3, HW)
    num = (lines * x2).sum(1).abs()
    den = torch.sqrt(lines[:, 0] ** 2 + lines[:, 1] ** 2) + LINE_EPS
    return (num / den).reshape(n, 1, h, w)


def _check_band(d_epi: torch.Tensor) -> None:
    if d_epi.dim() != 4 or d_epi.shape[1] != 1:
        raise InputError(f"d_epi: expected (N, 1, H, W), got {tuple(d_epi.shape)}")


def geometric_loss_per_image(d_epi: torch.Tensor, lo: float = 0.1, hi: float = 0.5) -> torch.Tensor:
    """Mean ``D_epi`` over the pixels with ``lo <= D_epi < hi``, per image ``(N,)``; 0 where none are.

    The band is a detached mask; the gradient goes through ``D_epi`` (to the flow).

    Args:
        d_epi: ``(N, 1, H, W)`` from :func:`epipolar_distance`.
        lo, hi: the band in pixels (the authors: inlier 0.1, rigid 0.5).
    """
    _check_band(d_epi)
    if not 0 <= lo < hi:
        raise InputError(f"geometric_loss: need 0 <= lo < hi, got lo={lo}, hi={hi}")
    band = ((d_epi >= lo) & (d_epi < hi)).to(d_epi.dtype).detach()
    count = band.sum(dim=(1, 2, 3))
    total = (d_epi * band).sum(dim=(1, 2, 3))
    return torch.where(count > 0, total / count.clamp(min=1.0), torch.zeros_like(total))


def geometric_loss(d_epi: torch.Tensor, lo: float = 0.1, hi: float = 0.5) -> torch.Tensor:
    """Scalar batch mean of :func:`geometric_loss_per_image`.

    Args:
        d_epi: ``(N, 1, H, W)``.
        lo, hi: the band in pixels.
    """
    return geometric_loss_per_image(d_epi, lo, hi).mean()


def rigid_mask(d_epi: torch.Tensor, thresh: float = 0.5) -> torch.Tensor:
    """The rigid score ``M_r = (D_epi < thresh) / (1 + D_epi)``, ``(N, 1, H, W)``, no gradient.

    Args:
        d_epi: ``(N, 1, H, W)``.
        thresh: pixels (the authors: 0.5; 1.0 on NYUv2).
    """
    _check_band(d_epi)
    d = d_epi.detach()
    return (d < thresh).to(d.dtype) / (1.0 + d)


def essential_candidates(E: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The four ``(R, t)`` of essential matrices, in the authors' order.

    With ``E = U S V^T`` and ``W = [[0,-1,0],[1,0,0],[0,0,1]]``: ``R_a = U W V^T``,
    ``R_b = U W^T V^T`` (each times the sign of its determinant), ``t = +-U[:, 2]``;
    candidates ``(R_a, t), (R_b, t), (R_a, -t), (R_b, -t)``.

    Args:
        E: ``(N, 3, 3)``.

    Returns:
        ``R`` ``(N, 4, 3, 3)``, ``t`` ``(N, 4, 3)`` unit vectors.
    """
    if E.dim() != 3 or E.shape[1:] != (3, 3):
        raise InputError(f"E: expected (N, 3, 3), got {tuple(E.shape)}")
    U, _, Vh = torch.linalg.svd(E)
    W = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=E.dtype, device=E.device)
    Ra = U @ W @ Vh
    Rb = U @ W.T @ Vh
    Ra = Ra * torch.sign(torch.linalg.det(Ra)).view(-1, 1, 1)
    Rb = Rb * torch.sign(torch.linalg.det(Rb)).view(-1, 1, 1)
    u3 = U[:, :, 2]
    return torch.stack((Ra, Rb, Ra, Rb), dim=1), torch.stack((u3, u3, -u3, -u3), dim=1)


def pose_from_fundamental(F: torch.Tensor, K: torch.Tensor, pts1: torch.Tensor, pts2: torch.Tensor
                          ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Relative pose from ``F`` and the intrinsics; cheirality on matches picks the candidate.

    ``E = K^T F K``; of :func:`essential_candidates` the one with most matches
    (mid-point triangulated) at positive depth in both cameras wins (first on ties). No
    gradient; computed in float64.

    Args:
        F: ``(N, 3, 3)`` fundamental matrices (``x2^T F x1 = 0``).
        K: ``(N, 3, 3)`` intrinsics of both images.
        pts1, pts2: ``(N, M, 2)`` matches used for the cheirality vote.

    Returns:
        ``R`` ``(N, 3, 3)``, ``t`` ``(N, 3)`` (``X2 = R X1 + t``, ``|t| = 1``), dtype of ``F``,
        and ``valid`` ``(N,)`` bool: False when ``F`` is zero or not finite or no match is
        in front of both cameras.
    """
    n = F.shape[0] if F.dim() == 3 else -1
    _check_F(F, n)
    if tuple(K.shape) != (n, 3, 3):
        raise InputError(f"K: expected ({n}, 3, 3), got {tuple(K.shape)}")
    if pts1.dim() != 3 or pts1.shape[0] != n or pts1.shape[-1] != 2 or pts1.shape != pts2.shape:
        raise InputError(f"pts1, pts2: expected two ({n}, M, 2) tensors, got {tuple(pts1.shape)} "
                         f"and {tuple(pts2.shape)}")
    with torch.no_grad():
        F64 = F.detach().double()
        K64 = K.detach().double()
        good = torch.isfinite(F64).all(dim=(1, 2)) & (F64.abs().amax(dim=(1, 2)) > 0)
        F64 = torch.where(good.view(-1, 1, 1), F64, torch.eye(3, dtype=F64.dtype, device=F64.device))
        E = K64.transpose(1, 2) @ F64 @ K64
        E = E / E.norm(dim=(1, 2), keepdim=True).clamp(min=1e-300)
        Rc, tc = essential_candidates(E)
        K_inv = torch.linalg.inv(K64)
        p1 = pts1.detach().double()
        p2 = pts2.detach().double()
        m = p1.shape[1]
        votes = []
        for c in range(4):
            X1, _ = midpoint_points(p1, p2, K_inv, Rc[:, c], tc[:, c])
            X2 = X1 @ Rc[:, c].transpose(1, 2) + tc[:, c].unsqueeze(1)
            front = (X1[..., 2] > 0) & (X2[..., 2] > 0) & torch.isfinite(X1).all(-1)
            votes.append(front.sum(1))
        votes = torch.stack(votes, dim=1)  # (N, 4)
        best = torch.argmax(votes, dim=1)
        R = Rc[torch.arange(n), best]
        t = tc[torch.arange(n), best]
        valid = good & (votes.amax(dim=1) > 0) & torch.isfinite(R).all(dim=(1, 2)) & torch.isfinite(t).all(1)
        if m == 0:
            valid = torch.zeros_like(valid)
    return R.to(F.dtype), t.to(F.dtype), valid
