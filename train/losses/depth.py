"""TrianFlow's depth losses: predicted depth against triangulated matches, and its reprojection.

Monocular depth has no scale, and neither has the triangulation (``|t| = 1``), so each
frame's predicted depth ``D`` is first brought to the triangulation's scale
(:func:`align_scale`, no gradient): ``s = median(d) / median(z)`` over the valid matches
(``d`` = ``D`` sampled at the reprojected triangulated points, ``z`` = their triangulated
depth), ``d' = d / s``, then the least-squares factor ``a = sum(d'/z) / sum(d'^2/z^2)``
(the minimiser of ``sum (1 - a d'/z)^2``). The aligned depth is ``(a / s) * D``.

* :func:`triangulation_depth_loss` (the paper's L_d, weight ``w_pt_depth``): per frame,
  the mean of ``(1 - a d'/z)^2`` over the valid matches; frames 1 and 2 summed.
* :func:`projected_depth_loss` (``w_pj_depth``): every pixel of frame 1, lifted with its
  aligned depth and moved by ``(R, t)`` into frame 2, should have the aligned depth frame 2
  predicts there: ``mean(|1 - z2 / D2(uv2)| * r * m) / mean(r * m)``, ``r`` the rigid score,
  ``m`` the authors' validity weight (their score map) times "lands inside image 2".
* :func:`flow_error_loss` (``w_flow_error``): the flow pulled towards that rigid flow:
  ``mean(r * |x + flow12 - uv2|) / mean(r)``, ``uv2`` detached.

Depth maps are sampled bilinearly with ``align_corners=True`` (pixel ``u`` at
``2u / (W - 1) - 1``) and reflection padding, as the authors. Every loss is per item,
``(N,)``; the caller averages over the batch.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from trianflow_vo.errors import InputError
from trianflow_vo.train.losses.triangulation import Triangulation, pixel_grid

EPS = 1e-12  # the authors' guard in every division here


def _check_map(x: torch.Tensor, name: str, channels: int = 1) -> None:
    if x.dim() != 4 or x.shape[1] != channels:
        raise InputError(f"{name}: expected (N, {channels}, H, W), got {tuple(x.shape)}")


def _normalised(uv: torch.Tensor, h: int, w: int) -> torch.Tensor:
    return torch.stack((2.0 * uv[..., 0] / (w - 1.0) - 1.0, 2.0 * uv[..., 1] / (h - 1.0) - 1.0), dim=-1)


def sample_depth(depth: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """``depth`` ``(N, 1, H, W)`` at pixels ``uv`` ``(N, M, 2)`` -> ``(N, M)``.

    Bilinear, ``align_corners=True``, reflection padding; differentiable in both.
    """
    _check_map(depth, "depth")
    n, _, h, w = depth.shape
    if uv.dim() != 3 or uv.shape[0] != n or uv.shape[-1] != 2:
        raise InputError(f"uv: expected ({n}, M, 2), got {tuple(uv.shape)}")
    grid = _normalised(uv, h, w).unsqueeze(2)  # (N, M, 1, 2)
    out = F.grid_sample(depth, grid.to(depth.dtype), mode="bilinear", padding_mode="reflection",
                        align_corners=True)
    return out[:, 0, :, 0]


def _masked_median(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Lower median of ``x`` ``(N, M)`` over ``valid`` per row (torch.median's convention)."""
    return torch.nanmedian(torch.where(valid, x, torch.full_like(x, float("nan"))), dim=1).values


def align_scale(d: torch.Tensor, z: torch.Tensor, valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The authors' two-step scale of predicted to triangulated depth. No gradient.

    ``s = median(d) / (median(z) + 1e-12)``, ``d' = d / (s + 1e-12)``,
    ``a = sum(d'/(z + 1e-12)) / (sum(d'^2/(z^2 + 1e-12)) + 1e-12)``, over ``valid``.

    Args:
        d: ``(N, M)`` predicted depth at the matches.
        z: ``(N, M)`` triangulated depth.
        valid: ``(N, M)`` bool; rows without a valid match get ``s = a = 1``.

    Returns:
        ``s`` ``(N,)``, ``a`` ``(N,)``; the aligned prediction is ``a * d / s``.
    """
    if d.dim() != 2 or d.shape != z.shape or valid.shape != d.shape:
        raise InputError(f"d, z, valid: expected three (N, M) tensors, got {tuple(d.shape)}, "
                         f"{tuple(z.shape)}, {tuple(valid.shape)}")
    with torch.no_grad():
        d = d.detach()
        z = z.detach()
        any_ = valid.any(dim=1)
        s = _masked_median(d, valid) / (_masked_median(z, valid) + EPS)
        s = torch.where(any_ & torch.isfinite(s), s, torch.ones_like(s))
        dp = d / (s.unsqueeze(1) + EPS)
        vf = valid.to(d.dtype)
        zs = torch.where(valid, z, torch.ones_like(z))
        dps = torch.where(valid, dp, torch.zeros_like(dp))
        A = (vf * dps ** 2 / (zs ** 2 + EPS)).sum(1)
        C = (vf * dps / (zs + EPS)).sum(1)
        a = C / (A + EPS)
        a = torch.where(any_ & torch.isfinite(a), a, torch.ones_like(a))
    return s, a


def _frame_loss(depth: torch.Tensor, uv: torch.Tensor, z: torch.Tensor, valid: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
    d = sample_depth(depth, uv)
    s, a = align_scale(d, z, valid)
    factor = a / (s + EPS)
    zs = torch.where(valid, z, torch.ones_like(z))
    err = (1.0 - factor.unsqueeze(1) * d / (zs + EPS)) ** 2
    err = torch.where(valid, err, torch.zeros_like(err))
    count = valid.sum(1).clamp(min=1).to(err.dtype)
    return err.sum(1) / count, factor


def triangulation_depth_loss(depth1: torch.Tensor, depth2: torch.Tensor, tri: Triangulation
                             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """L_d: each frame's aligned depth against the triangulated depth, both frames summed.

    Frame ``k``: ``d`` = ``depth_k`` sampled at ``tri.uv_k``, :func:`align_scale` against
    ``tri.z_k``, loss ``mean((1 - a d / (s z))^2)`` over ``tri.valid``. Differentiable in the
    depths and (through ``uv`` and ``z``) in the matches; ``s``, ``a`` are not.

    Args:
        depth1, depth2: ``(N, 1, H, W)`` predicted depth of frames 1 and 2.
        tri: :class:`Triangulation` of ``N`` items.

    Returns:
        ``loss`` ``(N,)``, ``scale1`` ``(N,)`` and ``scale2`` ``(N,)`` (``a / s`` of each frame,
        no gradient: ``scale_k * depth_k`` is frame k's depth at the triangulation's scale).
    """
    _check_map(depth1, "depth1")
    _check_map(depth2, "depth2")
    if depth1.shape != depth2.shape:
        raise InputError(f"depth1 {tuple(depth1.shape)} and depth2 {tuple(depth2.shape)} differ")
    if tri.z1.dim() != 2 or tri.z1.shape[0] != depth1.shape[0]:
        raise InputError(f"tri: expected {depth1.shape[0]} items, got z1 {tuple(tri.z1.shape)}")
    l1, f1 = _frame_loss(depth1, tri.uv1, tri.z1, tri.valid)
    l2, f2 = _frame_loss(depth2, tri.uv2, tri.z2, tri.valid)
    return l1 + l2, f1, f2


def _check_pose(K: torch.Tensor, K_inv: torch.Tensor, R: torch.Tensor, t: torch.Tensor, n: int) -> None:
    for name, x, want in (("K", K, (n, 3, 3)), ("K_inv", K_inv, (n, 3, 3)), ("R", R, (n, 3, 3)), ("t", t, (n, 3))):
        if tuple(x.shape) != want:
            raise InputError(f"{name}: expected {want}, got {tuple(x.shape)}")


def rigid_projection(depth1: torch.Tensor, K: torch.Tensor, K_inv: torch.Tensor, R: torch.Tensor,
                     t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every pixel of frame 1 lifted with ``depth1`` and moved into frame 2 (``X2 = R X1 + t``).

    Args:
        depth1: ``(N, 1, H, W)``; K, K_inv, R ``(N, 3, 3)``; t ``(N, 3)``.

    Returns:
        ``uv2`` ``(N, 2, H, W)`` pixel in image 2, ``z2`` ``(N, 1, H, W)`` depth in camera 2
        (both differentiable), ``inside`` ``(N, 1, H, W)`` float 0/1: ``0 < uv2 < (W-1, H-1)``.
    """
    _check_map(depth1, "depth1")
    n, _, h, w = depth1.shape
    _check_pose(K, K_inv, R, t, n)
    grid = pixel_grid(h, w, depth1.dtype, depth1.device).reshape(1, 2, h * w)
    x1 = torch.cat((grid, torch.ones_like(grid[:, :1])), dim=1)  # (1, 3, HW)
    X1 = (K_inv @ x1) * depth1.reshape(n, 1, h * w)
    x2 = K @ (R @ X1 + t.unsqueeze(-1))  # (N, 3, HW)
    z2 = x2[:, 2:3]
    uv2 = x2[:, :2] / (z2 + EPS)
    with torch.no_grad():
        lim = torch.tensor([w - 1.0, h - 1.0], dtype=uv2.dtype, device=uv2.device).view(1, 2, 1)
        inside = ((uv2 > 0) & (uv2 < lim)).all(dim=1, keepdim=True).to(depth1.dtype)
    return uv2.reshape(n, 2, h, w), z2.reshape(n, 1, h, w), inside.reshape(n, 1, h, w)


def projected_depth_loss(depth1: torch.Tensor, depth2: torch.Tensor, K: torch.Tensor, K_inv: torch.Tensor,
                         R: torch.Tensor, t: torch.Tensor, rigid: torch.Tensor, weight: torch.Tensor
                         ) -> torch.Tensor:
    """The authors' projected-depth loss of frame 2, per item ``(N,)``.

    ``mean(|1 - z2 / (D2(uv2) + 1e-12)| * r * m) / (mean(r * m) + 1e-12)`` with ``(uv2, z2)``
    from :func:`rigid_projection` of ``depth1``, ``D2(uv2)`` = ``depth2`` sampled there,
    ``r = rigid`` and ``m = weight * inside`` (both detached). 0 when ``depth2`` is what
    ``depth1`` and ``(R, t)`` predict.

    Args:
        depth1, depth2: ``(N, 1, H, W)`` aligned depths (the triangulation's scale).
        K, K_inv, R: ``(N, 3, 3)``; t: ``(N, 3)``.
        rigid: ``(N, 1, H, W)`` rigid score of frame-1 pixels.
        weight: ``(N, 1, H, W)`` validity weight of frame-1 pixels (the authors pass their
            score map ``valid / (0.1 + |fb|)`` here).
    """
    _check_map(depth2, "depth2")
    uv2, z2, inside = rigid_projection(depth1, K, K_inv, R, t)
    n, _, h, w = depth1.shape
    for name, x in (("depth2", depth2), ("rigid", rigid), ("weight", weight)):
        if tuple(x.shape) != (n, 1, h, w):
            raise InputError(f"{name}: expected ({n}, 1, {h}, {w}), got {tuple(x.shape)}")
    d2 = sample_depth(depth2, uv2.reshape(n, 2, h * w).transpose(1, 2)).reshape(n, 1, h, w)
    m = (weight * inside).detach()
    r = rigid.detach()
    err = (1.0 - z2 / (d2 + EPS)).abs() * r * m
    return err.mean(dim=(1, 2, 3)) / ((r * m).mean(dim=(1, 2, 3)) + EPS)


def flow_error_loss(flow12: torch.Tensor, depth1: torch.Tensor, K: torch.Tensor, K_inv: torch.Tensor,
                    R: torch.Tensor, t: torch.Tensor, rigid: torch.Tensor) -> torch.Tensor:
    """The flow pulled towards the rigid flow of the aligned depth, per item ``(N,)``.

    ``mean_{c,h,w}(r * |x + flow12 - uv2|) / (mean(r) + 1e-12)``, ``uv2`` from
    :func:`rigid_projection` of ``depth1`` (detached), ``r = rigid`` (detached). Only the
    flow gets a gradient; 0 when ``flow12`` is the rigid flow.

    Args:
        flow12: ``(N, 2, H, W)``.
        depth1: ``(N, 1, H, W)`` aligned depth of frame 1.
        K, K_inv, R: ``(N, 3, 3)``; t: ``(N, 3)``.
        rigid: ``(N, 1, H, W)``.
    """
    _check_map(flow12, "flow12", 2)
    n, _, h, w = flow12.shape
    if tuple(depth1.shape) != (n, 1, h, w) or tuple(rigid.shape) != (n, 1, h, w):
        raise InputError(f"depth1, rigid: expected ({n}, 1, {h}, {w}), got {tuple(depth1.shape)}, "
                         f"{tuple(rigid.shape)}")
    with torch.no_grad():
        uv2, _, _ = rigid_projection(depth1.detach(), K, K_inv, R, t)
    grid = pixel_grid(h, w, flow12.dtype, flow12.device).unsqueeze(0)
    r = rigid.detach()
    err = r * (flow12 + grid - uv2.to(flow12.dtype)).abs()
    return err.mean(dim=(1, 2, 3)) / (r.mean(dim=(1, 2, 3)) + EPS)
