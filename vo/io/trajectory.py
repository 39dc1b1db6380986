"""Trajectory files: KITTI (12 numbers per line), TUM (t tx ty tz qx qy qz qw).

Writers here are used by the run writer; readers are used by ``eval``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from trianflow_vo.errors import InputError


def format_kitti_line(T_world_cam: np.ndarray) -> str:
    """One KITTI line: the top 3x4 of a ``(4, 4)`` camera-to-world pose, row-major."""
    T = np.asarray(T_world_cam, dtype=np.float64)
    return " ".join(f"{v:.9e}" for v in T[:3, :4].reshape(-1))


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(4,)`` as ``(qx, qy, qz, qw)`` with ``qw >= 0`` of a ``(3, 3)`` rotation."""
    R = np.asarray(R, dtype=np.float64)
    m = R
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        q = np.array([(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s])
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = np.array([0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s])
    elif m[1, 1] > m[2, 2]:
        s = np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = np.array([(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s])
    else:
        s = np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = np.array([(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s])
    q /= np.linalg.norm(q)
    if q[3] < 0:
        q = -q
    return q


def format_tum_line(timestamp: float, T_world_cam: np.ndarray) -> str:
    """One TUM line ``timestamp tx ty tz qx qy qz qw`` of a ``(4, 4)`` camera-to-world pose."""
    T = np.asarray(T_world_cam, dtype=np.float64)
    q = rotation_to_quaternion(T[:3, :3])
    vals = [*T[:3, 3], *q]
    return f"{timestamp:.6f} " + " ".join(f"{v:.9f}" for v in vals)


# --------------------------------------------------------------------------- readers

KITTI_COLUMNS = 12
INDEXED_KITTI_COLUMNS = 13
TUM_COLUMNS = 8


@dataclass(frozen=True)
class TrajectoryFile:
    """A trajectory as read from disk, before any association.

    Attributes:
        path: the file it came from.
        kind: ``"kitti"`` (12 numbers, line i = frame i), ``"kitti-indexed"``
            (13 numbers, frame index first) or ``"tum"`` (timestamp tx ty tz qx qy qz qw).
        poses: ``(N, 4, 4)`` camera-to-world poses ``T_world_cam``.
        frames: ``(N,)`` int64 frame indices, or None when the file does not say
            (plain KITTI without ``frames.txt``, TUM).
        timestamps: ``(N,)`` float64 seconds (TUM), else None.
        lines: ``(N,)`` 1-based line numbers of the poses in ``path`` (for messages).
    """

    path: str
    kind: str
    poses: np.ndarray
    frames: np.ndarray | None
    timestamps: np.ndarray | None
    lines: np.ndarray


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """``(3, 3)`` rotation of a unit quaternion ``(4,)`` given as ``(qx, qy, qz, qw)``.

    The quaternion is normalised first; the caller must reject zero-norm input.
    """
    q = np.asarray(q, dtype=np.float64)
    x, y, z, w = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _numeric_rows(path: Path, what: str) -> tuple[list[list[float]], list[int]]:
    """Parse every non-empty, non-``#`` line of ``path`` into floats.

    All rows must have the same number of columns; NaN and inf are refused.
    Returns the rows and their 1-based line numbers.
    """
    rows: list[list[float]] = []
    lines: list[int] = []
    ncols = None
    with open(path, encoding="utf-8-sig", errors="replace") as fh:  # -sig: a BOM is not part of the first number
        for lineno, raw in enumerate(fh, start=1):
            text = raw.strip()
            if not text or text.startswith("#"):
                continue
            tokens = text.replace(",", " ").split()
            if ncols is None:
                ncols = len(tokens)
            elif len(tokens) != ncols:
                raise InputError(
                    f"{len(tokens)} columns, but the first {what} line has {ncols}", path, lineno
                )
            values = []
            for tok in tokens:
                try:
                    v = float(tok)
                except ValueError:
                    raise InputError(f"not a number: {tok!r}", path, lineno) from None
                if not np.isfinite(v):
                    raise InputError(f"non-finite value {tok!r}", path, lineno)
                values.append(v)
            rows.append(values)
            lines.append(lineno)
    return rows, lines


ROTATION_TOLERANCE = 1e-2


def _check_rotations(poses: np.ndarray, path: Path, line_nos: np.ndarray) -> None:
    """Refuse 3x3 blocks that are not rotations (``|R^T R - I| > 1e-2`` or ``det < 0``):
    usually a file with its columns in another order."""
    R = poses[:, :3, :3]
    dev = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    bad = np.nonzero((dev > ROTATION_TOLERANCE) | (det <= 0))[0]
    if bad.size:
        i = int(bad[0])
        raise InputError(
            f"the 3x3 part is not a rotation matrix (max |R^T R - I| = {dev[i]:.3g}, det = {det[i]:.3g}); "
            "expected row-major 3x4 [R | t] camera-to-world poses",
            path,
            int(line_nos[i]),
        )


def read_trajectory(path: str | Path) -> TrajectoryFile:
    """Read a KITTI (12 columns), indexed KITTI (13 columns) or TUM (8 columns) file.

    The format is recognised by the column count. Blank lines and lines starting with
    ``#`` are skipped. Every error names the file and line
    (:class:`vo.errors.InputError`): wrong or inconsistent column counts, non-numeric
    values, NaN/inf, a zero quaternion, a non-integer or repeated frame index.
    Indexed KITTI and TUM rows are sorted by frame index / timestamp.
    """
    path = Path(path)
    rows, lines = _numeric_rows(path, "trajectory")
    if not rows:
        raise InputError("no poses in file (empty or only comments)", path)
    data = np.asarray(rows, dtype=np.float64)
    line_nos = np.asarray(lines, dtype=np.int64)
    ncols = data.shape[1]
    n = data.shape[0]
    frames = None
    timestamps = None
    poses = np.tile(np.eye(4), (n, 1, 1))
    if ncols == KITTI_COLUMNS:
        kind = "kitti"
        poses[:, :3, :4] = data.reshape(n, 3, 4)
    elif ncols == INDEXED_KITTI_COLUMNS:
        kind = "kitti-indexed"
        idx = data[:, 0]
        bad = np.nonzero((idx != np.round(idx)) | (idx < 0))[0]
        if bad.size:
            i = int(bad[0])
            raise InputError(
                f"first column must be a non-negative integer frame index, got {rows[i][0]!r}",
                path,
                lines[i],
            )
        frames = idx.astype(np.int64)
        poses[:, :3, :4] = data[:, 1:].reshape(n, 3, 4)
    elif ncols == TUM_COLUMNS:
        kind = "tum"
        timestamps = data[:, 0].copy()
        for i in range(n):
            q = data[i, 4:8]
            if np.linalg.norm(q) < 1e-9:
                raise InputError("zero quaternion", path, lines[i])
            poses[i, :3, :3] = quaternion_to_rotation(q)
        poses[:, :3, 3] = data[:, 1:4]
    else:
        raise InputError(
            f"{ncols} columns per line: expected 12 (KITTI), 13 (frame index + KITTI) "
            "or 8 (TUM: timestamp tx ty tz qx qy qz qw)",
            path,
            lines[0],
        )
    _check_rotations(poses, path, line_nos)
    key = frames if frames is not None else timestamps
    if key is not None:
        order = np.argsort(key, kind="stable")
        key_sorted = key[order]
        dup = np.nonzero(np.diff(key_sorted) == 0)[0]
        if dup.size:
            i = int(order[dup[0] + 1])
            what = "frame index" if frames is not None else "timestamp"
            raise InputError(f"repeated {what} {key_sorted[dup[0]]!r}", path, lines[i])
        poses, line_nos = poses[order], line_nos[order]
        if frames is not None:
            frames = frames[order]
        else:
            timestamps = timestamps[order]
    return TrajectoryFile(str(path), kind, poses, frames, timestamps, line_nos)


def read_frame_indices(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a ``frames.txt``: one non-negative integer (source frame index) per line.

    Returns ``((N,) int64 indices, (N,) 1-based line numbers)``. Errors name the file
    and line (non-integers, negative values, extra columns, repeats).
    """
    path = Path(path)
    rows, lines = _numeric_rows(path, "frame-index")
    if not rows:
        raise InputError("no frame indices in file", path)
    if len(rows[0]) != 1:
        raise InputError(f"{len(rows[0])} columns: expected one frame index per line", path, lines[0])
    vals = np.asarray([r[0] for r in rows])
    bad = np.nonzero((vals != np.round(vals)) | (vals < 0))[0]
    if bad.size:
        i = int(bad[0])
        raise InputError(f"not a non-negative integer frame index: {rows[i][0]!r}", path, lines[i])
    idx = vals.astype(np.int64)
    seen: dict[int, int] = {}
    for v, ln in zip(idx.tolist(), lines):
        if v in seen:
            raise InputError(f"frame index {v} repeated (first on line {seen[v]})", path, ln)
        seen[v] = ln
    return idx, np.asarray(lines, dtype=np.int64)
