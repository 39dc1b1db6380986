"""Optical flow from an exported ONNX flow network (``trianflow-vo export``), via onnxruntime.

Opening, metadata checks, session settings and the image-to-input conversion are
those of every network (:mod:`trianflow_vo.nets.onnx_runtime`). No torch here.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from trianflow_vo.errors import ModelError
from trianflow_vo.nets.onnx_runtime import ModelInfo, OnnxModel, open_session, parse_metadata, read_metadata

log = logging.getLogger("trianflow_vo")


@dataclass(frozen=True)
class PreparedFrame:
    """What :meth:`OnnxFlow.prepare` returns: the graph input, the working size and,
    with split graphs, the frame's pyramid features (the encoder's outputs)."""

    tensor: np.ndarray  # (1, 3, H, W) float32
    hw: tuple[int, int]  # working (h, w)
    features: tuple[np.ndarray, ...] | None = None  # split graphs: encoder outputs, finest first


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

    When ``flow.onnx`` names split graphs (metadata ``split``, written by
    ``trianflow-vo export``) and they are beside it, :meth:`prepare` runs the encoder
    (the frame's pyramid, computed once per frame and kept with the keyframe) and
    ``flow_pair`` only the decoder (both directions as one batch): same flows, less
    work per pair. Otherwise (an older export, or ``split=False``) ``flow_pair`` runs
    the single graph: forward and backward flow from one call (shared feature
    pyramid, both directions decoded as one batch). When the working size
    differs from the model's input size, images are resized to the model size and
    the flow is resized back and its values rescaled to working pixels. Masks
    (M_s, M_o) are computed by the caller with :mod:`vo.flow.masks` (numpy), which
    measured faster than in-graph masks (benchmarks/NETWORK.md).
    """

    name = "onnx-pwc"

    def __init__(self, path: str | Path, threads: int = 2, split: bool = True):
        """``split=False``: run flow.onnx as one graph even when split graphs exist."""
        path = Path(path)
        self.encoder: OnnxModel | None = None
        self.decoder: OnnxModel | None = None
        self.model: OnnxModel | None = None
        self._info: ModelInfo | None = None
        self._threads = int(threads)
        parts = self._split_parts(path) if split else None
        if parts is not None:
            self.encoder = OnnxModel(parts[0], "flow_encoder", threads)
            self.decoder = OnnxModel(parts[1], "flow_decoder", threads)
            self._check_parts()
        else:
            self.model = OnnxModel(path, "flow", threads)
            self._info = self.model.info

    def _split_parts(self, path: Path) -> tuple[Path, Path] | None:
        """The encoder and decoder files flow.onnx names, or None (single graph)."""
        # a quick open for the metadata; the graph of the path taken is checked when opened
        info = parse_metadata(read_metadata(open_session(path, 1, "flow", optimise=False)), path, "flow")
        self._info = info
        if info.split is None:
            return None
        enc, dec = path.parent / info.split["encoder"], path.parent / info.split["decoder"]
        if not (enc.is_file() and dec.is_file()):
            log.warning("%s names split graphs %s, %s that are not beside it: running it as one graph "
                        "(slower per pair)", path, enc.name, dec.name)
            return None
        return enc, dec

    def _check_parts(self) -> None:
        info, enc, dec = self._info, self.encoder.info, self.decoder.info
        for part in (enc, dec):
            if part.split is None or part.split.get("id") != info.split["id"]:
                raise ModelError(f"{part.path}: not exported with {info.path} (split id differs); "
                                 "export the flow network again")
            for what in ("input_size", "channel_order", "resize", "config"):
                if getattr(part, what) != getattr(info, what):
                    raise ModelError(f"{part.path}: {what} differs from {info.path}")
        if enc.features != dec.features:
            raise ModelError(f"{dec.path}: its input features differ from {enc.path}'s outputs")

    @property
    def split(self) -> bool:
        """True when running the encoder/decoder graphs."""
        return self.encoder is not None

    @property
    def info(self) -> ModelInfo:
        """The metadata of flow.onnx."""
        return self._info

    @property
    def session(self):
        """The session of the per-pair graph (the decoder when split)."""
        return self.decoder.session if self.split else self.model.session

    @property
    def threads(self) -> int:
        return self._threads

    @property
    def n_inferences(self) -> int:
        """Per-pair graph calls so far (one per :meth:`flow_pair`)."""
        return self.decoder.n_inferences if self.split else self.model.n_inferences

    def prepare(self, image: np.ndarray) -> PreparedFrame:
        """``(h, w, 3)`` uint8 BGR at working resolution -> :class:`PreparedFrame`
        (split graphs: with the frame's pyramid)."""
        tensor = self.encoder.to_input(image) if self.split else self.model.to_input(image)
        hw = (int(image.shape[0]), int(image.shape[1]))
        if not self.split:
            return PreparedFrame(tensor, hw)
        return PreparedFrame(tensor, hw, tuple(self.encoder.run(tensor)))

    def flow_pair(self, a: PreparedFrame, b: PreparedFrame) -> tuple[np.ndarray, np.ndarray]:
        """Forward (a -> b) and backward (b -> a) flow, each ``(h, w, 2)`` float32 working pixels."""
        if a.hw != b.hw:
            raise ValueError(f"frames of different working sizes: {a.hw} and {b.hw}")
        if self.split:
            if a.features is None or b.features is None:
                raise ValueError("frames prepared without pyramid features (by another flow source?)")
            fw, bw = self.decoder.run(*a.features, *b.features)
        else:
            fw, bw = self.model.run(a.tensor, b.tensor)  # outputs flow_fw, flow_bw
        return _flow_to_working(fw[0], a.hw), _flow_to_working(bw[0], a.hw)

    def describe(self) -> dict:
        info = self.info
        out = {"name": self.name, "path": str(info.path), "input_size": list(info.input_size),
               "channel_order": info.channel_order, "resize": info.resize, "threads": self.threads,
               "exported_with_version": info.version, "config": info.config,
               "graphs": "encoder+decoder" if self.split else "single"}
        if self.split:
            out["encoder"], out["decoder"] = str(self.encoder.info.path), str(self.decoder.info.path)
            quant = self.decoder.info.meta.get("quantization")
            if quant:
                out["quantization"] = quant
        return out
