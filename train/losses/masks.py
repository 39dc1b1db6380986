"""Masks of TrianFlow's flow loss: forward-splat visibility, forward-backward consistency, score.

Naming: ``flow12`` maps pixels of image 1 into image 2 (``x -> x + flow12(x)``), ``flow21``
the reverse. Every mask here lives on the pixels of image 1:

* :func:`splat_visibility` ``(flow21)``: how much of image 2 lands on each image-1 pixel
  (clamped to [0, 1]); 0 = nothing lands there = occluded in image 2 (or out of view);
* :func:`fb_consistency` ``(flow12, flow21)``: 1 where going 1 -> 2 -> 1 returns close to
  the start;
* :func:`valid_mask` = visibility x consistency (the authors' ``img1_valid_mask``); for
  image 2 call it with the two flows swapped.

Masks carry no gradient (computed under ``torch.no_grad``), as the authors'.
Flows are ``(N, 2, H, W)`` in pixels of their resolution, channel 0 = x.
"""

from __future__ import annotations

import torch

from trianflow_vo.errors import InputError
from trianflow_vo.models.pwc import warp

NORM_EPS = 1e-12  # the authors add it to every flow norm before comparing


def _check_flow(flow: torch.Tensor, name: str) -> None:
    if flow.dim() != 4 or flow.shape[1] != 2:
        raise InputError(f"{name}: expected (N, 2, H, W), got {tuple(flow.shape)}")


def _check_flows(flow12: torch.Tensor, flow21: torch.Tensor) -> None:
    _check_flow(flow12, "flow12")
    _check_flow(flow21, "flow21")
    if flow12.shape != flow21.shape:
        raise InputError(f"flow12 {tuple(flow12.shape)} and flow21 {tuple(flow21.shape)} differ in shape")


def _norm(flow: torch.Tensor) -> torch.Tensor:
    """``(N, 1, H, W)`` L2 norm over the two channels, + 1e-12 (the authors' flow norm)."""
    return torch.linalg.vector_norm(flow, ord=2, dim=1, keepdim=True) + NORM_EPS


def splat_counts(flow21: torch.Tensor) -> torch.Tensor:
    """Unclamped forward splat: ``(N, 1, H, W)`` sum of the bilinear weights of every image-2
    pixel ``x`` moved to ``x + flow21(x)`` in image 1 (corners outside the image and
    non-finite flow vectors contribute nothing). No gradient.

    Args:
        flow21: ``(N, 2, H, W)``.
    """
    _check_flow(flow21, "flow21")
    n, _, h, w = flow21.shape
    with torch.no_grad():
        flow = flow21.detach()
        dtype = flow.dtype if flow.is_floating_point() else torch.float32
        flow = flow.to(dtype)
        xs = torch.arange(w, dtype=dtype, device=flow.device).view(1, 1, w)
        ys = torch.arange(h, dtype=dtype, device=flow.device).view(1, h, 1)
        x = xs + flow[:, 0]
        y = ys + flow[:, 1]
        finite = torch.isfinite(x) & torch.isfinite(y)
        # Clamping far-away targets keeps integer conversion safe and changes nothing:
        # every corner of a target beyond [-1, size] is outside the image anyway.
        x = torch.where(finite, x, torch.full_like(x, -2.0)).clamp(-2.0, w + 1.0)
        y = torch.where(finite, y, torch.full_like(y, -2.0)).clamp(-2.0, h + 1.0)
        x0 = torch.floor(x)
        y0 = torch.floor(y)
        fx = x - x0  # weight of the right column
        fy = y - y0  # weight of the lower row
        base = (torch.arange(n, device=flow.device) * (h * w)).view(n, 1, 1)
        out = torch.zeros(n * h * w, dtype=dtype, device=flow.device)
        for cx, cy, wgt in ((x0, y0, (1 - fx) * (1 - fy)), (x0, y0 + 1, (1 - fx) * fy),
                            (x0 + 1, y0, fx * (1 - fy)), (x0 + 1, y0 + 1, fx * fy)):
            inside = finite & (cx >= 0) & (cx <= w - 1) & (cy >= 0) & (cy <= h - 1)
            cxi = cx.clamp(0, w - 1).long()
            cyi = cy.clamp(0, h - 1).long()
            idx = (base + cyi * w + cxi).reshape(-1)
            out.scatter_add_(0, idx, torch.where(inside, wgt, torch.zeros_like(wgt)).reshape(-1))
        return out.view(n, 1, h, w)


def splat_visibility(flow21: torch.Tensor) -> torch.Tensor:
    """Forward-splat visibility of image-1 pixels: :func:`splat_counts` clamped to [0, 1].

    Every pixel of image 2 is moved along ``flow21`` into image 1 and spreads bilinear
    weights over its four neighbours (Wang et al. 2018, as the authors); image-1 pixels
    that receive nothing are not seen in image 2. No gradient.

    Args:
        flow21: ``(N, 2, H, W)`` flow from image 2 to image 1.

    Returns:
        ``(N, 1, H, W)`` in [0, 1].
    """
    return splat_counts(flow21).clamp_(0.0, 1.0)


def fb_difference(flow12: torch.Tensor, flow21: torch.Tensor) -> torch.Tensor:
    """Forward-backward difference on image-1 pixels: ``flow12(x) + flow21(x + flow12(x))``.

    ``flow21`` is sampled with :func:`trianflow_vo.models.pwc.warp` (bilinear,
    ``align_corners=True``, zeros outside, so where ``x + flow12`` leaves the image the
    difference is ``flow12`` itself). Signed (the authors keep its absolute value; take
    ``.abs()`` for that), differentiable.

    Args:
        flow12, flow21: ``(N, 2, H, W)``.

    Returns:
        ``(N, 2, H, W)``; zero for exactly inverse flows.
    """
    _check_flows(flow12, flow21)
    return flow12 + warp(flow21, flow12)


def fb_consistency(flow12: torch.Tensor, flow21: torch.Tensor, alpha: float = 0.05,
                   beta: float = 3.0) -> torch.Tensor:
    """Forward-backward consistency of image-1 pixels, float 0/1, no gradient.

    1 where ``|fb_difference| < max(alpha * |flow12|, beta)``: strict inequality, L2 norms
    per pixel (each + 1e-12, as the authors), ``|flow12|`` the norm of the forward flow at
    the pixel itself. (The authors' config calls the factor ``h_flow_consist_beta`` = 0.05
    and the floor ``h_flow_consist_alpha`` = 3.0; here ``alpha`` is the factor, ``beta``
    the floor in pixels.)

    Args:
        flow12, flow21: ``(N, 2, H, W)``.
        alpha: relative tolerance (fraction of the flow length).
        beta: absolute tolerance in pixels.

    Returns:
        ``(N, 1, H, W)`` of 0.0 / 1.0.
    """
    _check_flows(flow12, flow21)
    if alpha < 0 or beta < 0:
        raise InputError(f"fb_consistency: alpha and beta must be >= 0, got {alpha}, {beta}")
    with torch.no_grad():
        diff = fb_difference(flow12.detach(), flow21.detach())
        bound = torch.clamp(alpha * _norm(flow12.detach()), min=beta)
        return (_norm(diff) < bound).to(flow12.dtype)


def valid_mask(flow12: torch.Tensor, flow21: torch.Tensor, use_consistency: bool = True,
               alpha: float = 0.05, beta: float = 3.0) -> torch.Tensor:
    """Valid mask of image-1 pixels: ``splat_visibility(flow21) * fb_consistency(flow12, flow21)``
    (``use_consistency=False``, the authors' NYUv2 setting: visibility only). No gradient.

    Args:
        flow12, flow21: ``(N, 2, H, W)``.

    Returns:
        ``(N, 1, H, W)`` in [0, 1] (soft at splat borders).
    """
    _check_flows(flow12, flow21)
    vis = splat_visibility(flow21)
    if not use_consistency:
        return vis
    return vis * fb_consistency(flow12, flow21, alpha, beta)


def score_map(valid: torch.Tensor, fb_diff: torch.Tensor) -> torch.Tensor:
    """Match score of image-1 pixels: ``valid / (0.1 + mean over channels of |fb_diff|)``
    (the authors' weight for sampling matches for the fundamental matrix).

    Args:
        valid: ``(N, 1, H, W)``.
        fb_diff: ``(N, 2, H, W)`` from :func:`fb_difference` (signed or absolute).

    Returns:
        ``(N, 1, H, W)``, at most 10 * valid.
    """
    _check_flow(fb_diff, "fb_diff")
    n, _, h, w = fb_diff.shape
    if valid.dim() != 4 or tuple(valid.shape) != (n, 1, h, w):
        raise InputError(f"valid: expected ({n}, 1, {h}, {w}), got {tuple(valid.shape)}")
    return valid / (0.1 + fb_diff.abs().mean(dim=1, keepdim=True))
