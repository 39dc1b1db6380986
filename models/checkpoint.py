"""Our checkpoint format for the flow and depth networks, and reading checkpoint files.

A checkpoint is one file written by ``torch.save`` holding a plain dict (loadable
with ``torch.load(..., weights_only=True)``: only dicts, lists, strings, numbers
and tensors)::

    {
        "format": "trianflow-vo-checkpoint",   # fixed tag
        "format_version": 2,
        "input_size": [256, 832],               # (H, W) the networks were trained at
        "channel_order": "BGR",                 # order of the 3 input channels
        "resize": "linear",                     # how images were resized to input_size
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
in ``channel_order``, pixel values 0..255. ``resize`` is one of
:data:`trianflow_vo.nets.onnx_runtime.RESIZE_METHODS` (``"linear"``: cv2.INTER_LINEAR).
The defaults are those of the TrianFlow authors: BGR, INTER_LINEAR, the flow net sees
[0, 1] images (mean 0, std 1), the depth net ``(x - 0.45) / 0.225``.

Version 2 (this one) came with the flow and depth architectures that match the authors'
networks exactly (pyramid 196 channels at level 6, no activation on the cost volume, cost
volume alone at level 6, context input ``[flow, features]``, depth scale 0 only) and the
``resize`` key. Version 1 files hold weights of the earlier architecture and are refused
(:data:`OLD_VERSION_HINT`).

:func:`load_checkpoint` reads our format and, through :mod:`trianflow_vo.models.authors`,
the authors' own ``.pth`` files.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from trianflow_vo.errors import ModelError
from trianflow_vo.models.depth_net import DepthConfig, DepthNet
from trianflow_vo.models.pwc import PWCConfig, PWCNet
from trianflow_vo.nets.onnx_runtime import CHANNEL_ORDERS, RESIZE_LINEAR, RESIZE_METHODS

FORMAT_TAG = "trianflow-vo-checkpoint"
FORMAT_VERSION = 2
OLD_VERSION_HINT = ("it was written for the architecture before format 2 (the flow and depth nets now match "
                    "the TrianFlow authors' exactly) and its weights do not fit; re-create it with this version "
                    "(re-save the networks with models.checkpoint.make_checkpoint, or export the authors' .pth "
                    "directly: trianflow-vo export --checkpoint their.pth --out-dir DIR)")
DEFAULT_SIZE = (256, 832)
DEFAULT_CHANNEL_ORDER = "BGR"  # the authors read images with cv2 and feed them as they are
DEFAULT_RESIZE = RESIZE_LINEAR  # the authors resize with cv2.resize's default, INTER_LINEAR
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
    input_size: tuple[int, int]  # (H, W) the networks were trained at
    channel_order: str  # "RGB" or "BGR"
    flow: NetEntry | None
    depth: NetEntry | None
    resize: str = DEFAULT_RESIZE  # how images are resized to the network size (RESIZE_METHODS)
    source: str = FORMAT_TAG  # what the file was: our format, or "trianflow-authors-full" / "-flow"


def _entry(net: torch.nn.Module, norm: dict) -> dict:
    return {"config": net.config.to_dict(), "normalisation": {k: list(v) for k, v in norm.items()},
            "state_dict": {k: v.detach().cpu() for k, v in net.state_dict().items()}}


def make_checkpoint(flow: PWCNet | None, depth: DepthNet | None, input_size=DEFAULT_SIZE,
                    channel_order: str = DEFAULT_CHANNEL_ORDER, flow_norm: dict = FLOW_NORM,
                    depth_norm: dict = DEPTH_NORM, resize: str = DEFAULT_RESIZE) -> dict:
    """The checkpoint dict for the given networks (either may be None, not both)."""
    if flow is None and depth is None:
        raise ValueError("a checkpoint needs at least one network")
    if channel_order not in CHANNEL_ORDERS:
        raise ValueError(f"channel_order must be one of {list(CHANNEL_ORDERS)}, got {channel_order!r}")
    if resize not in RESIZE_METHODS:
        raise ValueError(f"resize must be one of {list(RESIZE_METHODS)}, got {resize!r}")
    ckpt = {"format": FORMAT_TAG, "format_version": FORMAT_VERSION,
            "input_size": [int(input_size[0]), int(input_size[1])], "channel_order": channel_order,
            "resize": resize}
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
    """Validate a checkpoint dict of our format and build its networks (eval mode)."""
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT_TAG:
        raise ModelError(f"{path}: not a trianflow-vo checkpoint (missing format tag '{FORMAT_TAG}')")
    version = ckpt.get("format_version")
    if isinstance(version, int) and version < FORMAT_VERSION:
        raise ModelError(f"{path}: checkpoint format_version {version} is no longer supported: {OLD_VERSION_HINT}")
    if version != FORMAT_VERSION:
        raise ModelError(f"{path}: unsupported checkpoint format_version {version!r} (this trianflow-vo "
                         f"reads version {FORMAT_VERSION}; a newer file needs a newer trianflow-vo)")
    size = ckpt.get("input_size")
    if not (isinstance(size, (list, tuple)) and len(size) == 2 and all(int(s) > 0 for s in size)):
        raise ModelError(f"{path}: input_size must be [H, W]")
    order = ckpt.get("channel_order")
    if order not in CHANNEL_ORDERS:
        raise ModelError(f"{path}: channel_order must be 'RGB' or 'BGR', got {order!r}")
    resize = ckpt.get("resize")
    if resize not in RESIZE_METHODS:
        raise ModelError(f"{path}: resize must be one of {list(RESIZE_METHODS)}, got {resize!r}")
    if "flow" not in ckpt and "depth" not in ckpt:
        raise ModelError(f"{path}: checkpoint holds neither a 'flow' nor a 'depth' network")
    flow = _build(ckpt["flow"], path, "flow", PWCNet, PWCConfig) if "flow" in ckpt else None
    depth = _build(ckpt["depth"], path, "depth", DepthNet, DepthConfig) if "depth" in ckpt else None
    return Checkpoint((int(size[0]), int(size[1])), order, flow, depth, resize, FORMAT_TAG)


def _short_reason(exc: BaseException) -> str:
    """The gist of a torch.load failure, on one line."""
    text = " ".join(str(exc).split())
    if isinstance(exc, EOFError) or not text:
        return f"{type(exc).__name__}: empty or truncated file"
    for marker in ("WeightsUnpickler error: ", "failed reading zip archive: "):
        if marker in text:
            text = text.split(marker, 1)[1]
    text = text.split(" Check the documentation")[0].split(". ")[0]
    return f"{type(exc).__name__}: {text[:160]}"


def read_file(path: str | Path, trust_pickle: bool = False):
    """``torch.load`` of a checkpoint file on the CPU, safely.

    Reads with ``weights_only=True`` (tensors, dicts, lists, numbers, strings only: no
    pickled code runs). A file that holds other pickled objects is refused with a one-line
    message, unless ``trust_pickle``: then it is read again with ``weights_only=False``
    (which can run code from the file) after a warning on stderr.

    Raises:
        ModelError: one line naming the file: not found, not a torch file, truncated,
            or pickled objects (without ``trust_pickle``).
    """
    import pickle
    import sys

    path = Path(path)
    if not path.is_file():
        raise ModelError(f"{path}: checkpoint not found")
    try:
        return torch.load(str(path), map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        text = str(exc)
        if "allowed global" not in text and "Unsupported global" not in text:
            raise ModelError(f"{path}: cannot read checkpoint: not a torch checkpoint file, or corrupt or "
                             f"truncated ({_short_reason(exc)})") from None
        if not trust_pickle:
            raise ModelError(f"{path}: cannot read checkpoint safely: it holds pickled objects that "
                             "torch.load(weights_only=True) refuses; if you trust the file, run again with "
                             "--trust-checkpoint") from None
    except Exception as exc:  # torch raises many types for a corrupt or truncated file
        raise ModelError(f"{path}: cannot read checkpoint: not a torch checkpoint file, or corrupt or "
                         f"truncated ({_short_reason(exc)})") from None
    print(f"warning: {path}: loading with torch.load(weights_only=False) because --trust-checkpoint was given; "
          "this runs pickled code from the file", file=sys.stderr)
    try:
        return torch.load(str(path), map_location="cpu", weights_only=False)
    except Exception as exc:
        raise ModelError(f"{path}: cannot read checkpoint ({_short_reason(exc)})") from None


def checkpoint_from_object(obj, path: str = "<checkpoint>") -> Checkpoint:
    """Our format (``format`` tag) or the authors' (:mod:`trianflow_vo.models.authors`)."""
    from trianflow_vo.models import authors

    if isinstance(obj, dict) and "format" in obj:
        return checkpoint_from_dict(obj, path)
    if authors.is_authors_file(obj):
        return authors.checkpoint_from_authors(obj, path)
    raise ModelError(f"{path}: not a trianflow-vo checkpoint (missing format tag '{FORMAT_TAG}') "
                     "nor a TrianFlow authors' checkpoint (no 'model_state_dict' with their tensor names)")


def load_checkpoint(path: str | Path, trust_pickle: bool = False) -> Checkpoint:
    """Read and validate a checkpoint file, ours or the authors'; errors are one line naming the file."""
    return checkpoint_from_object(read_file(path, trust_pickle), str(path))
