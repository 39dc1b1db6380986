"""Self-supervised flow losses: photometric (warping) error and flow smoothness."""

from __future__ import annotations

import torch

from trianflow_vo.models.pwc import warp


def inside_mask(flow: torch.Tensor) -> torch.Tensor:
    """``(N, 1, H, W)`` 1 where ``x + flow(x)`` lands inside the image, else 0."""
    _, _, h, w = flow.shape
    xs = torch.arange(w, dtype=flow.dtype, device=flow.device).view(1, 1, w) + flow[:, 0]
    ys = torch.arange(h, dtype=flow.dtype, device=flow.device).view(1, h, 1) + flow[:, 1]
    m = (xs >= 0) & (xs <= w - 1) & (ys >= 0) & (ys <= h - 1)
    return m.unsqueeze(1).to(flow.dtype)


def photometric_error(img1: torch.Tensor, img2: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """Mean absolute difference between ``img1`` and ``img2`` warped back by ``flow`` (1 -> 2).

    Args:
        img1, img2: ``(N, C, H, W)``.
        flow: ``(N, 2, H, W)`` in pixels of this resolution.

    Only pixels whose target lies inside ``img2`` count. Returns a scalar tensor.
    """
    if img1.shape != img2.shape or flow.shape[2:] != img1.shape[2:] or flow.shape[1] != 2:
        raise ValueError(f"shapes do not fit: img1 {tuple(img1.shape)}, img2 {tuple(img2.shape)}, "
                         f"flow {tuple(flow.shape)}")
    m = inside_mask(flow)
    diff = (warp(img2, flow) - img1).abs().mean(dim=1, keepdim=True)
    return (diff * m).sum() / m.sum().clamp(min=1.0)


def smoothness(flow: torch.Tensor) -> torch.Tensor:
    """First-order smoothness: mean absolute difference of neighbouring flow vectors."""
    return ((flow[..., 1:] - flow[..., :-1]).abs().mean()
            + (flow[..., 1:, :] - flow[..., :-1, :]).abs().mean())
