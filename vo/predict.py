"""Single-image depth and two-image flow from exported networks (``trianflow-vo predict``).

The tool form of TrianFlow's depth demo: every output is at the **network's input
size** (``ModelInfo.input_size``) and in the network's units; nothing is resized back.

* :func:`predict_depth`: per image ``NAME.depth.npy`` (float32 ``(H, W)``, the
  network's depth, within the model's ``depth_range`` metadata, up to the unknown
  scale of monocular depth) and ``NAME.depth.png`` (:func:`depth_to_color`).
* :func:`predict_flow`: per image pair (``NAME`` = stem of the first image)
  ``NAME.flow.npy`` (float32 ``(H, W, 2)``, forward flow 1 -> 2 in input-size pixels,
  channel 0 = dx), ``NAME.flo`` (Middlebury, :mod:`trianflow_vo.io.flo`) and
  ``NAME.flow.png`` (:func:`trianflow_vo.viz.flow_color.flow_to_rgb`).

Images are resized to the network's input size by
:func:`trianflow_vo.nets.onnx_runtime.to_model_input`, i.e. with the resize method
stored in the model's metadata (``ModelInfo.resize``). Every file is written to
``FILE.tmp`` and renamed, so an output file is never half-written.

No click here; the command is :mod:`trianflow_vo.cli.predict_cmd`.
"""

from __future__ import annotations

import io
import os
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import cv2
import numpy as np

from trianflow_vo.errors import InputError, ModelError
from trianflow_vo.io.atomic import write_atomic
from trianflow_vo.io.flo import encode_flo
from trianflow_vo.io.sequence import IMAGE_EXTENSIONS, decode_image, list_images
from trianflow_vo.nets.onnx_runtime import OnnxModel
from trianflow_vo.viz.flow_color import flow_to_rgb

DEPTH_NPY = ".depth.npy"
DEPTH_PNG = ".depth.png"
FLOW_NPY = ".flow.npy"
FLOW_FLO = ".flo"
FLOW_PNG = ".flow.png"

#: ``progress(done, total, name)``, called after each image (depth) or pair (flow)
Progress = Callable[[int, int, str], None]

PAIR_MODES = ("two", "consecutive")
#: percentiles of inverse depth mapped to the ends of the colour map
DEPTH_COLOR_PERCENTILES = (2.0, 98.0)

_SUFFIXES = "/".join(sorted(s.lstrip(".") for s in IMAGE_EXTENSIONS))


# ---------------------------------------------------------------------------
# inputs and outputs

def collect_images(inputs: Iterable[str | Path]) -> list[Path]:
    """Image files of ``inputs`` in order: a file as given, a folder as its images in
    natural order (``img2`` before ``img10``; :func:`~trianflow_vo.io.sequence.list_images`).

    A file given by name is accepted whatever its suffix when OpenCV recognises its
    content as an image; folders contribute their png/jpg/jpeg/bmp/tif/tiff files.

    Raises:
        InputError: naming the path: it does not exist, is a file that is not an
            image, or is a folder with no images; or no input at all.
    """
    out: list[Path] = []
    for raw in inputs:
        p = Path(raw)
        if p.is_dir():
            files = list_images(p)
            if not files:
                raise InputError(f"no images ({_SUFFIXES}) in this folder", p)
            out.extend(files)
        elif p.is_file():
            if not cv2.haveImageReader(str(p)):
                raise InputError(f"not an image (OpenCV does not recognise its content; expected {_SUFFIXES})", p)
            out.append(p)
        elif p.exists():
            raise InputError("neither a file nor a folder", p)
        else:
            raise InputError("no such file or folder", p)
    if not out:
        raise InputError("no input images given")
    return out


def flow_pairs(images: Sequence[Path], mode: str = "two") -> list[tuple[Path, Path]]:
    """The image pairs flow is computed for.

    ``"two"``: exactly two images, one pair. ``"consecutive"``: ``(images[i], images[i + 1])``
    for every ``i`` (at least two images).

    Raises:
        ValueError: unknown ``mode``.
        InputError: the wrong number of images for ``mode``.
    """
    if mode not in PAIR_MODES:
        raise ValueError(f"mode must be one of {list(PAIR_MODES)}, got {mode!r}")
    n = len(images)
    if mode == "two" and n != 2:
        raise InputError(f"flow needs exactly 2 images, got {n} (or pair mode 'consecutive' for a sequence)")
    if n < 2:
        raise InputError(f"flow needs at least 2 images, got {n}")
    return list(zip(images[:-1], images[1:]))


def check_unique_names(images: Sequence[Path], suffix: str) -> None:
    """Raise ``InputError`` when two different images would write the same ``NAME + suffix``."""
    seen: dict[str, Path] = {}
    for p in images:
        name = p.stem + suffix
        other = seen.setdefault(name, p)
        if other != p and other.resolve() != p.resolve():
            raise InputError(f"{other} and {p} would both write {name}; rename one or predict them separately")


def prepare_out_dir(out_dir: str | Path) -> Path:
    """Create ``out_dir`` (and its parents) if needed.

    Raises:
        InputError: it exists and is not a folder, or cannot be created (one line naming it).
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError("output path exists and is not a folder", out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the output folder: {exc.strerror or exc}", out_dir) from None
    if not os.access(out_dir, os.W_OK | os.X_OK):
        raise InputError("output folder is not writable", out_dir)
    return out_dir


def _npy_bytes(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=False)
    return buf.getvalue()


def _png_bytes(bgr: np.ndarray, path: Path) -> bytes:
    ok, enc = cv2.imencode(".png", bgr)
    if not ok:  # pragma: no cover - cv2 encodes any uint8 image
        raise InputError("cannot encode PNG", path)
    return enc.tobytes()


def _load(path: Path) -> np.ndarray:
    img, reason = decode_image(path)
    if img is None:
        raise InputError(reason, path)
    return img


def _open(model: str | Path | OnnxModel, kind: str, threads: int) -> OnnxModel:
    if isinstance(model, OnnxModel):
        if model.info.kind != kind:
            raise ModelError(f"{model.info.path}: is a {model.info.kind!r} model, expected a {kind!r} model")
        return model
    return OnnxModel(model, kind, threads)


# ---------------------------------------------------------------------------
# network calls (outputs at the network's input size)

def run_depth(model: OnnxModel, image: np.ndarray) -> np.ndarray:
    """``(H, W)`` float32 depth of a BGR uint8 image, ``(H, W)`` = the model's input size."""
    (depth,) = model.run(model.to_input(image))
    return np.ascontiguousarray(depth[0, 0], dtype=np.float32)


def run_flow(model: OnnxModel, input1: np.ndarray, input2: np.ndarray) -> np.ndarray:
    """``(H, W, 2)`` float32 forward flow between two graph inputs (from ``model.to_input``)."""
    flow_fw, _flow_bw = model.run(input1, input2)
    return np.ascontiguousarray(flow_fw[0].transpose(1, 2, 0), dtype=np.float32)


def depth_to_color(depth: np.ndarray) -> np.ndarray:
    """BGR uint8 colour image of a depth map: magma colour map of **inverse** depth
    (near = bright yellow, far = dark purple), ranged between the 2nd and 98th
    percentiles of the valid inverse depths (:data:`DEPTH_COLOR_PERCENTILES`).
    Non-finite or non-positive depths are black.
    """
    depth = np.asarray(depth, dtype=np.float32)
    valid = np.isfinite(depth) & (depth > 0)
    inv = np.zeros_like(depth)
    np.divide(1.0, depth, out=inv, where=valid)
    if valid.any():
        lo, hi = np.percentile(inv[valid], DEPTH_COLOR_PERCENTILES)
    else:
        lo = hi = 0.0
    if hi > lo:
        t = np.clip((inv - lo) / (hi - lo), 0.0, 1.0)
    else:
        t = np.full_like(inv, 0.5)
    u8 = np.rint(t * 255.0).astype(np.uint8)
    bgr = cv2.applyColorMap(u8, cv2.COLORMAP_MAGMA)
    bgr[~valid] = 0
    return bgr


# ---------------------------------------------------------------------------
# the two predictions

def predict_depth(images: Sequence[str | Path], model_path: str | Path | OnnxModel, out_dir: str | Path,
                  threads: int = 2, progress: Progress | None = None) -> list[Path]:
    """Depth of every image with an exported depth network.

    Args:
        images: image files (see :func:`collect_images` to expand folders).
        model_path: the ``depth.onnx`` (or an open depth :class:`OnnxModel`).
        out_dir: output folder (created if needed).
        threads: onnxruntime intra-op threads.
        progress: called as ``progress(done, total, name)`` after each image.

    Returns:
        the files written, per image ``NAME.depth.npy`` then ``NAME.depth.png``.

    Raises:
        InputError: an image cannot be decoded, two images share a stem, bad ``out_dir``.
        ModelError: missing file, not a depth model, bad metadata.
        DependencyError: onnxruntime missing.
    """
    images = [Path(p) for p in images]
    check_unique_names(images, DEPTH_NPY)
    model = _open(model_path, "depth", threads)
    out_dir = prepare_out_dir(out_dir)
    written: list[Path] = []
    for i, path in enumerate(images, start=1):
        depth = run_depth(model, _load(path))
        npy, png = out_dir / (path.stem + DEPTH_NPY), out_dir / (path.stem + DEPTH_PNG)
        written.append(write_atomic(npy, _npy_bytes(depth)))
        written.append(write_atomic(png, _png_bytes(depth_to_color(depth), png)))
        if progress is not None:
            progress(i, len(images), path.name)
    return written


def predict_flow(pairs: Sequence[tuple[str | Path, str | Path]], model_path: str | Path | OnnxModel,
                 out_dir: str | Path, threads: int = 2, progress: Progress | None = None) -> list[Path]:
    """Forward flow of every image pair with an exported flow network.

    Args:
        pairs: ``(image1, image2)`` files (see :func:`flow_pairs`); ``NAME`` is image1's stem.
        model_path: the ``flow.onnx`` (or an open flow :class:`OnnxModel`).
        out_dir: output folder (created if needed).
        threads: onnxruntime intra-op threads.
        progress: called as ``progress(done, total, name)`` after each pair.

    Returns:
        the files written, per pair ``NAME.flow.npy``, ``NAME.flo``, ``NAME.flow.png``.

    Raises:
        InputError: an image cannot be decoded, two pairs share a stem, bad ``out_dir``.
        ModelError: missing file, not a flow model, bad metadata.
        DependencyError: onnxruntime missing.
    """
    pairs = [(Path(a), Path(b)) for a, b in pairs]
    check_unique_names([a for a, _ in pairs], FLOW_NPY)
    model = _open(model_path, "flow", threads)
    out_dir = prepare_out_dir(out_dir)
    written: list[Path] = []
    cache: tuple[Path, np.ndarray] | None = None  # the last image's graph input (consecutive pairs)

    def graph_input(path: Path) -> np.ndarray:
        nonlocal cache
        if cache is not None and cache[0] == path:
            return cache[1]
        x = model.to_input(_load(path))
        cache = (path, x)
        return x

    for i, (p1, p2) in enumerate(pairs, start=1):
        x1 = graph_input(p1)
        flow = run_flow(model, x1, graph_input(p2))
        stem = p1.stem
        npy, flo, png = (out_dir / (stem + s) for s in (FLOW_NPY, FLOW_FLO, FLOW_PNG))
        written.append(write_atomic(npy, _npy_bytes(flow)))
        written.append(write_atomic(flo, encode_flo(flow)))
        rgb, _ = flow_to_rgb(flow)
        written.append(write_atomic(png, _png_bytes(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), png)))
        if progress is not None:
            progress(i, len(pairs), p1.name)
    return written
