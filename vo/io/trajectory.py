"""Trajectory files: KITTI (12 numbers per line), indexed KITTI (13), TUM (t tx ty tz qx qy qz qw).

Readers here validate every line (errors name the file and line) and hand the poses on as
evo's trajectory types (:class:`evo.core.trajectory.PosePath3D`, and
:class:`~evo.core.trajectory.PoseTrajectory3D` for TUM); the line formatters are used by
the run writer, which streams one line per frame.

evo's own file readers (``evo.tools.file_interface``) are not used: they split on single
spaces only, cannot skip blank lines, accept no commas and no 13-column files, and report
a bad file without its line. evo's whole-file writers do not fit a run that writes one
line per processed frame (a crashed run keeps what it wrote). The quaternion conversions
are evo's (``evo.core.transformations``); evo's ``trajectory`` module (scipy) is imported
only when a file is read, so writing a run stays light.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from evo.core import transformations as _tr

from trianflow_vo.errors import InputError

if TYPE_CHECKING:  # evo.core.trajectory pulls in scipy: imported when a file is read
    from evo.core.trajectory import PosePath3D, PoseTrajectory3D


def format_kitti_line(T_world_cam: np.ndarray) -> str:
    """One KITTI line: the top 3x4 of a ``(4, 4)`` camera-to-world pose, row-major."""
    T = np.asarray(T_world_cam, dtype=np.float64)
    return " ".join(f"{v:.9e}" for v in T[:3, :4].reshape(-1))


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(4,)`` as ``(qx, qy, qz, qw)`` with ``qw >= 0`` of a ``(3, 3)`` rotation.

    evo's ``quaternion_from_matrix`` (the eigenvector method: stable for half turns and
    for slightly non-orthonormal input), reordered from evo's ``(w, x, y, z)``.
    """
    R = np.ascontiguousarray(R, dtype=np.float64)  # evo asks numpy for no copy
    w, x, y, z = _tr.quaternion_from_matrix(R)
    q = np.array([x, y, z, w])
    return q / np.linalg.norm(q)


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
        traj: the poses as evo's type: a :class:`~evo.core.trajectory.PoseTrajectory3D`
            for TUM (with its timestamps), else a :class:`~evo.core.trajectory.PosePath3D`.
            Treat it as read-only (``copy.deepcopy`` it before ``align``/``transform``):
            :attr:`poses` is cached from it.
        frames: ``(N,)`` int64 frame indices, or None when the file does not say
            (plain KITTI without ``frames.txt``, TUM).
        lines: ``(N,)`` 1-based line numbers of the poses in ``path`` (for messages).

    Properties:
        poses: ``(N, 4, 4)`` float64 camera-to-world poses ``T_world_cam`` (from ``traj``).
        timestamps: ``(N,)`` float64 seconds (TUM), else None.
    """

    path: str
    kind: str
    traj: PosePath3D = field(repr=False)
    frames: np.ndarray | None
    lines: np.ndarray

    @cached_property
    def poses(self) -> np.ndarray:
        return np.array(self.traj.poses_se3, dtype=np.float64).reshape(-1, 4, 4)

    @property
    def timestamps(self) -> np.ndarray | None:
        ts = getattr(self.traj, "timestamps", None)
        return None if ts is None else np.asarray(ts, dtype=np.float64)

    def __len__(self) -> int:
        return int(self.traj.num_poses)


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """``(3, 3)`` rotation of a unit quaternion ``(4,)`` given as ``(qx, qy, qz, qw)``.

    evo's ``quaternion_matrix`` (which normalises first); the caller must reject
    zero-norm input.
    """
    x, y, z, w = np.asarray(q, dtype=np.float64)
    return _tr.quaternion_matrix([w, x, y, z])[:3, :3]


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
    values, NaN/inf, a zero quaternion, a 3x3 block that is not a rotation, a
    non-integer or repeated frame index, a repeated timestamp. Indexed KITTI and TUM
    rows are sorted by frame index / timestamp.

    Returns:
        A :class:`TrajectoryFile` whose ``traj`` is evo's ``PosePath3D`` (KITTI) or
        ``PoseTrajectory3D`` (TUM).
    """
    from evo.core.trajectory import PosePath3D, PoseTrajectory3D

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
    poses = None  # (N, 4, 4) for the KITTI kinds; TUM rotations come from evo's quaternion conversion
    if ncols == KITTI_COLUMNS:
        kind = "kitti"
        poses = np.tile(np.eye(4), (n, 1, 1))
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
        poses = np.tile(np.eye(4), (n, 1, 1))
        poses[:, :3, :4] = data[:, 1:].reshape(n, 3, 4)
    elif ncols == TUM_COLUMNS:
        kind = "tum"
        timestamps = data[:, 0].copy()
        zero = np.nonzero(np.linalg.norm(data[:, 4:8], axis=1) < 1e-9)[0]
        if zero.size:
            raise InputError("zero quaternion", path, lines[int(zero[0])])
    else:
        raise InputError(
            f"{ncols} columns per line: expected 12 (KITTI), 13 (frame index + KITTI) "
            "or 8 (TUM: timestamp tx ty tz qx qy qz qw)",
            path,
            lines[0],
        )
    if poses is not None:
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
        data, line_nos = data[order], line_nos[order]
        if frames is not None:
            poses, frames = poses[order], frames[order]
    if kind == "tum":
        # evo's type turns the unit quaternions (w first for evo) into rotation matrices
        traj = PoseTrajectory3D(
            positions_xyz=data[:, 1:4], orientations_quat_wxyz=data[:, [7, 4, 5, 6]], timestamps=data[:, 0],
            name=str(path),
        )
    else:
        traj = PosePath3D(poses_se3=list(poses), name=str(path))
    return TrajectoryFile(str(path), kind, traj, frames, line_nos)


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
