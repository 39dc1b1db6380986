"""Benchmark tool: a real clip's camera path through the synthetic hand-held room, with a rolling shutter.

Renders the room of ``handheld_indoor`` (``tests/synthetic_sequences.py``: exact images, known
intrinsics, no blur, no distortion) along a trajectory in KITTI layout (one 3x4 camera-to-world
pose per source frame, e.g. 7-Scenes kitchen's ``poses.txt``; read and checked by
:func:`trianflow_vo.io.trajectory.read_trajectory`), re-expressed relative to its first
pose and with its translations multiplied by ``--scale``. With ``--readout R`` (in frame intervals)
the image has a rolling shutter: row ``r`` of source frame ``i`` is seen from the pose at time
``i + R * r / H`` (rotation slerped, translation linear between the two poses around it), rendered in
``--bands`` horizontal bands. The pose written for a frame is the one at its middle row's time.
``--readout 0`` is a global shutter. Every ``--stride``-th source frame is written (a KITTI folder
that ``trianflow-vo run`` reads at stride 1).

Why: a run of the same path with a global shutter says whether the motion or the policy makes an
error; the same path with a rolling shutter says how much of a real clip's error the shutter can
explain (ROBUSTNESS.md, 2026-12-07).

Usage (from the repository root)::

    python benchmarks/rolling_shutter_clip.py POSES OUT [--scale 1] [--stride 3] [--readout 0.9]
        [--bands 24] [--focal 585] [--size 480x640] [--frames N]

Costs about one whole-image render per frame (each band renders its own rows only).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _synthetic():
    """The module ``tests/synthetic_sequences.py`` (the renderer and the room)."""
    if str(REPO / "tests") not in sys.path:
        sys.path.insert(0, str(REPO / "tests"))
    import synthetic_sequences

    return synthetic_sequences


def pose_interpolator(T_world_cam: np.ndarray):
    """``pose_at(t) -> (4, 4)`` for a real time ``t`` in frames (clamped to the path): rotation by slerp,
    translation linear between the poses ``floor(t)`` and ``floor(t) + 1``."""
    from scipy.spatial.transform import Rotation, Slerp

    n = len(T_world_cam)
    if n < 2:
        raise ValueError("a trajectory of at least 2 poses is needed")
    slerp = Slerp(np.arange(n), Rotation.from_matrix(T_world_cam[:, :3, :3]))

    def pose_at(t: float) -> np.ndarray:
        t = min(max(float(t), 0.0), n - 1.0)
        i = min(int(np.floor(t)), n - 2)
        a = t - i
        M = np.eye(4)
        M[:3, :3] = slerp([t]).as_matrix()[0]
        M[:3, 3] = (1 - a) * T_world_cam[i, :3, 3] + a * T_world_cam[i + 1, :3, 3]
        return M

    return pose_at


def render_rolling(scene, pose_at, i: float, K: np.ndarray, size: tuple[int, int], readout: float,
                   bands: int) -> np.ndarray:
    """``(H, W)`` uint8 image of source frame ``i`` whose rows are exposed over ``readout`` frames."""
    render = _synthetic().render
    h, w = size
    edges = np.linspace(0, h, bands + 1).astype(int)
    img = np.zeros((h, w), np.float32)
    for r0, r1 in zip(edges[:-1], edges[1:]):
        if r1 <= r0:
            continue
        t = i + readout * 0.5 * (r0 + r1) / h
        K_band = K.copy()
        K_band[1, 2] -= r0  # rows r0..r1-1 alone: the same rays as in the whole image
        img[r0:r1] = render(scene, pose_at(t), K_band, (r1 - r0, w), as_float=True)
    return np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)


def make_clip(poses_path: Path, out: Path, scale: float = 1.0, stride: int = 3, readout: float = 0.9,
              bands: int = 24, focal: float = 585.0, size: tuple[int, int] = (480, 640),
              frames: int | None = None) -> int:
    """Write the clip (KITTI folder ``out``); returns the number of frames written."""
    syn = _synthetic()
    if stride < 1 or bands < 1 or readout < 0 or scale <= 0:
        raise ValueError("stride and bands must be >= 1, readout >= 0 and scale > 0")
    from trianflow_vo.io.trajectory import read_trajectory

    T = read_trajectory(poses_path).poses
    if frames is not None:
        T = T[:frames]
    T = np.linalg.inv(T[0]) @ T
    T[:, :3, 3] *= scale
    pose_at = pose_interpolator(T)
    h, w = size
    K = syn.intrinsics(focal, focal, (w - 1) / 2.0, (h - 1) / 2.0)
    scene = syn.handheld_indoor(n_frames=2, size=size).scene
    idx = list(range(0, len(T) - 1, stride))
    images = (render_rolling(scene, pose_at, i, K, size, readout, bands) for i in idx)
    poses = np.stack([pose_at(i + 0.5 * readout) for i in idx])
    syn.write_kitti_sequence(out, images, poses, K, fps=30.0 / stride)
    return len(idx)


def main(argv=None) -> int:
    from trianflow_vo.errors import VOError

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("poses", type=Path, help="KITTI-layout camera-to-world poses of the path to follow")
    ap.add_argument("out", type=Path)
    ap.add_argument("--scale", type=float, default=1.0, help="multiply the path's translations")
    ap.add_argument("--stride", type=int, default=3, help="write every n-th source frame")
    ap.add_argument("--readout", type=float, default=0.9, help="rolling-shutter readout in frame intervals; 0 = global")
    ap.add_argument("--bands", type=int, default=24, help="horizontal bands rendered per image")
    ap.add_argument("--focal", type=float, default=585.0)
    ap.add_argument("--size", default="480x640", help="HxW")
    ap.add_argument("--frames", type=int, default=None, help="use only the first N poses")
    a = ap.parse_args(argv)
    try:
        size = tuple(int(v) for v in a.size.lower().split("x"))
        n = make_clip(a.poses, a.out, a.scale, a.stride, a.readout, a.bands, a.focal, size, a.frames)
    except (OSError, ValueError, VOError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {n} frames to {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
