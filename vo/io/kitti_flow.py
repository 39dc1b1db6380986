"""KITTI optical-flow PNGs, ground-truth flow files and the KITTI flow benchmark layout.

A KITTI flow PNG (the ``flow_occ/`` and ``flow_noc/`` files of KITTI 2012 and 2015)
is a 16-bit, 3-channel PNG; in the file's RGB order, per pixel:

* R = ``u * 64 + 2**15`` (``u`` = dx, pixels), G = ``v * 64 + 2**15`` (``v`` = dy),
* B = 1 where the flow is valid (ground truth exists), 0 elsewhere.

So a stored flow is exact to 1/64 px and lies in about ``[-512, 512)`` px. OpenCV
reads and writes the channels in BGR order, i.e. ``[..., 0]`` = valid,
``[..., 1]`` = v, ``[..., 2]`` = u of the array.

Ground-truth flow files (:func:`read_flow_file`): a KITTI PNG, or a Middlebury ``.flo``
(:mod:`trianflow_vo.io.flo`) whose pixels are valid where the flow is finite and below
:data:`FLO_UNKNOWN` in both components (Middlebury marks unknown flow with 1e10).

The benchmark layout (:func:`kitti_flow_pairs`): a folder with ``image_2/`` (or
``colored_0/``, ``image_0/`` for KITTI 2012) holding ``NNNNNN_10.png`` and
``NNNNNN_11.png``, and the ground truth ``flow_occ/NNNNNN_10.png`` (all pixels) and/or
``flow_noc/NNNNNN_10.png`` (non-occluded pixels). Or a list file of
``image1 image2 ground_truth`` lines (:func:`read_pair_list`).

Every reader raises :class:`~trianflow_vo.errors.InputError` naming the file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from trianflow_vo.errors import InputError
from trianflow_vo.io.atomic import write_atomic
from trianflow_vo.io.read import read_bytes
from trianflow_vo.io.flo import read_flo
from trianflow_vo.io.sequence import natural_key

#: the PNG value of zero flow
KITTI_FLOW_OFFSET = 2 ** 15
#: the PNG value of one pixel of flow
KITTI_FLOW_SCALE = 64.0
#: flow components at or above this (in magnitude) in a .flo are unknown (Middlebury: 1e10)
FLO_UNKNOWN = 1e9
#: image folders of the KITTI flow layout, in order of preference
KITTI_IMAGE_DIRS = ("image_2", "colored_0", "image_0")
#: ground-truth folders of the KITTI flow layout, in order of preference (occ = all pixels)
KITTI_GT_DIRS = ("flow_occ", "flow_noc")
#: ground-truth suffixes accepted in a folder, in order of preference
GT_SUFFIXES = (".png", ".flo")


# ---------------------------------------------------------------------------
# KITTI flow PNG

def encode_kitti_flow(flow: np.ndarray, valid: np.ndarray | None = None) -> bytes:
    """The PNG bytes of a flow in the KITTI format.

    Args:
        flow: ``(H, W, 2)`` flow in pixels, ``[..., 0]`` = dx.
        valid: ``(H, W)`` bool, where the flow is valid; None = every pixel.

    Values are rounded to the nearest 1/64 px and clipped to what 16 bits hold
    (about ``[-512, 512)`` px); invalid pixels are stored as ``(0, 0, 0)``.

    Raises:
        ValueError: bad shapes, or a valid pixel whose flow is not finite.
    """
    flow = np.asarray(flow, dtype=np.float64)
    if flow.ndim != 3 or flow.shape[2] != 2 or flow.shape[0] < 1 or flow.shape[1] < 1:
        raise ValueError(f"flow must be (H, W, 2) with H, W >= 1, got {flow.shape}")
    if valid is None:
        valid = np.ones(flow.shape[:2], dtype=bool)
    valid = np.asarray(valid, dtype=bool)
    if valid.shape != flow.shape[:2]:
        raise ValueError(f"valid must be (H, W) = {flow.shape[:2]}, got {valid.shape}")
    if not np.isfinite(flow[valid]).all():
        raise ValueError("flow has non-finite values at valid pixels")
    code = np.clip(np.rint(np.where(valid[..., None], flow, 0.0) * KITTI_FLOW_SCALE + KITTI_FLOW_OFFSET),
                   0, 65535).astype(np.uint16)
    bgr = np.zeros(flow.shape[:2] + (3,), dtype=np.uint16)
    bgr[..., 0] = valid
    bgr[..., 1] = np.where(valid, code[..., 1], 0)
    bgr[..., 2] = np.where(valid, code[..., 0], 0)
    ok, enc = cv2.imencode(".png", bgr)
    if not ok:  # pragma: no cover - OpenCV encodes any uint16 3-channel image
        raise ValueError("OpenCV could not encode the flow PNG")
    return enc.tobytes()


def write_kitti_flow(path: str | Path, flow: np.ndarray, valid: np.ndarray | None = None) -> Path:
    """Write :func:`encode_kitti_flow` to ``path`` (via ``path.tmp`` and a rename); returns ``path``."""
    return write_atomic(path, encode_kitti_flow(flow, valid))


def decode_kitti_flow(data: bytes, source: str | Path = "<bytes>") -> tuple[np.ndarray, np.ndarray]:
    """Flow and validity from the bytes of a KITTI flow PNG.

    Returns:
        ``(flow, valid)``: ``(H, W, 2)`` float32 flow in pixels (0 at invalid pixels)
        and ``(H, W)`` bool.

    Raises:
        InputError: naming ``source``: empty, not a decodable image, or not a 16-bit
            3-channel image.
    """
    buf = np.frombuffer(data, dtype=np.uint8)
    if buf.size == 0:
        raise InputError("empty file (expected a KITTI flow PNG)", source)
    try:
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    except cv2.error:
        img = None
    if img is None:
        raise InputError("cannot decode the flow PNG (truncated, corrupt or not an image)", source)
    if img.dtype != np.uint16 or img.ndim != 3 or img.shape[2] != 3:
        chans = 1 if img.ndim == 2 else img.shape[2]
        raise InputError(f"not a KITTI flow PNG: {img.dtype} with {chans} channel(s), "
                         "expected 16-bit with 3 channels", source)
    valid = img[..., 0] > 0
    flow = np.empty(img.shape[:2] + (2,), dtype=np.float32)
    flow[..., 0] = (img[..., 2].astype(np.float32) - KITTI_FLOW_OFFSET) / KITTI_FLOW_SCALE
    flow[..., 1] = (img[..., 1].astype(np.float32) - KITTI_FLOW_OFFSET) / KITTI_FLOW_SCALE
    flow[~valid] = 0.0
    return flow, valid


def read_kitti_flow(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """``(flow (H, W, 2) float32, valid (H, W) bool)`` of a KITTI flow PNG (see :func:`decode_kitti_flow`).

    Raises:
        InputError: missing, unreadable or not a KITTI flow PNG (one line naming the file).
    """
    path = Path(path)
    return decode_kitti_flow(read_bytes(path), path)


def read_flow_file(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth flow of a ``.png`` (KITTI) or ``.flo`` (Middlebury) file, by suffix.

    Returns:
        ``(flow, valid)``: ``(H, W, 2)`` float32 (0 at invalid pixels), ``(H, W)`` bool.
        For ``.flo``, a pixel is valid when both components are finite and below
        :data:`FLO_UNKNOWN` in magnitude.

    Raises:
        InputError: another suffix, or a file that cannot be read (naming it).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".png":
        return read_kitti_flow(path)
    if suffix == ".flo":
        flow = read_flo(path)
        valid = np.isfinite(flow).all(axis=2) & (np.abs(flow) < FLO_UNKNOWN).all(axis=2)
        flow[~valid] = 0.0
        return flow, valid
    raise InputError(f"unknown ground-truth flow format {path.suffix or '(no suffix)'!r}; "
                     "expected a KITTI flow .png or a .flo", path)


# ---------------------------------------------------------------------------
# image pairs with their ground truth

@dataclass(frozen=True)
class FlowPair:
    """Two images and the ground-truth flow from the first to the second."""

    image1: Path
    image2: Path
    gt: Path

    @property
    def name(self) -> str:
        """The first image's file stem (KITTI: ``NNNNNN_10``)."""
        return self.image1.stem


def _gt_in(folder: Path, stem: str, image: Path) -> Path:
    for suffix in GT_SUFFIXES:
        p = folder / (stem + suffix)
        if p.is_file():
            return p
    raise InputError(f"no ground-truth flow for this image (looked for {stem}.png and {stem}.flo in {folder})",
                     image)


def kitti_flow_pairs(folder: str | Path, gt_dir: str | Path | None = None) -> tuple[list[FlowPair], Path]:
    """The image pairs of a KITTI flow folder and their ground-truth files.

    Args:
        folder: the benchmark folder (holding ``image_2/``, or ``colored_0/`` or
            ``image_0/``), or the image folder itself.
        gt_dir: folder of ground-truth flow files named like the first image
            (``NNNNNN_10.png`` or ``.flo``); None = ``flow_occ/`` beside the image
            folder, else ``flow_noc/``.

    Returns:
        ``(pairs, gt_dir)``: every ``*_10.<ext>`` image with its ``*_11.<ext>`` and its
        ground truth, in natural order, and the ground-truth folder used.

    Raises:
        InputError: naming the path: no such folder, no ``*_10`` image, a missing second
            image, no ground-truth folder, or a missing ground-truth file.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("no such folder" if not folder.exists() else "not a folder", folder)
    image_dir = next((folder / d for d in KITTI_IMAGE_DIRS if (folder / d).is_dir()), None)
    root = folder
    if image_dir is None:
        image_dir, root = folder, folder.parent
    firsts = sorted((p for p in image_dir.iterdir()
                     if p.is_file() and p.stem.endswith("_10") and p.suffix.lower() in (".png", ".jpg", ".jpeg")),
                    key=lambda p: natural_key(p.name))
    if not firsts:
        raise InputError(f"no first images (NNNNNN_10.png) here; expected a KITTI flow folder with "
                         f"{'/'.join(KITTI_IMAGE_DIRS)}/NNNNNN_10.png and NNNNNN_11.png, or a list file",
                         image_dir)
    if gt_dir is None:
        gt_dir = next((root / d for d in KITTI_GT_DIRS if (root / d).is_dir()), None)
        if gt_dir is None:
            raise InputError(f"no ground-truth folder ({' or '.join(KITTI_GT_DIRS)}) here; give --gt-flow", root)
    gt_dir = Path(gt_dir)
    if not gt_dir.is_dir():
        raise InputError("ground-truth flow folder not found" if not gt_dir.exists() else "not a folder", gt_dir)
    pairs = []
    for p1 in firsts:
        p2 = p1.with_name(p1.stem[:-3] + "_11" + p1.suffix)
        if not p2.is_file():
            raise InputError(f"no second image {p2.name} for this image", p1)
        pairs.append(FlowPair(p1, p2, _gt_in(gt_dir, p1.stem, p1)))
    return pairs, gt_dir


def read_pair_list(path: str | Path) -> list[FlowPair]:
    """The pairs of a list file: one ``image1 image2 ground_truth`` line per pair.

    Paths are relative to the list file's folder unless absolute; blank lines and
    lines starting with ``#`` are ignored; paths must not contain spaces.

    Raises:
        InputError: naming the file and line: unreadable, not three fields, a missing
            file, or no pair at all.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError("no such file or folder", path) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read the pair list: {getattr(exc, 'strerror', None) or exc}", path) from None
    base = path.parent
    pairs = []
    for n, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.split()
        if len(fields) != 3:
            raise InputError(f"expected 'image1 image2 ground_truth', got {len(fields)} field(s)", path, n)
        files = [Path(f) if Path(f).is_absolute() else base / f for f in fields]
        for f in files:
            if not f.is_file():
                raise InputError(f"{f}: no such file", path, n)
        pairs.append(FlowPair(*files))
    if not pairs:
        raise InputError("no pairs in the list (expected 'image1 image2 ground_truth' lines)", path)
    return pairs
