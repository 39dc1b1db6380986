"""PWC-Net optical flow (Sun et al., CVPR 2018) as TrianFlow's authors built it, for ONNX export.

By default the architecture is exactly that of the authors' flow network ("PWC_tf",
TrianFlow commit af3f2bf), so their weights load through
:mod:`trianflow_vo.models.authors`. Structure, coarse to fine:

* feature pyramid, shared by both images: per level two 3x3 convolutions (the first
  with stride 2), each followed by leaky ReLU 0.1; ``pyramid_channels[i]`` channels at
  1/2**(i+1) resolution (16, 32, 64, 96, 128, 196);
* at every decoded level ``l`` (6 = coarsest first, down to ``output_level`` = 2): the
  second image's features are warped by the upsampled flow of level ``l+1``
  (``grid_sample`` bilinear, ``align_corners=True``, zero padding; the behaviour their
  model was trained with under torch 1.2), and a cost volume is built with a local search
  range ``d`` (``(2d+1)**2`` = 81 channels, dy major: mean over feature channels of
  ``f1 * shifted f2``, zero outside; **no activation** on it). The coarsest level's
  estimator sees the cost volume alone; the others see ``[cost volume, features of
  image 1, upsampled flow]`` in that order. An estimator of five 3x3 convolutions (+ leaky
  ReLU) predicts a flow residual that is added to the upsampled flow (at the coarsest
  level the prediction is the flow). Its connections are set by
  ``estimator_connections``: ``"pairwise"`` (default, the authors': x0 = c0(in),
  x1 = c1(x0), x2 = c2([x0, x1]), x3 = c3([x1, x2]), x4 = c4([x2, x3]),
  flow = predict([x3, x4]), and x4 is handed on) or ``"dense"`` (the original PWC-Net:
  each convolution sees the input and every earlier output; about twice the arithmetic);
* at the output level a context network of dilated convolutions (1, 2, 4, 8, 16, 1;
  + leaky ReLU) and a predictor refine the flow: its input is ``[flow, x4]`` in that
  order and its output is added to the flow.

Every flow inside this module is in pixels of the resolution of the level it lives
at. Coarser flow goes up by bilinear x2 (``align_corners=False``) with its values x2.
The output-level flow (1/4) times ``2**output_level`` (= 4, no x20 anywhere), resized
bilinearly to ``(H, W)``, is the flow in input pixels (:meth:`PWCNet.full_flow`), what
the authors' network returns as its first output and what their VO and losses use;
:meth:`PWCNet.multiscale` gives all four of their outputs.

Input: a pair of images ``(N, 3, H, W)``, as the authors feed them: BGR, pixel / 255, no
mean/std (the exported graph does that scaling itself), with ``H`` and ``W`` multiples
of ``2**len(pyramid_channels)`` (64 by default). The cost volume uses only pad, slice,
reshape, transpose, concat and batched matrix products (:func:`cost_volume`), so the
exported graph needs no custom operator.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn


@dataclass(frozen=True)
class PWCConfig:
    """Constructor sizes of :class:`PWCNet` (stored in checkpoints). Defaults = the authors' network."""

    pyramid_channels: tuple[int, ...] = (16, 32, 64, 96, 128, 196)
    estimator_channels: tuple[int, ...] = (128, 128, 96, 64, 32)
    context_channels: tuple[int, ...] = (128, 128, 128, 96, 64, 32)
    context_dilations: tuple[int, ...] = (1, 2, 4, 8, 16, 1)
    search_range: int = 4
    output_level: int = 2  # finest decoded level: flow at 1/2**output_level
    estimator_connections: str = "pairwise"  # or "dense" (see the module docstring)

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> "PWCConfig":
        known = {f for f in cls.__dataclass_fields__}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown PWC-Net config keys: {sorted(unknown)}")
        return cls(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items()})


def _conv(cin: int, cout: int, stride: int = 1, dilation: int = 1, act: bool = True) -> nn.Module:
    conv = nn.Conv2d(cin, cout, 3, stride=stride, padding=dilation, dilation=dilation)
    if not act:
        return conv
    return nn.Sequential(conv, nn.LeakyReLU(0.1))


def warp(feat: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """Sample ``feat`` ``(N, C, H, W)`` at ``x + flow(x)``; ``flow`` ``(N, 2, H, W)`` in pixels.

    Bilinear, ``align_corners=True`` (pixel centres at -1 and +1 for the first and
    last column), zeros outside the image.
    """
    n, _, h, w = feat.shape
    ys = torch.arange(h, dtype=feat.dtype, device=feat.device).view(1, h, 1).expand(1, h, w)
    xs = torch.arange(w, dtype=feat.dtype, device=feat.device).view(1, 1, w).expand(1, h, w)
    x = xs + flow[:, 0]
    y = ys + flow[:, 1]
    gx = 2.0 * x / max(w - 1, 1) - 1.0
    gy = 2.0 * y / max(h - 1, 1) - 1.0
    grid = torch.stack((gx, gy), dim=3)
    return F.grid_sample(feat, grid, mode="bilinear", padding_mode="zeros", align_corners=True)


COST_TILE = 8  # pixels of a row per tile in :func:`cost_volume` (fastest of 4, 8, 16 at 256x832)


def cost_volume_reference(f1: torch.Tensor, f2: torch.Tensor, search_range: int) -> torch.Tensor:
    """The cost volume by its definition, one slice, product and channel mean per shift.

    Same contract as :func:`cost_volume` (which computes the same values faster); kept as
    the reference for tests and benchmarks. ``f1``, ``f2`` ``(N, C, H, W)`` ->
    ``(N, (2d+1)**2, H, W)``."""
    d = search_range
    _, _, h, w = f1.shape
    f2p = F.pad(f2, (d, d, d, d))
    out = []
    for dy in range(2 * d + 1):
        rows = f2p[:, :, dy:dy + h, :]
        for dx in range(2 * d + 1):
            out.append((f1 * rows[:, :, :, dx:dx + w]).mean(dim=1, keepdim=True))
    return torch.cat(out, dim=1)


def cost_volume(f1: torch.Tensor, f2: torch.Tensor, search_range: int) -> torch.Tensor:
    """Correlation ``(N, (2d+1)**2, H, W)`` of ``f1`` ``(N, C, H, W)`` with ``f2`` ``(N, C, H, W)``
    shifted by ``(dx, dy)`` in ``[-d, d]**2`` (dy major, then dx): channel ``(dy + d) * (2d+1) +
    (dx + d)`` at ``(y, x)`` is ``mean_c f1[c, y, x] * f2[c, y+dy, x+dx]``, zero where
    ``(y+dy, x+dx)`` is outside the image. ``d = search_range >= 0``.

    Equal to :func:`cost_volume_reference` up to float rounding (~3e-7 in float32 at the
    network's sizes), gradients included, but computed with matrix products, so that the
    exported graph has ~7 nodes per ``dy`` instead of 3 per shift and materialises no
    ``(N, C, H, W)`` product per shift:

    * each row of ``f1`` is cut into tiles of ``T = COST_TILE`` pixels (zero padded on the
      right), with the mean's ``1/C`` folded in: ``a`` ``(rows, W/T, T, C)``;
    * ``f2`` (zero padded by ``d``) gives per tile the window of the ``T + 2d`` columns that
      the tile's shifts reach: ``win`` ``(rows, W/T, C, T + 2d)``;
    * per ``dy`` one batched MatMul ``a x win`` (rows of ``win`` offset by ``dy``) gives every
      pixel ``i`` of a tile against every window column ``j``; the wanted ``j = i + dx + d``
      form a band that a pad by ``T`` and a reshape to rows of ``T + 2d + 1`` turn into the
      first ``2d + 1`` columns.

    The batch is folded into the rows (each image followed by ``2d`` junk rows, whose outputs
    are dropped) so that the row offset of ``win`` is a plain slice: torch then saves views
    for the backward pass (saved memory as with the reference) instead of a copy per ``dy``.
    Measured in benchmarks/NETWORK.md (2026-12-02).
    """
    if f1.dim() != 4 or tuple(f1.shape) != tuple(f2.shape):
        raise ValueError(f"cost_volume needs two (N, C, H, W) tensors of the same shape, got "
                         f"{tuple(f1.shape)} and {tuple(f2.shape)}")
    if search_range < 0:
        raise ValueError(f"search_range must be >= 0, got {search_range}")
    d = int(search_range)
    k = 2 * d + 1
    n, c, h, w = f1.shape
    t = COST_TILE
    nt = (w + t - 1) // t  # tiles per row
    wt = nt * t
    span = t + 2 * d  # window width: the columns of f2 one tile's shifts reach
    hp = h + 2 * d  # rows per image, padded
    rows = n * hp - 2 * d  # folded rows computed: the last image's 2d junk rows are not needed
    # f1 tiles: image b's row y at folded row b * hp + y; rows y >= h are zeros
    a = F.pad(f1 * (1.0 / c), (0, wt - w, 0, 2 * d)).reshape(n, c, hp, nt, t).permute(0, 2, 3, 4, 1)
    a = a.reshape(n * hp, nt, t, c)[:rows]
    # f2 windows: padded f2 in blocks of T columns; window j = n_blocks blocks from block j, cut to span
    n_blocks = (span + t - 1) // t
    wp = (nt + n_blocks - 1) * t
    f2p = F.pad(f2, (d, wp - w - d, d, d)).reshape(n, c, hp, nt + n_blocks - 1, t)
    win = torch.cat([f2p[:, :, :, j:j + nt] for j in range(n_blocks)], dim=4) if n_blocks > 1 else f2p
    if n_blocks * t != span:
        win = win[..., :span]
    win = win.permute(0, 2, 3, 1, 4).reshape(n * hp, nt, c, span)  # image b's padded row r at b * hp + r
    out = []
    for dy in range(k):
        m = torch.matmul(a, win[dy:dy + rows])  # (rows, nt, T, span): f1 row y against padded f2 row y + dy
        # band m[..., i, i + dx'] (dx' = dx + d) at flat index i * (span + 1) + dx'; pad the junk rows back
        m = F.pad(m.reshape(rows, nt, t * span), (0, t, 0, 0, 0, 2 * d))
        out.append(m.reshape(n, hp, nt, t, span + 1)[:, :h, :, :, :k])
    cost = torch.stack(out, dim=1)  # (N, 2d+1 (dy), H, nt, T, 2d+1 (dx))
    cost = cost.permute(0, 1, 5, 2, 3, 4).reshape(n, k * k, h, wt)
    return cost if wt == w else cost[..., :w]


def upsample_flow(flow: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Bilinear upsampling of a flow field to ``size`` with values scaled by the size ratio."""
    h, w = flow.shape[2:]
    up = F.interpolate(flow, size=size, mode="bilinear", align_corners=False)
    sx = size[1] / w
    sy = size[0] / h
    if sx == sy:
        return up * sx
    return torch.cat((up[:, :1] * sx, up[:, 1:] * sy), dim=1)


class FeaturePyramid(nn.Module):
    def __init__(self, channels: tuple[int, ...]):
        super().__init__()
        layers = []
        cin = 3
        for c in channels:
            layers.append(nn.Sequential(_conv(cin, c, stride=2), _conv(c, c)))
            cin = c
        self.levels = nn.ModuleList(layers)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Features at levels 1..L (index 0 = 1/2 resolution)."""
        feats = []
        for layer in self.levels:
            x = layer(x)
            feats.append(x)
        return feats


class DenseEstimator(nn.Module):
    """Flow estimator. ``connections="dense"``: each conv sees the input and all
    earlier outputs (original PWC-Net). ``"pairwise"``: conv k sees the outputs of
    convs k-2 and k-1 (the first two see the input and conv 0), the flow is predicted
    from the last two outputs, and the features handed on are the last output."""

    def __init__(self, cin: int, channels: tuple[int, ...], connections: str = "dense"):
        super().__init__()
        if connections not in ("dense", "pairwise"):
            raise ValueError(f"estimator_connections must be 'dense' or 'pairwise', got {connections!r}")
        if connections == "pairwise" and len(channels) < 2:
            raise ValueError("a pairwise estimator needs at least two convolutions")
        self.connections = connections
        convs = []
        if connections == "dense":
            c = cin
            for cout in channels:
                convs.append(_conv(c, cout))
                c += cout
            self.predict = _conv(c, 2, act=False)
            self.out_channels = c
        else:
            for k, cout in enumerate(channels):
                c_in = cin if k == 0 else channels[0] if k == 1 else channels[k - 2] + channels[k - 1]
                convs.append(_conv(c_in, cout))
            self.predict = _conv(channels[-2] + channels[-1], 2, act=False)
            self.out_channels = channels[-1]
        self.convs = nn.ModuleList(convs)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if self.connections == "dense":
            for conv in self.convs:
                x = torch.cat((x, conv(x)), dim=1)
            return x, self.predict(x)
        outs = [self.convs[0](x)]
        outs.append(self.convs[1](outs[0]))
        for conv in self.convs[2:]:
            outs.append(conv(torch.cat((outs[-2], outs[-1]), dim=1)))
        return outs[-1], self.predict(torch.cat((outs[-2], outs[-1]), dim=1))


class ContextNetwork(nn.Module):
    def __init__(self, cin: int, channels: tuple[int, ...], dilations: tuple[int, ...]):
        super().__init__()
        if len(channels) != len(dilations):
            raise ValueError("context_channels and context_dilations differ in length")
        layers = []
        c = cin
        for cout, dil in zip(channels, dilations):
            layers.append(_conv(c, cout, dilation=dil))
            c = cout
        layers.append(_conv(c, 2, act=False))
        self.net = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class PWCNet(nn.Module):
    """PWC-Net. ``forward(img1, img2)`` returns flows 1 -> 2 at every decoded level,
    finest first: ``flows[k]`` is ``(N, 2, H / 2**(output_level+k), W / 2**(output_level+k))``
    in pixels of that level. :meth:`full_flow` gives the flow in input pixels."""

    def __init__(self, config: PWCConfig | None = None):
        super().__init__()
        cfg = config or PWCConfig()
        if not 1 <= cfg.output_level <= len(cfg.pyramid_channels):
            raise ValueError(f"output_level must be in [1, {len(cfg.pyramid_channels)}]")
        self.config = cfg
        self.pyramid = FeaturePyramid(cfg.pyramid_channels)
        n_cost = (2 * cfg.search_range + 1) ** 2
        estimators = []
        # decoded levels, coarsest first: L, L-1, ..., output_level
        self.levels = list(range(len(cfg.pyramid_channels), cfg.output_level - 1, -1))
        for k, lvl in enumerate(self.levels):
            # the coarsest level sees the cost volume alone, the others [cost, f1, up_flow]
            cin = n_cost if k == 0 else n_cost + cfg.pyramid_channels[lvl - 1] + 2
            estimators.append(DenseEstimator(cin, cfg.estimator_channels, cfg.estimator_connections))
        self.estimators = nn.ModuleList(estimators)
        self.context = ContextNetwork(2 + estimators[-1].out_channels, cfg.context_channels,
                                      cfg.context_dilations)
        self.multiple = 2 ** len(cfg.pyramid_channels)

    def check_size(self, h: int, w: int) -> None:
        if h % self.multiple or w % self.multiple:
            raise ValueError(f"PWC-Net input size must be a multiple of {self.multiple}, got {h}x{w}")

    def decode(self, feats1: list[torch.Tensor], feats2: list[torch.Tensor]) -> list[torch.Tensor]:
        """Flows 1 -> 2 (finest first) from the two feature pyramids."""
        d = self.config.search_range
        flow = None
        flows = []
        for k, lvl in enumerate(self.levels):
            f1 = feats1[lvl - 1]
            f2 = feats2[lvl - 1]
            if flow is None:
                feat, flow = self.estimators[k](cost_volume(f1, f2, d))
            else:
                flow = upsample_flow(flow, tuple(f1.shape[2:]))
                cost = cost_volume(f1, warp(f2, flow), d)
                feat, residual = self.estimators[k](torch.cat((cost, f1, flow), dim=1))
                flow = residual + flow
            if lvl == self.config.output_level:
                flow = flow + self.context(torch.cat((flow, feat), dim=1))
            flows.append(flow)
        return flows[::-1]

    def forward(self, img1: torch.Tensor, img2: torch.Tensor) -> list[torch.Tensor]:
        self.check_size(img1.shape[2], img1.shape[3])
        n = img1.shape[0]
        feats = self.pyramid(torch.cat((img1, img2), dim=0))
        return self.decode([f[:n] for f in feats], [f[n:] for f in feats])

    def full_flow(self, flow: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        """Upsample an output-level flow to the input size ``(H, W)``, in input pixels."""
        return upsample_flow(flow, size)

    def multiscale(self, flows: list[torch.Tensor], size: tuple[int, int]) -> list[torch.Tensor]:
        """The authors' four outputs from :meth:`forward`'s ``flows``: for ``k = 0..3`` the
        flow of level ``output_level + k`` times ``2**output_level`` (4, whatever the level),
        bilinearly resized to ``(H / 2**k, W / 2**k)``; so output ``k`` is in pixels of
        resolution ``1 / 2**k`` and output 0 equals :meth:`full_flow` of ``flows[0]``.
        (Their losses use these; the VO uses output 0.)"""
        h, w = size
        s = float(2 ** self.config.output_level)
        return [F.interpolate(f * s, size=(h // 2 ** k, w // 2 ** k), mode="bilinear", align_corners=False)
                for k, f in enumerate(flows[:4])]

    def forward_backward(self, img1: torch.Tensor, img2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Forward (1 -> 2) and backward (2 -> 1) flow ``(N, 2, H, W)`` in input pixels.

        The pyramid runs once on both images; both directions are decoded as one batch.
        """
        h, w = img1.shape[2:]
        self.check_size(h, w)
        n = img1.shape[0]
        feats = self.pyramid(torch.cat((img1, img2), dim=0))
        swapped = [torch.cat((f[n:], f[:n]), dim=0) for f in feats]
        flows = self.decode(feats, swapped)
        full = self.full_flow(flows[0], (h, w))
        return full[:n], full[n:]
