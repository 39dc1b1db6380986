"""KITTI depth PNGs and the ground-truth depth sources of ``trianflow-vo eval-depth``.

A KITTI depth PNG (the ``proj_depth/groundtruth`` files of the KITTI depth benchmark)
is a 16-bit, 1-channel PNG: depth in metres = value / 256, value 0 = no depth.

Ground-truth depth (:func:`open_gt_depth`) for a list of images comes as

* a **folder**: per image ``STEM.png`` (KITTI depth PNG) or ``STEM.npy`` (float
  ``(H, W)`` metres), ``STEM`` = the image's file stem;
* one **stack** ``.npz`` (key ``data``, or its only array) or ``.npy`` of ``(N, H, W)``
  depth maps, map ``i`` = image ``i`` in order. That is what the KITTI Eigen-split
  export scripts (monodepth2's, the TrianFlow authors') write as ``gt_depths.npz``;
  their maps have several sizes, so the file holds an *object* array, which needs
  pickle to load (``allow_pickle=True``: only for files you trust);
* a single ``.npy``/``.png`` of one ``(H, W)`` map when there is one image.

Depth maps come out float32 ``(H, W)`` metres with 0 (or any value <= 0) where there
is no ground truth; non-finite values are set to 0. Every reader raises
:class:`~trianflow_vo.errors.InputError` naming the file.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import cv2
import numpy as np

from trianflow_vo.errors import InputError
from trianflow_vo.io.atomic import write_atomic
from trianflow_vo.io.read import read_bytes

#: one metre in a KITTI depth PNG
KITTI_DEPTH_SCALE = 256.0
#: per-image ground-truth suffixes looked for in a folder, in order of preference
GT_DEPTH_SUFFIXES = (".png", ".npy")
#: the key of the stack in an ``.npz`` (what the Eigen-split export scripts write)
NPZ_KEY = "data"
_PICKLE_HINT = ("holds Python objects (an object array, e.g. depth maps of several sizes), which need pickle "
                "to load; pass --allow-pickle if you trust this file")


# ---------------------------------------------------------------------------
# KITTI depth PNG

def encode_depth_png(depth: np.ndarray) -> bytes:
    """The PNG bytes of ``depth`` ``(H, W)`` metres in the KITTI format.

    Rounded to 1/256 m and clipped to what 16 bits hold (< 256 m); pixels that are
    not finite or <= 0 are stored as 0 (no depth).

    Raises:
        ValueError: not a non-empty 2-D array.
    """
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2 or depth.size == 0:
        raise ValueError(f"depth must be (H, W) with H, W >= 1, got {depth.shape}")
    ok = np.isfinite(depth) & (depth > 0)
    code = np.zeros(depth.shape, dtype=np.uint16)
    code[ok] = np.clip(np.rint(depth[ok] * KITTI_DEPTH_SCALE), 0, 65535).astype(np.uint16)
    ok_enc, enc = cv2.imencode(".png", code)
    if not ok_enc:  # pragma: no cover - OpenCV encodes any uint16 grey image
        raise ValueError("OpenCV could not encode the depth PNG")
    return enc.tobytes()


def write_depth_png(path: str | Path, depth: np.ndarray) -> Path:
    """Write :func:`encode_depth_png` to ``path`` (via ``path.tmp`` and a rename); returns ``path``."""
    return write_atomic(path, encode_depth_png(depth))


def decode_depth_png(data: bytes, source: str | Path = "<bytes>") -> np.ndarray:
    """``(H, W)`` float32 depth (metres, 0 = none) from the bytes of a KITTI depth PNG.

    Raises:
        InputError: naming ``source``: empty, not decodable, or not 16-bit 1-channel.
    """
    buf = np.frombuffer(data, dtype=np.uint8)
    if buf.size == 0:
        raise InputError("empty file (expected a KITTI depth PNG)", source)
    try:
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    except cv2.error:
        img = None
    if img is None:
        raise InputError("cannot decode the depth PNG (truncated, corrupt or not an image)", source)
    if img.dtype != np.uint16 or img.ndim != 2:
        chans = 1 if img.ndim == 2 else img.shape[2]
        raise InputError(f"not a KITTI depth PNG: {img.dtype} with {chans} channel(s), "
                         "expected 16-bit with 1 channel (depth = value / 256)", source)
    return img.astype(np.float32) / np.float32(KITTI_DEPTH_SCALE)


def read_depth_png(path: str | Path) -> np.ndarray:
    """``(H, W)`` float32 depth in metres (0 = no depth) of a KITTI depth PNG.

    Raises:
        InputError: missing, unreadable, or not a 16-bit 1-channel PNG (naming the file).
    """
    path = Path(path)
    return decode_depth_png(read_bytes(path), path)


# ---------------------------------------------------------------------------
# ground-truth sources

def _as_depth_map(array, source: str | Path) -> np.ndarray:
    """A 2-D real array -> float32 metres with non-finite values set to 0."""
    a = np.asarray(array)
    if a.ndim != 2 or a.size == 0 or not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise InputError(f"expected a (H, W) depth map of numbers, got shape {a.shape} {a.dtype}", source)
    a = a.astype(np.float32)
    a[~np.isfinite(a)] = 0.0
    return a


def _load_npy(path: Path, allow_pickle: bool):
    try:
        return np.load(path, allow_pickle=allow_pickle)
    except FileNotFoundError:
        raise InputError("no such file", path) from None
    except ValueError as exc:
        if "Object arrays" in str(exc):
            raise InputError(_PICKLE_HINT, path) from None
        if "pickled data" in str(exc):  # neither .npy nor .npz magic: numpy would unpickle it
            raise InputError("not a readable .npy/.npz file (no numpy header)", path) from None
        raise InputError(f"not a readable .npy/.npz file ({exc})", path) from None
    except (OSError, EOFError) as exc:
        raise InputError(f"not a readable .npy/.npz file ({getattr(exc, 'strerror', None) or exc})", path) from None


def read_depth_file(path: str | Path, allow_pickle: bool = False) -> np.ndarray:
    """``(H, W)`` float32 depth (metres, 0 = none) of one ``.png`` (KITTI) or ``.npy`` file.

    Raises:
        InputError: another suffix, unreadable, or not one depth map (naming the file).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".png":
        return read_depth_png(path)
    if suffix == ".npy":
        return _as_depth_map(_load_npy(path, allow_pickle), path)
    raise InputError(f"unknown ground-truth depth format {path.suffix or '(no suffix)'!r}; "
                     "expected a KITTI depth .png or a .npy", path)


def _load_stack(path: Path, allow_pickle: bool) -> list | np.ndarray:
    """The depth maps of an .npz/.npy stack, indexable, without converting them yet."""
    loaded = _load_npy(path, allow_pickle)
    if isinstance(loaded, np.lib.npyio.NpzFile):
        with loaded:
            keys = list(loaded.files)
            if NPZ_KEY in keys:
                key = NPZ_KEY
            elif len(keys) == 1:
                key = keys[0]
            else:
                raise InputError(f"no array named {NPZ_KEY!r} and {len(keys)} arrays ({', '.join(keys[:5])}); "
                                 f"expected the stack under {NPZ_KEY!r}", path)
            try:
                stack = loaded[key]
            except ValueError as exc:
                if "Object arrays" in str(exc):
                    raise InputError(_PICKLE_HINT, path) from None
                raise InputError(f"array {key!r} is not readable ({exc})", path) from None
    else:
        stack = loaded
    if stack.dtype == object:
        if stack.ndim != 1:
            raise InputError(f"expected a list of (H, W) depth maps, got an object array of shape {stack.shape}",
                             path)
        return list(stack)
    if stack.ndim == 2:
        return [stack]
    if stack.ndim != 3:
        raise InputError(f"expected (N, H, W) depth maps, got shape {stack.shape}", path)
    return stack


def open_gt_depth(gt: str | Path, images: Sequence[Path],
                  allow_pickle: bool = False) -> list[tuple[str, Callable[[], np.ndarray]]]:
    """The ground-truth depth of each image, resolved now and loaded on demand.

    Args:
        gt: a folder (``STEM.png``/``STEM.npy`` per image), an ``.npz``/``.npy`` stack
            (one map per image, in order) or one ``.png``/``.npy`` map (one image).
        images: the image files, in evaluation order.
        allow_pickle: let an object-array stack be unpickled (trusted files only).

    Returns:
        per image ``(source, load)``: ``source`` names the ground truth (the file, or
        ``FILE[i]`` in a stack), ``load()`` returns its ``(H, W)`` float32 depth.

    Raises:
        InputError: naming the path: ``gt`` missing or of an unknown kind; an image
            without a ground-truth file; a stack whose length is not the number of
            images; a stack that cannot be read.
    """
    gt = Path(gt)
    images = [Path(p) for p in images]
    if gt.is_dir():
        out = []
        for img in images:
            found = next((gt / (img.stem + s) for s in GT_DEPTH_SUFFIXES if (gt / (img.stem + s)).is_file()), None)
            if found is None:
                looked = " and ".join(img.stem + s for s in GT_DEPTH_SUFFIXES)
                raise InputError(f"no ground-truth depth for this image (looked for {looked} in {gt})", img)
            out.append((str(found), lambda f=found: read_depth_file(f, allow_pickle)))
        return out
    if not gt.exists():
        raise InputError("no such file or folder", gt)
    suffix = gt.suffix.lower()
    if suffix == ".png":
        if len(images) != 1:
            raise InputError(f"one depth map for {len(images)} images; give a folder or an (N, H, W) stack", gt)
        return [(str(gt), lambda: read_depth_png(gt))]
    if suffix not in (".npz", ".npy"):
        raise InputError(f"unknown ground-truth depth {gt.suffix or '(no suffix)'!r}; expected a folder, "
                         "an .npz/.npy stack or a KITTI depth .png", gt)
    stack = _load_stack(gt, allow_pickle)
    if len(stack) != len(images):
        raise InputError(f"holds {len(stack)} depth map(s) for {len(images)} image(s); the stack must have one "
                         "map per image, in image order", gt)
    return [(f"{gt}[{i}]", lambda i=i: _as_depth_map(stack[i], f"{gt}[{i}]")) for i in range(len(images))]
