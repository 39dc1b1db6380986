"""Monocular depth network: ResNet18 encoder + monodepth2-style decoder, as TrianFlow's
authors have it (their ``Depth_Model``, commit af3f2bf), so their weights load through
:mod:`trianflow_vo.models.authors`.

Input: ``(x / 255 - 0.45) / 0.225`` of a BGR image (the exported graph applies it).
Decoder, from the 1/32 features up to full resolution, at each of five stages
(channels 256, 128, 64, 32, 16): 3x3 conv (reflection padding) + ELU, **bilinear** x2
upsampling (``align_corners=False``; monodepth2 uses nearest), concatenation with the
encoder skip of that resolution (none at full resolution), 3x3 conv (reflection padding)
+ ELU. A 3x3 conv (reflection padding) + sigmoid gives a disparity ``sigma`` in (0, 1)
at each scale of ``scales``; the authors' configurations have scale 0 only
(``depth_scale: 1``), and inference uses scale 0.

Depth the monodepth way: ``disp = 1/max_depth + (1/min_depth - 1/max_depth) * sigma``
and ``depth = 1 / disp``, i.e. ``1 / (0.01 + 9.99 * sigma)`` in [0.1, 100] by default.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn

from trianflow_vo.models.resnet_encoder import ENCODER_CHANNELS, ResNet18Encoder


@dataclass(frozen=True)
class DepthConfig:
    """Constructor sizes of :class:`DepthNet` (stored in checkpoints). Defaults = the authors' network."""

    decoder_channels: tuple[int, ...] = (16, 32, 64, 128, 256)  # full res .. 1/16
    scales: tuple[int, ...] = (0,)  # the authors' depth_scale: 1
    min_depth: float = 0.1
    max_depth: float = 100.0

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> "DepthConfig":
        known = {f for f in cls.__dataclass_fields__}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown depth-net config keys: {sorted(unknown)}")
        return cls(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items()})


def disp_to_depth(sigma: torch.Tensor, min_depth: float, max_depth: float) -> torch.Tensor:
    """Sigmoid output ``sigma`` in (0, 1) -> depth in ``[min_depth, max_depth]``."""
    min_disp = 1.0 / max_depth
    max_disp = 1.0 / min_depth
    return 1.0 / (min_disp + (max_disp - min_disp) * sigma)


class ConvELU(nn.Module):
    def __init__(self, cin: int, cout: int, act: bool = True):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, 3)
        self.act = act

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.conv(F.pad(x, (1, 1, 1, 1), mode="reflect"))
        return F.elu(x) if self.act else x


class DispDecoder(nn.Module):
    def __init__(self, enc_channels: tuple[int, ...], dec_channels: tuple[int, ...], scales: tuple[int, ...]):
        super().__init__()
        if len(dec_channels) != 5:
            raise ValueError("decoder_channels must have 5 entries")
        self.scales = tuple(int(s) for s in scales)
        if 0 not in self.scales or len(set(self.scales)) != len(self.scales) or not set(self.scales) <= {0, 1, 2, 3, 4}:
            raise ValueError(f"scales must be distinct values in 0..4 including 0, got {list(scales)}")
        self.upconv0 = nn.ModuleList()
        self.upconv1 = nn.ModuleList()
        for i in range(4, -1, -1):
            cin = enc_channels[-1] if i == 4 else dec_channels[i + 1]
            self.upconv0.append(ConvELU(cin, dec_channels[i]))
            cskip = enc_channels[i - 1] if i > 0 else 0
            self.upconv1.append(ConvELU(dec_channels[i] + cskip, dec_channels[i]))
        self.dispconv = nn.ModuleDict({str(s): ConvELU(dec_channels[s], 1, act=False) for s in self.scales})

    def forward(self, feats: list[torch.Tensor], out_size: tuple[int, int]) -> dict[int, torch.Tensor]:
        """Sigmoid disparities per scale ``{s: (N, 1, H / 2**s, W / 2**s)}``."""
        x = feats[-1]
        out = {}
        for k, i in enumerate(range(4, -1, -1)):
            x = self.upconv0[k](x)
            if i > 0:
                size = feats[i - 1].shape[2:]
            else:
                size = out_size
            x = F.interpolate(x, size=(int(size[0]), int(size[1])), mode="bilinear", align_corners=False)
            if i > 0:
                x = torch.cat((x, feats[i - 1]), dim=1)
            x = self.upconv1[k](x)
            if i in self.scales:
                out[i] = torch.sigmoid(self.dispconv[str(i)](x))
        return out


class DepthNet(nn.Module):
    """``forward(img)`` -> ``{scale: sigmoid disparity}``; :meth:`depth` -> ``(N, 1, H, W)`` depth."""

    def __init__(self, config: DepthConfig | None = None):
        super().__init__()
        cfg = config or DepthConfig()
        self.config = cfg
        self.encoder = ResNet18Encoder()
        self.decoder = DispDecoder(ENCODER_CHANNELS, cfg.decoder_channels, cfg.scales)

    def check_size(self, h: int, w: int) -> None:
        if h % 32 or w % 32:
            raise ValueError(f"depth-net input size must be a multiple of 32, got {h}x{w}")

    def forward(self, img: torch.Tensor) -> dict[int, torch.Tensor]:
        h, w = img.shape[2:]
        self.check_size(h, w)
        return self.decoder(self.encoder(img), (h, w))

    def depth(self, img: torch.Tensor) -> torch.Tensor:
        """Depth ``(N, 1, H, W)`` in ``[min_depth, max_depth]`` at scale 0."""
        sigma = self.forward(img)[0]
        return disp_to_depth(sigma, self.config.min_depth, self.config.max_depth)
