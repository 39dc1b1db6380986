"""Build the shipped sample ``sample/kitti00`` from a KITTI odometry clip.

Usage::

    python sample/make_sample.py SOURCE_DIR [--out sample/kitti00] [--frames 48] [--quality 92]

SOURCE_DIR is a KITTI odometry sequence folder with ``image_0/`` (PNG),
``calib.txt`` and ``poses.txt`` (e.g. the shared ``kitti00-f0000-0150`` clip).
The first ``--frames`` frames are re-encoded as JPEG at their original
resolution (grayscale stays grayscale), ``calib.txt`` is copied unchanged, and
``poses.txt`` keeps its first ``--frames`` lines, so the result is itself a
valid KITTI folder. An ``ATTRIBUTION.txt`` records the source and the licence.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import cv2

ATTRIBUTION = """\
KITTI Vision Benchmark Suite, odometry dataset, sequence 00, left grayscale camera (image_0).
A. Geiger, P. Lenz, R. Urtasun: "Are we ready for Autonomous Driving? The KITTI
Vision Benchmark Suite", CVPR 2012. http://www.cvlibs.net/datasets/kitti/

Licence: Creative Commons Attribution-NonCommercial-ShareAlike 3.0
(CC BY-NC-SA 3.0), https://creativecommons.org/licenses/by-nc-sa/3.0/
This sample is distributed under the same licence.

Changes made for this sample (by sample/make_sample.py):
- subset: frames {first}-{last} of sequence 00 only ({n} frames);
- images re-encoded from PNG to JPEG, quality {quality}, at the original
  resolution ({width}x{height}), still grayscale;
- calib.txt copied unchanged; poses.txt = the first {n} lines of the ground
  truth poses of sequence 00 (camera-to-world, KITTI 12-number format).
"""


def make_sample(src: Path, out: Path, n_frames: int = 48, quality: int = 92) -> Path:
    """Write the sample folder ``out`` from the KITTI folder ``src``; returns ``out``."""
    src_images = src / "image_0"
    pngs = sorted(src_images.glob("*.png"))
    if len(pngs) < n_frames:
        raise SystemExit(f"{src_images}: need {n_frames} PNG frames, found {len(pngs)}")
    for name in ("calib.txt", "poses.txt"):
        if not (src / name).is_file():
            raise SystemExit(f"{src / name}: missing")
    poses = (src / "poses.txt").read_text().splitlines()
    if len(poses) < n_frames:
        raise SystemExit(f"{src / 'poses.txt'}: need {n_frames} lines, found {len(poses)}")

    out_images = out / "image_0"
    if out_images.exists():
        shutil.rmtree(out_images)
    out_images.mkdir(parents=True)
    height = width = None
    for png in pngs[:n_frames]:
        img = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise SystemExit(f"{png}: cannot be decoded")
        height, width = img.shape[:2]
        ok = cv2.imwrite(str(out_images / (png.stem + ".jpg")), img, [cv2.IMWRITE_JPEG_QUALITY, quality])
        if not ok:
            raise SystemExit(f"{out_images / (png.stem + '.jpg')}: cannot be written")
    shutil.copyfile(src / "calib.txt", out / "calib.txt")
    (out / "poses.txt").write_text("\n".join(poses[:n_frames]) + "\n")
    (out / "ATTRIBUTION.txt").write_text(
        ATTRIBUTION.format(first=0, last=n_frames - 1, n=n_frames, quality=quality, width=width, height=height)
    )
    return out


def main(argv: list[str] | None = None) -> int:
    here = Path(__file__).resolve().parent
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("source", type=Path, help="KITTI sequence folder with image_0/, calib.txt, poses.txt")
    p.add_argument("--out", type=Path, default=here / "kitti00", help="output folder (default: %(default)s)")
    p.add_argument("--frames", type=int, default=48, help="number of leading frames to keep")
    p.add_argument("--quality", type=int, default=92, help="JPEG quality")
    a = p.parse_args(argv)
    out = make_sample(a.source, a.out, a.frames, a.quality)
    total = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    print(f"wrote {out} ({total / 1e6:.2f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
