"""Optical flow from an exported ONNX flow network (``trianflow-vo export``), via onnxruntime.

Also holds :func:`open_model`, shared with :mod:`vo.depth.onnx_depth`: it opens an
exported model and checks its ``trianflow.*`` metadata (kind, input size, channel
order, normalisation, input/output names) against the graph. No torch here.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from trianflow_vo.errors import DependencyError, ModelError

META_PREFIX = "trianflow."
META_FORMAT_VERSION = "1"
EXPECTED_IO = {
    "flow": (["image1", "image2"], ["flow_fw", "flow_bw"]),
    "depth": (["image"], ["depth"]),
}


@dataclass(frozen=True)
class ModelInfo:
    """What the metadata of an exported model says."""

    path: Path
    kind: str
    input_size: tuple[int, int]  # (H, W) of the graph input
    channel_order: str  # "RGB" or "BGR"
    version: str
    config: dict
    meta: dict  # every trianflow.* key, prefix removed


def _parse_size(text: str, path: Path) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ModelError(f"{path}: metadata input_size {text!r} is not 'HxW'") from None
    if h <= 0 or w <= 0:
        raise ModelError(f"{path}: metadata input_size {text!r} is not positive")
    return h, w


def _json(meta: dict, key: str, path: Path):
    try:
        return json.loads(meta[key])
    except (KeyError, json.JSONDecodeError):
        raise ModelError(f"{path}: metadata '{META_PREFIX}{key}' is missing or not JSON") from None


def open_model(path: str | Path, kind: str, threads: int = 2):
    """Open an exported model with onnxruntime and validate it.

    Args:
        path: the ``.onnx`` file.
        kind: ``"flow"`` or ``"depth"``.
        threads: ``intra_op_num_threads`` (``inter_op_num_threads`` is 1).

    Returns:
        ``(session, ModelInfo)``.

    Raises:
        DependencyError: onnxruntime is not installed.
        ModelError: missing file, not ONNX, no or wrong metadata, shapes that disagree.
    """
    path = Path(path)
    if kind not in EXPECTED_IO:
        raise ValueError(f"kind must be one of {sorted(EXPECTED_IO)}")
    if int(threads) < 1:
        raise ValueError("threads must be >= 1")
    try:
        import onnxruntime as ort
    except ImportError:
        raise DependencyError("onnxruntime is needed to run network models: pip install onnxruntime "
                              "(or pip install 'trianflow-vo[onnx]')") from None
    if not path.is_file():
        raise ModelError(f"{path}: {kind} model file not found")
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = int(threads)
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.log_severity_level = 3
    # idle worker threads sleep instead of spinning: on a busy CPU (and between calls,
    # while the pipeline runs OpenCV/numpy) spinning threads steal the cores that do
    # the work; see benchmarks/NETWORK.md
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    try:
        sess = ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own exception types for unreadable graphs
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ModelError(f"{path}: not a usable ONNX model ({first[:200]})") from None

    raw = sess.get_modelmeta().custom_metadata_map
    meta = {k[len(META_PREFIX):]: v for k, v in raw.items() if k.startswith(META_PREFIX)}
    if "kind" not in meta:
        raise ModelError(f"{path}: no trianflow-vo metadata; export the model with 'trianflow-vo export'")
    if meta["kind"] != kind:
        raise ModelError(f"{path}: is a {meta['kind']!r} model, expected a {kind!r} model")
    if meta.get("format_version") != META_FORMAT_VERSION:
        raise ModelError(f"{path}: unsupported metadata format_version {meta.get('format_version')!r}")
    if "input_size" not in meta:
        raise ModelError(f"{path}: metadata has no input_size")
    size = _parse_size(meta["input_size"], path)
    order = meta.get("channel_order")
    if order not in ("RGB", "BGR"):
        raise ModelError(f"{path}: metadata channel_order must be RGB or BGR, got {order!r}")
    norm = _json(meta, "normalisation", path)
    if not isinstance(norm, dict) or norm.get("applied") != "in_graph":
        raise ModelError(f"{path}: normalisation must be applied in the graph (metadata normalisation.applied)")
    config = _json(meta, "config", path) if "config" in meta else {}

    want_in, want_out = EXPECTED_IO[kind]
    inputs = sess.get_inputs()
    if [i.name for i in inputs] != want_in:
        raise ModelError(f"{path}: graph inputs {[i.name for i in inputs]} != expected {want_in}")
    for i in inputs:
        if list(i.shape) != [1, 3, size[0], size[1]]:
            raise ModelError(f"{path}: input {i.name!r} has shape {i.shape}, metadata input_size says "
                             f"[1, 3, {size[0]}, {size[1]}]")
    out_names = [o.name for o in sess.get_outputs()]
    missing = [n for n in want_out if n not in out_names]
    if missing:
        raise ModelError(f"{path}: graph lacks outputs {missing}")
    n_ch = 2 if kind == "flow" else 1
    for o in sess.get_outputs():
        if o.name in want_out and list(o.shape) != [1, n_ch, size[0], size[1]]:
            raise ModelError(f"{path}: output {o.name!r} has shape {o.shape}, expected "
                             f"[1, {n_ch}, {size[0]}, {size[1]}]")
    info = ModelInfo(path, kind, size, order, meta.get("version", "?"), config, meta)
    return sess, info


def to_model_input(image: np.ndarray, info: ModelInfo) -> np.ndarray:
    """A working-resolution BGR uint8 image ``(h, w, 3)`` -> graph input ``(1, 3, H, W)`` float32 0..255."""
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"image must be (h, w, 3) uint8 BGR, got {image.shape} {image.dtype}")
    H, W = info.input_size
    h, w = image.shape[:2]
    if (h, w) != (H, W):
        interp = cv2.INTER_AREA if (h > H and w > W) else cv2.INTER_LINEAR
        image = cv2.resize(image, (W, H), interpolation=interp)
    if info.channel_order == "RGB":
        image = image[:, :, ::-1]
    return np.ascontiguousarray(image.transpose(2, 0, 1)[None], dtype=np.float32)


@dataclass(frozen=True)
class PreparedFrame:
    """What :meth:`OnnxFlow.prepare` returns: the graph input and the working size."""

    tensor: np.ndarray  # (1, 3, H, W) float32
    hw: tuple[int, int]  # working (h, w)


def _flow_to_working(flow_chw: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    """``(2, H, W)`` flow in model pixels -> ``(h, w, 2)`` float32 in working pixels."""
    H, W = flow_chw.shape[1:]
    h, w = hw
    flow = np.ascontiguousarray(flow_chw.transpose(1, 2, 0), dtype=np.float32)
    if (H, W) == (h, w):
        return flow
    flow = cv2.resize(flow, (w, h), interpolation=cv2.INTER_LINEAR)
    flow[..., 0] *= w / W
    flow[..., 1] *= h / H
    return flow


class OnnxFlow:
    """A :class:`vo.flow.base.FlowSource` running an exported PWC-Net.

    ``flow_pair`` gets the forward and backward flow from one graph call (shared
    feature pyramid, both directions decoded as one batch). When the working size
    differs from the model's input size, images are resized to the model size and
    the flow is resized back and its values rescaled to working pixels. Masks
    (M_s, M_o) are computed by the caller with :mod:`vo.flow.masks` (numpy), which
    measured faster than in-graph masks (benchmarks/NETWORK.md).
    """

    name = "onnx-pwc"

    def __init__(self, path: str | Path, threads: int = 2):
        self.session, self.info = open_model(path, "flow", threads)
        self.threads = int(threads)
        self.n_inferences = 0

    def prepare(self, image: np.ndarray) -> PreparedFrame:
        """``(h, w, 3)`` uint8 BGR at working resolution -> :class:`PreparedFrame`."""
        return PreparedFrame(to_model_input(image, self.info), (int(image.shape[0]), int(image.shape[1])))

    def flow_pair(self, a: PreparedFrame, b: PreparedFrame) -> tuple[np.ndarray, np.ndarray]:
        """Forward (a -> b) and backward (b -> a) flow, each ``(h, w, 2)`` float32 working pixels."""
        if a.hw != b.hw:
            raise ValueError(f"frames of different working sizes: {a.hw} and {b.hw}")
        fw, bw = self.session.run(["flow_fw", "flow_bw"], {"image1": a.tensor, "image2": b.tensor})
        self.n_inferences += 1
        return _flow_to_working(fw[0], a.hw), _flow_to_working(bw[0], a.hw)

    def describe(self) -> dict:
        return {"name": self.name, "path": str(self.info.path), "input_size": list(self.info.input_size),
                "channel_order": self.info.channel_order, "threads": self.threads,
                "exported_with_version": self.info.version, "config": self.info.config}
