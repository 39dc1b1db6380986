"""The training objective of each TrianFlow stage: which losses, with which weights, on which nets.

Stages (the authors' modes ``flow``, ``depth``, ``depth_pose``):

* ``flow``: the flow net alone, ``L_f`` = photometric (L1/SSIM mix, both directions,
  3 scales) + ``w_flow_smooth`` * second-order smoothness (:mod:`.losses.flow`).
* ``depth``: the flow is frozen (the flow net runs without gradient, or precomputed
  flows are given, e.g. DIS); from it: valid mask, score, ``F`` (RANSAC), ``D_epi``, rigid
  score, pose, triangulated matches; the depth net is trained with ``w_pt_depth * L_d +
  w_pj_depth * projected + w_flow_error * flow error + w_depth_smooth * smoothness``.
  ``w_geo * geo`` is evaluated too (as the authors' total has it) but cannot train
  anything here: the flow is constant.
* ``joint``: both nets; ``L_f + w_geo * geo`` + the depth terms, with gradients reaching
  the flow through ``D_epi``, the triangulated matches and the flow error. On KITTI
  (``kitti_3stage``) the depth weights are 0: the flow net is refined by the geometric
  terms and the depth net only provides the rigid flow of the flow error.

When the pose or the triangulation of an item fails (no ``F``, no valid pose, the
triangulation's flags), the depth terms (``pt_depth``, ``pj_depth``, ``flow_error``,
``depth_smooth``) are zeroed rather than skipped, as the authors do. With
``depth_failure="batch"`` (the default, the authors' rule: their filters flag the whole
batch) one failing item zeroes the depth terms of the whole batch; with ``"item"`` (our
option) only the failing items' terms are zero and they still count in the batch mean.
Every term is a batch mean; ``total`` is the weighted sum (terms of weight 0 are reported
but not added). ``total`` always depends on the outputs of the nets
that ran with gradient (times 0 where nothing else does), so ``backward`` works and every
trained parameter gets a (possibly zero) gradient even when all depth terms are zeroed.

The geometry is the authors' KITTI path for every preset (RANSAC ``F``, rigid threshold
0.5 px, cheirality vote). Their NYUv2 path differs (LMedS ``F``, ``cv2.recoverPose`` with
an inlier-count flag, rigid threshold 1.0 px) and is not reproduced here; only its
visibility-only valid mask is (``fb_consistency=False``).

Images are ``(N, 3, H, W)`` BGR in [0, 1] (the flow net's input); the depth net gets
``(img - 0.45) / 0.225`` (:data:`trianflow_vo.models.checkpoint.DEPTH_NORM`).

Mixed precision: called under ``torch.autocast`` (CUDA AMP), only the networks' forward
passes run in half precision; their outputs are cast back to the images' dtype and the
masks, ``F``, ``D_epi`` (a 0.1-0.5 px band), triangulation and losses run with autocast off
(float16 resolves 0.5 px at x = 832).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields

import torch

from trianflow_vo.errors import ConfigError, InputError

STAGES = ("flow", "depth", "joint")
N_SCALES = 3  # scales of L_f (the authors' num_scales)
TOP_RATIO = 0.2  # share of the pixels matches are drawn from (F and depth)
N_MATCHES = 6000  # matches drawn for the RANSAC and for the triangulation
INLIER_PX = 0.1  # D_epi below this: inlier (lower edge of the geometric band)
RIGID_PX = 0.5  # D_epi below this: rigid (upper edge of the band)
FLOW_TERMS = ("photometric", "flow_smooth")
DEPTH_TERMS = ("pt_depth", "pj_depth", "flow_error", "depth_smooth")
DEPTH_FAILURE_MODES = ("batch", "item")  # what a failed pose/triangulation zeroes: the batch (authors) or the item
STAGE_TERMS = {"flow": FLOW_TERMS, "depth": ("geo", *DEPTH_TERMS), "joint": (*FLOW_TERMS, "geo", *DEPTH_TERMS)}


@dataclass(frozen=True)
class LossWeights:
    """Loss weights of a stage (the authors' names) and the valid-mask variant.

    ``w_ssim`` is the SSIM share of the photometric mix (L1 gets ``1 - w_ssim``);
    ``w_flow_consis`` is in the authors' configs but their term is switched off (kept for
    the record, no effect). ``fb_consistency`` False: the valid mask is visibility only
    (the authors' NYUv2 setting). ``depth_failure``: ``"batch"`` (the authors: an item whose
    pose or triangulation fails zeroes the depth terms of the whole batch) or ``"item"``
    (ours: only that item's).
    """

    w_ssim: float = 0.85
    w_flow_smooth: float = 10.0
    w_flow_consis: float = 0.01
    w_geo: float = 1.0
    w_pt_depth: float = 1.0
    w_pj_depth: float = 0.1
    w_flow_error: float = 0.0
    w_depth_smooth: float = 1e-3
    fb_consistency: bool = True
    depth_failure: str = "batch"

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "fb_consistency":
                if not isinstance(v, bool):
                    raise ConfigError(f"must be true or false, got {v!r}", source="loss weights", key=f.name)
                continue
            if f.name == "depth_failure":
                if v not in DEPTH_FAILURE_MODES:
                    raise ConfigError(f"must be one of {', '.join(DEPTH_FAILURE_MODES)}, got {v!r}",
                                      source="loss weights", key=f.name)
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ConfigError(f"must be a finite number >= 0, got {v!r}", source="loss weights", key=f.name)
            object.__setattr__(self, f.name, float(v))
        if self.w_ssim > 1:
            raise ConfigError(f"must be in [0, 1], got {self.w_ssim}", source="loss weights", key="w_ssim")

    @classmethod
    def from_dict(cls, d: dict, source: str = "loss weights") -> "LossWeights":
        """From ``{name: value}``; missing names keep their defaults.

        Raises ConfigError on an unknown name or a bad value.
        """
        if not isinstance(d, dict):
            raise ConfigError(f"expected a mapping of weights, got {type(d).__name__}", source=source, key="losses")
        known = [f.name for f in fields(cls)]
        for k in d:
            if k not in known:
                raise ConfigError(f"unknown loss weight; valid: {', '.join(known)}", source=source, key=str(k))
        try:
            return cls(**d)
        except ConfigError as e:
            raise ConfigError(e.message, source=source, key=e.key) from None

    def to_dict(self) -> dict:
        """``{name: value}`` of every field (``from_dict(to_dict())`` is the identity)."""
        return asdict(self)


# The authors' configs: kitti / odo (their stages 1 and 2 share one file), kitti_3stage /
# odo_3stage (stage 3), nyu / nyu_3stage. w_ssim 0.85, w_flow_smooth 10 and w_flow_consis
# 0.01 everywhere.
_KITTI_12 = dict(w_geo=1.0, w_pt_depth=1.0, w_pj_depth=0.1, w_flow_error=0.0, w_depth_smooth=1e-3)
_ODO_12 = dict(w_geo=0.1, w_pt_depth=1.0, w_pj_depth=0.1, w_flow_error=0.0, w_depth_smooth=1e-4)
_KITTI_3 = dict(w_geo=0.002, w_pt_depth=0.0, w_pj_depth=0.0, w_flow_error=0.01, w_depth_smooth=0.0)
_NYU_12 = dict(w_geo=0.0, w_pt_depth=1.0, w_pj_depth=0.1, w_flow_error=0.0, w_depth_smooth=1e-4,
               fb_consistency=False)
_NYU_3 = dict(w_geo=0.1, w_pt_depth=0.1, w_pj_depth=0.01, w_flow_error=0.0, w_depth_smooth=1e-4,
              fb_consistency=False)

PRESETS: dict[str, dict[str, LossWeights]] = {
    name: {"flow": LossWeights(**s12), "depth": LossWeights(**s12), "joint": LossWeights(**s3)}
    for name, (s12, s3) in {"kitti": (_KITTI_12, _KITTI_3), "kitti_odometry": (_ODO_12, _KITTI_3),
                            "nyu": (_NYU_12, _NYU_3)}.items()
}


@dataclass
class StepOutput:
    """The losses of one batch.

    Attributes:
        total: scalar tensor, the weighted sum (with gradient unless run under no_grad).
        terms: every weighted term of the stage by name (:data:`STAGE_TERMS`), plus
            ``"total"``; floats.
        depth_failed: batch items whose pose or triangulation failed.
        depth_zeroed: True when depth terms of this batch were zeroed because of such a
            failure (``depth_failure="batch"``: all of them; ``"item"``: the failed items').
        visuals: detached tensors of the first item: ``"flow12"`` ``(2, H, W)``,
            ``"valid12"`` ``(1, H, W)``, ``"rigid12"`` ``(1, H, W)`` (stages with geometry),
            ``"disp1"`` ``(1, H, W)`` sigmoid disparity (when a depth net ran).
    """

    total: torch.Tensor
    terms: dict[str, float]
    depth_failed: int = 0
    depth_zeroed: bool = False
    visuals: dict[str, torch.Tensor] = field(default_factory=dict)


def _check_inputs(img1, img2, K, K_inv, weights) -> None:
    if not isinstance(weights, LossWeights):
        raise InputError(f"weights: expected LossWeights, got {type(weights).__name__}")
    if not (torch.is_tensor(img1) and torch.is_tensor(img2)) or img1.dim() != 4 or img1.shape[1] != 3 \
            or img1.shape != img2.shape:
        raise InputError(f"img1, img2: expected two (N, 3, H, W) tensors of one shape, got "
                         f"{tuple(getattr(img1, 'shape', ()))} and {tuple(getattr(img2, 'shape', ()))}")
    if not img1.is_floating_point():
        raise InputError(f"img1, img2: expected float images in [0, 1], got {img1.dtype}")
    n = img1.shape[0]
    for name, x in (("K", K), ("K_inv", K_inv)):
        if not torch.is_tensor(x) or tuple(x.shape) != (n, 3, 3):
            raise InputError(f"{name}: expected ({n}, 3, 3), got {tuple(getattr(x, 'shape', ()))}")


def _net_autocast(amp: tuple[str, bool, torch.dtype]):
    """The caller's autocast (mixed precision) for a network's forward pass."""
    device_type, enabled, dtype = amp
    return torch.autocast(device_type, dtype=dtype, enabled=enabled)


def _flow_pyramids(flow_net, img1: torch.Tensor, img2: torch.Tensor, amp):
    """Both directions' multiscale flows (the authors' 4 outputs), the pyramid run once; in the
    images' dtype whatever the autocast."""
    n, _, h, w = img1.shape
    flow_net.check_size(h, w)
    with _net_autocast(amp):
        feats = flow_net.pyramid(torch.cat((img1, img2), dim=0))
        swapped = [torch.cat((f[n:], f[:n]), dim=0) for f in feats]
        outs = flow_net.multiscale(flow_net.decode(feats, swapped), (h, w))
    outs = [f.to(img1.dtype) for f in outs]
    return [f[:n] for f in outs], [f[n:] for f in outs]


def _run_depth(depth_net, img1: torch.Tensor, img2: torch.Tensor, amp):
    from trianflow_vo.models.checkpoint import DEPTH_NORM
    from trianflow_vo.models.depth_net import disp_to_depth

    n = img1.shape[0]
    mean = torch.tensor(DEPTH_NORM["mean"], dtype=img1.dtype, device=img1.device).view(1, 3, 1, 1)
    std = torch.tensor(DEPTH_NORM["std"], dtype=img1.dtype, device=img1.device).view(1, 3, 1, 1)
    with _net_autocast(amp):
        sigma = depth_net((torch.cat((img1, img2), dim=0) - mean) / std)[0]
    sigma = sigma.to(img1.dtype)
    cfg = depth_net.config
    depth = disp_to_depth(sigma, cfg.min_depth, cfg.max_depth)
    return sigma[:n], sigma[n:], depth[:n], depth[n:]


def _scatter(n: int, idx: torch.Tensor, values: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    out = torch.zeros(n, dtype=values.dtype, device=like.device)
    return out.index_put((idx,), values) if idx.numel() else out


def _depth_terms(img1, img2, flow12, score12, rigid12, F, F_ok, K, K_inv, sigma1, sigma2, depth1, depth2,
                 generator):
    """Per-item depth terms ``{name: (N,)}`` (unweighted, zero for failed items) and the ok mask."""
    from trianflow_vo.train.losses.depth import flow_error_loss, projected_depth_loss, triangulation_depth_loss
    from trianflow_vo.train.losses.epipolar import pose_from_fundamental
    from trianflow_vo.train.losses.smoothness import depth_smoothness_per_image
    from trianflow_vo.train.losses.triangulation import sample_matches, triangulate_matches

    n, _, h, w = flow12.shape
    weight = (rigid12 * score12).detach()
    pts1, pts2, ok_s = sample_matches(flow12, weight, TOP_RATIO, N_MATCHES, generator)
    R, t, ok_p = pose_from_fundamental(F, K, pts1, pts2)
    tri = triangulate_matches(pts1, pts2, K_inv, R.to(flow12.dtype), t.to(flow12.dtype), size=(h, w))
    ok = F_ok & ok_s & ok_p & tri.ok
    idx = torch.nonzero(ok).flatten()
    zeros = {k: torch.zeros(n, dtype=depth1.dtype, device=depth1.device) for k in DEPTH_TERMS}
    if idx.numel() == 0:
        return zeros, ok
    sub = tri.select(idx)
    d1, d2 = depth1[idx], depth2[idx]
    Ks, Kis, Rs, ts = K[idx].to(d1.dtype), K_inv[idx].to(d1.dtype), R[idx].to(d1.dtype), t[idx].to(d1.dtype)
    pt, scale1, scale2 = triangulation_depth_loss(d1, d2, sub)
    a1 = scale1.view(-1, 1, 1, 1) * d1
    a2 = scale2.view(-1, 1, 1, 1) * d2
    pj = projected_depth_loss(a1, a2, Ks, Kis, Rs, ts, rigid12[idx], score12[idx])
    fe = flow_error_loss(flow12[idx], a1, Ks, Kis, Rs, ts, rigid12[idx])
    sm = depth_smoothness_per_image(sigma1[idx], img1[idx]) + depth_smoothness_per_image(sigma2[idx], img2[idx])
    out = {"pt_depth": pt, "pj_depth": pj, "flow_error": fe, "depth_smooth": sm}
    return {k: _scatter(n, idx, v.to(depth1.dtype), depth1) for k, v in out.items()}, ok


def compute_losses(stage: str, img1: torch.Tensor, img2: torch.Tensor, K: torch.Tensor, K_inv: torch.Tensor,
                   weights: LossWeights, *, flow_net=None, depth_net=None,
                   flows: tuple[torch.Tensor, torch.Tensor] | None = None,
                   generator: torch.Generator | None = None) -> StepOutput:
    """The losses of one batch of pairs for ``stage``.

    Args:
        stage: ``"flow"``, ``"depth"`` or ``"joint"``.
        img1, img2: ``(N, 3, H, W)`` BGR in [0, 1]; ``H, W`` multiples of 64 with a flow net.
        K, K_inv: ``(N, 3, 3)`` intrinsics at the image size and their inverse.
        weights: :class:`LossWeights` of the stage (e.g. ``PRESETS["kitti"]["depth"]``).
        flow_net: :class:`trianflow_vo.models.pwc.PWCNet`; needed by ``flow`` and ``joint``,
            and by ``depth`` unless ``flows`` is given (it then runs without gradient).
        depth_net: :class:`trianflow_vo.models.depth_net.DepthNet`; needed by ``depth`` and ``joint``.
        flows: stage ``depth`` only: precomputed full-resolution ``(flow12, flow21)``, each
            ``(N, 2, H, W)`` (masks then come from them, one scale).
        generator: torch generator of the match draws (deterministic with a seeded one).

    Returns:
        :class:`StepOutput`.

    Raises:
        ValueError on an unknown stage or missing/extra networks; InputError on bad tensors.
    """
    if stage not in STAGES:
        raise ValueError(f"unknown stage {stage!r}; valid: {', '.join(STAGES)}")
    _check_inputs(img1, img2, K, K_inv, weights)
    if stage in ("flow", "joint") and flow_net is None:
        raise ValueError(f"stage {stage!r} needs flow_net")
    if stage in ("flow", "joint") and flows is not None:
        raise ValueError(f"stage {stage!r} trains the flow net: flows must not be given")
    if stage in ("depth", "joint") and depth_net is None:
        raise ValueError(f"stage {stage!r} needs depth_net")
    if stage == "depth" and flow_net is None and flows is None:
        raise ValueError("stage 'depth' needs flow_net or flows=(flow12, flow21)")

    # Mixed precision (CUDA AMP) is for the networks only: pixel coordinates, F, D_epi (0.1 px band),
    # triangulation and the losses run in the images' dtype (float16 resolves 0.5 px at x = 832).
    dev = img1.device.type
    amp = (dev, torch.is_autocast_enabled(dev), torch.get_autocast_dtype(dev))
    with torch.autocast(dev, enabled=False):
        return _compute_losses(stage, img1, img2, K, K_inv, weights, flow_net, depth_net, flows, generator, amp)


def _compute_losses(stage, img1, img2, K, K_inv, weights, flow_net, depth_net, flows, generator, amp) -> StepOutput:
    from trianflow_vo.train.losses.epipolar import (epipolar_distance, fundamental_from_flow,
                                                    geometric_loss_per_image, rigid_mask)
    from trianflow_vo.train.losses.flow import flow_loss
    from trianflow_vo.train.losses.masks import fb_difference, score_map, valid_mask

    n, _, h, w = img1.shape
    wt = weights
    terms: dict[str, torch.Tensor] = {}
    visuals: dict[str, torch.Tensor] = {}
    anchor = img1.new_zeros(())  # keeps every trained net in the graph (zero-weight / zeroed terms)

    # -- flow ---------------------------------------------------------------------------------
    if stage in ("flow", "joint"):
        flows12, flows21 = _flow_pyramids(flow_net, img1, img2, amp)
        fl = flow_loss(img1, img2, flows12, flows21, w_ssim=wt.w_ssim, w_flow_smooth=wt.w_flow_smooth,
                       use_consistency=wt.fb_consistency, n_scales=N_SCALES)
        terms["photometric"] = fl.photometric
        terms["flow_smooth"] = wt.w_flow_smooth * fl.flow_smooth
        flow12, valid12, score12 = flows12[0], fl.valid12, fl.score12
        anchor = anchor + 0.0 * (flows12[0].mean() + flows21[0].mean())
    else:
        with torch.no_grad():
            if flows is not None:
                if len(flows) != 2:
                    raise InputError("flows: expected a pair (flow12, flow21)")
                flow12, flow21 = (f.detach().to(img1.dtype) for f in flows)
                for name, f in (("flow12", flow12), ("flow21", flow21)):
                    if tuple(f.shape) != (n, 2, h, w):
                        raise InputError(f"flows: {name} expected ({n}, 2, {h}, {w}), got {tuple(f.shape)}")
            else:
                f12s, f21s = _flow_pyramids(flow_net, img1, img2, amp)
                flow12, flow21 = f12s[0], f21s[0]
            valid12 = valid_mask(flow12, flow21, wt.fb_consistency)
            score12 = score_map(valid12, fb_difference(flow12, flow21))
    visuals["flow12"] = flow12[0].detach()
    visuals["valid12"] = valid12[0].detach()

    depth_failed = 0
    if stage in ("depth", "joint"):
        # -- geometry from the flow -----------------------------------------------------------
        F, F_ok = fundamental_from_flow(flow12, score12, TOP_RATIO, N_MATCHES, generator)
        d_epi = epipolar_distance(F, flow12)
        okf = F_ok.to(d_epi.dtype)
        rigid12 = rigid_mask(d_epi, RIGID_PX) * okf.view(-1, 1, 1, 1)
        terms["geo"] = wt.w_geo * (geometric_loss_per_image(d_epi, INLIER_PX, RIGID_PX) * okf).mean()
        visuals["rigid12"] = rigid12[0].detach()

        # -- depth ----------------------------------------------------------------------------
        sigma1, sigma2, depth1, depth2 = _run_depth(depth_net, img1, img2, amp)
        anchor = anchor + 0.0 * (sigma1.mean() + sigma2.mean())
        visuals["disp1"] = sigma1[0].detach()
        per_item, ok = _depth_terms(img1, img2, flow12, score12.detach(), rigid12, F, F_ok, K, K_inv,
                                    sigma1, sigma2, depth1, depth2, generator)
        depth_failed = int(n - int(ok.sum()))
        if depth_failed and wt.depth_failure == "batch":  # the authors: the whole batch's depth terms are zeroed
            per_item = {k: torch.zeros_like(v) for k, v in per_item.items()}
        w_of = {"pt_depth": wt.w_pt_depth, "pj_depth": wt.w_pj_depth, "flow_error": wt.w_flow_error,
                "depth_smooth": wt.w_depth_smooth}
        for k in DEPTH_TERMS:
            terms[k] = w_of[k] * per_item[k].mean()

    w_term = {"photometric": 1.0, "flow_smooth": wt.w_flow_smooth, "geo": wt.w_geo, "pt_depth": wt.w_pt_depth,
              "pj_depth": wt.w_pj_depth, "flow_error": wt.w_flow_error, "depth_smooth": wt.w_depth_smooth}
    total = anchor
    for k, v in terms.items():
        if w_term[k] != 0:  # a zero weight must not turn a non-finite term into a NaN total
            total = total + v
    out_terms = {k: float(v.detach()) for k, v in terms.items()}
    out_terms["total"] = float(total.detach())
    return StepOutput(total=total, terms=out_terms, depth_failed=depth_failed, depth_zeroed=depth_failed > 0,
                      visuals=visuals)
