"""PNG figure of an evaluation: top-down trajectories and errors per segment length.

matplotlib is imported inside :func:`plot_evaluation` only (Agg canvas, headless).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def plot_evaluation(result, path: str | Path, title: str | None = None) -> Path:
    """Write ``path`` (PNG): ground truth and aligned prediction seen from above (x-z
    plane, camera convention y down), and t_err / r_err per segment length.

    Args:
        result: a :class:`vo.eval.EvalResult`.
        path: output file; its folder must exist.
        title: figure title (default: alignment and main numbers).

    Returns:
        ``path`` as a Path.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    m = result.metrics
    gt = result.gt_rebased[:, :3, 3]
    pr = result.pred_aligned[:, :3, 3]
    fig = Figure(figsize=(12, 5), dpi=100)
    FigureCanvasAgg(fig)
    ax_traj = fig.add_subplot(1, 2, 1)
    ax_traj.plot(gt[:, 0], gt[:, 2], "-", color="black", lw=1.5, label="ground truth")
    ax_traj.plot(pr[:, 0], pr[:, 2], "-", color="tab:red", lw=1.2, label=f"prediction ({m['align']} aligned)")
    ax_traj.plot(gt[0, 0], gt[0, 2], "o", color="black", ms=5, label="start")
    ax_traj.set_xlabel("x (m)")
    ax_traj.set_ylabel("z (m)")
    ax_traj.set_aspect("equal", adjustable="datalim")
    ax_traj.grid(True, alpha=0.3)
    ax_traj.legend(loc="best", fontsize=8)
    ax_traj.set_title(f"top view, ATE rmse {m['ate_rmse']:.3f} m")

    ax_t = fig.add_subplot(1, 2, 2)
    rows = [r for r in m["per_length"] if r["num_segments"] > 0]
    if rows:
        L = np.array([r["length"] for r in rows])
        te = np.array([r["t_err"] for r in rows])
        re = np.array([r["r_err"] for r in rows])
        ax_t.plot(L, te, "o-", color="tab:blue", label="t_err (%)")
        ax_t.set_xlabel("segment length (m)")
        ax_t.set_ylabel("t_err (%)", color="tab:blue")
        ax_t.set_ylim(bottom=0)
        ax_r = ax_t.twinx()
        ax_r.plot(L, re, "s--", color="tab:green", label="r_err (deg/100m)")
        ax_r.set_ylabel("r_err (deg/100m)", color="tab:green")
        ax_r.set_ylim(bottom=0)
        ax_t.grid(True, alpha=0.3)
        ax_t.set_title(f"per length: t_err {m['t_err']:.3f} %, r_err {m['r_err']:.3f} deg/100m")
    else:
        ax_t.axis("off")
        ax_t.text(0.5, 0.5, m.get("note", "no segment"), ha="center", va="center", wrap=True, fontsize=9,
                  transform=ax_t.transAxes)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, format="png")
    return path
