"""A small real training experiment: the three stages on one shared clip, judged on another.

Trains stage flow, then depth (flow frozen), then joint on ``--train`` at a reduced size,
with validation on ``--val`` (losses and the odometry's ATE); exports each stage's
networks; runs ``trianflow-vo run`` on ``--val`` with (a) the trained networks, (b) the same
networks at random initialisation, (c) DIS flow (no networks); evaluates each; plots the
loss curves of every stage to PNG. Everything through the CLI, as a user would.

    python benchmarks/train_experiment.py --out /tmp/tfx --iters 60 --size 128x384 --batch 2
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


def plot(out: Path, stages: list[str]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(stages), figsize=(5 * len(stages), 3.6))
    for ax, st in zip(axes, stages):
        rows = list(csv.DictReader(open(out / st / "metrics.csv")))
        it = [int(r["iteration"]) for r in rows]
        for key in rows[0]:
            if key in ("iteration", "seconds", "lr", "depth_failed", "skipped") or key.startswith("val_"):
                continue
            ys = [float(r[key]) if r[key] else float("nan") for r in rows]
            if any(y != 0 for y in ys):
                ax.plot(it, ys, label=key, lw=2 if key == "total" else 1)
        vt = [(int(r["iteration"]), float(r["val_total"])) for r in rows if r.get("val_total")]
        if vt:
            ax.plot(*zip(*vt), "k^", label="val total")
        ax.set_title(f"stage {st}")
        ax.set_xlabel("iteration")
        ax.set_yscale("log")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "loss_curves.png", dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--train", default=str(SHARED / "kitti00-f0000-0150"))
    ap.add_argument("--val", default=str(SHARED / "kitti06-f0000-0050"))
    ap.add_argument("--out", required=True)
    ap.add_argument("--iters", type=int, default=60)
    ap.add_argument("--size", default="128x384")
    ap.add_argument("--batch", type=int, default=2)
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    common = ["--size", a.size, "--batch", str(a.batch), "--iters", str(a.iters), "--workers", "1", "--quiet",
              "--val", a.val, "--set", "schedule.log_every=2", "--set", f"schedule.val_every={a.iters // 2}",
              "--set", "schedule.image_every=20", "--set", f"schedule.checkpoint_every={a.iters}"]
    times = {}
    times["flow"] = sh("train", "--stage", "flow", a.train, "--out", str(out / "flow"), *common)
    times["depth"] = sh("train", "--stage", "depth", a.train, "--out", str(out / "depth"), "--init",
                        str(out / "flow" / "checkpoint.pt"), *common)
    times["joint"] = sh("train", "--stage", "joint", a.train, "--out", str(out / "joint"), "--init",
                        str(out / "depth" / "checkpoint.pt"), *common)
    plot(out, ["flow", "depth", "joint"])
    gt = Path(a.val) / "poses.txt"
    h, w = a.size.split("x")
    results = {"train_seconds": times}
    sh("export", "--checkpoint", str(out / "joint" / "checkpoint.pt"), "--out-dir", str(out / "m_trained"))
    sh("export", "--random-init", "--seed", "0", "--size", a.size, "--out-dir", str(out / "m_random"))
    for name, extra in {
        "trained_depth_scale": ["--flow-model", str(out / "m_trained/flow.onnx"), "--depth-model",
                                str(out / "m_trained/depth.onnx"), "--scale-from", "depth"],
        "trained_triangulation": ["--flow-model", str(out / "m_trained/flow.onnx"), "--scale-from", "triangulation"],
        "random_depth_scale": ["--flow-model", str(out / "m_random/flow.onnx"), "--depth-model",
                               str(out / "m_random/depth.onnx"), "--scale-from", "depth"],
        "random_triangulation": ["--flow-model", str(out / "m_random/flow.onnx"), "--scale-from", "triangulation"],
        "dis_same_size": [],
    }.items():
        rd = out / f"run_{name}"
        try:
            sh("run", a.val, "--size", a.size, "--out", str(rd), "--quiet", "--no-plot", "--overwrite", *extra)
            results[name] = ate(rd, gt)
        except Exception as exc:  # record, keep going
            results[name] = {"error": str(exc)[:300]}
        print(name, results[name], flush=True)
    (out / "results.json").write_text(json.dumps(results, indent=2))
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    sys.exit(main())
