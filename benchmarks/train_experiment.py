"""A small real training experiment: the three stages on one shared clip, judged on another.

Trains stage flow, then depth (flow frozen), then joint on ``--train`` at a reduced size,
with validation on ``--val`` (losses and the odometry's ATE); exports the last stage's
networks; runs ``trianflow-vo run`` on ``--val`` with (a) the trained networks, (b) the same
networks at random initialisation, (c) DIS flow (no networks), (d) DIS flow with the trained
depth network; evaluates each; plots the loss curves and the validation ATE of every stage
to PNG. Everything through the CLI, as a user would.

    python benchmarks/train_experiment.py --out /tmp/tfx --iters 60 --size 128x384 --batch 2
    python benchmarks/train_experiment.py --out /tmp/tfx --iters-flow 300 --iters-depth 150 --iters-joint 100

A stage whose folder already holds a completed run of the asked length is not trained again
(``--skip-done``), so the evaluation can be repeated alone.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("TRIANFLOW_SHARED_DATA", REPO.parent / "shared" / "data"))


def sh(*args: str) -> float:
    t = time.perf_counter()
    print("$ trianflow-vo", " ".join(args), flush=True)
    subprocess.run(["trianflow-vo", *args], check=True)
    return time.perf_counter() - t


def ate(run_dir: Path, gt: Path) -> dict:
    from trianflow_vo.eval import evaluate_files

    m = evaluate_files(run_dir, gt).metrics
    info = json.loads((run_dir / "run.json").read_text())
    return {"ate_rmse_m": m["ate_rmse"], "ate_pct": 100 * m["ate_rmse"] / m["path_length"],
            "branches": info.get("branch_counts"), "fps": info.get("fps")}


def _smooth(ys: list[float], k: int) -> list[float]:
    out = []
    for i in range(len(ys)):
        win = [y for y in ys[max(0, i - k + 1): i + 1] if y == y]
        out.append(sum(win) / len(win) if win else float("nan"))
    return out


def plot(out: Path, stages: list[str]) -> None:
    """Top: every non-zero loss term per logged row (thin), the total smoothed over 10 rows (thick)
    and the validation total (triangles); bottom: the validation odometry's ATE (% of path)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(stages), figsize=(5 * len(stages), 6.4), squeeze=False,
                             gridspec_kw={"height_ratios": [2, 1]})
    for col, st in enumerate(stages):
        ax, ax2 = axes[0][col], axes[1][col]
        rows = list(csv.DictReader(open(out / st / "metrics.csv")))
        it = [int(r["iteration"]) for r in rows]
        for key in rows[0]:
            if key in ("iteration", "seconds", "lr", "depth_failed", "skipped") or key.startswith("val_"):
                continue
            ys = [float(r[key]) if r[key] else float("nan") for r in rows]
            if any(y != 0 for y in ys):
                ax.plot(it, ys, label=key, lw=0.6, alpha=0.5 if key == "total" else 0.8)
                if key == "total":
                    ax.plot(it, _smooth(ys, 10), "k-", lw=2, label="total (mean of 10 rows)")
        vt = [(int(r["iteration"]), float(r["val_total"])) for r in rows if r.get("val_total")]
        if vt:
            ax.plot(*zip(*vt), "r^", ms=7, label="val total")
        ax.set_title(f"stage {st}")
        ax.set_yscale("log")
        ax.legend(fontsize=6)
        va = [(int(r["iteration"]), float(r["val_ate_pct"])) for r in rows if r.get("val_ate_pct")]
        if va:
            ax2.plot(*zip(*va), "bo-")
        ax2.set_xlabel("iteration")
        ax2.set_ylabel("val ATE % of path")
        ax2.set_xlim(ax.get_xlim())
        if not va:
            ax2.text(0.5, 0.5, "no validation ATE (why: train.json warnings)", ha="center", va="center",
                     transform=ax2.transAxes, fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "loss_curves.png", dpi=110)


def _done(stage_dir: Path, iters: int) -> bool:
    try:
        doc = json.loads((stage_dir / "train.json").read_text())
    except (OSError, ValueError):
        return False
    return doc.get("status") == "completed" and doc.get("iteration") == iters


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--train", default=str(SHARED / "kitti00-f0000-0150"))
    ap.add_argument("--val", default=str(SHARED / "kitti06-f0000-0050"))
    ap.add_argument("--out", required=True)
    ap.add_argument("--iters", type=int, default=60, help="iterations of each stage (unless given per stage)")
    ap.add_argument("--iters-flow", type=int, default=None)
    ap.add_argument("--iters-depth", type=int, default=None)
    ap.add_argument("--iters-joint", type=int, default=None)
    ap.add_argument("--validations", type=int, default=4, help="validations per stage (evenly spaced)")
    ap.add_argument("--log-every", type=int, default=2)
    ap.add_argument("--size", default="128x384")
    ap.add_argument("--batch", type=int, default=2)
    ap.add_argument("--skip-done", action="store_true", help="do not retrain a stage that completed already")
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    iters = {st: getattr(a, f"iters_{st}") or a.iters for st in ("flow", "depth", "joint")}

    def common(n: int) -> list[str]:
        return ["--size", a.size, "--batch", str(a.batch), "--iters", str(n), "--workers", "1", "--quiet",
                "--val", a.val, "--set", f"schedule.log_every={a.log_every}",
                "--set", f"schedule.val_every={max(1, n // a.validations)}",
                "--set", f"schedule.image_every={max(1, n // 5)}", "--set", f"schedule.checkpoint_every={n}"]

    times = {}
    init = {"flow": [], "depth": ["--init", str(out / "flow" / "checkpoint.pt")],
            "joint": ["--init", str(out / "depth" / "checkpoint.pt")]}
    for st in ("flow", "depth", "joint"):
        if a.skip_done and _done(out / st, iters[st]):
            print(f"stage {st}: done already, not retrained", flush=True)
            continue
        times[st] = sh("train", "--stage", st, a.train, "--out", str(out / st), *init[st], *common(iters[st]))
    plot(out, ["flow", "depth", "joint"])
    gt = Path(a.val) / "poses.txt"
    results = {"iterations": iters, "size": a.size, "batch": a.batch, "train_seconds": times,
               "load_average_end_of_training": os.getloadavg()}
    for st in ("flow", "depth", "joint"):
        doc = json.loads((out / st / "train.json").read_text())
        results[f"train_{st}"] = {k: doc.get(k) for k in ("iteration", "pairs", "seconds_per_iter_median",
                                                          "peak_rss_mb", "skipped", "depth_failed", "last_terms",
                                                          "warnings")}
    sh("export", "--checkpoint", str(out / "joint" / "checkpoint.pt"), "--out-dir", str(out / "m_trained"))
    sh("export", "--random-init", "--seed", "0", "--size", a.size, "--out-dir", str(out / "m_random"))
    runs = {}
    for tag, m in (("trained", out / "m_trained"), ("random", out / "m_random")):
        both = ["--flow-model", str(m / "flow.onnx"), "--depth-model", str(m / "depth.onnx")]
        runs[f"{tag}_depth_scale"] = [*both, "--scale-from", "depth"]
        runs[f"{tag}_keyframe_depth"] = [*both, "--scale-from", "keyframe-depth"]
        runs[f"{tag}_triangulation"] = ["--flow-model", str(m / "flow.onnx"), "--scale-from", "triangulation"]
        runs[f"dis_flow_{tag}_depth_scale"] = ["--depth-model", str(m / "depth.onnx"), "--scale-from", "depth"]
    runs["dis_same_size"] = []
    for name, extra in runs.items():
        rd = out / f"run_{name}"
        try:
            sh("run", a.val, "--size", a.size, "--out", str(rd), "--quiet", "--no-plot", "--overwrite", *extra)
            results[name] = ate(rd, gt)
        except Exception as exc:  # record, keep going
            results[name] = {"error": str(exc)[:300]}
            try:
                results[name]["branches"] = json.loads((rd / "run.json").read_text()).get("branch_counts")
            except (OSError, ValueError):
                pass
        print(name, results[name], flush=True)
    (out / "results.json").write_text(json.dumps(results, indent=2))
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    sys.exit(main())
