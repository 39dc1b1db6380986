"""Camera intrinsics from the places users keep them.

Every reader returns ``K``, a ``(3, 3)`` float64 pinhole matrix
``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (skew kept when a file gives one) at
the resolution of the source images. Supported sources:

* KITTI ``calib.txt``: lines ``P0: <12 numbers>`` (a row-major ``(3, 4)``
  projection matrix ``K [R | t]`` of a rectified camera; ``K`` is its left
  ``(3, 3)`` block). The line is chosen by camera name (``P0`` for
  ``image_0/``, ``P2`` for ``image_2/``), never by position.
  ``P_rect_00:``-style keys of KITTI raw calibration files are accepted as
  synonyms of ``P0:``.
* a ``(3, 3)`` K text file: 3 lines of 3 numbers;
* one line ``fx fy cx cy``;
* the ``--intrinsics fx,fy,cx,cy`` option string.

Malformed input raises :class:`vo.errors.InputError` naming the file and the
1-based line.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from trianflow_vo.errors import InputError

# Published intrinsics of the TUM RGB-D colour cameras (fx, fy, cx, cy) at
# 640x480. Freiburg 1 and 2 images are not undistorted; their small lens
# distortion is ignored here. Freiburg 3 images are already undistorted.
TUM_INTRINSICS: dict[str, tuple[float, float, float, float]] = {
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}

_KEY_LINE = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*:(.*)$")
_P_KEY = re.compile(r"^P(\d+)$|^P_rect_(\d+)$")
_IMAGE_DIR = re.compile(r"^image_(\d+)$")
_HOW_TO = "give them with --intrinsics fx,fy,cx,cy or --calib FILE"


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """``(3, 3)`` K from focal lengths and principal point (pixels).

    Raises ``ValueError`` for non-finite values or non-positive focal lengths.
    """
    vals = [float(fx), float(fy), float(cx), float(cy)]
    if not all(math.isfinite(v) for v in vals):
        raise ValueError(f"intrinsics must be finite numbers, got {vals}")
    if vals[0] <= 0 or vals[1] <= 0:
        raise ValueError(f"focal lengths must be positive, got fx={vals[0]:g}, fy={vals[1]:g}")
    return np.array([[vals[0], 0.0, vals[2]], [0.0, vals[1], vals[3]], [0.0, 0.0, 1.0]], dtype=np.float64)


def parse_intrinsics(text: str) -> tuple[float, float, float, float]:
    """``"fx,fy,cx,cy"`` (commas and/or spaces) -> ``(fx, fy, cx, cy)``.

    Raises :class:`InputError` (without a path) when the string is not four
    finite numbers with positive focal lengths.
    """
    parts = [p for p in re.split(r"[,\s]+", text.strip()) if p]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        vals = []
    if len(vals) != 4:
        raise InputError(f"--intrinsics expects four numbers fx,fy,cx,cy, got {text!r}")
    try:
        intrinsics_matrix(*vals)
    except ValueError as e:
        raise InputError(f"--intrinsics {text!r}: {e}") from None
    return vals[0], vals[1], vals[2], vals[3]


def kitti_camera_for_folder(image_dir: str | Path) -> str:
    """Calibration key of a KITTI image folder by its name: ``image_2`` -> ``"P2"``.

    Raises ``ValueError`` for a name that is not ``image_<n>``.
    """
    name = Path(image_dir).name
    m = _IMAGE_DIR.match(name)
    if m is None:
        raise ValueError(f"not a KITTI image folder name: {name!r}")
    return f"P{int(m.group(1))}"


def _numbers(text: str) -> list[float] | None:
    """Floats of a whitespace/comma separated string, or None if any token is not a number."""
    toks = [t for t in re.split(r"[,\s]+", text.strip()) if t]
    try:
        vals = [float(t) for t in toks]
    except ValueError:
        return None
    if not all(math.isfinite(v) for v in vals):
        return None
    return vals


def _content_lines(path: Path) -> list[tuple[int, str]]:
    """``(line_number, text)`` of non-blank, non-comment lines (1-based numbers)."""
    try:
        raw = path.read_text()
    except FileNotFoundError:
        raise InputError("calibration file not found", path) from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"cannot read calibration file: {e}", path) from None
    out = []
    for i, line in enumerate(raw.splitlines(), start=1):
        s = line.strip()
        if s and not s.startswith("#"):
            out.append((i, s))
    return out


def _check_K(K: np.ndarray, path: Path, line: int | None) -> np.ndarray:
    """Reject matrices that are not pinhole intrinsics (positive focals, last row 0 0 1)."""
    if not np.all(np.isfinite(K)):
        raise InputError("intrinsics contain non-finite values", path, line)
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(f"focal lengths must be positive, got fx={K[0, 0]:g}, fy={K[1, 1]:g}", path, line)
    if abs(K[1, 0]) > 1e-9 or not np.allclose(K[2], [0.0, 0.0, 1.0], atol=1e-9):
        raise InputError("not an intrinsics matrix: expected rows [fx s cx], [0 fy cy], [0 0 1]", path, line)
    return K


def _kitti_key(key: str) -> str | None:
    """Normalised camera key (``"P2"``) of a calibration key, or None if not a projection matrix."""
    m = _P_KEY.match(key)
    if m is None:
        return None
    return f"P{int(m.group(1) or m.group(2))}"


def read_kitti_projections(path: str | Path) -> dict[str, tuple[np.ndarray, int]]:
    """All projection matrices of a KITTI calibration file.

    Returns ``{"P0": (P, line), ...}`` with ``P`` ``(3, 4)`` float64 and the
    1-based line it came from. Other keys (``Tr:``, ``calib_time:``...) are
    ignored; a projection line without exactly 12 numbers, or a content line
    without a ``key:``, raises :class:`InputError` with its line number.
    """
    path = Path(path)
    out: dict[str, tuple[np.ndarray, int]] = {}
    for i, s in _content_lines(path):
        m = _KEY_LINE.match(s)
        if m is None:
            raise InputError(f"malformed calibration line (expected 'P0: <12 numbers>'): {s[:60]!r}", path, i)
        key = _kitti_key(m.group(1))
        if key is None:
            continue
        vals = _numbers(m.group(2))
        if vals is None or len(vals) != 12:
            n = "non-numeric values" if vals is None else f"{len(vals)} numbers"
            raise InputError(f"malformed calibration line: {m.group(1)} needs 12 numbers, got {n}", path, i)
        if key in out:
            raise InputError(f"{key} given twice (first on line {out[key][1]})", path, i)
        out[key] = (np.array(vals, dtype=np.float64).reshape(3, 4), i)
    return out


def read_kitti_calib(path: str | Path, camera: str = "P0") -> np.ndarray:
    """``(3, 3)`` K of ``camera`` (``"P0"``, ``"P2"``...) from a KITTI ``calib.txt``."""
    path = Path(path)
    mats = read_kitti_projections(path)
    if camera not in mats:
        have = ", ".join(sorted(mats)) or "none"
        raise InputError(f"no {camera}: line (projection matrices found: {have})", path)
    P, line = mats[camera]
    return _check_K(P[:, :3].copy(), path, line)


def read_calib_file(path: str | Path, camera: str | None = None) -> np.ndarray:
    """``(3, 3)`` K from a calibration file of any supported layout.

    * KITTI-style ``key: numbers`` lines: the ``camera`` line (e.g. ``"P2"``)
      when given, else ``P0``, else the only projection line there is.
    * 3 lines of 3 numbers: K itself.
    * 1 line of 4 numbers: ``fx fy cx cy``.

    ``camera`` only applies to KITTI-style files. Raises :class:`InputError`
    naming the file (and line) for anything else.
    """
    path = Path(path)
    lines = _content_lines(path)
    if not lines:
        raise InputError("calibration file is empty", path)
    if any(_KEY_LINE.match(s) for _, s in lines):
        mats = read_kitti_projections(path)
        if camera is None:
            if "P0" in mats:
                camera = "P0"
            elif len(mats) == 1:
                camera = next(iter(mats))
            else:
                have = ", ".join(sorted(mats)) or "none"
                raise InputError(f"cannot tell which projection matrix to use (found: {have}; no P0)", path)
        return read_kitti_calib(path, camera)

    layout = "expected 3 lines of 3 numbers (K), one line 'fx fy cx cy', or KITTI 'P0: <12 numbers>' lines"
    rows = []
    for i, s in lines:
        vals = _numbers(s)
        if vals is None:
            raise InputError(f"malformed calibration line: non-numeric values in {s[:60]!r}", path, i)
        rows.append((i, vals))
    if len(rows) == 1:
        i, vals = rows[0]
        if len(vals) != 4:
            raise InputError(f"malformed calibration line: {len(vals)} numbers; {layout}", path, i)
        try:
            return intrinsics_matrix(*vals)
        except ValueError as e:
            raise InputError(str(e), path, i) from None
    if len(rows) == 3:
        for i, vals in rows:
            if len(vals) != 3:
                raise InputError(f"malformed calibration line: {len(vals)} numbers in a row of K; {layout}", path, i)
        K = np.array([vals for _, vals in rows], dtype=np.float64)
        return _check_K(K, path, None)
    raise InputError(f"{len(rows)} numeric lines; {layout}", path, rows[min(3, len(rows) - 1)][0])


def tum_default_intrinsics(folder: str | Path) -> tuple[tuple[float, float, float, float], str] | None:
    """Published TUM RGB-D intrinsics for a folder named like ``*freiburg2*``.

    Returns ``((fx, fy, cx, cy), "freiburg2")`` or None when the folder name
    names no TUM camera.
    """
    name = Path(folder).name.lower()
    hits = [cam for cam in TUM_INTRINSICS if cam in name]
    if len(hits) != 1:
        return None
    return TUM_INTRINSICS[hits[0]], hits[0]


def how_to_give_intrinsics() -> str:
    """The hint every 'no intrinsics' error ends with."""
    return _HOW_TO
