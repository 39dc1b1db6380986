"""Photometric error of TrianFlow's flow loss: L1 mixed with an SSIM dissimilarity.

SSIM follows the authors' form: local statistics from a 3x3 average pool (stride 1,
zero padding of 1 pixel that counts in the average, so border windows see zeros),
``C1 = 0.01**2``, ``C2 = 0.03**2``, no Gaussian window. The dissimilarity is
``clamp((1 - SSIM) / 2, 0, 1)``.

:func:`photometric_loss` reproduces the authors' normalisation with a valid mask: both
images are multiplied by the mask *before* SSIM (so windows at the mask border compare
masked images), the per-image mean over all channels and pixels is divided by the mean
of the mask (+1e-12), and the batch is averaged.

Images are ``(N, C, H, W)`` float, nominally in [0, 1].
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from trianflow_vo.errors import InputError

SSIM_C1 = 0.01 ** 2
SSIM_C2 = 0.03 ** 2
MASK_EPS = 1e-12  # added to the mean of the mask, as the authors


def _check_pair(a: torch.Tensor, b: torch.Tensor, names: str) -> None:
    if a.dim() != 4 or a.shape != b.shape:
        raise InputError(f"{names}: expected two (N, C, H, W) tensors of one shape, "
                         f"got {tuple(a.shape)} and {tuple(b.shape)}")


def _check_mask(valid: torch.Tensor, img: torch.Tensor) -> None:
    n, _, h, w = img.shape
    if valid.dim() != 4 or tuple(valid.shape) != (n, 1, h, w):
        raise InputError(f"valid: expected ({n}, 1, {h}, {w}), got {tuple(valid.shape)}")


def _check_weight(w_ssim: float) -> None:
    if not 0.0 <= float(w_ssim) <= 1.0:
        raise InputError(f"w_ssim must be in [0, 1], got {w_ssim}")


def ssim_dissimilarity(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Per-pixel, per-channel ``clamp((1 - SSIM(x, y)) / 2, 0, 1)``.

    Args:
        x, y: ``(N, C, H, W)``.

    Returns:
        ``(N, C, H, W)`` in [0, 1]; 0 where the 3x3 neighbourhoods agree.
    """
    _check_pair(x, y, "ssim_dissimilarity(x, y)")

    def pool(t: torch.Tensor) -> torch.Tensor:
        return F.avg_pool2d(t, kernel_size=3, stride=1, padding=1, count_include_pad=True)

    mu_x = pool(x)
    mu_y = pool(y)
    var_x = pool(x * x) - mu_x * mu_x
    var_y = pool(y * y) - mu_y * mu_y
    cov_xy = pool(x * y) - mu_x * mu_y
    num = (2.0 * mu_x * mu_y + SSIM_C1) * (2.0 * cov_xy + SSIM_C2)
    den = (mu_x * mu_x + mu_y * mu_y + SSIM_C1) * (var_x + var_y + SSIM_C2)
    return torch.clamp((1.0 - num / den) / 2.0, 0.0, 1.0)


def photometric_map(img1: torch.Tensor, img2_warped: torch.Tensor, w_ssim: float = 0.85) -> torch.Tensor:
    """Per-pixel photometric error ``(1 - w) * |img1 - img2_warped| + w * SSIM-dissimilarity``,
    averaged over channels.

    Args:
        img1: ``(N, C, H, W)`` the reference image.
        img2_warped: ``(N, C, H, W)`` the other image sampled at ``x + flow12(x)``.
        w_ssim: share of the SSIM term, in [0, 1].

    Returns:
        ``(N, 1, H, W)``.
    """
    _check_pair(img1, img2_warped, "photometric_map(img1, img2_warped)")
    _check_weight(w_ssim)
    l1 = (img1 - img2_warped).abs()
    if w_ssim == 0.0:
        return l1.mean(dim=1, keepdim=True)
    err = (1.0 - w_ssim) * l1 + w_ssim * ssim_dissimilarity(img1, img2_warped)
    return err.mean(dim=1, keepdim=True)


def photometric_loss_per_image(img1: torch.Tensor, img2_warped: torch.Tensor, valid: torch.Tensor,
                               w_ssim: float = 0.85) -> torch.Tensor:
    """The authors' masked photometric loss of each image of the batch, ``(N,)``.

    ``mean_{c,h,w} photometric_map(img1 * valid, img2_warped * valid) / (mean_{h,w} valid + 1e-12)``.
    (``|a v - b v| = |a - b| v`` for ``v >= 0``, so the L1 part is the plain masked L1; the
    SSIM part compares the masked images.)

    Args:
        img1, img2_warped: ``(N, C, H, W)``.
        valid: ``(N, 1, H, W)`` in [0, 1] (soft masks allowed), no gradient expected.
        w_ssim: share of the SSIM term, in [0, 1].
    """
    _check_pair(img1, img2_warped, "photometric_loss(img1, img2_warped)")
    _check_mask(valid, img1)
    _check_weight(w_ssim)
    err = photometric_map(img1 * valid, img2_warped * valid, w_ssim)
    return err.mean(dim=(1, 2, 3)) / (valid.mean(dim=(1, 2, 3)) + MASK_EPS)


def photometric_loss(img1: torch.Tensor, img2_warped: torch.Tensor, valid: torch.Tensor,
                     w_ssim: float = 0.85) -> torch.Tensor:
    """Scalar masked photometric loss: :func:`photometric_loss_per_image` averaged over the batch
    (the authors' training step takes the batch mean of every loss term).

    Args:
        img1, img2_warped: ``(N, C, H, W)``.
        valid: ``(N, 1, H, W)`` in [0, 1].
        w_ssim: share of the SSIM term, in [0, 1].
    """
    return photometric_loss_per_image(img1, img2_warped, valid, w_ssim).mean()
