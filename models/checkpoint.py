"""Our checkpoint format for the flow and depth networks.

A checkpoint is one file written by ``torch.save`` holding a plain dict (loadable
with ``torch.load(..., weights_only=True)``: only dicts, lists, strings, numbers
and tensors)::

    {
        "format": "trianflow-vo-checkpoint",   # fixed tag
        "format_version": 1,
        "input_size": [256, 832],               # (H, W) the networks were trained at
        "channel_order": "RGB",                 # order of the 3 input channels
        "flow": {                               # optional (at least one of flow/depth)
            "config": {...},                    # PWCConfig.to_dict(): constructor sizes
            "normalisation": {"mean": [m, m, m], "std": [s, s, s]},
            "state_dict": {name: tensor},       # PWCNet.state_dict()
        },
        "depth": {                              # optional
            "config": {...},                    # DepthConfig.to_dict()
            "normalisation": {"mean": [...], "std": [...]},
            "state_dict": {name: tensor},       # DepthNet.state_dict()
        },
    }

Normalisation: a network sees ``(pixel / 255 - mean) / std`` per channel, channels
in ``channel_order``, pixel values 0..255. The defaults are those of TrianFlow and
monodepth: the flow net sees [0, 1] images (mean 0, std 1), the depth net
``(x - 0.45) / 0.225``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from trianflow_vo.models.depth_net import DepthConfig, DepthNet
from trianflow_vo.models.pwc import PWCConfig, PWCNet
from trianflow_vo.errors import ModelError

FORMAT_TAG = "trianflow-vo-checkpoint"
FORMAT_VERSION = 1
DEFAULT_SIZE = (256, 832)
FLOW_NORM = {"mean": [0.0, 0.0, 0.0], "std": [1.0, 1.0, 1.0]}
DEPTH_NORM = {"mean": [0.45, 0.45, 0.45], "std": [0.225, 0.225, 0.225]}


@dataclass
class NetEntry:
    """One network of a checkpoint, built and in eval mode."""

    net: torch.nn.Module
    config: dict
    normalisation: dict


@dataclass
class Checkpoint:
    input_size: tuple[int, int]
    channel_order: str
    flow: NetEntry | None
    depth: NetEntry | None


def _entry(net: torch.nn.Module, norm: dict) -> dict:
    return {"config": net.config.to_dict(), "normalisation": {k: list(v) for k, v in norm.items()},
            "state_dict": {k: v.detach().cpu() for k, v in net.state_dict().items()}}


def make_checkpoint(flow: PWCNet | None, depth: DepthNet | None, input_size=DEFAULT_SIZE,
                    channel_order: str = "RGB", flow_norm: dict = FLOW_NORM,
                    depth_norm: dict = DEPTH_NORM) -> dict:
    """The checkpoint dict for the given networks (either may be None, not both)."""
    if flow is None and depth is None:
        raise ValueError("a checkpoint needs at least one network")
    ckpt = {"format": FORMAT_TAG, "format_version": FORMAT_VERSION,
            "input_size": [int(input_size[0]), int(input_size[1])], "channel_order": channel_order}
    if flow is not None:
        ckpt["flow"] = _entry(flow, flow_norm)
    if depth is not None:
        ckpt["depth"] = _entry(depth, depth_norm)
    return ckpt


def save_checkpoint(path: str | Path, ckpt: dict) -> None:
    torch.save(ckpt, str(path))


def random_checkpoint(seed: int, input_size=DEFAULT_SIZE, flow_config: PWCConfig | None = None,
                      depth_config: DepthConfig | None = None) -> dict:
    """A checkpoint of freshly initialised networks (deterministic for a seed)."""
    torch.manual_seed(seed)
    flow = PWCNet(flow_config)
    depth = DepthNet(depth_config)
    return make_checkpoint(flow, depth, input_size)


def _check_norm(norm, path: str, what: str) -> dict:
    ok = (isinstance(norm, dict) and set(norm) == {"mean", "std"}
          and all(isinstance(norm[k], (list, tuple)) and len(norm[k]) == 3 for k in norm)
          and all(float(s) > 0 for s in norm["std"]))
    if not ok:
        raise ModelError(f"{path}: {what}.normalisation must be {{'mean': [3 numbers], 'std': [3 positive numbers]}}")
    return {"mean": [float(x) for x in norm["mean"]], "std": [float(x) for x in norm["std"]]}


def _build(entry, path: str, what: str, cls, cfg_cls) -> NetEntry:
    if not isinstance(entry, dict) or not {"config", "normalisation", "state_dict"} <= set(entry):
        raise ModelError(f"{path}: '{what}' must hold config, normalisation and state_dict")
    try:
        cfg = cfg_cls.from_dict(entry["config"])
        net = cls(cfg)
    except (TypeError, ValueError) as exc:
        raise ModelError(f"{path}: bad {what} config: {exc}") from None
    try:
        net.load_state_dict(entry["state_dict"])
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()
        raise ModelError(f"{path}: {what} weights do not fit its config: {' '.join(first[:3])}") from None
    net.eval()
    return NetEntry(net, cfg.to_dict(), _check_norm(entry["normalisation"], path, what))


def checkpoint_from_dict(ckpt: dict, path: str = "<checkpoint>") -> Checkpoint:
    """Validate a checkpoint dict and build its networks (eval mode)."""
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT_TAG:
        raise ModelError(f"{path}: not a trianflow-vo checkpoint (missing format tag '{FORMAT_TAG}')")
    if ckpt.get("format_version") != FORMAT_VERSION:
        raise ModelError(f"{path}: unsupported checkpoint format_version {ckpt.get('format_version')!r}")
    size = ckpt.get("input_size")
    if not (isinstance(size, (list, tuple)) and len(size) == 2 and all(int(s) > 0 for s in size)):
        raise ModelError(f"{path}: input_size must be [H, W]")
    order = ckpt.get("channel_order")
    if order not in ("RGB", "BGR"):
        raise ModelError(f"{path}: channel_order must be 'RGB' or 'BGR', got {order!r}")
    if "flow" not in ckpt and "depth" not in ckpt:
        raise ModelError(f"{path}: checkpoint holds neither a 'flow' nor a 'depth' network")
    flow = _build(ckpt["flow"], path, "flow", PWCNet, PWCConfig) if "flow" in ckpt else None
    depth = _build(ckpt["depth"], path, "depth", DepthNet, DepthConfig) if "depth" in ckpt else None
    return Checkpoint((int(size[0]), int(size[1])), order, flow, depth)


def load_checkpoint(path: str | Path) -> Checkpoint:
    """Read and validate a checkpoint file; errors name the file."""
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"{path}: checkpoint not found")
    try:
        ckpt = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for a corrupt or foreign file
        raise ModelError(f"{path}: cannot read checkpoint ({type(exc).__name__}: {exc})") from None
    return checkpoint_from_dict(ckpt, str(path))
