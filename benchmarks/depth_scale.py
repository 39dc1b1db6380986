"""Benchmark tool: where a run loses its scale, keyframe by keyframe, measured against the ground truth.

A monocular run has one free scale, and the drift of that scale is what its ATE is mostly made
of (ROBUSTNESS.md). The depth each keyframe carries is in the run's units; this tool measures
those units in metres at every keyframe:

1. the clip is run through :func:`trianflow_vo.pipeline.run` with the given settings; an
   observer keeps each keyframe's image and the depth map that later frames were solved
   against (``FrameView.depth``, the front-end's carried depth);
2. for each keyframe ``f``, the first later keyframe ``g`` whose ground-truth position is at
   least ``--min-baseline`` metres away is its partner; OpenCV DIS (``medium``) gives the flow
   ``f -> g``, and the pixels that carry depth are triangulated with the *ground-truth* relative
   pose (metres), keeping rays that meet at ``--min-angle`` radians or more;
3. ``units/m`` is the median of carried depth / metric depth over those pixels.

A run that kept its scale has a constant ``units/m``; a step in it says which keyframe changed
the scale, and the ``how`` column says how that keyframe came to be (a two-view step, or a
frame handed on after PnP). The ground truth's own relative-pose error and the flow's enter the
measure: on 7-Scenes a keyframe's value moves by up to ~15 % with the partner chosen (smallest
baseline 4, 8 or 12 cm), so read trends over several keyframes, not single values.

Usage (from the repository root)::

    python benchmarks/depth_scale.py SEQUENCE [--gt poses.txt] [--stride N] [--seed S]
        [--set section.key=value ...] [--min-baseline 0.04] [--min-angle 0.02] [--json OUT]

The ground truth must be in KITTI layout (one 3x4 camera-to-world pose per source frame).
Costs one run of the clip plus one DIS flow per keyframe.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from trianflow_vo.observer import Observer


@dataclass
class KeyframeDepths(Observer):
    """What the observer keeps: per keyframe source index, its gray image, the branch of the
    frame that made it, and the carried depth (``(M,)`` flat pixel indices and depths)."""

    gray: dict = field(default_factory=dict)
    how: dict = field(default_factory=dict)
    depth: dict = field(default_factory=dict)
    K: np.ndarray | None = None

    def on_frame(self, result):
        import cv2

        view = result.view
        if self.K is None:
            self.K = np.asarray(result.K, dtype=np.float64)
        if result.is_keyframe and view is not None and view.image is not None:
            self.gray[result.frame_index] = cv2.cvtColor(np.ascontiguousarray(view.image), cv2.COLOR_BGR2GRAY)
            self.how[result.frame_index] = result.branch.value
        ref = result.ref_index
        if ref is not None and ref not in self.depth and view is not None and view.depth is not None:
            d = np.asarray(view.depth).ravel()
            idx = np.flatnonzero(d > 0)
            self.depth[ref] = (idx, d[idx].astype(np.float64))


def units_per_metre(kd: KeyframeDepths, T_world_cam: np.ndarray, min_baseline: float, min_angle: float) -> list[dict]:
    """One row per keyframe with carried depth: ``units/m`` against the ground truth
    ``T_world_cam`` ``(n, 4, 4)`` indexed by source frame (see the module docstring)."""
    import cv2

    from trianflow_vo.geometry.triangulation import triangulate_midpoint

    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    keys = sorted(k for k in kd.gray if k < len(T_world_cam))
    rows = []
    for f in keys:
        if f not in kd.depth:
            continue
        g = next((h for h in keys if h > f
                  and np.linalg.norm(T_world_cam[h][:3, 3] - T_world_cam[f][:3, 3]) >= min_baseline), None)
        row = {"keyframe": f, "how": kd.how.get(f, "?"), "partner": g, "points": int(kd.depth[f][0].size),
               "used": 0, "units_per_m": None, "spread": None}
        if g is not None:
            T_g_f = np.linalg.inv(T_world_cam[g]) @ T_world_cam[f]
            flow = dis.calc(kd.gray[f], kd.gray[g], None)
            h, w = flow.shape[:2]
            idx, depth = kd.depth[f]
            ys, xs = np.divmod(idx, w)
            q1 = np.column_stack([xs, ys]).astype(np.float64)
            q2 = q1 + flow[ys, xs]
            X, ok, _ = triangulate_midpoint(q1, q2, kd.K, T_g_f[:3, :3], T_g_f[:3, 3], min_angle=min_angle)
            ok &= (q2[:, 0] >= 0) & (q2[:, 0] < w) & (q2[:, 1] >= 0) & (q2[:, 1] < h)
            row["baseline_m"] = float(np.linalg.norm(T_g_f[:3, 3]))
            row["used"] = int(ok.sum())
            if ok.sum() >= 20:
                r = depth[ok] / X[ok, 2]
                med = float(np.median(r))
                row["units_per_m"] = med
                row["spread"] = float(np.median(np.abs(np.log(r / med))))
        rows.append(row)
    return rows


def load_kitti_poses(path: Path) -> np.ndarray:
    """``(n, 4, 4)`` camera-to-world poses from a KITTI pose file (12 numbers a line, line i =
    frame i), read and checked by the tool's own reader (an ``InputError`` names the file and
    line); another valid layout (TUM, indexed KITTI) is refused with a ``ValueError``."""
    from trianflow_vo.io.trajectory import read_trajectory

    traj = read_trajectory(path)
    if traj.kind != "kitti":
        raise ValueError(f"{path}: a {traj.kind} trajectory; this tool needs the KITTI layout (line i = frame i)")
    return traj.poses


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequence", type=Path)
    ap.add_argument("--gt", type=Path, help="KITTI-layout ground truth (default SEQUENCE/poses.txt)")
    ap.add_argument("--stride", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE")
    ap.add_argument("--min-baseline", type=float, default=0.04, help="metres between a keyframe and its partner")
    ap.add_argument("--min-angle", type=float, default=0.02, help="smallest ray angle (radians) measured")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)

    from trianflow_vo.config import Config, ConfigError, apply_overrides, merge_dict
    from trianflow_vo.errors import VOError
    from trianflow_vo.pipeline import run

    gt_path = args.gt or args.sequence / "poses.txt"
    try:
        T = load_kitti_poses(gt_path)
        cfg = merge_dict(Config(), {"input": {"stride": args.stride}, "sampling": {"seed": args.seed}}, "arguments")
        cfg = apply_overrides(cfg, args.overrides)
        kd = KeyframeDepths()
        with tempfile.TemporaryDirectory() as tmp:
            run(args.sequence, Path(tmp) / "run", cfg, observers=[kd])
    except (OSError, ValueError, ConfigError, VOError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    rows = units_per_metre(kd, T, args.min_baseline, args.min_angle)
    print("| keyframe | how | partner | baseline m | carried px | used | units/m | change | spread |")
    print("|---|---|---|---|---|---|---|---|---|")
    last = None
    for r in rows:
        u, sp = r["units_per_m"], r["spread"]
        change = "" if (u is None or last is None) else f"{u / last:.2f}x"
        partner = "-" if r["partner"] is None else r["partner"]
        units = "-" if u is None else f"{u:.2f}"
        spread = "-" if sp is None else f"{sp:.2f}"
        print(f"| {r['keyframe']} | {r['how']} | {partner} | {r.get('baseline_m', float('nan')):.3f} | "
              f"{r['points']} | {r['used']} | {units} | {change} | {spread} |")
        last = u if u is not None else last
    if args.json:
        args.json.write_text(json.dumps({"sequence": str(args.sequence), "stride": args.stride, "seed": args.seed,
                                         "overrides": args.overrides, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
