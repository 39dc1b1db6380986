"""Export the flow and depth networks to ONNX and check them against torch.

Each exported file is a single self-contained ONNX model (weights inside, no
external-data sidecar) with a fixed input size. The graph does the normalisation
itself: its inputs are float32 ``(1, 3, H, W)`` images with pixel values 0..255 in
the recorded channel order.

* ``flow.onnx``: inputs ``image1``, ``image2``; outputs ``flow_fw`` (1 -> 2) and
  ``flow_bw`` (2 -> 1), ``(1, 2, H, W)`` float32 in input pixels, channel 0 = dx.
  Both directions come from one call (shared pyramid, batched decoder). The masks
  M_s, M_o are not in the graph: the run path computes them with numpy
  (:mod:`trianflow_vo.flow.masks`), which measured faster (benchmarks/NETWORK.md).
* ``depth.onnx``: input ``image``; output ``depth`` ``(1, 1, H, W)`` in [min_depth, max_depth].

Metadata (``metadata_props``, keys prefixed ``trianflow.``): built by
:func:`trianflow_vo.nets.onnx_runtime.model_metadata`, the schema the run path
validates with (``kind``, ``format_version``, ``input_size`` (the graph's fixed size),
``channel_order``, ``normalisation``, ``input_names``, ``output_names``, ``config``,
``version``, ``resize``; depth adds ``depth_range``). :func:`export_checkpoint` adds
``train_input_size`` (JSON ``[H, W]``, the size the weights were trained at) and
``weights`` (JSON ``{"source": ..., "file": ...}``: our format or the authors' layout).
For the authors' networks: ``BGR``, mean 0 / std 1 (flow) and 0.45 / 0.225 (depth),
``train_input_size`` [256, 832], ``resize`` ``"linear"`` (cv2.INTER_LINEAR).
The parity check opens the written file the way the run path does
(:func:`trianflow_vo.nets.onnx_runtime.open_model`).

:func:`export_checkpoint` writes into a fresh temporary directory beside ``out_dir``
(inside its parent) and moves the files into ``out_dir`` only when every export and
parity check succeeded, so a failure leaves nothing half-written there.

Exporter: ``torch.onnx.export(..., dynamo=False)``, the TorchScript exporter, opset 18.
torch 2.13 defaults to the dynamo exporter; both give a single file with the same
results (max difference to torch ~5e-7 px) and the same onnxruntime speed, but the
dynamo exporter takes ~25 s on the flow graph (hundreds of cost-volume slices)
against ~8 s, which matters for tests and for users. ``EXPORTER`` selects it.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import warnings
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from trianflow_vo.models.checkpoint import Checkpoint
from trianflow_vo.models.depth_net import DepthNet, disp_to_depth
from trianflow_vo.models.pwc import PWCNet
from trianflow_vo.nets.onnx_runtime import (
    DEFAULT_RESIZE,
    KEY_DEPTH_RANGE,
    KINDS,
    model_metadata,
    open_model,
    open_session,
)

KEY_TRAIN_INPUT_SIZE = "train_input_size"
KEY_WEIGHTS = "weights"

OPSET = 18
EXPORTER = "torchscript"  # or "dynamo"


class _Normalise(nn.Module):
    def __init__(self, norm: dict):
        super().__init__()
        mean = torch.tensor(norm["mean"], dtype=torch.float32).view(1, 3, 1, 1)
        std = torch.tensor(norm["std"], dtype=torch.float32).view(1, 3, 1, 1)
        # (x / 255 - mean) / std  ==  x * a + b
        self.register_buffer("a", 1.0 / (255.0 * std))
        self.register_buffer("b", -mean / std)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.a + self.b


class FlowGraph(nn.Module):
    """What ``flow.onnx`` computes: normalisation, forward and backward flow."""

    def __init__(self, net: PWCNet, norm: dict):
        super().__init__()
        self.net = net
        self.norm = _Normalise(norm)

    def output_names(self) -> list[str]:
        return list(KINDS["flow"].outputs)

    def forward(self, image1: torch.Tensor, image2: torch.Tensor):
        return self.net.forward_backward(self.norm(image1), self.norm(image2))


class DepthGraph(nn.Module):
    """What ``depth.onnx`` computes: normalisation and depth at full resolution."""

    def __init__(self, net: DepthNet, norm: dict):
        super().__init__()
        self.net = net
        self.norm = _Normalise(norm)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        sigma = self.net(self.norm(image))[0]
        return disp_to_depth(sigma, self.net.config.min_depth, self.net.config.max_depth)


def export_module(module: nn.Module, args: tuple, path: str | Path, input_names, output_names,
                  metadata: dict[str, str]) -> Path:
    """Export ``module`` at the fixed shapes of ``args`` to one ONNX file with ``metadata``."""
    import onnx

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    module.eval()
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # tracer warnings about shape checks: shapes are fixed here
        torch.onnx.export(module, args, str(path), input_names=list(input_names),
                          output_names=list(output_names), opset_version=OPSET, dynamo=(EXPORTER == "dynamo"),
                          external_data=False, verbose=False)
    model = onnx.load(str(path))
    del model.metadata_props[:]
    for k, v in metadata.items():
        prop = model.metadata_props.add()
        prop.key = k
        prop.value = v
    onnx.checker.check_model(model)
    onnx.save_model(model, str(path), save_as_external_data=False)
    return path


def export_flow(net: PWCNet, norm: dict, size, channel_order: str, path, resize: str = DEFAULT_RESIZE,
                extra: dict | None = None) -> Path:
    """``flow.onnx`` at the fixed ``size`` (H, W); ``extra``: more metadata keys."""
    graph = FlowGraph(net, norm)
    h, w = size
    args = (torch.zeros(1, 3, h, w), torch.zeros(1, 3, h, w))
    ins, outs = list(KINDS["flow"].inputs), graph.output_names()
    meta = model_metadata("flow", size, channel_order, norm, ins, outs, net.config.to_dict(), extra,
                          resize=resize)
    return export_module(graph, args, path, ins, outs, meta)


def export_depth(net: DepthNet, norm: dict, size, channel_order: str, path, resize: str = DEFAULT_RESIZE,
                 extra: dict | None = None) -> Path:
    """``depth.onnx`` at the fixed ``size`` (H, W); ``extra``: more metadata keys."""
    graph = DepthGraph(net, norm)
    h, w = size
    cfg = net.config
    ins, outs = list(KINDS["depth"].inputs), list(KINDS["depth"].outputs)
    meta = model_metadata("depth", size, channel_order, norm, ins, outs, cfg.to_dict(),
                          {KEY_DEPTH_RANGE: [cfg.min_depth, cfg.max_depth], **(extra or {})}, resize=resize)
    return export_module(graph, (torch.zeros(1, 3, h, w),), path, ins, outs, meta)


def parity(module: nn.Module, path: str | Path, inputs: dict[str, np.ndarray], session=None) -> dict[str, float]:
    """Max abs difference per output between torch ``module`` and onnxruntime on ``inputs``.

    ``session``: an open onnxruntime session of ``path`` (default: one from
    :func:`trianflow_vo.nets.onnx_runtime.open_session`, the run path's settings).
    """
    sess = open_session(path) if session is None else session
    names = [o.name for o in sess.get_outputs()]
    got = sess.run(names, inputs)
    with torch.no_grad():
        ref = module(*[torch.from_numpy(v) for v in inputs.values()])
    if isinstance(ref, torch.Tensor):
        ref = (ref,)
    return {n: float(np.max(np.abs(g - r.numpy()))) for n, g, r in zip(names, got, ref)}


def random_images(size, n: int, seed: int) -> list[np.ndarray]:
    """``n`` smooth random images ``(1, 3, H, W)`` float32 0..255 (structure at several scales)."""
    rng = np.random.default_rng(seed)
    h, w = size
    out = []
    for _ in range(n):
        img = np.zeros((3, h, w), np.float32)
        for s in (4, 16, 64):
            small = rng.uniform(0, 255, (3, max(1, h // s), max(1, w // s))).astype(np.float32)
            t = torch.from_numpy(small)[None]
            img += F.interpolate(t, size=(h, w), mode="bilinear", align_corners=False)[0].numpy() / 3
        out.append(img[None].copy())
    return out


def export_checkpoint(ckpt: Checkpoint, out_dir: str | Path, size=None, seed: int = 0,
                      weights_file: str | None = None) -> dict:
    """Write ``flow.onnx`` and/or ``depth.onnx`` into ``out_dir`` and check parity.

    Everything is written to a temporary directory inside ``out_dir``'s parent first; the
    files are moved into ``out_dir`` (created if needed, other files left alone) only when
    all exports and checks succeeded. ``weights_file``: recorded in the ``weights`` metadata.

    Returns ``{name: {"path": str, "max_abs_diff": {output: float}}}``.
    """
    out_dir = Path(out_dir)
    size = tuple(size or ckpt.input_size)
    for entry in (ckpt.flow, ckpt.depth):
        if entry is not None:
            entry.net.check_size(*size)
    extra = {KEY_TRAIN_INPUT_SIZE: [int(v) for v in ckpt.input_size],
             KEY_WEIGHTS: {"source": ckpt.source, "file": weights_file}}
    results = {}
    imgs = random_images(size, 2, seed)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.export-", dir=out_dir.parent))
    try:
        if ckpt.flow is not None:
            net = ckpt.flow.net
            path = export_flow(net, ckpt.flow.normalisation, size, ckpt.channel_order, tmp / "flow.onnx",
                               ckpt.resize, extra)
            sess, _ = open_model(path, "flow")  # the file passes the run path's checks
            graph = FlowGraph(net, ckpt.flow.normalisation).eval()
            diffs = parity(graph, path, {"image1": imgs[0], "image2": imgs[1]}, session=sess)
            results["flow"] = {"path": str(out_dir / path.name), "max_abs_diff": diffs}
        if ckpt.depth is not None:
            net = ckpt.depth.net
            path = export_depth(net, ckpt.depth.normalisation, size, ckpt.channel_order, tmp / "depth.onnx",
                                ckpt.resize, extra)
            sess, _ = open_model(path, "depth")
            graph = DepthGraph(net, ckpt.depth.normalisation).eval()
            diffs = parity(graph, path, {"image": imgs[0]}, session=sess)
            results["depth"] = {"path": str(out_dir / path.name), "max_abs_diff": diffs}
        out_dir.mkdir(parents=True, exist_ok=True)
        for name in results:
            try:
                os.replace(tmp / f"{name}.onnx", out_dir / f"{name}.onnx")
            except OSError:  # out_dir on another file system (e.g. a symlink): copy, then replace
                shutil.move(str(tmp / f"{name}.onnx"), str(out_dir / f"{name}.onnx"))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return results
