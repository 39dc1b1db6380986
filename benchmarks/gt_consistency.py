"""Benchmark tool: how well the ground truth and runs explain the images (SIFT, not our flow).

For each run folder given (``poses.txt`` + ``frames.txt``), the frames it solved are read
with the tool's own reader (the same intrinsics as ``trianflow-vo run``). The ground truth is
associated exactly as ``trianflow-vo eval`` associates it. Each trajectory is then scored
on consecutive frames with :func:`trianflow_vo.eval.consistency.consistency_table`:

* ``epi px``: the median over the frame pairs of each pair's median Sampson distance
  (full-resolution pixels) of the SIFT matches under the trajectory's relative pose.
* ``|log s|``: the median over the triples of ``|log(z_ab / z_bc)|``, the disagreement
  between the lengths of two consecutive steps as seen by points in three frames
  (0.01 = 1 %).
* ``std``: the spread of ``log s``.
* ``GT worse``: the share of pairs / triples where the ground truth's value is larger
  than the run's.

If the ground truth scores well above a run, its local errors exceed the run's. Its ATE
then mixes the run's drift with the ground truth's own error.

Usage (from the repository root)::

    python benchmarks/gt_consistency.py SEQUENCE RUN [RUN ...] [--gt FILE] [--json OUT]
        [--per-pair]

``SEQUENCE`` is the folder given to ``trianflow-vo run``; ``--gt`` defaults to its
``poses.txt``. SIFT at the source resolution costs about 0.1-0.3 s a frame on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def gray_reader(seq, seq_dir: Path, frames):
    """``read_gray(position) -> (h, w) uint8``: source frame ``frames[position]`` of the opened
    sequence ``seq`` in grey (exits naming the frame when it does not decode)."""
    import cv2

    from trianflow_vo.frames import Frame

    def read_gray(i: int) -> np.ndarray:
        fr = seq.read_frame(int(frames[i]))
        if not isinstance(fr, Frame):
            raise SystemExit(f"{seq_dir}: frame {frames[i]} does not decode")
        img = fr.image
        return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)

    return read_gray


def write_json(path: Path | None, obj) -> None:
    """``obj`` as indented JSON at ``path`` (its folder made); nothing when ``path`` is None."""
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(obj, indent=1))


def _score(seq_dir: Path, run_dir: Path, gt_path: Path) -> tuple[dict, object]:
    from trianflow_vo.eval.consistency import consistency_table
    from trianflow_vo.eval.loader import associate, load_ground_truth, load_prediction
    from trianflow_vo.io.sequence import open_sequence

    pred, desc = load_prediction(run_dir)
    a = associate(pred, load_ground_truth(gt_path), pred_source=desc)
    if a.frames is None:
        raise SystemExit(f"{run_dir}: matched by timestamp; this tool needs frame indices (frames.txt)")
    seq = open_sequence(seq_dir)
    table = consistency_table(gray_reader(seq, seq_dir, a.frames), seq.K, {"gt": a.gt_poses, "run": a.pred_poses})
    summary = table.summary()
    for key, arrs in (("pairs", table.epipolar_px), ("triples", table.scale_log_ratio)):
        g, r = arrs["gt"], arrs["run"]
        ok = np.isfinite(g) & np.isfinite(r)
        both = np.abs(g[ok]) > np.abs(r[ok])
        summary[f"gt_worse_{key}"] = f"{int(both.sum())}/{int(ok.sum())}"
    summary["frames"] = [int(a.frames[0]), int(a.frames[-1])]
    return summary, (a.frames, table)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", type=Path)
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--gt", type=Path, default=None, help="ground truth (default: SEQUENCE/poses.txt)")
    ap.add_argument("--json", type=Path, default=None, help="write the summaries here")
    ap.add_argument("--per-pair", action="store_true", help="print every pair's and triple's values")
    args = ap.parse_args(argv)
    gt = args.gt or args.sequence / "poses.txt"
    out = {}
    print(f"{'run':40s} {'epi px gt / run':>16s} {'|log s| gt / run':>18s} {'std gt / run':>16s} "
          f"{'GT worse (pairs, triples)':>26s}")
    for run in args.runs:
        s, (frames, table) = _score(args.sequence, run, gt)
        out[str(run)] = s
        g, r = s["gt"], s["run"]

        def both(key: str, width: int, digits: int) -> str:  # 'gt / run', '-' where there is no value
            fmt = (lambda v: "-" if v is None else f"{v:.{digits}f}")  # noqa: E731
            return f"{fmt(g[key]):>{width}s} / {fmt(r[key]):>6s}"

        print(f"{str(run)[-40:]:40s} {both('epipolar_px_median', 7, 3)} {both('scale_abs_log_median', 9, 4)} "
              f"{both('scale_log_std', 8, 4)} {s['gt_worse_pairs']:>13s}, {s['gt_worse_triples']}")
        if args.per_pair:
            for (i, j), eg, er in zip(table.pairs, table.epipolar_px["gt"], table.epipolar_px["run"]):
                line = f"  frames {frames[i]:5d}-{frames[j]:5d}  epi gt {eg:.3f} run {er:.3f}"
                if 1 <= j <= len(table.triples):
                    line += (f"   log s at {frames[j]:5d}: gt {table.scale_log_ratio['gt'][j - 1]:+.4f} "
                             f"run {table.scale_log_ratio['run'][j - 1]:+.4f}")
                print(line)
    write_json(args.json, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
