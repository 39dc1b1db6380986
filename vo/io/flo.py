"""Middlebury ``.flo`` optical-flow files.

Layout (every value little-endian): the float32 magic ``202021.25`` (the bytes
``PIEH``), int32 width, int32 height, then ``height * width * 2`` float32 values,
row by row, interleaved ``u, v`` (``u`` = dx, ``v`` = dy, in pixels). That is the
memory layout of a C-contiguous ``(H, W, 2)`` float32 array.

:func:`write_flo` writes ``PATH.tmp`` and renames it, so ``PATH`` is never half-written.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from trianflow_vo.errors import InputError
from trianflow_vo.io.atomic import write_atomic
from trianflow_vo.io.read import read_bytes

FLO_MAGIC = 202021.25
_MAGIC_BYTES = np.array([FLO_MAGIC], dtype="<f4").tobytes()  # b"PIEH"
_HEADER_BYTES = 12
# sanity bound on a header's width/height (guards against reading garbage as a size)
_MAX_SIDE = 1 << 16


def encode_flo(flow: np.ndarray) -> bytes:
    """The ``.flo`` bytes of an ``(H, W, 2)`` flow (any real dtype; stored as float32)."""
    flow = np.asarray(flow)
    if flow.ndim != 3 or flow.shape[2] != 2 or flow.shape[0] < 1 or flow.shape[1] < 1:
        raise ValueError(f"flow must be (H, W, 2) with H, W >= 1, got {flow.shape}")
    h, w = flow.shape[:2]
    header = _MAGIC_BYTES + np.array([w, h], dtype="<i4").tobytes()
    return header + np.ascontiguousarray(flow, dtype="<f4").tobytes()


def decode_flo(data: bytes, source: str | Path = "<bytes>") -> np.ndarray:
    """``(H, W, 2)`` float32 flow from ``.flo`` bytes.

    Raises:
        InputError: naming ``source``: too short, wrong magic, bad size, wrong length.
    """
    if len(data) < _HEADER_BYTES:
        raise InputError(f"not a .flo file ({len(data)} bytes, shorter than the 12-byte header)", source)
    if data[:4] != _MAGIC_BYTES:
        raise InputError(f"not a .flo file (magic {data[:4]!r}, expected {_MAGIC_BYTES!r} = {FLO_MAGIC})", source)
    w, h = (int(v) for v in np.frombuffer(data, dtype="<i4", count=2, offset=4))
    if not (0 < w <= _MAX_SIDE and 0 < h <= _MAX_SIDE):
        raise InputError(f".flo header has an invalid size {w}x{h} (width x height)", source)
    want = _HEADER_BYTES + 8 * w * h
    if len(data) != want:
        raise InputError(f".flo file has {len(data)} bytes, expected {want} for {w}x{h}", source)
    flow = np.frombuffer(data, dtype="<f4", count=2 * w * h, offset=_HEADER_BYTES)
    return flow.reshape(h, w, 2).astype(np.float32)  # native byte order, writeable copy


def write_flo(path: str | Path, flow: np.ndarray) -> Path:
    """Write ``flow`` ``(H, W, 2)`` to ``path`` (via ``path.tmp`` and a rename); returns ``path``."""
    return write_atomic(path, encode_flo(flow))


def read_flo(path: str | Path) -> np.ndarray:
    """``(H, W, 2)`` float32 flow of a ``.flo`` file.

    Raises:
        InputError: missing file or not a valid ``.flo`` (one line naming the file).
    """
    path = Path(path)
    return decode_flo(read_bytes(path), path)
