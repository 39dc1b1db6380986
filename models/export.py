"""Export the flow and depth networks to ONNX and check them against torch.

Each exported file is a single self-contained ONNX model (weights inside, no
external-data sidecar) with a fixed input size. The graph does the normalisation
itself: its inputs are float32 ``(1, 3, H, W)`` images with pixel values 0..255 in
the recorded channel order.

* ``flow.onnx``: inputs ``image1``, ``image2``; outputs ``flow_fw`` (1 -> 2) and
  ``flow_bw`` (2 -> 1), ``(1, 2, H, W)`` float32 in input pixels, channel 0 = dx.
  Both directions come from one call (shared pyramid, batched decoder). Exported
  with ``with_masks=True`` it also outputs ``d_fb``, ``m_s``, ``m_o`` ``(1, 1, H, W)``
  (see :mod:`vo.flow.masks`); ``OnnxFlow`` uses the plain graph (see benchmarks/NETWORK.md).
* ``depth.onnx``: input ``image``; output ``depth`` ``(1, 1, H, W)`` in [min_depth, max_depth].

Metadata (``metadata_props``, keys prefixed ``trianflow.``): ``kind`` (flow|depth),
``input_size`` ("HxW"), ``channel_order`` (RGB|BGR), ``normalisation`` (JSON: mean,
std, pixel range, applied in graph), ``input_names`` and ``output_names`` (JSON lists),
``config`` (JSON constructor sizes), ``version`` (``vo.__version__``),
``format_version``; depth adds ``depth_range`` (JSON [min, max]).

Exporter: ``torch.onnx.export(..., dynamo=False)``, the TorchScript exporter, opset 18.
torch 2.13 defaults to the dynamo exporter; both give a single file with the same
results (max difference to torch ~5e-7 px) and the same onnxruntime speed, but the
dynamo exporter takes ~25 s on the flow graph (hundreds of cost-volume slices)
against ~8 s, which matters for tests and for users. ``EXPORTER`` selects it.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

import trianflow_vo
from trianflow_vo.models.checkpoint import Checkpoint
from trianflow_vo.models.depth_net import DepthNet, disp_to_depth
from trianflow_vo.models.pwc import PWCNet

OPSET = 18
EXPORTER = "torchscript"  # or "dynamo"
META_FORMAT_VERSION = "1"


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


def fb_distance_torch(flow_fw: torch.Tensor, flow_bw: torch.Tensor) -> torch.Tensor:
    """``|f(x) + b(x + f(x))|`` ``(N, 1, H, W)``; border-replicate sampling like the numpy version."""
    n, _, h, w = flow_fw.shape
    ys = torch.arange(h, dtype=flow_fw.dtype).view(1, h, 1).expand(1, h, w)
    xs = torch.arange(w, dtype=flow_fw.dtype).view(1, 1, w).expand(1, h, w)
    gx = (xs + flow_fw[:, 0]) * (2.0 / (w - 1)) - 1.0
    gy = (ys + flow_fw[:, 1]) * (2.0 / (h - 1)) - 1.0
    bw_at = F.grid_sample(flow_bw, torch.stack((gx, gy), dim=3), mode="bilinear",
                          padding_mode="border", align_corners=True)
    d = flow_fw + bw_at
    return torch.sqrt(d[:, :1] ** 2 + d[:, 1:] ** 2)


def occlusion_torch(flow_fw: torch.Tensor, flow_bw: torch.Tensor, range_threshold: float = 0.5) -> torch.Tensor:
    """M_o ``(1, 1, H, W)`` in {0, 1}: range map of ``flow_bw`` (bilinear forward splatting)
    above the threshold and forward flow landing inside the image. Batch size 1."""
    _, _, h, w = flow_bw.shape
    ys = torch.arange(h, dtype=flow_bw.dtype).view(h, 1).expand(h, w)
    xs = torch.arange(w, dtype=flow_bw.dtype).view(1, w).expand(h, w)
    x = (xs + flow_bw[0, 0]).reshape(-1)
    y = (ys + flow_bw[0, 1]).reshape(-1)
    x0 = torch.floor(x)
    y0 = torch.floor(y)
    idx_all = []
    wgt_all = []
    for dx in (0.0, 1.0):
        for dy in (0.0, 1.0):
            xi = x0 + dx
            yi = y0 + dy
            wgt = (1.0 - torch.abs(x - xi)) * (1.0 - torch.abs(y - yi))
            ok = (xi >= 0) & (xi <= w - 1) & (yi >= 0) & (yi <= h - 1)
            idx = (yi.clamp(0, h - 1) * w + xi.clamp(0, w - 1)).to(torch.int64)
            idx_all.append(idx)
            wgt_all.append(torch.where(ok, wgt, torch.zeros_like(wgt)))
    rng = torch.zeros(h * w, dtype=flow_bw.dtype).scatter_add(0, torch.cat(idx_all), torch.cat(wgt_all))
    visible = rng.view(1, 1, h, w) > range_threshold
    xt = xs + flow_fw[0, 0]
    yt = ys + flow_fw[0, 1]
    inside = ((xt >= 0) & (xt <= w - 1) & (yt >= 0) & (yt <= h - 1)).view(1, 1, h, w)
    return (visible & inside).to(flow_fw.dtype)


class FlowGraph(nn.Module):
    """What ``flow.onnx`` computes: normalisation, forward and backward flow (and masks)."""

    def __init__(self, net: PWCNet, norm: dict, with_masks: bool = False):
        super().__init__()
        self.net = net
        self.norm = _Normalise(norm)
        self.with_masks = with_masks

    def output_names(self) -> list[str]:
        return ["flow_fw", "flow_bw"] + (["d_fb", "m_s", "m_o"] if self.with_masks else [])

    def forward(self, image1: torch.Tensor, image2: torch.Tensor):
        fw, bw = self.net.forward_backward(self.norm(image1), self.norm(image2))
        if not self.with_masks:
            return fw, bw
        d_fb = fb_distance_torch(fw, bw)
        return fw, bw, d_fb, 1.0 / (0.1 + d_fb), occlusion_torch(fw, bw)


class DepthGraph(nn.Module):
    """What ``depth.onnx`` computes: normalisation and depth at full resolution."""

    def __init__(self, net: DepthNet, norm: dict):
        super().__init__()
        self.net = net
        self.norm = _Normalise(norm)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        sigma = self.net(self.norm(image))[0]
        return disp_to_depth(sigma, self.net.config.min_depth, self.net.config.max_depth)


def _metadata(kind: str, size, channel_order: str, norm: dict, inputs, outputs, config: dict,
              extra: dict | None = None) -> dict[str, str]:
    meta = {
        "kind": kind,
        "format_version": META_FORMAT_VERSION,
        "input_size": f"{int(size[0])}x{int(size[1])}",
        "channel_order": channel_order,
        "normalisation": json.dumps({"mean": norm["mean"], "std": norm["std"], "pixel_range": [0, 255],
                                     "formula": "(x / 255 - mean) / std", "applied": "in_graph"}),
        "input_names": json.dumps(list(inputs)),
        "output_names": json.dumps(list(outputs)),
        "config": json.dumps(config),
        "version": trianflow_vo.__version__,
    }
    meta.update(extra or {})
    return {"trianflow." + k: v for k, v in meta.items()}


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


def export_flow(net: PWCNet, norm: dict, size, channel_order: str, path, with_masks: bool = False) -> Path:
    graph = FlowGraph(net, norm, with_masks)
    h, w = size
    args = (torch.zeros(1, 3, h, w), torch.zeros(1, 3, h, w))
    outs = graph.output_names()
    meta = _metadata("flow", size, channel_order, norm, ["image1", "image2"], outs, net.config.to_dict())
    return export_module(graph, args, path, ["image1", "image2"], outs, meta)


def export_depth(net: DepthNet, norm: dict, size, channel_order: str, path) -> Path:
    graph = DepthGraph(net, norm)
    h, w = size
    cfg = net.config
    meta = _metadata("depth", size, channel_order, norm, ["image"], ["depth"], cfg.to_dict(),
                     {"depth_range": json.dumps([cfg.min_depth, cfg.max_depth])})
    return export_module(graph, (torch.zeros(1, 3, h, w),), path, ["image"], ["depth"], meta)


def ort_session(path: str | Path, threads: int = 2):
    """An onnxruntime session with the settings the inference path uses."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])


def parity(module: nn.Module, path: str | Path, inputs: dict[str, np.ndarray]) -> dict[str, float]:
    """Max abs difference per output between torch ``module`` and onnxruntime on ``inputs``."""
    sess = ort_session(path)
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


def export_checkpoint(ckpt: Checkpoint, out_dir: str | Path, size=None, seed: int = 0) -> dict:
    """Write ``flow.onnx`` and/or ``depth.onnx`` into ``out_dir`` and check parity.

    Returns ``{name: {"path": str, "max_abs_diff": {output: float}}}``.
    """
    out_dir = Path(out_dir)
    size = tuple(size or ckpt.input_size)
    results = {}
    imgs = random_images(size, 2, seed)
    if ckpt.flow is not None:
        net = ckpt.flow.net
        net.check_size(*size)
        path = export_flow(net, ckpt.flow.normalisation, size, ckpt.channel_order, out_dir / "flow.onnx")
        graph = FlowGraph(net, ckpt.flow.normalisation).eval()
        diffs = parity(graph, path, {"image1": imgs[0], "image2": imgs[1]})
        results["flow"] = {"path": str(path), "max_abs_diff": diffs}
    if ckpt.depth is not None:
        net = ckpt.depth.net
        net.check_size(*size)
        path = export_depth(net, ckpt.depth.normalisation, size, ckpt.channel_order, out_dir / "depth.onnx")
        graph = DepthGraph(net, ckpt.depth.normalisation).eval()
        diffs = parity(graph, path, {"image": imgs[0]})
        results["depth"] = {"path": str(path), "max_abs_diff": diffs}
    return results
