"""Validation during training: the same losses on held-out pairs, and the odometry's ATE.

The ATE is the figure users care about: the current networks are exported to ONNX
(split flow graphs, as ``trianflow-vo export`` writes them), ``trianflow-vo run``'s pipeline
runs on the validation sequence with them at the training size, and the trajectory is
evaluated against its ground truth (7-DoF alignment) as ``trianflow-vo eval`` does.
"""

from __future__ import annotations

import tempfile
from dataclasses import replace
from pathlib import Path

import torch

from trianflow_vo.models.checkpoint import DEFAULT_CHANNEL_ORDER, DEPTH_NORM, FLOW_NORM

MOVING_BRANCHES = ("two-view", "pnp")  # the branches of a run's frames that can move the camera


@torch.no_grad()
def validation_losses(compute, loader, max_pairs: int, device: torch.device) -> tuple[dict[str, float], int]:
    """Mean of every loss term over at most ``max_pairs`` pairs of ``loader``.

    ``compute(batch) -> StepOutput``; returns ``(means, pairs used)``.
    """
    sums: dict[str, float] = {}
    n = 0
    for batch, _ in loader:
        if batch is None:
            continue
        out = compute(batch)
        b = int(batch["img1"].shape[0])
        for k, v in out.terms.items():
            sums[k] = sums.get(k, 0.0) + float(v) * b
        n += b
        if n >= max_pairs:
            break
    return ({k: v / n for k, v in sums.items()} if n else {}), n


def export_current(flow_net, depth_net, size: tuple[int, int], out_dir: Path) -> tuple[Path | None, Path | None]:
    """ONNX files of the current networks (eval-mode copies on the CPU) in ``out_dir``."""
    import copy

    from trianflow_vo.models.export import export_depth, export_flow

    flow_path = depth_path = None
    if flow_net is not None:
        net = copy.deepcopy(flow_net).cpu().eval()
        flow_path = export_flow(net, FLOW_NORM, size, DEFAULT_CHANNEL_ORDER, out_dir / "flow.onnx", split=True)
    if depth_net is not None:
        net = copy.deepcopy(depth_net).cpu().eval()
        depth_path = export_depth(net, DEPTH_NORM, size, DEFAULT_CHANNEL_ORDER, out_dir / "depth.onnx")
    return flow_path, depth_path


def odometry_ate(seq: Path, gt: Path, flow_net, depth_net, size: tuple[int, int], threads: int = 1,
                 scale_from: str | None = None) -> dict[str, float]:
    """Run the odometry on ``seq`` with the current networks and evaluate it against ``gt``.

    Without a flow network (stage depth with DIS flow) the run uses DIS flow. Returns
    ``{"ate_rmse": m, "ate_pct": % of path, "t_err": %, "frames": n}``. Raises ValueError when
    no frame moved the camera (every frame rotation-only or static: no trajectory to align).
    """
    from trianflow_vo.config import Config, merge_dict
    from trianflow_vo.eval import evaluate_files
    from trianflow_vo.pipeline import run

    with tempfile.TemporaryDirectory(prefix="tfvo-val-") as tmp:
        tmp = Path(tmp)
        flow_path, depth_path = export_current(flow_net, depth_net, size, tmp)
        cfg = merge_dict(Config(), {
            "input": {"size": list(size)},
            "flow": {"model": None if flow_path is None else str(flow_path)},
            "depth": {"model": None if depth_path is None else str(depth_path)},
            "output": {"plot": False},
            "runtime": {"threads": max(1, int(threads))},
        }, "validation")
        if scale_from is not None:
            cfg = replace(cfg, scale=replace(cfg.scale, source=scale_from))
        summary = run(seq, tmp / "run", cfg)
        counts = summary.get("branch_counts") or {}
        if counts and not any(int(counts.get(b, 0)) for b in MOVING_BRANCHES):
            shown = ", ".join(f"{b} {n}" for b, n in counts.items() if n)
            raise ValueError(f"the odometry with the current networks never left its first pose ({shown}; "
                             "typically a flow below the two-view threshold): no ATE")
        result = evaluate_files(tmp / "run", gt)
    m = result.metrics
    path = float(m.get("path_length") or 0.0)
    return {"ate_rmse": float(m["ate_rmse"]), "ate_pct": 100.0 * float(m["ate_rmse"]) / path if path > 0 else
            float("nan"), "t_err": float(m["t_err"]) if m.get("t_err") is not None else float("nan"),
            "frames": float(summary.get("frames_processed", m["num_frames"]) or m["num_frames"])}
