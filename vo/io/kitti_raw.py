"""KITTI raw drives: layout, rectified intrinsics and timestamps.

The raw recordings are laid out as::

    <root>/<date>/calib_cam_to_cam.txt
    <root>/<date>/<date>_drive_<NNNN>_sync/image_02/data/0000000000.png
    <root>/<date>/<date>_drive_<NNNN>_sync/image_02/timestamps.txt

``image_00``/``image_01`` are the grey cameras, ``image_02``/``image_03`` the colour
ones; ``image_02`` (left colour, the one depth/flow networks are trained on) is
preferred, else ``image_00``. The ``_sync`` drives hold rectified images, so the
intrinsics are the left ``(3, 3)`` block of ``P_rect_<cc>`` in the date folder's
``calib_cam_to_cam.txt``; the ``_extract`` drives are unrectified and refused.

``calib_cam_to_cam.txt`` is ``key: values`` lines, e.g.::

    calib_time: 09-Jan-2012 13:57:47
    corner_dist: 9.950000e-02
    S_00: 1.392000e+03 5.120000e+02
    K_00: 9.842439e+02 0.000000e+00 6.900000e+02 ...
    S_rect_02: 1.242000e+03 3.750000e+02
    P_rect_02: 7.215377e+02 0.000000e+00 6.095593e+02 4.485728e+01 ...

(values are numbers except ``calib_time``). ``S_rect_<cc>`` is the rectified
image size ``(W, H)``.

This module only finds and parses; :func:`trianflow_vo.io.sequence.open_sequence`
opens a drive folder as a sequence of kind ``"kitti_raw"``.
"""

from __future__ import annotations

import calendar
import datetime
import re
from pathlib import Path

import numpy as np

from trianflow_vo.errors import InputError

CALIB_NAME = "calib_cam_to_cam.txt"
# camera folders in order of preference (left colour first, then left grey)
CAMERAS = ("image_02", "image_00", "image_03", "image_01")
_KEY_LINE = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*:(.*)$")
_CAMERA_DIR = re.compile(r"^image_(\d\d)$")
_STAMP = re.compile(r"^(\d{4})-(\d\d)-(\d\d)[ T](\d\d):(\d\d):(\d\d)(\.\d+)?$")


def _list_images(folder: Path) -> list[Path]:
    from trianflow_vo.io.sequence import list_images  # local: sequence imports this module

    return list_images(folder)


def is_drive(path: str | Path) -> bool:
    """True when ``path`` is a folder holding at least one ``image_0<c>/data/`` folder."""
    p = Path(path)
    return p.is_dir() and any((p / cam / "data").is_dir() for cam in CAMERAS)


def is_extract_drive(path: str | Path) -> bool:
    """True for an unrectified ``*_extract`` drive folder (its images do not fit ``P_rect``)."""
    return Path(path).name.endswith("_extract")


def drive_image_dir(drive: str | Path) -> Path | None:
    """The ``image_0<c>/data`` folder of a drive: the first of :data:`CAMERAS` holding images,
    else the first that exists (so that the caller can say it is empty), else None."""
    drive = Path(drive)
    existing = [drive / cam / "data" for cam in CAMERAS if (drive / cam / "data").is_dir()]
    for d in existing:
        if _list_images(d):
            return d
    return existing[0] if existing else None


def camera_of(image_dir: str | Path) -> str:
    """Two-digit camera number of ``.../image_02/data`` (or ``.../image_02``): ``"02"``.

    Raises ``ValueError`` when the folder is not a KITTI raw camera folder.
    """
    p = Path(image_dir)
    if p.name == "data":
        p = p.parent
    m = _CAMERA_DIR.match(p.name)
    if m is None:
        raise ValueError(f"not a KITTI raw camera folder: {str(image_dir)!r}")
    return m.group(1)


def _natural(p: Path) -> tuple:
    from trianflow_vo.io.sequence import natural_key

    return natural_key(p.name)


def find_drives(path: str | Path) -> list[Path]:
    """Drive folders under ``path``: the drive itself, the drives of a date folder, or those
    of every date folder of the raw root (natural order by date, then drive).

    ``*_extract`` (unrectified) drives inside a date folder are left out; a drive given
    directly is returned as is (the caller refuses an ``_extract`` one with a reason).
    Returns ``[]`` when ``path`` holds no drive at these depths.
    """
    p = Path(path)
    if not p.is_dir():
        return []
    if is_drive(p):
        return [p]

    def drives_in(folder: Path) -> list[Path]:
        subs = [d for d in folder.iterdir() if d.is_dir() and not d.name.startswith(".")]
        return sorted((d for d in subs if is_drive(d) and not is_extract_drive(d)), key=_natural)

    found = drives_in(p)
    if found:
        return found
    out: list[Path] = []
    for date in sorted((d for d in p.iterdir() if d.is_dir() and not d.name.startswith(".")), key=_natural):
        out += drives_in(date)
    return out


def calib_file_for(drive: str | Path) -> Path | None:
    """``calib_cam_to_cam.txt`` of a drive: in its date folder (the parent), else inside the drive."""
    drive = Path(drive)
    for cand in (drive.parent / CALIB_NAME, drive / CALIB_NAME):
        if cand.is_file():
            return cand
    return None


def read_cam_to_cam(path: str | Path) -> dict[str, tuple[np.ndarray, int]]:
    """All numeric entries of a ``calib_cam_to_cam.txt``.

    Returns ``{key: (values, line)}``, ``values`` a 1-D float64 array and ``line`` 1-based.
    Entries whose values are not all numbers (``calib_time``) are left out; blank lines
    and ``#`` comments are ignored. Raises :class:`InputError` naming the file and line for
    a content line without ``key:`` or a key given twice, and when the file cannot be read.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise InputError("calibration file not found", path) from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"cannot read calibration file: {e}", path) from None
    out: dict[str, tuple[np.ndarray, int]] = {}
    for i, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        m = _KEY_LINE.match(s)
        if m is None:
            raise InputError(f"malformed calibration line (expected 'key: values'): {s[:60]!r}", path, i)
        key, rest = m.group(1), m.group(2).split()
        if key in out:
            raise InputError(f"{key} given twice (first on line {out[key][1]})", path, i)
        try:
            vals = np.array([float(t) for t in rest], dtype=np.float64)
        except ValueError:
            continue  # e.g. calib_time: 09-Jan-2012 13:57:47
        if vals.size == 0 or not np.all(np.isfinite(vals)):
            continue
        out[key] = (vals, i)
    return out


def rect_intrinsics(path: str | Path, camera: str = "02") -> tuple[np.ndarray, tuple[int, int] | None]:
    """Rectified intrinsics of ``camera`` from a ``calib_cam_to_cam.txt``.

    Args:
        path: the calibration file.
        camera: two-digit camera number, ``"00"`` .. ``"03"``.

    Returns:
        ``(K, size)``: ``K`` ``(3, 3)`` float64, the left block of ``P_rect_<camera>``;
        ``size`` the rectified ``(H, W)`` from ``S_rect_<camera>``, or None without it.

    Raises:
        InputError: no ``P_rect_<camera>`` entry (listing those found), not 12 numbers,
            or not a pinhole matrix (non-positive focal lengths, last row not ``0 0 1``).
    """
    path = Path(path)
    entries = read_cam_to_cam(path)
    key = f"P_rect_{camera}"
    if key not in entries:
        have = ", ".join(k for k in sorted(entries) if k.startswith("P_rect_")) or "none"
        raise InputError(f"no {key}: line (rectified projections found: {have})", path)
    vals, line = entries[key]
    if vals.size != 12:
        raise InputError(f"malformed calibration line: {key} needs 12 numbers, got {vals.size}", path, line)
    P = vals.reshape(3, 4)
    K = P[:, :3].copy()
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(f"focal lengths must be positive, got fx={K[0, 0]:g}, fy={K[1, 1]:g}", path, line)
    if abs(K[1, 0]) > 1e-9 or not np.allclose(K[2], [0.0, 0.0, 1.0], atol=1e-9):
        raise InputError(f"{key} is not K [R|t]: expected rows [fx s cx], [0 fy cy], [0 0 1]", path, line)
    size = None
    s = entries.get(f"S_rect_{camera}")
    if s is not None and s[0].size == 2 and np.all(s[0] > 0):
        size = (int(round(s[0][1])), int(round(s[0][0])))
    return K, size


def read_timestamps(path: str | Path) -> list[float]:
    """``timestamps.txt`` of a camera folder: ``2011-09-26 13:02:25.594360375`` lines -> seconds.

    Seconds since 1970-01-01 of the wall-clock time written (taken as UTC; only
    differences matter), nanosecond fraction kept as far as float64 allows (~0.2 µs).
    Raises :class:`InputError` with the line number for a malformed line.
    """
    path = Path(path)
    out = []
    for i, line in enumerate(path.read_text().splitlines(), start=1):
        s = line.strip()
        if not s:
            continue
        m = _STAMP.match(s)
        if m is None:
            raise InputError(f"malformed timestamp (expected 'YYYY-MM-DD hh:mm:ss.fff'): {s[:60]!r}", path, i)
        y, mo, d, hh, mm, ss = (int(g) for g in m.groups()[:6])
        try:
            whole = calendar.timegm(datetime.datetime(y, mo, d, hh, mm, ss).timetuple())
        except (ValueError, OverflowError):
            raise InputError(f"malformed timestamp: {s[:60]!r}", path, i) from None
        out.append(whole + (float(m.group(7)) if m.group(7) else 0.0))
    return out


def drive_name(drive: str | Path) -> str:
    """The drive's scene name without the ``_sync`` suffix: ``2011_09_26_drive_0001``
    (the form of the Eigen split's scene lists)."""
    name = Path(drive).name
    return name[: -len("_sync")] if name.endswith("_sync") else name
