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
* ``flow_encoder.onnx`` + ``flow_decoder.onnx`` (written beside ``flow.onnx`` by
  :func:`export_checkpoint`; ``split=False`` skips them): the same flow network in two
  graphs, so the run path computes a frame's pyramid once (``OnnxFlow.prepare``) and only
  decodes per pair. Encoder: input ``image`` -> the pyramid levels the decoder reads
  (``pyr2`` .. ``pyr6`` by default, normalisation inside). Decoder: ``image1_pyr*``,
  ``image2_pyr*`` -> ``flow_fw``, ``flow_bw`` (both directions as one batch of 2), equal
  to ``flow.onnx``'s outputs. ``flow.onnx`` records them in its ``split`` metadata key,
  and the parts carry the same ``split`` id (the reader checks that they belong together).
* ``depth.onnx``: input ``image``; output ``depth`` ``(1, 1, H, W)`` in [min_depth, max_depth].
* ``export_checkpoint(..., quantize="int8", calibration=frames)``: the flow decoder and
  depth.onnx are then static int8 (QDQ) graphs, metadata ``quantization``
  (:func:`quantize_int8`); flow.onnx and the encoder stay fp32.

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
import uuid
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
    KEY_FEATURES,
    KEY_QUANTIZATION,
    KEY_SPLIT,
    KINDS,
    PART_KINDS,
    decoder_input_names,
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


FLOW_ENCODER_FILE = "flow_encoder.onnx"
FLOW_DECODER_FILE = "flow_decoder.onnx"


def feature_names(net: PWCNet) -> list[str]:
    """Names of the pyramid levels the decoder reads, finest first (``pyr2`` .. ``pyr6``)."""
    return [f"pyr{lvl}" for lvl in sorted(net.levels)]


def feature_shapes(net: PWCNet, size) -> list[list[int]]:
    h, w = (int(v) for v in size)
    return [[1, net.config.pyramid_channels[lvl - 1], h >> lvl, w >> lvl] for lvl in sorted(net.levels)]


class FlowEncoderGraph(nn.Module):
    """What ``flow_encoder.onnx`` computes: normalisation and the pyramid levels the decoder reads."""

    def __init__(self, net: PWCNet, norm: dict):
        super().__init__()
        self.net = net
        self.norm = _Normalise(norm)

    def forward(self, image: torch.Tensor):
        self.net.check_size(image.shape[2], image.shape[3])
        feats = self.net.pyramid(self.norm(image))
        return tuple(feats[lvl - 1] for lvl in sorted(self.net.levels))


class FlowDecoderGraph(nn.Module):
    """What ``flow_decoder.onnx`` computes: from the two pyramids (``image1_*`` then
    ``image2_*``, finest first) both flows, decoded as one batch of 2, in input pixels."""

    def __init__(self, net: PWCNet, size):
        super().__init__()
        self.net = net
        self.size = tuple(int(v) for v in size)

    def forward(self, *feats: torch.Tensor):
        levels = sorted(self.net.levels)
        k = len(levels)
        a, b = feats[:k], feats[k:]
        n_all = len(self.net.config.pyramid_channels)
        f1: list = [None] * n_all
        f2: list = [None] * n_all
        for i, lvl in enumerate(levels):
            f1[lvl - 1] = torch.cat((a[i], b[i]), dim=0)
            f2[lvl - 1] = torch.cat((b[i], a[i]), dim=0)
        flows = self.net.decode(f1, f2)
        full = self.net.full_flow(flows[0], self.size)
        return full[:1], full[1:]


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
                extra: dict | None = None, split: bool = False) -> Path:
    """``flow.onnx`` at the fixed ``size`` (H, W); ``extra``: more metadata keys.

    ``split``: also write ``flow_encoder.onnx`` and ``flow_decoder.onnx`` beside it
    (:func:`export_flow_split`) and record them in flow.onnx's ``split`` key.
    """
    graph = FlowGraph(net, norm)
    h, w = size
    args = (torch.zeros(1, 3, h, w), torch.zeros(1, 3, h, w))
    ins, outs = list(KINDS["flow"].inputs), graph.output_names()
    extra = dict(extra or {})
    if split:
        split_id = uuid.uuid4().hex
        extra[KEY_SPLIT] = {"id": split_id, "encoder": FLOW_ENCODER_FILE, "decoder": FLOW_DECODER_FILE}
        export_flow_split(net, norm, size, channel_order, Path(path).parent, split_id, resize,
                          {k: v for k, v in extra.items() if k != KEY_SPLIT})
    meta = model_metadata("flow", size, channel_order, norm, ins, outs, net.config.to_dict(), extra,
                          resize=resize)
    return export_module(graph, args, path, ins, outs, meta)


def export_flow_split(net: PWCNet, norm: dict, size, channel_order: str, out_dir, split_id: str,
                      resize: str = DEFAULT_RESIZE, extra: dict | None = None) -> tuple[Path, Path]:
    """``flow_encoder.onnx`` and ``flow_decoder.onnx`` in ``out_dir`` (``split`` id ``split_id``)."""
    out_dir = Path(out_dir)
    h, w = (int(v) for v in size)
    net.check_size(h, w)
    names, shapes = feature_names(net), feature_shapes(net, size)
    feats = {"names": names, "shapes": shapes}
    common = {**(extra or {}), KEY_FEATURES: feats, KEY_SPLIT: {"id": split_id, "of": "flow.onnx"}}
    cfg = net.config.to_dict()
    enc_meta = model_metadata("flow_encoder", size, channel_order, norm, ["image"], names, cfg, common,
                              resize=resize)
    enc = export_module(FlowEncoderGraph(net, norm), (torch.zeros(1, 3, h, w),), out_dir / FLOW_ENCODER_FILE,
                        ["image"], names, enc_meta)
    dec_in, dec_out = decoder_input_names(names), list(PART_KINDS["flow_decoder"].outputs)
    dec_meta = model_metadata("flow_decoder", size, channel_order, norm, dec_in, dec_out, cfg, common,
                              resize=resize)
    dec_args = tuple(torch.zeros(*sh) for sh in shapes) * 2
    dec = export_module(FlowDecoderGraph(net, size), dec_args, out_dir / FLOW_DECODER_FILE, dec_in, dec_out,
                        dec_meta)
    return enc, dec


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


QUANTIZATION_INT8 = "int8-static-qdq"


def quantize_int8(src: str | Path, dst: str | Path, feeds: list[dict[str, np.ndarray]]) -> Path:
    """Static int8 quantisation of ``src``'s convolutions into ``dst`` (QDQ format:
    activations uint8 with ranges calibrated (min/max) on ``feeds``, one input dict per
    call; weights int8 per output channel, reduced range (no VNNI saturation on AVX2)).
    ``src``'s metadata is kept and ``quantization`` added. (Dynamic quantisation,
    ``ConvInteger``, measured 3.5x slower than fp32 here: benchmarks/NETWORK.md.)"""
    import onnx
    from onnxruntime.quantization import (
        CalibrationDataReader,
        CalibrationMethod,
        QuantFormat,
        QuantType,
        quantize_static,
    )
    from onnxruntime.quantization.shape_inference import quant_pre_process

    class _Reader(CalibrationDataReader):
        def __init__(self):
            self.it = iter(feeds)

        def get_next(self):
            return next(self.it, None)

    src, dst = Path(src), Path(dst)
    pre = dst.with_name(dst.stem + ".pre.onnx")
    try:
        quant_pre_process(str(src), str(pre), skip_symbolic_shape=True)
        quantize_static(str(pre), str(dst), _Reader(), quant_format=QuantFormat.QDQ,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                        op_types_to_quantize=["Conv"], per_channel=True, reduce_range=True,
                        calibrate_method=CalibrationMethod.MinMax)
    finally:
        pre.unlink(missing_ok=True)
    model = onnx.load(str(dst))
    meta = {p.key: p.value for p in onnx.load(str(src)).metadata_props}
    meta["trianflow." + KEY_QUANTIZATION] = QUANTIZATION_INT8
    del model.metadata_props[:]
    for k, v in meta.items():
        prop = model.metadata_props.add()
        prop.key, prop.value = k, v
    onnx.save_model(model, str(dst), save_as_external_data=False)
    return dst


def split_parity(net: PWCNet, norm: dict, size, out_dir: str | Path, inputs: dict[str, np.ndarray],
                 threads: int = 2) -> dict[str, float]:
    """Max abs difference per flow output between torch :class:`FlowGraph` and the split
    graphs in ``out_dir`` run as the run path does (encoder per image, then the decoder)."""
    from trianflow_vo.nets.onnx_runtime import OnnxModel

    out_dir = Path(out_dir)
    enc = OnnxModel(out_dir / FLOW_ENCODER_FILE, "flow_encoder", threads)
    dec = OnnxModel(out_dir / FLOW_DECODER_FILE, "flow_decoder", threads)
    pa, pb = enc.run(inputs["image1"]), enc.run(inputs["image2"])
    got = dec.run(*pa, *pb)
    with torch.no_grad():
        ref = FlowGraph(net, norm).eval()(torch.from_numpy(inputs["image1"]), torch.from_numpy(inputs["image2"]))
    return {n: float(np.max(np.abs(g - r.numpy()))) for n, g, r in zip(dec.info.output_names, got, ref)}


def _quantize_parts(tmp: Path, results: dict, calibration: list[np.ndarray], threads: int = 2) -> None:
    """Replace ``tmp``'s flow decoder and depth graphs by their int8 versions, calibrated on
    ``calibration`` (BGR uint8 frames of a sequence, in order); record in ``results`` the
    max and median abs difference int8 - fp32 on those frames."""
    from trianflow_vo.nets.onnx_runtime import OnnxModel

    if len(calibration) < 2:
        raise ValueError("int8 quantisation needs at least 2 calibration frames")
    if (tmp / FLOW_DECODER_FILE).is_file():
        enc = OnnxModel(tmp / FLOW_ENCODER_FILE, "flow_encoder", threads)
        dec = OnnxModel(tmp / FLOW_DECODER_FILE, "flow_decoder", threads)
        pyrs = [enc.run(enc.to_input(im)) for im in calibration]
        feeds = [dict(zip(dec.info.input_names, [*pyrs[i], *pyrs[i + 1]])) for i in range(len(pyrs) - 1)]
        ref = [dec.session.run(["flow_fw"], f)[0] for f in feeds]
        del dec
        quantize_int8(tmp / FLOW_DECODER_FILE, tmp / "q.onnx", feeds)
        os.replace(tmp / "q.onnx", tmp / FLOW_DECODER_FILE)
        q = OnnxModel(tmp / FLOW_DECODER_FILE, "flow_decoder", threads)
        epe = [np.linalg.norm(q.session.run(["flow_fw"], f)[0] - r, axis=1) for f, r in zip(feeds, ref)]
        results["flow_decoder_int8"] = {"path": results["flow_split"]["path"], "vs_fp32": {
            "epe_median_px": float(np.median(np.concatenate([e.ravel() for e in epe]))),
            "epe_max_px": float(max(e.max() for e in epe)),
            "fp32_flow_max_px": float(max(np.abs(r).max() for r in ref))}}
    if (tmp / "depth.onnx").is_file():
        depth = OnnxModel(tmp / "depth.onnx", "depth", threads)
        feeds = [{"image": depth.to_input(im)} for im in calibration]
        ref = [depth.session.run(None, f)[0] for f in feeds]
        del depth
        quantize_int8(tmp / "depth.onnx", tmp / "q.onnx", feeds)
        os.replace(tmp / "q.onnx", tmp / "depth.onnx")
        q = OnnxModel(tmp / "depth.onnx", "depth", threads)
        rel = [np.abs(q.session.run(None, f)[0] - r) / r for f, r in zip(feeds, ref)]
        results["depth_int8"] = {"path": results["depth"]["path"], "vs_fp32": {
            "rel_err_median": float(np.median(np.concatenate([e.ravel() for e in rel]))),
            "rel_err_max": float(max(e.max() for e in rel))}}


def export_checkpoint(ckpt: Checkpoint, out_dir: str | Path, size=None, seed: int = 0,
                      weights_file: str | None = None, split: bool = True, quantize: str | None = None,
                      calibration: list[np.ndarray] | None = None) -> dict:
    """Write ``flow.onnx`` (+ ``flow_encoder.onnx``, ``flow_decoder.onnx`` unless
    ``split=False``) and/or ``depth.onnx`` into ``out_dir`` and check parity.

    ``quantize="int8"``: after the fp32 parity checks, the flow decoder and the depth
    graph are replaced by static int8 versions (:func:`quantize_int8`) calibrated on
    ``calibration`` (BGR uint8 frames, consecutive); ``flow.onnx`` and the encoder stay
    fp32. Their difference to fp32 is in the results (``flow_decoder_int8``, ``depth_int8``:
    ``vs_fp32``) instead of a parity check.

    Everything is written to a temporary directory inside ``out_dir``'s parent first; the
    files are moved into ``out_dir`` (created if needed, other files left alone) only when
    all exports and checks succeeded. ``weights_file``: recorded in the ``weights`` metadata.

    Returns ``{name: {"path": str, "max_abs_diff": {output: float}}}`` (name ``flow``,
    ``flow_split`` (the path is the decoder's; the differences of encoder + decoder), ``depth``).
    """
    out_dir = Path(out_dir)
    size = tuple(size or ckpt.input_size)
    if quantize not in (None, "int8"):
        raise ValueError(f"quantize must be None or 'int8', got {quantize!r}")
    if quantize and (not calibration or len(calibration) < 2):
        raise ValueError("int8 quantisation needs calibration frames (at least 2)")
    if quantize and ckpt.flow is not None and not split:
        raise ValueError("int8 quantisation of the flow network needs the split graphs")
    for entry in (ckpt.flow, ckpt.depth):
        if entry is not None:
            entry.net.check_size(*size)
    extra = {KEY_TRAIN_INPUT_SIZE: [int(v) for v in ckpt.input_size],
             KEY_WEIGHTS: {"source": ckpt.source, "file": weights_file}}
    results = {}
    files: dict[str, list[str]] = {}
    imgs = random_images(size, 2, seed)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.export-", dir=out_dir.parent))
    try:
        if ckpt.flow is not None:
            net = ckpt.flow.net
            path = export_flow(net, ckpt.flow.normalisation, size, ckpt.channel_order, tmp / "flow.onnx",
                               ckpt.resize, extra, split=split)
            sess, _ = open_model(path, "flow")  # the file passes the run path's checks
            graph = FlowGraph(net, ckpt.flow.normalisation).eval()
            feed = {"image1": imgs[0], "image2": imgs[1]}
            diffs = parity(graph, path, feed, session=sess)
            del sess
            results["flow"] = {"path": str(out_dir / path.name), "max_abs_diff": diffs}
            files["flow"] = ["flow.onnx"]
            if split:
                diffs = split_parity(net, ckpt.flow.normalisation, size, tmp, feed)
                results["flow_split"] = {"path": str(out_dir / FLOW_DECODER_FILE), "max_abs_diff": diffs}
                files["flow"] += [FLOW_ENCODER_FILE, FLOW_DECODER_FILE]
        if ckpt.depth is not None:
            net = ckpt.depth.net
            path = export_depth(net, ckpt.depth.normalisation, size, ckpt.channel_order, tmp / "depth.onnx",
                                ckpt.resize, extra)
            sess, _ = open_model(path, "depth")
            graph = DepthGraph(net, ckpt.depth.normalisation).eval()
            diffs = parity(graph, path, {"image": imgs[0]}, session=sess)
            results["depth"] = {"path": str(out_dir / path.name), "max_abs_diff": diffs}
            files["depth"] = ["depth.onnx"]
        if quantize:
            _quantize_parts(tmp, results, calibration)
        out_dir.mkdir(parents=True, exist_ok=True)
        # the parts first, flow.onnx (which names them) last
        names = [f for group in files.values() for f in group]
        names.sort(key=lambda f: f == "flow.onnx")
        if not split and ckpt.flow is not None:  # a re-export without split: no stale parts beside it
            for stale in (FLOW_ENCODER_FILE, FLOW_DECODER_FILE):
                (out_dir / stale).unlink(missing_ok=True)
        for name in names:
            try:
                os.replace(tmp / name, out_dir / name)
            except OSError:  # out_dir on another file system (e.g. a symlink): copy, then replace
                shutil.move(str(tmp / name), str(out_dir / name))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return results
