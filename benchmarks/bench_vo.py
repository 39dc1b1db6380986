"""Benchmark: the dense (TrianFlow, weight-free) pipeline vs a classical sparse baseline.

Runs both methods on the shared clips (KITTI 00 at stride 1 and 3, KITTI 06,
7-Scenes kitchen at stride 1 and 3), evaluates them with :func:`vo.eval.evaluate`
(Sim(3)-aligned ATE, RPE, KITTI segment error on short segments) and reports
branch counts, median ms per stage, frames/s (decoding included) and peak RSS.
Every run is a separate subprocess, so peak RSS and timings are per run.

The dense pipeline draws 12000 random matches per pair, so its accuracy varies
with the seed: the table gives the median over ``--seeds`` (and the min-max).
The sparse baseline uses every track (no random sampling) and is run once.

Usage (from the repository root)::

    python benchmarks/bench_vo.py [--data ../shared/data] [--seeds 0,1,2] [--quick] [--only NAME]

Writes ``--json`` (default ``benchmarks/out/vo.json``) and ``--md`` (default
``benchmarks/VO.md``); run folders go to ``--out`` (default ``benchmarks/out``).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

KITTI_LENGTHS = [10.0, 20.0, 30.0, 40.0, 50.0]
INDOOR_LENGTHS = [0.5, 1.0, 1.5, 2.0]
# name: (folder, stride, end, segment lengths, configuration overrides of the dense method)
CASES = {
    "kitti00-s1": ("kitti00-f0000-0150", 1, None, KITTI_LENGTHS, {}),
    "kitti00-s3": ("kitti00-f0000-0150", 3, None, KITTI_LENGTHS, {}),
    "kitti06-s1": ("kitti06-f0000-0050", 1, None, KITTI_LENGTHS, {}),
    "7scenes-s1": ("7scenes-kitchen-f0000-0499", 1, None, INDOOR_LENGTHS, {}),
    "7scenes-s3": ("7scenes-kitchen-f0000-0499", 3, None, INDOOR_LENGTHS, {}),
    # not the default: the finer DIS setting recommended for hand-held indoor video
    "7scenes-s1-fine": ("7scenes-kitchen-f0000-0499", 1, None, INDOOR_LENGTHS, {"flow": {"dis_preset": "fine"}}),
    "7scenes-s3-fine": ("7scenes-kitchen-f0000-0499", 3, None, INDOOR_LENGTHS, {"flow": {"dis_preset": "fine"}}),
}
MEMORY_CASE = "7scenes-kitchen-f0000-0499"  # dense, --end 150 vs all 500 frames
TARGET_ATE_KITTI = 0.3
TARGET_ATE_INDOOR = 2.0
TARGET_FPS = 10.0
TARGET_RSS_MB = 50.0
THREADS = 2


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


# ---------------------------------------------------------------------------
# worker: one method on one clip, in its own process


def _worker(job: dict) -> dict:
    import cv2
    import numpy as np

    cv2.setNumThreads(THREADS)
    from trianflow_vo.eval.evaluate import evaluate
    from trianflow_vo.io.trajectory import read_trajectory
    from trianflow_vo.config import Config, merge_dict
    from trianflow_vo.eval import load_ground_truth

    seq = Path(job["seq"])
    t0 = time.perf_counter()
    out = Path(job["out_dir"])
    if job["method"] == "dense":
        from trianflow_vo.pipeline import run

        cfg = merge_dict(Config(), {"input": {"stride": job["stride"], "end": job["end"]},
                                    "sampling": {"seed": job["seed"]}, "runtime": {"threads": THREADS},
                                    "output": {"plot": False}}, "benchmark")
        summary = run(seq, out, merge_dict(cfg, job.get("overrides", {}), "benchmark case"))
    else:
        from trianflow_vo.baseline.sparse import run_sparse

        cfg = merge_dict(Config(), {"sampling": {"seed": job["seed"]}}, "benchmark")
        summary = run_sparse(seq, out, stride=job["stride"], end=job["end"], config=cfg)
    poses = read_trajectory(out / "poses.txt").poses
    frames = np.loadtxt(out / "frames.txt", dtype=np.int64, ndmin=1)
    res = {"branch_counts": summary["branch_counts"], "timing_ms_median": summary["timing_ms_median"],
           "frames_processed": summary["frames_processed"], "fps": summary["fps"],
           "elapsed_s": summary["elapsed_s"]}
    wall = time.perf_counter() - t0
    gt = load_ground_truth(seq / "poses.txt")
    gt_poses, gt_frames = gt.poses, gt.frames
    m = evaluate(poses, frames, gt_poses, gt_frames, align="7dof", lengths=job["lengths"], step=1)
    res.update({
        "ate_rmse": m["ate_rmse"],
        "path_length": m["path_length"],
        "ate_pct": 100.0 * m["ate_rmse"] / m["path_length"],
        "rpe_trans": m["rpe_trans"],
        "rpe_rot": m["rpe_rot"],
        "t_err": m["t_err"],
        "r_err": m["r_err"],
        "num_segments": m["num_segments"],
        "per_length": m["per_length"],
        "wall_s": wall,
        "peak_rss_mb": peak_rss_mb(),
    })
    return res


def run_job(job: dict) -> dict:
    """Run one job in a fresh interpreter; returns its result dict (or ``{"error": ...}``)."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", json.dumps(job)]
    env = dict(os.environ, OMP_NUM_THREADS=str(THREADS))
    p = subprocess.run(cmd, capture_output=True, text=True, cwd=str(REPO), env=env)
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")]
    if p.returncode != 0 or not lines:
        tail = (p.stderr or p.stdout).strip().splitlines()[-3:]
        return {"error": f"exit {p.returncode}: " + " | ".join(tail)}
    return json.loads(lines[-1][len("RESULT "):])


# ---------------------------------------------------------------------------
# aggregation and report


def _median(xs):
    xs = [x for x in xs if x is not None]
    return statistics.median(xs) if xs else None


def aggregate(runs: list[dict]) -> dict:
    ok = [r for r in runs if "error" not in r]
    if not ok:
        return {"error": "; ".join(r["error"] for r in runs)}
    stages = sorted({k for r in ok for k in r["timing_ms_median"]})
    branches = sorted({k for r in ok for k in r["branch_counts"]})
    return {
        "n_runs": len(ok),
        "frames": ok[0]["frames_processed"],
        "path_length": ok[0]["path_length"],
        "ate_rmse": _median([r["ate_rmse"] for r in ok]),
        "ate_pct": _median([r["ate_pct"] for r in ok]),
        "ate_pct_min": min(r["ate_pct"] for r in ok),
        "ate_pct_max": max(r["ate_pct"] for r in ok),
        "t_err": _median([r["t_err"] for r in ok]),
        "r_err": _median([r["r_err"] for r in ok]),
        "rpe_trans": _median([r["rpe_trans"] for r in ok]),
        "rpe_rot": _median([r["rpe_rot"] for r in ok]),
        "branch_counts": {b: _median([r["branch_counts"].get(b, 0) for r in ok]) for b in branches},
        "timing_ms_median": {s: _median([r["timing_ms_median"].get(s) for r in ok]) for s in stages},
        "fps": _median([r["fps"] for r in ok]),
        "peak_rss_mb": max(r["peak_rss_mb"] for r in ok),
        "errors": [r["error"] for r in runs if "error" in r],
    }


def _f(x, fmt="{:.3f}"):
    return "n/a" if x is None else fmt.format(x)


def markdown(results: dict, memory: dict | None, meta: dict) -> str:
    out = ["## VO benchmark: dense (weight-free TrianFlow) vs sparse baseline", ""]
    out.append(f"- Date: {meta['date']}; machine: {meta['machine']}, {meta['cores']} cores, "
               f"Python {meta['python']}, OpenCV {meta['opencv']}; {THREADS} threads.")
    out.append(f"- Command: `{meta['command']}`; code: {meta.get('git', 'unknown')}")
    if meta.get("merged_from"):
        mf = meta["merged_from"]
        out.append(f"- Cases {', '.join(mf['cases'])} (and the memory check unless re-run) are taken from "
                   f"`{Path(mf['file']).name}` ({mf['date']}).")
    out.append(f"- Seeds (dense): {meta['seeds']}; ATE % is the median over seeds [min-max]. "
               "The sparse baseline has no random sampling and runs once.")
    out.append("- Speeds depend on what else runs on this shared 2-core machine (load average "
               f"{meta['load_before']} before, {meta.get('load_after', 'n/a')} after); accuracies do not.")
    out.append("- ATE after Sim(3) (7-DoF Umeyama) alignment; segment error = KITTI metric on 10-50 m "
               "(KITTI) / 0.5-2 m (7-Scenes) segments, every frame a start; RPE between consecutive frames.")
    out.append("")
    out.append("| case | method | frames | path m | ATE m | ATE % [min-max] | seg t_err % | seg r_err deg/100m "
               "| RPE m | RPE deg | branches | fps | peak RSS MB |")
    out.append("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for case, by_method in results.items():
        for method, a in by_method.items():
            if "error" in a:
                out.append(f"| {case} | {method} | error: {a['error']} |" + " |" * 10)
                continue
            br = ", ".join(f"{k} {v:g}" for k, v in a["branch_counts"].items() if k != "init" and v)
            out.append(
                f"| {case} | {method} | {a['frames']} | {a['path_length']:.1f} | {_f(a['ate_rmse'])} | "
                f"{a['ate_pct']:.2f} [{a['ate_pct_min']:.2f}-{a['ate_pct_max']:.2f}] | {_f(a['t_err'], '{:.2f}')} | "
                f"{_f(a['r_err'], '{:.2f}')} | {_f(a['rpe_trans'], '{:.4f}')} | {_f(a['rpe_rot'], '{:.3f}')} | {br} | "
                f"{_f(a['fps'], '{:.1f}')} | {a['peak_rss_mb']:.0f} |")
    out.append("")
    out.append("Median ms per stage (median over frames, then over seeds; stages a frame skips are not counted):")
    out.append("")
    for case, by_method in results.items():
        for method, a in by_method.items():
            if "error" in a:
                continue
            st = ", ".join(f"{k} {v:.1f}" for k, v in a["timing_ms_median"].items() if v is not None)
            out.append(f"- {case} / {method}: {st}")
    out.append("")
    if memory is not None:
        if "error" in memory:
            out.append(f"Memory check: error: {memory['error']}")
        else:
            out.append(f"Memory check (dense, {MEMORY_CASE}, one process each): peak RSS "
                       f"{memory['rss_150']:.0f} MB for {memory['frames_150']} frames, {memory['rss_500']:.0f} MB for "
                       f"{memory['frames_500']} frames: difference {memory['diff_mb']:+.0f} MB "
                       f"(target within {TARGET_RSS_MB:.0f} MB).")
        out.append("")
    out.append("Targets:")
    out.append("")
    for line in targets(results, memory):
        out.append(f"- {line}")
    out.append("")
    return "\n".join(out)


def targets(results: dict, memory: dict | None) -> list[str]:
    lines = []

    def get(case, method):
        a = results.get(case, {}).get(method)
        return None if a is None or "error" in a else a

    for case in CASES:
        d = get(case, "dense")
        if d is None:
            continue
        lim = TARGET_ATE_KITTI if case.startswith("kitti") else TARGET_ATE_INDOOR
        met = d["ate_pct"] <= lim
        s = get(case, "sparse")
        txt = f"{case}: dense ATE {d['ate_pct']:.2f}% vs target <= {lim}%: {'MET' if met else 'MISSED'}"
        if not met:
            txt += f" (by {d['ate_pct'] - lim:.2f} points)"
        if s is not None and case.startswith("kitti"):
            better = d["ate_pct"] < s["ate_pct"]
            txt += f"; sparse {s['ate_pct']:.2f}%: dense {'better (MET)' if better else 'NOT better (MISSED)'}"
        elif s is not None:
            txt += f"; sparse {s['ate_pct']:.2f}%"
        lines.append(txt)
    d = get("kitti00-s1", "dense")
    if d is not None and d["fps"] is not None:
        lines.append(f"KITTI 00 end-to-end speed: {d['fps']:.1f} frames/s vs >= {TARGET_FPS:g}: "
                     f"{'MET' if d['fps'] >= TARGET_FPS else 'MISSED'} (shared CPU: see note above)")
    if memory is not None and "error" not in memory:
        ok = abs(memory["diff_mb"]) <= TARGET_RSS_MB
        lines.append(f"Peak RSS 500 vs 150 frames: {memory['diff_mb']:+.0f} MB: {'MET' if ok else 'MISSED'}")
    return lines


# ---------------------------------------------------------------------------


def _git_state() -> str:
    """Commit and whether vo/ has uncommitted changes (the code measured)."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=str(REPO)).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "vo"], capture_output=True, text=True,
                               cwd=str(REPO)).stdout.strip()
    except OSError:
        return "unknown"
    return head + (" + uncommitted changes in vo/" if dirty else "")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data",
                    help="folder holding the shared clips (default: ../shared/data beside the repo)")
    ap.add_argument("--seeds", default="0,1,2", help="comma-separated seeds for the dense pipeline")
    ap.add_argument("--quick", action="store_true", help="one seed (the first of --seeds)")
    ap.add_argument("--only", default=None,
                    help=f"comma-separated cases to run: {', '.join(CASES)}, memory")
    ap.add_argument("--merge", type=Path, default=None,
                    help="a previous results JSON: its cases that this run does not redo are kept in the report")
    ap.add_argument("--methods", default="dense,sparse", help="comma-separated: dense, sparse")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "out", help="run folders go here")
    ap.add_argument("--json", type=Path, default=None, help="results JSON (default OUT/vo.json)")
    ap.add_argument("--md", type=Path, default=REPO / "benchmarks" / "VO.md", help="markdown table")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.worker is not None:
        res = _worker(json.loads(args.worker))
        print("RESULT " + json.dumps(res, default=float), flush=True)
        return 0

    data = args.data.resolve()
    if not data.is_dir():
        print(f"error: shared data not found at {data} (pass --data DIR)", file=sys.stderr)
        return 2
    try:
        seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    except ValueError:
        print(f"error: --seeds must be comma-separated integers, got {args.seeds!r}", file=sys.stderr)
        return 2
    if not seeds:
        print("error: --seeds is empty", file=sys.stderr)
        return 2
    if args.quick:
        seeds = seeds[:1]
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    if any(m not in ("dense", "sparse") for m in methods):
        print(f"error: --methods must name dense and/or sparse, got {args.methods!r}", file=sys.stderr)
        return 2
    only = None if args.only is None else [x.strip() for x in args.only.split(",") if x.strip()]
    bad = [x for x in (only or []) if x not in CASES and x != "memory"]
    if bad:
        print(f"error: unknown case {bad[0]!r}; expected one of {', '.join(CASES)}, memory", file=sys.stderr)
        return 2
    previous = None
    if args.merge is not None:
        try:
            previous = json.loads(args.merge.read_text())
        except (OSError, ValueError) as exc:
            print(f"error: {args.merge}: cannot read previous results ({exc})", file=sys.stderr)
            return 2
    cases = {k: v for k, v in CASES.items() if only is None or k in only}
    for name, (folder, *_rest) in cases.items():
        if not (data / folder).is_dir():
            print(f"error: clip {folder} not found in {data}", file=sys.stderr)
            return 2

    import cv2

    meta = {
        "date": datetime.datetime.now().strftime("%Y-%m-%d %H:%M"),
        "machine": " ".join(x for x in (platform.machine(), platform.processor()) if x),
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "opencv": cv2.__version__,
        "command": "python benchmarks/bench_vo.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "seeds": seeds,
        "git": _git_state(),
        "load_before": " ".join(f"{x:.1f}" for x in os.getloadavg()),
    }
    results: dict = {}
    raw: dict = {}
    for name, (folder, stride, end, lengths, overrides) in cases.items():
        results[name], raw[name] = {}, {}
        for method in methods:
            if overrides and method != "dense":
                continue  # the variants are settings of the dense method
            runs = []
            for seed in (seeds if method == "dense" else seeds[:1]):
                job = {"method": method, "seq": str(data / folder), "stride": stride, "end": end, "seed": seed,
                       "lengths": lengths, "out_dir": str(args.out / method / f"{name}-seed{seed}"),
                       "overrides": overrides}
                r = run_job(job)
                runs.append(r)
                msg = r.get("error") or (f"ATE {r['ate_rmse']:.3f} m ({r['ate_pct']:.2f}%), "
                                         f"{r['fps']:.1f} fps, {r['peak_rss_mb']:.0f} MB")
                print(f"{name:12s} {method:6s} seed {seed}: {msg}", flush=True)
            raw[name][method] = runs
            results[name][method] = aggregate(runs)

    memory = None
    if (only is None or "memory" in only) and "dense" in methods:
        folder = MEMORY_CASE
        res = {}
        for end in (150, None):
            prev = raw.get("7scenes-s1", {}).get("dense")
            if end is None and prev and "error" not in prev[0]:
                res[end] = prev[0]  # the same job (all 500 frames, first seed) already ran in its own process
                continue
            job = {"method": "dense", "seq": str(data / folder), "stride": 1, "end": end, "seed": seeds[0],
                   "lengths": INDOOR_LENGTHS, "out_dir": str(args.out / "memory" / f"end{end}")}
            res[end] = run_job(job)
        if any("error" in r for r in res.values()):
            memory = {"error": "; ".join(r["error"] for r in res.values() if "error" in r)}
        else:
            memory = {"rss_150": res[150]["peak_rss_mb"], "rss_500": res[None]["peak_rss_mb"],
                      "frames_150": res[150]["frames_processed"], "frames_500": res[None]["frames_processed"],
                      "diff_mb": res[None]["peak_rss_mb"] - res[150]["peak_rss_mb"]}
        print(f"memory: {memory}", flush=True)

    meta["load_after"] = " ".join(f"{x:.1f}" for x in os.getloadavg())
    if previous is not None:
        merged = {k: v for k, v in previous.get("results", {}).items() if k not in results}
        merged_raw = {k: v for k, v in previous.get("runs", {}).items() if k not in raw}
        results = {k: ({**merged, **results})[k] for k in CASES if k in merged or k in results}
        raw = {**merged_raw, **raw}
        if memory is None:
            memory = previous.get("memory")
        meta["merged_from"] = {"file": str(args.merge), "cases": sorted(merged),
                               "date": previous.get("meta", {}).get("date")}
    md = markdown(results, memory, meta)
    print()
    print(md)
    json_path = args.json or (args.out / "vo.json")
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps({"meta": meta, "results": results, "memory": memory, "runs": raw,
                                     "targets": targets(results, memory)}, indent=2, default=float))
    args.md.parent.mkdir(parents=True, exist_ok=True)
    args.md.write_text(md)
    print(f"\nwrote {json_path} and {args.md}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
