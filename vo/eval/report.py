"""Plain-text table of eval metrics (what ``trianflow-vo eval`` prints)."""

from __future__ import annotations


def _num(x, fmt: str) -> str:
    """``x`` formatted with ``fmt`` (``"10.4f"``), or ``-`` padded to the same width."""
    if x is not None:
        return format(x, fmt)
    width = int(fmt.split(".")[0] or 0)
    return "-".rjust(width)


def format_report(metrics: dict) -> str:
    """A readable multi-line summary of an :func:`vo.eval.evaluate` result dict."""
    m = metrics
    out = []
    if "pred" in m:
        out.append(f"prediction   {m['pred']}")
        out.append(f"ground truth {m['gt']}")
        out.append(
            f"frames       {m['num_frames']} common (prediction {m['num_pred_frames']}, ground truth "
            f"{m['num_gt_frames']}), matched by {m['matched_by']}"
        )
    else:
        out.append(f"frames       {m['num_frames']} common")
    out.append(f"alignment    {m['align']} (scale {m['scale']:.6g}), both re-based to the first common frame")
    out.append(f"path length  {m['path_length']:.1f} m (ground truth)")
    out.append("")
    if m["num_segments"]:
        if m.get("protocol") == "kitti-odom-eval":
            starts = (f"first frames: ground-truth frames 0, {m['step']}, {2 * m['step']}, ... that are predicted, "
                      "kitti-odom-eval protocol")
        else:
            starts = f"first frames every {m['step']} frames"
        out.append(f"KITTI segment metric ({m['num_segments']} segments, {starts})")
        out.append(f"  t_err  {m['t_err']:.4f} %")
        out.append(f"  r_err  {m['r_err']:.4f} deg/100m")
        out.append("")
        out.append(f"  {'length (m)':>10}  {'t_err (%)':>10}  {'r_err (deg/100m)':>16}  {'segments':>8}")
        for row in m["per_length"]:
            out.append(
                f"  {row['length']:>10g}  {_num(row['t_err'], '10.4f')}  {_num(row['r_err'], '16.4f')}"
                f"  {row['num_segments']:>8d}"
            )
    else:
        out.append("KITTI segment metric: " + m.get("note", "no segment"))
    out.append("")
    out.append(f"ATE          rmse {m['ate_rmse']:.4f} m  (mean {m['ate_mean']:.4f}, max {m['ate_max']:.4f})")
    out.append(
        f"RPE (1 frame) rmse {m['rpe_trans']:.4f} m, {m['rpe_rot']:.4f} deg  "
        f"(mean {m['rpe_trans_mean']:.4f} m, {m['rpe_rot_mean']:.4f} deg)"
    )
    return "\n".join(out)
