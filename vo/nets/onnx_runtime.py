"""The ONNX runtime of every network: metadata schema, session, model input.

One module for what the exporter writes and what the run path reads, so the two
cannot drift:

* the **metadata schema** of an exported model (ONNX ``metadata_props``, keys
  prefixed ``trianflow.``): :func:`model_metadata` builds it (the exporter writes
  it), :func:`parse_metadata` validates it (every reader opens models through it);
* the **onnxruntime session** (:func:`session_options`, :func:`open_session`), used by
  the run path and by the exporter's torch/onnxruntime parity check;
* :func:`open_model` / :class:`OnnxModel`: a session plus its validated
  :class:`ModelInfo`;
* :func:`to_model_input`: a working-resolution BGR uint8 image -> the graph input.

Metadata keys (without the prefix), all string values:

==================  =============================================================
``kind``            ``flow`` or ``depth`` (:data:`KINDS`); the parts of a split flow
                    network: ``flow_encoder``, ``flow_decoder`` (:data:`PART_KINDS`)
``format_version``  :data:`FORMAT_VERSION`
``input_size``      ``"HxW"``, the fixed size of every graph input and output
``channel_order``   ``RGB`` or ``BGR``: order of the 3 input channels
``normalisation``   JSON ``{mean, std, pixel_range, formula, applied: "in_graph"}``
``input_names``     JSON list, the graph inputs of the kind
``output_names``    JSON list, the graph outputs
``config``          JSON object: the network's constructor sizes
``version``         ``trianflow_vo.__version__`` of the exporter
``resize``          how an image is resized to ``input_size`` (:data:`RESIZE_METHODS`);
                    absent in models exported before it existed, which are read as
                    :data:`DEFAULT_RESIZE` (what the run path always did)
``depth_range``     (depth) JSON ``[min_depth, max_depth]``
``features``        (flow_encoder, flow_decoder) JSON ``{"names": [...], "shapes": [[1, C, h, w], ...]}``:
                    the pyramid levels handed from encoder to decoder; the encoder's
                    outputs are ``names``, the decoder's inputs ``image1_<name>`` ...
                    then ``image2_<name>`` ... (:func:`decoder_input_names`)
``split``           (optional) JSON ``{"id": str, "encoder": file, "decoder": file}``
                    in ``flow.onnx``: the same network is also exported as an encoder
                    (image -> pyramid, run once per frame) and a decoder (two pyramids
                    -> flow_fw, flow_bw) beside it; the two parts carry the same
                    ``split`` ``{"id": ..., "of": "flow.onnx"}``. A flow.onnx without
                    it (older exports) is run as one graph.
``quantization``    (optional) ``"int8-static-qdq"``: convolutions quantised to int8 (not fp32)
==================  =============================================================

onnxruntime is imported inside the functions that need it: this module imports
without it (and without torch); opening a model without it raises
:class:`~trianflow_vo.errors.DependencyError`.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

import trianflow_vo
from trianflow_vo.errors import DependencyError, ModelError

# ---------------------------------------------------------------------------
# metadata schema

META_PREFIX = "trianflow."
FORMAT_VERSION = "1"

KEY_KIND = "kind"
KEY_FORMAT_VERSION = "format_version"
KEY_INPUT_SIZE = "input_size"
KEY_CHANNEL_ORDER = "channel_order"
KEY_NORMALISATION = "normalisation"
KEY_INPUT_NAMES = "input_names"
KEY_OUTPUT_NAMES = "output_names"
KEY_CONFIG = "config"
KEY_VERSION = "version"
KEY_RESIZE = "resize"
KEY_DEPTH_RANGE = "depth_range"
KEY_FEATURES = "features"
KEY_SPLIT = "split"
KEY_QUANTIZATION = "quantization"
SCHEMA_KEYS = (KEY_KIND, KEY_FORMAT_VERSION, KEY_INPUT_SIZE, KEY_CHANNEL_ORDER, KEY_NORMALISATION,
               KEY_INPUT_NAMES, KEY_OUTPUT_NAMES, KEY_CONFIG, KEY_VERSION, KEY_RESIZE)

CHANNEL_ORDERS = ("RGB", "BGR")

#: INTER_AREA when shrinking in both directions, INTER_LINEAR otherwise (our exports)
RESIZE_AREA_DOWN_LINEAR_UP = "area-down-linear-up"
#: plain bilinear ``cv2.INTER_LINEAR`` in every case (the TrianFlow authors' preprocessing)
RESIZE_LINEAR = "linear"
RESIZE_METHODS = (RESIZE_AREA_DOWN_LINEAR_UP, RESIZE_LINEAR)
#: what a model without the ``resize`` key gets
DEFAULT_RESIZE = RESIZE_AREA_DOWN_LINEAR_UP

NORMALISATION_FORMULA = "(x / 255 - mean) / std"
PIXEL_RANGE = (0, 255)


@dataclass(frozen=True)
class KindSpec:
    """The graph interface of one kind of network.

    ``features``: ``"outputs"`` (encoder) or ``"inputs"`` (decoder) when those names and
    shapes are not fixed by the kind but recorded in the ``features`` metadata key.
    """

    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    output_channels: int
    features: str | None = None

    def input_shape(self, size_hw: tuple[int, int]) -> list[int]:
        return [1, 3, int(size_hw[0]), int(size_hw[1])]

    def output_shape(self, size_hw: tuple[int, int]) -> list[int]:
        return [1, self.output_channels, int(size_hw[0]), int(size_hw[1])]


KINDS: dict[str, KindSpec] = {
    # forward (1 -> 2) and backward (2 -> 1) flow, channel 0 = dx, in input pixels
    "flow": KindSpec(inputs=("image1", "image2"), outputs=("flow_fw", "flow_bw"), output_channels=2),
    # depth in [min_depth, max_depth]
    "depth": KindSpec(inputs=("image",), outputs=("depth",), output_channels=1),
}

#: kinds of the graphs a model is split into (never given to the run on their own): the
#: flow network split in two (see the ``split`` key)
PART_KINDS: dict[str, KindSpec] = {
    # image -> pyramid features ...
    "flow_encoder": KindSpec(inputs=("image",), outputs=(), output_channels=0, features="outputs"),
    # ... and pyramids of image 1 and image 2 -> both flows (one batch of 2 inside)
    "flow_decoder": KindSpec(inputs=(), outputs=("flow_fw", "flow_bw"), output_channels=2, features="inputs"),
}


def decoder_input_names(feature_names: Sequence[str]) -> list[str]:
    """The flow decoder's inputs: ``image1_<name>`` for every feature, then ``image2_<name>``."""
    return [f"image1_{n}" for n in feature_names] + [f"image2_{n}" for n in feature_names]


def _check_features(features) -> tuple[list[str], list[list[int]]]:
    """``features`` metadata -> (names, shapes); raises ValueError when malformed."""
    if not isinstance(features, Mapping):
        raise ValueError("features must be a JSON object with names and shapes")
    names, shapes = features.get("names"), features.get("shapes")
    if (not isinstance(names, list) or not names or not all(isinstance(n, str) and n for n in names)
            or not isinstance(shapes, list) or len(shapes) != len(names)
            or not all(isinstance(sh, list) and len(sh) == 4 and all(isinstance(v, int) and v > 0 for v in sh)
                       for sh in shapes)):
        raise ValueError("features must hold equally long lists of names and 4-d positive shapes")
    return list(names), [list(sh) for sh in shapes]


ALL_KINDS: dict[str, KindSpec] = {**KINDS, **PART_KINDS}


def _check_kind(kind: str) -> KindSpec:
    if kind not in ALL_KINDS:
        raise ValueError(f"kind must be one of {sorted(ALL_KINDS)}")
    return ALL_KINDS[kind]


def model_metadata(kind: str, size_hw: Sequence[int], channel_order: str, normalisation: Mapping,
                   input_names: Sequence[str], output_names: Sequence[str], config: Mapping,
                   extra: Mapping | None = None, *, resize: str = DEFAULT_RESIZE,
                   version: str | None = None) -> dict[str, str]:
    """The ``trianflow.*`` metadata of an exported model (what the exporter writes).

    Args:
        kind: ``"flow"`` or ``"depth"``.
        size_hw: fixed ``(H, W)`` of the graph.
        channel_order: ``"RGB"`` or ``"BGR"``.
        normalisation: ``{"mean": [3 floats], "std": [3 floats]}``, applied in the graph.
        input_names: the graph inputs (must be those of ``kind``).
        output_names: the graph outputs (must include those of ``kind``).
        config: JSON-ready constructor sizes of the network.
        extra: more keys (without the prefix), e.g. ``depth_range``; string values are
            written as they are, others as JSON. Must not redefine a schema key.
        resize: how images are resized to the model size (:data:`RESIZE_METHODS`).
        version: exporter version (default ``trianflow_vo.__version__``).

    Returns:
        ``{"trianflow.<key>": str}``; :func:`parse_metadata` accepts it.

    Raises:
        ValueError: a value the reader would reject.
    """
    spec = _check_kind(kind)
    h, w = (int(v) for v in size_hw)
    if h <= 0 or w <= 0:
        raise ValueError(f"size must be positive, got {h}x{w}")
    if channel_order not in CHANNEL_ORDERS:
        raise ValueError(f"channel_order must be one of {list(CHANNEL_ORDERS)}, got {channel_order!r}")
    if resize not in RESIZE_METHODS:
        raise ValueError(f"resize must be one of {list(RESIZE_METHODS)}, got {resize!r}")
    mean = [float(v) for v in normalisation["mean"]]
    std = [float(v) for v in normalisation["std"]]
    if len(mean) != 3 or len(std) != 3:
        raise ValueError("normalisation mean and std must have 3 values each")
    want_in = list(spec.inputs)
    if spec.features is not None:
        if KEY_FEATURES not in (extra or {}):
            raise ValueError(f"a {kind} model needs the {KEY_FEATURES!r} metadata (extra)")
        feat_names, _ = _check_features(extra[KEY_FEATURES])
        if spec.features == "inputs":
            want_in = decoder_input_names(feat_names)
        elif list(output_names) != feat_names:
            raise ValueError(f"{kind} output names must be the features {feat_names}, got {list(output_names)}")
    if list(input_names) != want_in:
        raise ValueError(f"{kind} input names must be {want_in}, got {list(input_names)}")
    missing = [n for n in spec.outputs if n not in output_names]
    if missing:
        raise ValueError(f"{kind} output names lack {missing}")
    meta = {
        KEY_KIND: kind,
        KEY_FORMAT_VERSION: FORMAT_VERSION,
        KEY_INPUT_SIZE: f"{h}x{w}",
        KEY_CHANNEL_ORDER: channel_order,
        KEY_NORMALISATION: json.dumps({"mean": mean, "std": std, "pixel_range": list(PIXEL_RANGE),
                                       "formula": NORMALISATION_FORMULA, "applied": "in_graph"}),
        KEY_INPUT_NAMES: json.dumps(list(input_names)),
        KEY_OUTPUT_NAMES: json.dumps(list(output_names)),
        KEY_CONFIG: json.dumps(dict(config)),
        KEY_VERSION: trianflow_vo.__version__ if version is None else str(version),
        KEY_RESIZE: resize,
    }
    for k, v in (extra or {}).items():
        if k in meta:
            raise ValueError(f"extra metadata key {k!r} is a schema key")
        meta[k] = v if isinstance(v, str) else json.dumps(v)
    return {META_PREFIX + k: v for k, v in meta.items()}


@dataclass(frozen=True)
class ModelInfo:
    """What the (validated) metadata of an exported model says."""

    path: Path
    kind: str
    input_size: tuple[int, int]  # (H, W) of the graph inputs and outputs
    channel_order: str  # "RGB" or "BGR"
    normalisation: dict  # the parsed normalisation JSON (applied in the graph)
    resize: str  # one of RESIZE_METHODS
    version: str  # exporter version, "?" when not recorded
    config: dict = field(default_factory=dict)
    meta: dict = field(default_factory=dict)  # every trianflow.* key, prefix removed
    features: tuple[tuple[str, tuple[int, ...]], ...] = ()  # (name, shape) (flow_encoder/decoder)
    split: dict | None = None  # the parsed ``split`` key, None when absent

    @property
    def spec(self) -> KindSpec:
        return ALL_KINDS[self.kind]

    @property
    def input_names(self) -> list[str]:
        """The graph inputs, in order (fixed by the kind or, for a decoder, by ``features``)."""
        if self.spec.features == "inputs":
            return decoder_input_names([n for n, _ in self.features])
        return list(self.spec.inputs)

    @property
    def output_names(self) -> list[str]:
        """The graph outputs the reader uses, in order."""
        if self.spec.features == "outputs":
            return [n for n, _ in self.features]
        return list(self.spec.outputs)

    def input_shapes(self) -> list[list[int]]:
        if self.spec.features == "inputs":
            return [list(sh) for _, sh in self.features] * 2
        return [self.spec.input_shape(self.input_size) for _ in self.spec.inputs]

    def output_shapes(self) -> list[list[int]]:
        if self.spec.features == "outputs":
            return [list(sh) for _, sh in self.features]
        return [self.spec.output_shape(self.input_size) for _ in self.spec.outputs]


def _parse_size(text: str, path: Path) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ModelError(f"{path}: metadata input_size {text!r} is not 'HxW'") from None
    if h <= 0 or w <= 0:
        raise ModelError(f"{path}: metadata input_size {text!r} is not positive")
    return h, w


def _json(meta: Mapping[str, str], key: str, path: Path):
    try:
        return json.loads(meta[key])
    except (KeyError, TypeError, json.JSONDecodeError):
        raise ModelError(f"{path}: metadata '{META_PREFIX}{key}' is missing or not JSON") from None


def parse_metadata(raw: Mapping[str, str], path: str | Path, kind: str | None = None) -> ModelInfo:
    """Validate the metadata of a model (what every reader does).

    Args:
        raw: the model's custom metadata (``trianflow.*`` keys; other keys are ignored).
        path: the model file, named in error messages.
        kind: the kind the caller needs, or None for any kind (:data:`KINDS`, :data:`PART_KINDS`).

    Returns:
        :class:`ModelInfo` (``resize`` is :data:`DEFAULT_RESIZE` when the key is absent).

    Raises:
        ModelError: one line naming ``path``: no metadata, wrong kind, unsupported
            format version, bad input size, channel order, normalisation, resize,
            config or input/output names.
    """
    path = Path(path)
    if kind is not None:
        _check_kind(kind)
    meta = {k[len(META_PREFIX):]: v for k, v in raw.items() if k.startswith(META_PREFIX)}
    if KEY_KIND not in meta:
        raise ModelError(f"{path}: no trianflow-vo metadata; export the model with 'trianflow-vo export'")
    if kind is not None and meta[KEY_KIND] != kind:
        raise ModelError(f"{path}: is a {meta[KEY_KIND]!r} model, expected a {kind!r} model")
    if meta[KEY_KIND] not in ALL_KINDS:
        raise ModelError(f"{path}: unknown model kind {meta[KEY_KIND]!r} (expected one of {sorted(KINDS)})")
    kind = meta[KEY_KIND]
    spec = ALL_KINDS[kind]
    if meta.get(KEY_FORMAT_VERSION) != FORMAT_VERSION:
        raise ModelError(f"{path}: unsupported metadata format_version {meta.get(KEY_FORMAT_VERSION)!r}")
    if KEY_INPUT_SIZE not in meta:
        raise ModelError(f"{path}: metadata has no input_size")
    size = _parse_size(meta[KEY_INPUT_SIZE], path)
    order = meta.get(KEY_CHANNEL_ORDER)
    if order not in CHANNEL_ORDERS:
        raise ModelError(f"{path}: metadata channel_order must be RGB or BGR, got {order!r}")
    norm = _json(meta, KEY_NORMALISATION, path)
    if not isinstance(norm, dict) or norm.get("applied") != "in_graph":
        raise ModelError(f"{path}: normalisation must be applied in the graph (metadata normalisation.applied)")
    resize = meta.get(KEY_RESIZE, DEFAULT_RESIZE)
    if resize not in RESIZE_METHODS:
        raise ModelError(f"{path}: metadata resize {resize!r} is not one of {list(RESIZE_METHODS)}")
    config = _json(meta, KEY_CONFIG, path) if KEY_CONFIG in meta else {}
    if not isinstance(config, dict):
        raise ModelError(f"{path}: metadata '{META_PREFIX}{KEY_CONFIG}' is not a JSON object")
    features: tuple = ()
    want_in, want_out = list(spec.inputs), list(spec.outputs)
    if spec.features is not None:
        try:
            names, shapes = _check_features(_json(meta, KEY_FEATURES, path))
        except ValueError as exc:
            raise ModelError(f"{path}: metadata '{META_PREFIX}{KEY_FEATURES}': {exc}") from None
        features = tuple((n, tuple(sh)) for n, sh in zip(names, shapes))
        if spec.features == "inputs":
            want_in = decoder_input_names(names)
        else:
            want_out = names
    split = None
    if KEY_SPLIT in meta:
        split = _json(meta, KEY_SPLIT, path)
        if not isinstance(split, dict) or not isinstance(split.get("id"), str):
            raise ModelError(f"{path}: metadata '{META_PREFIX}{KEY_SPLIT}' must be a JSON object with an id")
        if kind == "flow" and not all(isinstance(split.get(k), str) and split[k] and Path(split[k]).name == split[k]
                                      for k in ("encoder", "decoder")):
            raise ModelError(f"{path}: metadata '{META_PREFIX}{KEY_SPLIT}' must name the encoder and decoder "
                             "files (plain file names beside it)")
    # the name lists are optional (the graph is checked anyway) but must agree when present
    if KEY_INPUT_NAMES in meta and _json(meta, KEY_INPUT_NAMES, path) != want_in:
        raise ModelError(f"{path}: metadata input_names {meta[KEY_INPUT_NAMES]} != expected {want_in}")
    if KEY_OUTPUT_NAMES in meta:
        outs = _json(meta, KEY_OUTPUT_NAMES, path)
        if not isinstance(outs, list) or any(n not in outs for n in want_out):
            raise ModelError(f"{path}: metadata output_names {meta[KEY_OUTPUT_NAMES]} lack some of "
                             f"{want_out}")
    return ModelInfo(path=path, kind=kind, input_size=size, channel_order=order, normalisation=norm,
                     resize=resize, version=meta.get(KEY_VERSION, "?"), config=config, meta=meta,
                     features=features, split=split)


# ---------------------------------------------------------------------------
# onnxruntime session

ORT_INSTALL_HINT = ("onnxruntime is needed to run network models: pip install onnxruntime "
                    "(or pip install 'trianflow-vo[onnx]')")
PROVIDERS = ["CPUExecutionProvider"]


def require_onnxruntime():
    """The ``onnxruntime`` module, imported now.

    Raises:
        DependencyError: it is not installed (message with the install hint).
    """
    try:
        import onnxruntime as ort
    except ImportError:
        raise DependencyError(ORT_INSTALL_HINT) from None
    return ort


def session_options(threads: int = 2, optimise: bool = True):
    """The onnxruntime options of every session: ``threads`` intra-op threads, one
    inter-op thread, sequential execution, all graph optimisations (none with
    ``optimise=False``: only to read a model's metadata), warnings off, no spinning.

    Raises:
        ValueError: ``threads < 1``.
        DependencyError: onnxruntime is not installed.
    """
    if int(threads) < 1:
        raise ValueError("threads must be >= 1")
    ort = require_onnxruntime()
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = int(threads)
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = (ort.GraphOptimizationLevel.ORT_ENABLE_ALL if optimise
                                     else ort.GraphOptimizationLevel.ORT_DISABLE_ALL)
    opts.log_severity_level = 3
    # idle worker threads sleep instead of spinning: on a busy CPU (and between calls,
    # while the pipeline runs OpenCV/numpy) spinning threads steal the cores that do
    # the work; see benchmarks/NETWORK.md
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return opts


def open_session(path: str | Path, threads: int = 2, kind: str | None = None, optimise: bool = True):
    """An onnxruntime ``InferenceSession`` of ``path`` on the CPU with :func:`session_options`.

    No metadata check (see :func:`open_model`). ``kind`` only words the not-found error.
    ``optimise=False``: no graph optimisation, a quick open to read the metadata only
    (output shapes are then not inferred: :func:`check_graph` needs an optimised session).

    Raises:
        ValueError: ``threads < 1``.
        DependencyError: onnxruntime is not installed.
        ModelError: missing file, or not a graph onnxruntime can load.
    """
    path = Path(path)
    opts = session_options(threads, optimise)
    ort = require_onnxruntime()
    if not path.is_file():
        raise ModelError(f"{path}: {kind + ' ' if kind else ''}model file not found")
    try:
        return ort.InferenceSession(str(path), sess_options=opts, providers=PROVIDERS)
    except Exception as exc:  # onnxruntime raises its own exception types for unreadable graphs
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ModelError(f"{path}: not a usable ONNX model ({first[:200]})") from None


def read_metadata(session) -> dict[str, str]:
    """The custom metadata map of an open session (every key, prefixed or not)."""
    return dict(session.get_modelmeta().custom_metadata_map)


def check_graph(session, info: ModelInfo) -> None:
    """Check the graph's input and output names and shapes against ``info``.

    Raises:
        ModelError: one line naming the file.
    """
    path = info.path
    inputs = session.get_inputs()
    want_in = info.input_names
    if [i.name for i in inputs] != want_in:
        raise ModelError(f"{path}: graph inputs {[i.name for i in inputs]} != expected {want_in}")
    for i, want in zip(inputs, info.input_shapes()):
        if list(i.shape) != want:
            raise ModelError(f"{path}: input {i.name!r} has shape {i.shape}, the metadata says {want}")
    outputs = session.get_outputs()
    want_out = dict(zip(info.output_names, info.output_shapes()))
    missing = [n for n in want_out if n not in [o.name for o in outputs]]
    if missing:
        raise ModelError(f"{path}: graph lacks outputs {missing}")
    for o in outputs:
        if o.name in want_out and list(o.shape) != want_out[o.name]:
            raise ModelError(f"{path}: output {o.name!r} has shape {o.shape}, expected {want_out[o.name]}")


def open_model(path: str | Path, kind: str, threads: int = 2):
    """Open an exported model with onnxruntime and validate it.

    Args:
        path: the ``.onnx`` file.
        kind: ``"flow"`` or ``"depth"``.
        threads: ``intra_op_num_threads`` (``inter_op_num_threads`` is 1).

    Returns:
        ``(session, ModelInfo)``.

    Raises:
        ValueError: unknown ``kind`` or ``threads < 1``.
        DependencyError: onnxruntime is not installed.
        ModelError: missing file, not ONNX, no or wrong metadata, shapes that disagree.
    """
    _check_kind(kind)
    sess = open_session(path, threads, kind)
    info = parse_metadata(read_metadata(sess), path, kind)
    check_graph(sess, info)
    return sess, info


class OnnxModel:
    """An open, validated exported model: ``session``, ``info``, ``threads``.

    :meth:`run` feeds the graph inputs of the kind and returns its outputs, in the
    order of :data:`KINDS` ``[kind].outputs``, counting the calls in ``n_inferences``.
    """

    def __init__(self, path: str | Path, kind: str, threads: int = 2):
        self.session, self.info = open_model(path, kind, threads)
        self.threads = int(threads)
        self.n_inferences = 0

    def to_input(self, image: np.ndarray) -> np.ndarray:
        """:func:`to_model_input` for this model."""
        return to_model_input(image, self.info)

    def run(self, *tensors: np.ndarray) -> list[np.ndarray]:
        """One graph call on ``tensors`` (one per graph input, in order); outputs in
        the order of :attr:`ModelInfo.output_names`."""
        names = self.info.input_names
        if len(tensors) != len(names):
            raise ValueError(f"a {self.info.kind} model takes {len(names)} inputs, got {len(tensors)}")
        out = self.session.run(self.info.output_names, dict(zip(names, tensors)))
        self.n_inferences += 1
        return out

    def describe(self) -> dict:
        """JSON-ready: path, input size, channel order, resize, threads, version, config."""
        info = self.info
        return {"path": str(info.path), "input_size": list(info.input_size), "channel_order": info.channel_order,
                "resize": info.resize, "threads": self.threads, "exported_with_version": info.version,
                "config": info.config}


# ---------------------------------------------------------------------------
# model input

def resize_image(image: np.ndarray, size_hw: tuple[int, int], method: str = DEFAULT_RESIZE) -> np.ndarray:
    """``image`` resized to ``size_hw`` with a :data:`RESIZE_METHODS` method (unchanged if already that size)."""
    H, W = (int(v) for v in size_hw)
    h, w = image.shape[:2]
    if (h, w) == (H, W):
        return image
    if method == RESIZE_AREA_DOWN_LINEAR_UP:
        interp = cv2.INTER_AREA if (h > H and w > W) else cv2.INTER_LINEAR
    elif method == RESIZE_LINEAR:
        interp = cv2.INTER_LINEAR
    else:
        raise ValueError(f"resize must be one of {list(RESIZE_METHODS)}, got {method!r}")
    return cv2.resize(image, (W, H), interpolation=interp)


def to_model_input(image: np.ndarray, info: ModelInfo) -> np.ndarray:
    """A working-resolution BGR uint8 image ``(h, w, 3)`` -> graph input ``(1, 3, H, W)`` float32 0..255.

    Resized to ``info.input_size`` with ``info.resize``, channels in ``info.channel_order``.
    """
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"image must be (h, w, 3) uint8 BGR, got {image.shape} {image.dtype}")
    image = resize_image(image, info.input_size, info.resize)
    if info.channel_order == "RGB":
        image = image[:, :, ::-1]
    return np.ascontiguousarray(image.transpose(2, 0, 1)[None], dtype=np.float32)
