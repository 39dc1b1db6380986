"""Benchmark tool: how far the trajectory that best explains the images is from the ground truth.

Each start (the ground truth, and every run folder given) is bundle-adjusted over all its
frames with SIFT tracks, by :func:`trianflow_vo.eval.image_optimum.image_optimum`. Only the
reprojection error counts (no motion prior); the intrinsics are held. Each frame is
matched with the next ``--overlap`` frames. The matches that fit the start's epipolar
geometry (Sampson < 1.5 px) are linked into tracks. The tool prints, for each start:

* ``start ATE %``: the start against the ground truth (Sim(3) alignment, RMSE over the GT
  path length, as ``trianflow-vo eval``);
* ``optimum ATE %``: the adjusted trajectory against the ground truth;
* ``error``: the graph's robust error at the start and at the end, and the median
  reprojection residual (pixels) after the adjustment.

One adjustment per ``--min-angle`` value: tracks whose rays (first and last observation)
meet at a smaller angle are left out. Low-parallax points add noise and little
geometry. Indoors the result depends on this choice (see ROBUSTNESS.md).

If the ground truth explained the images to their noise, the adjustment would leave it
where it is. How far it moves is a floor for comparing runs against that ground truth:
differences in ATE well below it are not resolved by this ground truth.

Usage (from the repository root)::

    python benchmarks/image_optimum.py SEQUENCE [RUN ...] [--stride S] [--overlap N]
        [--rounds R] [--min-angle A[,A...]] [--json OUT]

``SEQUENCE`` is the folder given to ``trianflow-vo run``; without runs, the ground truth
alone at ``--stride``; with runs, the ground truth at the first run's frames. SIFT (once,
at the source resolution) costs about 0.1-0.3 s a frame, the matching (once) ``overlap``
times that, and each adjustment 0.5-3 min for 150-170 frames on 2 cores. Seconds printed
per start include the shared SIFT and matching.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np


def ate_percent(T_world_cam: np.ndarray, gt: np.ndarray) -> float:
    """ATE RMSE after a Sim(3) alignment of the positions, in % of the ground truth's path."""
    from trianflow_vo.eval.align import umeyama

    p, g = T_world_cam[:, :3, 3], gt[:, :3, 3]
    (s, R, t), ok = umeyama(p, g)
    if not ok:
        return float("nan")
    e = np.linalg.norm(s * p @ R.T + t - g, axis=1)
    return float(100 * np.sqrt(np.mean(e ** 2)) / np.linalg.norm(np.diff(g, axis=0), axis=1).sum())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", type=Path)
    ap.add_argument("runs", type=Path, nargs="*")
    ap.add_argument("--gt", type=Path, default=None, help="ground truth (default: SEQUENCE/poses.txt)")
    ap.add_argument("--stride", type=int, default=1, help="without runs: every stride-th ground-truth frame")
    ap.add_argument("--overlap", type=int, default=5, help="each frame is matched with the next N frames")
    ap.add_argument("--rounds", type=int, default=6, help="most triangulate-and-adjust rounds")
    ap.add_argument("--min-angle", default="0,2",
                    help="comma-separated smallest ray angles (degrees) of a track; one adjustment each")
    ap.add_argument("--json", type=Path, default=None, help="write the results here")
    args = ap.parse_args(argv)

    from gt_consistency import gray_reader, write_json  # beside this script

    from trianflow_vo.eval.image_optimum import image_optimum, sift_matches, tracks_from_matches
    from trianflow_vo.eval.loader import associate, load_ground_truth, load_prediction
    from trianflow_vo.io.sequence import open_sequence

    gt_path = args.gt or args.sequence / "poses.txt"
    gt_all = load_ground_truth(gt_path)
    seq = open_sequence(args.sequence)
    starts = []  # (name, frames, start poses, gt poses)
    for run in args.runs:
        pred, desc = load_prediction(run)
        a = associate(pred, gt_all, pred_source=desc)
        if a.frames is None:
            raise SystemExit(f"{run}: matched by timestamp; this tool needs frame indices (frames.txt)")
        if not starts:
            starts.append(("ground truth", a.frames, a.gt_poses, a.gt_poses))
        starts.append((str(run), a.frames, a.pred_poses, a.gt_poses))
    if not starts:
        if gt_all.kind == "tum":
            raise SystemExit(f"{gt_path}: a TUM ground truth has timestamps, not frame indices: give a run folder")
        gt_frames = gt_all.frames if gt_all.frames is not None else np.arange(gt_all.poses.shape[0])
        sel = np.arange(0, gt_all.poses.shape[0], args.stride)
        starts.append(("ground truth", gt_frames[sel], gt_all.poses[sel], gt_all.poses[sel]))

    out = {}
    print(f"{'start, smallest ray angle':52s} {'frames':>6s} {'start ATE %':>11s} {'optimum ATE %':>13s} {'error start -> end':>22s} "
          f"{'res px':>6s} {'points':>7s} {'s':>5s}")
    angles = [float(a) for a in args.min_angle.split(",")]
    # every start has the same frames: SIFT and the matching run once, the epipolar filter per start
    t0 = time.perf_counter()
    frames0 = starts[0][1]
    matches = sift_matches(gray_reader(seq, args.sequence, frames0), len(frames0), overlap=args.overlap)
    t_matches = time.perf_counter() - t0
    for name, frames, start, gt in starts:
        if not np.array_equal(frames, frames0):
            raise SystemExit(f"{name}: its frames differ from {starts[0][0]}'s; give runs of one stride")
        t0 = time.perf_counter()
        obs = tracks_from_matches(seq.K, start, matches)
        t_tracks = t_matches + time.perf_counter() - t0
        for angle in angles:
            t1 = time.perf_counter()
            opt, ok = image_optimum(seq.K, start, obs, rounds=args.rounds, min_angle_deg=angle)
            secs = t_tracks + time.perf_counter() - t1
            row = {"frames": [int(frames[0]), int(frames[-1]), int(len(frames))], "min_angle_deg": angle,
                   "start_ate_percent": ate_percent(start, gt), "tracks": obs.n_tracks,
                   "observations": int(obs.frame.size), "seconds": secs, "valid": ok}
            label = f"{name[-42:]} >={angle:g}deg"
            if ok:
                row.update(optimum_ate_percent=ate_percent(opt.T_world_cam, gt), error_before=opt.error_before,
                           error_after=opt.error_after, residual_px_median=opt.residual_px_median,
                           points=opt.n_points, rounds=len(opt.error_after))
                print(f"{label:52s} {len(frames):6d} {row['start_ate_percent']:11.4f} "
                      f"{row['optimum_ate_percent']:13.4f} {opt.error_before[0]:10.0f} -> {opt.error_after[-1]:9.0f} "
                      f"{opt.residual_px_median:6.3f} {opt.n_points:7d} {secs:5.0f}", flush=True)
            else:
                print(f"{label:52s} {len(frames):6d} {row['start_ate_percent']:11.4f} {'failed':>13s}", flush=True)
            out[f"{name} min_angle {angle:g}"] = row
    write_json(args.json, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
