"""The TrianFlow authors' checkpoint layout: detect it, map it onto our networks and back,
and build deterministic checkpoints in it.

The authors (Zhao et al., CVPR 2020; public code, commit af3f2bf) save
``torch.save({"iteration": int, "model_state_dict": ..., "optimizer_state_dict": ...})``.
Two layouts of ``model_state_dict`` exist:

* ``"full"`` (their ``depth`` / ``depth_pose`` stages, what their VO loads): the depth
  network under ``depth_net.`` (``encoder.encoder.*``: a torchvision ResNet-18 with an
  unused 1000-way ``fc.*`` head; ``decoder.upconvs.{i}.{j}.conv.conv.*`` and
  ``decoder.dispconvs.{s}.conv.*``), then the flow network under ``model_pose.model_flow.``
  (``fpyramid.conv1..12.0.*``, ``pwc_model.conv{6..2}_{0..4}.0.*``,
  ``pwc_model.predict_flow{6..2}.*``, ``pwc_model.dc_conv{1..6}.0.*``, ``pwc_model.dc_conv7.*``);
* ``"flow"`` (their first stage, the flow network alone): ``fpyramid.*`` and
  ``pwc_model.*`` without a prefix (a ``model_flow.`` prefix is accepted too).

A ``module.`` prefix on every key (a checkpoint saved from ``DataParallel``) is accepted.

Our networks (:class:`~trianflow_vo.models.pwc.PWCNet` with its default
:class:`~trianflow_vo.models.pwc.PWCConfig`, :class:`~trianflow_vo.models.depth_net.DepthNet`
with ``scales = range(n)`` for their ``n`` disparity heads) have the same tensors under
other names; :func:`their_to_ours` and :func:`ours_to_theirs` are pure renamings (the
``fc.*`` head, which their code never uses, is dropped on import and written as zeros on
export). The authors' preprocessing goes with their weights: BGR images, resized with
``cv2.INTER_LINEAR`` to 256x832, the flow net sees ``x / 255``, the depth net
``(x / 255 - 0.45) / 0.225`` (:func:`checkpoint_from_authors`).

:func:`deterministic_checkpoint` makes a checkpoint in their layout whose every value
follows from the tensor's name and shape (numpy PCG64 seeded from the sha256 of the name),
so any program can rebuild the same weights: the equivalence test compares our exported
graphs with the authors' own code run on such weights (``tests/fixtures/README.md``).
"""

from __future__ import annotations

import hashlib
import math
from collections import OrderedDict
from collections.abc import Mapping

import numpy as np
import torch

from trianflow_vo.errors import ModelError
from trianflow_vo.models.checkpoint import DEPTH_NORM, FLOW_NORM, Checkpoint, NetEntry
from trianflow_vo.models.depth_net import DepthConfig, DepthNet
from trianflow_vo.models.pwc import PWCConfig, PWCNet
from trianflow_vo.nets.onnx_runtime import RESIZE_LINEAR

LAYOUT_FULL = "full"
LAYOUT_FLOW = "flow"
LAYOUTS = (LAYOUT_FULL, LAYOUT_FLOW)

FULL_FLOW_PREFIX = "model_pose.model_flow."
DEPTH_PREFIX = "depth_net."
FLOW_ONLY_PREFIXES = ("", "model_flow.")
PARALLEL_PREFIX = "module."
FILE_KEYS = ("iteration", "model_state_dict", "optimizer_state_dict")

#: the preprocessing the authors' weights were trained with
TRAIN_SIZE = (256, 832)
CHANNEL_ORDER = "BGR"
RESIZE = RESIZE_LINEAR
#: their unused classifier head (torchvision ResNet-18), relative to ``depth_net.encoder.encoder.``
FC_SHAPES = {"fc.weight": (1000, 512), "fc.bias": (1000,)}
SOURCE_TAG = "trianflow-authors"

_WB = ("weight", "bias")
_FLOW_LEVELS = (6, 5, 4, 3, 2)


# ---------------------------------------------------------------------------
# name pairs (theirs, ours), in the order of their state dict


def _flow_pairs() -> list[tuple[str, str]]:
    """(their name without prefix, our PWCNet name) for every flow tensor."""
    pairs = []
    for i in range(6):  # pyramid level i+1: their conv(2i+1) (stride 2) and conv(2i+2)
        for j in range(2):
            pairs += [(f"fpyramid.conv{2 * i + j + 1}.0.{p}", f"pyramid.levels.{i}.{j}.0.{p}") for p in _WB]
    for k, lvl in enumerate(_FLOW_LEVELS):
        for j in range(5):
            pairs += [(f"pwc_model.conv{lvl}_{j}.0.{p}", f"estimators.{k}.convs.{j}.0.{p}") for p in _WB]
        pairs += [(f"pwc_model.predict_flow{lvl}.{p}", f"estimators.{k}.predict.{p}") for p in _WB]
    for i in range(6):
        pairs += [(f"pwc_model.dc_conv{i + 1}.0.{p}", f"context.net.{i}.0.{p}") for p in _WB]
    pairs += [(f"pwc_model.dc_conv7.{p}", f"context.net.6.{p}") for p in _WB]
    return pairs


def _encoder_names() -> list[str]:
    with torch.device("meta"):
        enc = DepthNet(DepthConfig()).encoder
    return list(enc.state_dict())


def _depth_pairs(n_scales: int) -> list[tuple[str, str | None]]:
    """(their name without ``depth_net.``, our DepthNet name or None for the dropped fc head)."""
    pairs: list[tuple[str, str | None]] = [(f"encoder.encoder.{n}", f"encoder.{n}") for n in _encoder_names()]
    pairs += [(f"encoder.encoder.{n}", None) for n in FC_SHAPES]
    for k in range(5):  # their upconvs[k] = decoder stage at scale 4 - k: [upconv_0, upconv_1]
        for j in range(2):
            pairs += [(f"decoder.upconvs.{k}.{j}.conv.conv.{p}", f"decoder.upconv{j}.{k}.conv.{p}") for p in _WB]
    for s in range(n_scales):  # their scales = range(depth_scale): index == scale
        pairs += [(f"decoder.dispconvs.{s}.conv.{p}", f"decoder.dispconv.{s}.conv.{p}") for p in _WB]
    return pairs


def _our_shapes(n_scales: int | None) -> tuple[dict, dict | None]:
    """Shapes and dtypes of our default networks' tensors (built on the meta device: no memory)."""
    with torch.device("meta"):
        flow = {k: (tuple(v.shape), v.dtype) for k, v in PWCNet(PWCConfig()).state_dict().items()}
        depth = None
        if n_scales is not None:
            net = DepthNet(DepthConfig(scales=tuple(range(n_scales))))
            depth = {k: (tuple(v.shape), v.dtype) for k, v in net.state_dict().items()}
    return flow, depth


# ---------------------------------------------------------------------------
# detection


def _strip_parallel(sd: Mapping) -> Mapping:
    keys = list(sd)
    if keys and all(isinstance(k, str) and k.startswith(PARALLEL_PREFIX) for k in keys):
        return OrderedDict((k[len(PARALLEL_PREFIX):], v) for k, v in sd.items())
    return sd


def _flow_only_prefix(sd: Mapping) -> str | None:
    for prefix in FLOW_ONLY_PREFIXES:
        if any(isinstance(k, str) and (k.startswith(prefix + "fpyramid.") or k.startswith(prefix + "pwc_model."))
               for k in sd):
            return prefix
    return None


def detect_layout(state_dict: Mapping) -> str | None:
    """``"full"`` (``depth_net.*`` and/or ``model_pose.model_flow.*``), ``"flow"``
    (``fpyramid.*`` / ``pwc_model.*``, optionally under ``model_flow.``) or None (not theirs).
    Only the key names are looked at; :func:`their_to_ours` checks every tensor."""
    if not isinstance(state_dict, Mapping):
        return None
    sd = _strip_parallel(state_dict)
    if any(isinstance(k, str) and (k.startswith(FULL_FLOW_PREFIX) or k.startswith(DEPTH_PREFIX)) for k in sd):
        return LAYOUT_FULL
    if _flow_only_prefix(sd) is not None:
        return LAYOUT_FLOW
    return None


def is_authors_file(obj) -> bool:
    """True for their file dict (with ``model_state_dict``) or a bare state dict of their layout."""
    if isinstance(obj, Mapping) and "model_state_dict" in obj:
        return True
    return detect_layout(obj) is not None


# ---------------------------------------------------------------------------
# mapping


def _take(sd: Mapping, key: str, want, source: str) -> torch.Tensor:
    if key not in sd:
        raise ModelError(f"{source}: missing tensor '{key}'")
    t = sd[key]
    if not isinstance(t, torch.Tensor):
        raise ModelError(f"{source}: '{key}' is a {type(t).__name__}, not a tensor")
    shape, dtype = want
    if tuple(t.shape) != shape:
        raise ModelError(f"{source}: tensor '{key}' has shape {list(t.shape)}, expected {list(shape)}")
    if dtype.is_floating_point != t.dtype.is_floating_point:
        raise ModelError(f"{source}: tensor '{key}' has dtype {t.dtype}, expected {dtype}")
    return t.detach().to(dtype=dtype, device="cpu")


def _n_scales(sd: Mapping) -> int:
    n = 0
    while f"{DEPTH_PREFIX}decoder.dispconvs.{n}.conv.weight" in sd:
        n += 1
    return max(n, 1)  # none: the check of dispconvs.0 names the missing key


def their_to_ours(state_dict: Mapping, source: str = "<state_dict>") -> tuple[dict, dict | None]:
    """Their ``model_state_dict`` -> ``(flow_sd, depth_sd or None)`` for our default
    :class:`PWCNet` and a :class:`DepthNet` with ``scales = range(n)`` (n = their disparity
    heads, 1 in all their configurations). ``depth_sd`` is None for the flow-only layout.

    Raises:
        ModelError: one line ``"{source}: ..."`` naming the first missing, mis-shaped or
            non-tensor key in their order, or the first key that is not theirs.
    """
    layout = detect_layout(state_dict)
    if layout is None:
        raise ModelError(f"{source}: not the TrianFlow authors' layout (no 'fpyramid.*', 'pwc_model.*', "
                         f"'{FULL_FLOW_PREFIX}*' or '{DEPTH_PREFIX}*' tensors)")
    sd = _strip_parallel(state_dict)
    if layout == LAYOUT_FULL:
        flow_prefix = FULL_FLOW_PREFIX
        n_scales = _n_scales(sd)
    else:
        flow_prefix = _flow_only_prefix(sd)
        n_scales = None
    flow_shapes, depth_shapes = _our_shapes(n_scales)
    used = set()
    depth_sd = None
    if layout == LAYOUT_FULL:  # their order: depth_net first
        depth_sd = OrderedDict()
        for theirs, ours in _depth_pairs(n_scales):
            key = DEPTH_PREFIX + theirs
            if ours is None:  # the unused fc head: optional, dropped
                if key in sd:
                    _take(sd, key, (FC_SHAPES[theirs.split(".", 2)[2]], torch.float32), source)
                    used.add(key)
                continue
            depth_sd[ours] = _take(sd, key, depth_shapes[ours], source)
            used.add(key)
    flow_sd = OrderedDict()
    for theirs, ours in _flow_pairs():
        key = flow_prefix + theirs
        flow_sd[ours] = _take(sd, key, flow_shapes[ours], source)
        used.add(key)
    for key in sd:
        if key not in used:
            raise ModelError(f"{source}: unexpected tensor '{key}' (not part of the authors' flow or depth network)")
    return flow_sd, depth_sd


def ours_to_theirs(flow_sd: Mapping, depth_sd: Mapping | None = None) -> OrderedDict:
    """Our state dicts -> their ``model_state_dict``: the full layout when ``depth_sd`` is
    given (depth first, as their model orders it; ``fc.*`` written as zeros), else the
    flow-only layout. ``flow_sd`` must be of the default :class:`PWCConfig`, ``depth_sd``
    of a :class:`DepthNet` with ``scales = range(n)``.

    Raises:
        KeyError: a tensor of the architecture is missing from the input.
    """
    out = OrderedDict()
    if depth_sd is not None:
        n = 0
        while f"decoder.dispconv.{n}.conv.weight" in depth_sd:
            n += 1
        extra = [k for k in depth_sd if k.startswith("decoder.dispconv.") and int(k.split(".")[2]) >= n]
        if n == 0 or extra:
            raise ValueError("their layout needs disparity heads at scales 0..n-1")
        for theirs, ours in _depth_pairs(n):
            if ours is None:
                out[DEPTH_PREFIX + theirs] = torch.zeros(FC_SHAPES[theirs.split(".", 2)[2]])
            else:
                out[DEPTH_PREFIX + theirs] = depth_sd[ours]
        prefix = FULL_FLOW_PREFIX
    else:
        prefix = ""
    for theirs, ours in _flow_pairs():
        out[prefix + theirs] = flow_sd[ours]
    return out


def their_layout(layout: str = LAYOUT_FULL, n_scales: int = 1) -> list[tuple[str, tuple[int, ...], torch.dtype]]:
    """``(name, shape, dtype)`` of every tensor of their ``model_state_dict``, in their order."""
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {list(LAYOUTS)}, got {layout!r}")
    flow, depth = _our_shapes(n_scales if layout == LAYOUT_FULL else None)
    rows = []
    if layout == LAYOUT_FULL:
        for theirs, ours in _depth_pairs(n_scales):
            shape, dtype = (FC_SHAPES[theirs.split(".", 2)[2]], torch.float32) if ours is None else depth[ours]
            rows.append((DEPTH_PREFIX + theirs, tuple(shape), dtype))
    prefix = FULL_FLOW_PREFIX if layout == LAYOUT_FULL else ""
    rows += [(prefix + theirs, flow[ours][0], flow[ours][1]) for theirs, ours in _flow_pairs()]
    return rows


# ---------------------------------------------------------------------------
# deterministic weights

#: gains of the deterministic weights (std = gain / sqrt(fan_in)); part of their definition
GAIN_HIDDEN = math.sqrt(2.0)  # convolutions followed by (leaky) ReLU / ELU
GAIN_FLOW_HEAD = 1.0  # the flow predictors (2 output channels): flows of a few pixels
GAIN_DISP_HEAD = 0.5  # the disparity heads (1 output channel): sigmoid inputs of order 1
NUM_BATCHES_TRACKED = 200_000


def seed_name(name: str) -> str:
    """The name a tensor's values are seeded from: its name in their state dict without the
    ``model_pose.model_flow.`` prefix, so the flow network gets the same values in the full
    and in the flow-only layout."""
    return name[len(FULL_FLOW_PREFIX):] if name.startswith(FULL_FLOW_PREFIX) else name


def _uniform(name: str, shape: tuple[int, ...]) -> np.ndarray:
    """Uniform in [-1, 1), float64: ``Generator(PCG64(s)).random(shape) * 2 - 1`` with ``s``
    the first 8 bytes (little endian) of the sha256 of :func:`seed_name` ``(name)``."""
    seed = int.from_bytes(hashlib.sha256(seed_name(name).encode("utf-8")).digest()[:8], "little")
    rng = np.random.Generator(np.random.PCG64(seed))
    return rng.random(shape) * 2.0 - 1.0


def deterministic_tensor(name: str, shape: tuple[int, ...], dtype: torch.dtype = torch.float32,
                         batch_norm: bool = False) -> torch.Tensor:
    """The deterministic value of one tensor from its name and shape (see the module doc).

    * ``*.num_batches_tracked``: :data:`NUM_BATCHES_TRACKED`;
    * batch norm (``batch_norm``): weight 1 + 0.1 u, bias 0.05 u, running_mean 0.1 u,
      running_var 1 + 0.5 u (so in [0.5, 1.5]);
    * weights with 2+ dims: u * sqrt(3) * gain / sqrt(fan_in), i.e. std gain / sqrt(fan_in),
      gain :data:`GAIN_FLOW_HEAD` for 2 output channels, :data:`GAIN_DISP_HEAD` for 1,
      :data:`GAIN_HIDDEN` otherwise (``fc.weight``: gain 1);
    * other 1-dim tensors (biases): 0.05 u;

    where u is :func:`_uniform` of the name (float64, cast at the end). So the flow
    network's values are the same in the ``"full"`` and ``"flow"`` layouts.
    """
    shape = tuple(int(s) for s in shape)
    leaf = name.rsplit(".", 1)[-1]
    if leaf == "num_batches_tracked":
        return torch.tensor(NUM_BATCHES_TRACKED, dtype=dtype)
    u = _uniform(name, shape)
    if batch_norm:
        scale = {"weight": (1.0, 0.1), "bias": (0.0, 0.05), "running_mean": (0.0, 0.1),
                 "running_var": (1.0, 0.5)}[leaf]
        v = scale[0] + scale[1] * u
    elif len(shape) >= 2:
        fan_in = int(np.prod(shape[1:]))
        if name.endswith("fc.weight"):
            gain = 1.0
        elif shape[0] == 2:
            gain = GAIN_FLOW_HEAD
        elif shape[0] == 1:
            gain = GAIN_DISP_HEAD
        else:
            gain = GAIN_HIDDEN
        v = u * (math.sqrt(3.0) * gain / math.sqrt(fan_in))
    else:
        v = 0.05 * u
    return torch.from_numpy(v).to(dtype)


def deterministic_state_dict(layout: str = LAYOUT_FULL) -> OrderedDict:
    """Their ``model_state_dict`` (``"full"`` or ``"flow"`` layout) with deterministic values."""
    rows = their_layout(layout)
    bn_prefixes = {n[: -len("running_var")] for n, _, _ in rows if n.endswith(".running_var")}
    out = OrderedDict()
    for name, shape, dtype in rows:
        out[name] = deterministic_tensor(name, shape, dtype, batch_norm=name.rsplit(".", 1)[0] + "." in bn_prefixes)
    return out


def deterministic_checkpoint(layout: str = LAYOUT_FULL) -> dict:
    """A checkpoint dict in their file format ``{"iteration", "model_state_dict",
    "optimizer_state_dict"}`` (empty optimizer state) with :func:`deterministic_state_dict`."""
    return {"iteration": 0, "model_state_dict": deterministic_state_dict(layout),
            "optimizer_state_dict": {"state": {}, "param_groups": []}}


# ---------------------------------------------------------------------------
# their file -> our Checkpoint


def checkpoint_from_authors(obj, path: str = "<checkpoint>") -> Checkpoint:
    """Build our networks (eval mode) from their file dict (or a bare ``model_state_dict``)
    with their preprocessing: 256x832, BGR, ``cv2.INTER_LINEAR``, flow ``x / 255``,
    depth ``(x / 255 - 0.45) / 0.225``.

    Raises:
        ModelError: one line naming ``path`` (and the first offending key).
    """
    sd = obj.get("model_state_dict") if isinstance(obj, Mapping) and "model_state_dict" in obj else obj
    if not isinstance(sd, Mapping):
        raise ModelError(f"{path}: 'model_state_dict' is a {type(sd).__name__}, not a dict of tensors")
    layout = detect_layout(sd)
    flow_sd, depth_sd = their_to_ours(sd, path)
    flow = PWCNet(PWCConfig())
    flow.load_state_dict(flow_sd)
    flow.eval()
    entries = {"flow": NetEntry(flow, flow.config.to_dict(), {k: list(v) for k, v in FLOW_NORM.items()})}
    depth_entry = None
    if depth_sd is not None:
        n = sum(1 for k in depth_sd if k.startswith("decoder.dispconv.") and k.endswith(".weight"))
        depth = DepthNet(DepthConfig(scales=tuple(range(n))))
        depth.load_state_dict(depth_sd)
        depth.eval()
        depth_entry = NetEntry(depth, depth.config.to_dict(), {k: list(v) for k, v in DEPTH_NORM.items()})
    return Checkpoint(TRAIN_SIZE, CHANNEL_ORDER, entries["flow"], depth_entry, RESIZE, f"{SOURCE_TAG}-{layout}")
