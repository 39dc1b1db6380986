"""TrianFlow's flow loss L_f over both directions and the first scales of the flow pyramid.

For each scale ``k < n_scales`` (output ``k`` of :meth:`PWCNet.multiscale`, at 1/2**k):

* both images are resized to the flow's size with ``adaptive_avg_pool2d`` (detached), as
  the authors build their image pyramid;
* valid masks of image 1 (``valid_mask(flow12, flow21)``) and image 2
  (``valid_mask(flow21, flow12)``) are computed at that scale, without gradient;
* photometric: :func:`photometric_loss` of image 1 against image 2 warped by ``flow12``
  plus that of image 2 against image 1 warped by ``flow21``;
* smoothness: :func:`flow_smoothness` of ``flow12`` (edges of image 1) plus that of
  ``flow21`` (edges of image 2).

The scales are summed with weight 1 each; every term is a batch mean. This equals the
authors' ``(1 - w_ssim) * loss_pixel + w_ssim * loss_ssim`` and ``loss_flow_smooth``
after their training step's batch mean. Their flow consistency term is switched off in
their code and is not computed here.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from trianflow_vo.errors import InputError
from trianflow_vo.models.pwc import warp
from trianflow_vo.train.losses.masks import fb_difference, score_map, valid_mask
from trianflow_vo.train.losses.photometric import photometric_loss
from trianflow_vo.train.losses.smoothness import flow_smoothness


@dataclass(frozen=True)
class FlowLossOutput:
    """Terms of L_f and the scale-0 masks for the geometric part.

    Attributes:
        photometric: scalar, both directions, summed over scales (already the
            ``(1 - w_ssim) * L1 + w_ssim * SSIM`` mix; no other weight applied).
        flow_smooth: scalar, both directions, summed over scales, **not** multiplied by
            ``w_flow_smooth``.
        valid12: ``(N, 1, H, W)`` valid mask of image-1 pixels (flow 1 -> 2), detached.
        valid21: ``(N, 1, H, W)`` valid mask of image-2 pixels (flow 2 -> 1), detached.
        fb_diff12: ``(N, 2, H, W)`` signed ``flow12 + flow21(x + flow12)`` on image 1, detached.
        fb_diff21: ``(N, 2, H, W)`` signed ``flow21 + flow12(x + flow21)`` on image 2, detached.
        score12: ``(N, 1, H, W)`` ``valid12 / (0.1 + mean_c |fb_diff12|)``, detached.
        score21: ``(N, 1, H, W)`` the same for image 2.
        total: scalar ``photometric + w_flow_smooth * flow_smooth`` (the weighted L_f, for
            callers that use it directly; the objective may recompute it from the terms).
    """

    photometric: torch.Tensor
    flow_smooth: torch.Tensor
    valid12: torch.Tensor
    valid21: torch.Tensor
    fb_diff12: torch.Tensor
    fb_diff21: torch.Tensor
    score12: torch.Tensor
    score21: torch.Tensor
    total: torch.Tensor


def _check_inputs(img1: torch.Tensor, img2: torch.Tensor, flows12: list, flows21: list, n_scales: int) -> None:
    if img1.dim() != 4 or img1.shape != img2.shape:
        raise InputError(f"img1, img2: expected two (N, C, H, W) tensors of one shape, "
                         f"got {tuple(img1.shape)} and {tuple(img2.shape)}")
    if int(n_scales) != n_scales or n_scales < 1:
        raise InputError(f"n_scales must be a positive integer, got {n_scales}")
    if len(flows12) < n_scales or len(flows21) < n_scales:
        raise InputError(f"n_scales={n_scales} but flows12 has {len(flows12)} scales and flows21 {len(flows21)}")
    n, _, h, w = img1.shape
    for k in range(n_scales):
        want = (n, 2, h // 2 ** k, w // 2 ** k)
        for name, flows in (("flows12", flows12), ("flows21", flows21)):
            got = tuple(flows[k].shape)
            if got != want:
                raise InputError(f"{name}[{k}]: expected {want} (scale 1/2**{k} of the images), got {got}")


def flow_loss(img1: torch.Tensor, img2: torch.Tensor, flows12: list[torch.Tensor], flows21: list[torch.Tensor],
              w_ssim: float = 0.85, w_flow_smooth: float = 10.0, use_consistency: bool = True,
              n_scales: int = 3) -> FlowLossOutput:
    """The authors' flow loss L_f of a batch of pairs.

    Args:
        img1, img2: ``(N, 3, H, W)`` float in [0, 1].
        flows12: flows 1 -> 2 from :meth:`PWCNet.multiscale`, finest first; entry ``k`` is
            ``(N, 2, H // 2**k, W // 2**k)`` in pixels of that resolution.
        flows21: flows 2 -> 1, the same layout.
        w_ssim: SSIM share of the photometric error.
        w_flow_smooth: weight of the smoothness in ``total`` only.
        use_consistency: valid mask = visibility x forward-backward consistency (True) or
            visibility only (the authors' NYUv2 setting).
        n_scales: how many of the finest scales enter the loss (the authors: 3).

    Returns:
        :class:`FlowLossOutput`; its masks are those of scale 0.
    """
    _check_inputs(img1, img2, flows12, flows21, n_scales)
    img1 = img1.detach()
    img2 = img2.detach()
    photometric = img1.new_zeros(())
    smooth = img1.new_zeros(())
    scale0 = None
    for k in range(n_scales):
        f12, f21 = flows12[k], flows21[k]
        size = tuple(f12.shape[2:])
        im1 = img1 if k == 0 else F.adaptive_avg_pool2d(img1, size)
        im2 = img2 if k == 0 else F.adaptive_avg_pool2d(img2, size)
        valid12 = valid_mask(f12, f21, use_consistency)
        valid21 = valid_mask(f21, f12, use_consistency)
        photometric = photometric + photometric_loss(im1, warp(im2, f12), valid12, w_ssim) \
            + photometric_loss(im2, warp(im1, f21), valid21, w_ssim)
        smooth = smooth + flow_smoothness(f12, im1) + flow_smoothness(f21, im2)
        if k == 0:
            scale0 = (valid12, valid21)
    valid12, valid21 = scale0
    with torch.no_grad():
        d12 = fb_difference(flows12[0].detach(), flows21[0].detach())
        d21 = fb_difference(flows21[0].detach(), flows12[0].detach())
        s12 = score_map(valid12, d12)
        s21 = score_map(valid21, d21)
    return FlowLossOutput(photometric=photometric, flow_smooth=smooth, valid12=valid12.detach(),
                          valid21=valid21.detach(), fb_diff12=d12, fb_diff21=d21, score12=s12, score21=s21,
                          total=photometric + w_flow_smooth * smooth)
