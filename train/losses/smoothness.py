"""Edge-aware smoothness terms of TrianFlow: second order on flow, first order on disparity.

Both are averaged over the batch (the authors' training step takes the batch mean of every
term). Differences are forward differences between neighbours (``a[..., 1:] - a[..., :-1]``).
"""

from __future__ import annotations

import torch

from trianflow_vo.errors import InputError

FLOW_SCALE = 20.0  # the authors smooth flow / 20
MEAN_EPS = 1e-12


def _check(field: torch.Tensor, img: torch.Tensor, channels: int, name: str) -> None:
    if field.dim() != 4 or field.shape[1] != channels:
        raise InputError(f"{name}: expected (N, {channels}, H, W), got {tuple(field.shape)}")
    if img.dim() != 4 or img.shape[0] != field.shape[0] or img.shape[2:] != field.shape[2:]:
        raise InputError(f"img: expected (N, C, H, W) with N, H, W of {name} {tuple(field.shape)}, "
                         f"got {tuple(img.shape)}")
    if field.shape[2] < 3 or field.shape[3] < 3:
        raise InputError(f"{name}: needs at least 3x3 pixels, got {tuple(field.shape[2:])}")


def _dx(t: torch.Tensor) -> torch.Tensor:
    return t[..., :, 1:] - t[..., :, :-1]


def _dy(t: torch.Tensor) -> torch.Tensor:
    return t[..., 1:, :] - t[..., :-1, :]


def flow_smoothness_per_image(flow: torch.Tensor, img: torch.Tensor, alpha: float = 10.0) -> torch.Tensor:
    """The authors' second-order edge-aware flow smoothness of each image, ``(N,)``.

    On ``f = flow / 20``: ``(mean(w_x * |f_xx|) + mean(w_y * |f_yy|)) / 2`` with the pure
    second differences ``f_xx[j] = f[j+2] - 2 f[j+1] + f[j]`` (same along y; no mixed
    term), the means over both flow channels and all pixels, and the edge weights
    ``w_x[j] = exp(-alpha * mean_c |I[j+2] - I[j+1]|)`` (the image gradient one step to
    the right of where the second difference starts, as the authors index it).

    Args:
        flow: ``(N, 2, H, W)`` in pixels of this resolution.
        img: ``(N, C, H, W)`` the image the flow starts from, at the same resolution.
        alpha: edge sensitivity (the authors: 10).
    """
    _check(flow, img, 2, "flow")
    f = flow / FLOW_SCALE
    w_x = torch.exp(-alpha * _dx(img).abs().mean(dim=1, keepdim=True))[..., :, 1:]
    w_y = torch.exp(-alpha * _dy(img).abs().mean(dim=1, keepdim=True))[..., 1:, :]
    fxx = _dx(_dx(f))
    fyy = _dy(_dy(f))
    return ((w_x * fxx.abs()).mean(dim=(1, 2, 3)) + (w_y * fyy.abs()).mean(dim=(1, 2, 3))) / 2.0


def flow_smoothness(flow: torch.Tensor, img: torch.Tensor, alpha: float = 10.0) -> torch.Tensor:
    """Scalar :func:`flow_smoothness_per_image` averaged over the batch.

    Args:
        flow: ``(N, 2, H, W)`` in pixels of this resolution.
        img: ``(N, C, H, W)`` at the same resolution.
        alpha: edge sensitivity.
    """
    return flow_smoothness_per_image(flow, img, alpha).mean()


def depth_smoothness_per_image(disp: torch.Tensor, img: torch.Tensor) -> torch.Tensor:
    """The authors' first-order edge-aware disparity smoothness of each image, ``(N,)``.

    ``d = disp / (mean_{h,w} disp + 1e-12)`` (so invariant to the scale of ``disp``), then
    ``mean(|d_x| exp(-mean_c |I_x|)) + mean(|d_y| exp(-mean_c |I_y|))`` with forward
    differences (no factor 1/2).

    Args:
        disp: ``(N, 1, H, W)`` disparity (positive).
        img: ``(N, C, H, W)`` at the same resolution.
    """
    _check(disp, img, 1, "disp")
    d = disp / (disp.mean(dim=(2, 3), keepdim=True) + MEAN_EPS)
    w_x = torch.exp(-_dx(img).abs().mean(dim=1, keepdim=True))
    w_y = torch.exp(-_dy(img).abs().mean(dim=1, keepdim=True))
    return (_dx(d).abs() * w_x).mean(dim=(1, 2, 3)) + (_dy(d).abs() * w_y).mean(dim=(1, 2, 3))


def depth_smoothness(disp: torch.Tensor, img: torch.Tensor) -> torch.Tensor:
    """Scalar :func:`depth_smoothness_per_image` averaged over the batch.

    Args:
        disp: ``(N, 1, H, W)``.
        img: ``(N, C, H, W)`` at the same resolution.
    """
    return depth_smoothness_per_image(disp, img).mean()
