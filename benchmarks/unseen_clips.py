"""Benchmark tool: rebuild the two unseen clips of the robustness table in ``../bench_data``.

The clips are not shipped. Both come from public repositories that hold copies of the data;
this script reads them from local clones (a work tree or a bare git directory, for example what
``git clone --mirror`` makes) and writes the folders ``bench_robustness.py`` finds:

* ``kitti07-f0000-0159``: KITTI odometry sequence 07, frames 0-159 of ``image_0``, from
  ``mint-lab/3dv_tutorial`` (``data/KITTI07``: ``image_0/``, ``calib.txt``, ``times.txt``). The
  first 160 lines of ``times.txt`` are kept (the tool refuses more timestamps than images) and
  ``poses.txt`` is the first 160 lines of the KITTI ground truth ``07.txt``
  (``../shared/data/kitti-odometry-eval/gt_poses/07.txt``).
* ``tum-fr3teddy-f0004-0199``: TUM RGB-D ``freiburg3_teddy``, the images at positions 4-199 of
  ``rgb.txt``, from ``Zielon/3DScanning`` (``Exercises/Exercise4/assets/rgbd_dataset_freiburg3_teddy``),
  saved as ``color/000000.png`` onwards; ``calib.txt`` holds the fr3 intrinsics
  (535.4, 539.2, 320.1, 247.6) and ``poses.txt`` the nearest ground-truth sample of each image in
  KITTI layout (at most 9.1 ms away).

Usage (from the repository root)::

    python benchmarks/unseen_clips.py --kitti07-repo CLONE --teddy-repo CLONE
        [--kitti-gt ../shared/data/kitti-odometry-eval/gt_poses/07.txt] [--out ../bench_data]

On 2026-12-05 the rebuilt clips gave every KITTI 07 and teddy result of the earlier tables to
the digit (ROBUSTNESS.md).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np

from trianflow_vo.io.trajectory import format_kitti_line, quaternion_to_rotation

REPO = Path(__file__).resolve().parents[1]
KITTI07_DIR = "data/KITTI07"
TEDDY_DIR = "Exercises/Exercise4/assets/rgbd_dataset_freiburg3_teddy"
TEDDY_CALIB = "P0: 535.4 0 320.1 0 0 539.2 247.6 0 0 0 1 0\n"
KITTI07_FRAMES = 160
TEDDY_FIRST, TEDDY_LAST = 4, 199


class CloneError(RuntimeError):
    """A file the recipe needs is missing from a clone."""


def read_from_clone(clone: Path, path: str) -> bytes:
    """The bytes of ``path`` in ``clone``: from its work tree when the file is there, else from
    ``HEAD`` of its git directory (a bare clone)."""
    on_disk = clone / path
    if on_disk.is_file():
        return on_disk.read_bytes()
    git_dir = clone / ".git" if (clone / ".git").exists() else clone
    out = subprocess.run(["git", "--git-dir", str(git_dir), "show", f"HEAD:{path}"], capture_output=True)
    if out.returncode != 0:
        raise CloneError(f"{clone}: no {path} ({out.stderr.decode(errors='replace').strip()})")
    return out.stdout


def nearest_poses(stamps: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, float]:
    """Camera-to-world poses ``(N, 3, 4)`` at image times ``stamps`` ``(N,)`` from the nearest row
    of a TUM ground truth ``gt`` ``(M, 8)`` (``t tx ty tz qx qy qz qw``), and the largest time gap
    (seconds) between an image and its sample."""
    gt = np.asarray(gt, dtype=np.float64)
    if gt.ndim != 2 or gt.shape[1] != 8 or len(gt) == 0:
        raise ValueError(f"the ground truth must be (M, 8) rows 't tx ty tz qx qy qz qw', got {gt.shape}")
    order = np.argsort(gt[:, 0])
    gt = gt[order]
    stamps = np.asarray(stamps, dtype=np.float64)
    j = np.clip(np.searchsorted(gt[:, 0], stamps), 1, len(gt) - 1) if len(gt) > 1 else np.zeros(len(stamps), int)
    if len(gt) > 1:
        j = np.where(np.abs(gt[j - 1, 0] - stamps) <= np.abs(gt[j, 0] - stamps), j - 1, j)
    rows = gt[j]
    R = np.array([quaternion_to_rotation(q) for q in rows[:, 4:8]]).reshape(-1, 3, 3)
    poses = np.concatenate([R, rows[:, 1:4, None]], axis=2)
    return poses, float(np.max(np.abs(rows[:, 0] - stamps))) if len(stamps) else 0.0


def _table(text: str) -> list[list[str]]:
    return [ln.split() for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]


def _write_poses(path: Path, poses: np.ndarray) -> None:
    path.write_text("".join(format_kitti_line(P) + "\n" for P in poses))


def build_kitti07(clone: Path, kitti_gt: Path, out: Path) -> Path:
    """Write ``out/kitti07-f0000-0159`` from a clone of ``mint-lab/3dv_tutorial``."""
    gt_lines = kitti_gt.read_text().splitlines(keepends=True)
    if len(gt_lines) < KITTI07_FRAMES:
        raise CloneError(f"{kitti_gt}: {len(gt_lines)} poses, {KITTI07_FRAMES} needed")
    seq = out / "kitti07-f0000-0159"
    (seq / "image_0").mkdir(parents=True, exist_ok=True)
    for i in range(KITTI07_FRAMES):
        (seq / "image_0" / f"{i:06d}.png").write_bytes(read_from_clone(clone, f"{KITTI07_DIR}/image_0/{i:06d}.png"))
    (seq / "calib.txt").write_bytes(read_from_clone(clone, f"{KITTI07_DIR}/calib.txt"))
    times = read_from_clone(clone, f"{KITTI07_DIR}/times.txt").decode().splitlines(keepends=True)
    (seq / "times.txt").write_text("".join(times[:KITTI07_FRAMES]))
    (seq / "poses.txt").write_text("".join(gt_lines[:KITTI07_FRAMES]))
    return seq


def build_teddy(clone: Path, out: Path) -> tuple[Path, float]:
    """Write ``out/tum-fr3teddy-f0004-0199`` from a clone of ``Zielon/3DScanning``; also returns
    the largest image-to-ground-truth time gap (seconds)."""
    rgb = _table(read_from_clone(clone, f"{TEDDY_DIR}/rgb.txt").decode())[TEDDY_FIRST:TEDDY_LAST + 1]
    gt = np.array(_table(read_from_clone(clone, f"{TEDDY_DIR}/groundtruth.txt").decode()), dtype=np.float64)
    seq = out / "tum-fr3teddy-f0004-0199"
    (seq / "color").mkdir(parents=True, exist_ok=True)
    for k, (_, name) in enumerate(rgb):
        (seq / "color" / f"{k:06d}.png").write_bytes(read_from_clone(clone, f"{TEDDY_DIR}/{name}"))
    poses, gap = nearest_poses(np.array([float(s) for s, _ in rgb]), gt)
    _write_poses(seq / "poses.txt", poses)
    (seq / "calib.txt").write_text(TEDDY_CALIB)
    return seq, gap


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kitti07-repo", type=Path, help="clone of mint-lab/3dv_tutorial")
    ap.add_argument("--teddy-repo", type=Path, help="clone of Zielon/3DScanning")
    ap.add_argument("--kitti-gt", type=Path,
                    default=REPO.parent / "shared" / "data" / "kitti-odometry-eval" / "gt_poses" / "07.txt")
    ap.add_argument("--out", type=Path, default=REPO.parent / "bench_data")
    args = ap.parse_args(argv)
    if args.kitti07_repo is None and args.teddy_repo is None:
        ap.error("give --kitti07-repo, --teddy-repo or both")
    try:
        if args.kitti07_repo is not None:
            print(f"wrote {build_kitti07(args.kitti07_repo, args.kitti_gt, args.out)}")
        if args.teddy_repo is not None:
            seq, gap = build_teddy(args.teddy_repo, args.out)
            print(f"wrote {seq} (largest image-to-ground-truth gap {gap * 1e3:.1f} ms)")
    except (CloneError, OSError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
