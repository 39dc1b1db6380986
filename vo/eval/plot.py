"""Figure of an evaluation (PNG, JPEG, PDF or SVG, as the file's suffix says): top-down
trajectories and errors per segment length.

The trajectories are drawn by evo's plotting (:func:`evo.tools.plot.traj`, top view
``PlotMode.xz``) on a headless Agg figure of our own; the per-length panel is ours (evo
has no segment metric). matplotlib and evo's plotting are imported on first use only.

Importing ``evo.tools.plot`` has side effects, contained by :func:`evo_plot`: on first
use evo writes ``~/.evo/settings.json`` and *prints* that to stdout (swallowed here:
the tool's stdout carries only its report), it selects the matplotlib backend of its
settings (Agg here, unless pyplot is already in use) and restyles matplotlib with seaborn
(undone: the import runs inside ``matplotlib.rc_context``). When it cannot be imported
(read-only or missing HOME, broken settings file, missing package) the figures are drawn
with matplotlib directly and a :class:`PlotFallbackWarning` says so, once.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np


# file suffix -> matplotlib format; anything else is refused (never a PNG under another name)
PLOT_FORMATS = {".png": "png", ".jpg": "jpeg", ".jpeg": "jpeg", ".pdf": "pdf", ".svg": "svg"}


def plot_format(path: str | Path) -> str:
    """The matplotlib format that ``path``'s suffix names (``"png"``, ``"jpeg"``, ``"pdf"``, ``"svg"``).

    Raises:
        vo.errors.InputError: any other suffix (or none), naming the file and the choices.
    """
    from trianflow_vo.errors import InputError

    suffix = Path(path).suffix.lower()
    if suffix not in PLOT_FORMATS:
        what = f"'{Path(path).suffix}'" if suffix else "no suffix"
        raise InputError(f"cannot tell the image format from {what}: name the plot .png, .jpg/.jpeg, .pdf or .svg",
                         path)
    return PLOT_FORMATS[suffix]


def axis_units(align: str) -> str:
    """Unit of the top view's axes: metres when the alignment fixes the prediction's scale
    (``7dof``, ``scale``); otherwise the prediction keeps its own, monocular, scale-free
    units (``none``, ``6dof``) while the ground truth is in metres."""
    return "m" if align in ("7dof", "scale") else "m; prediction scale-free, not scale-aligned"


class PlotFallbackWarning(RuntimeWarning):
    """evo's plotting could not be imported; figures are drawn with matplotlib directly."""


_EVO_PLOT = None  # evo.tools.plot once imported, False once the import failed


def evo_plot():
    """``evo.tools.plot``, imported once and quietly; None when it cannot be imported
    (then a :class:`PlotFallbackWarning` is issued, the first time)."""
    global _EVO_PLOT
    if _EVO_PLOT is None:
        _EVO_PLOT = _import_evo_plot()
    return _EVO_PLOT or None


def _import_evo_plot():
    import contextlib
    import io
    import sys

    try:
        import matplotlib

        already = "evo.tools.plot" in sys.modules
        with contextlib.redirect_stdout(io.StringIO()), matplotlib.rc_context():
            from evo.tools import settings as evo_settings

            if not already:
                # evo calls matplotlib.use(its setting) on import: keep the backend in use, or Agg
                backend = matplotlib.get_backend() if "matplotlib.pyplot" in sys.modules else "agg"
                evo_settings.SETTINGS.plot_backend = backend
            from evo.tools import plot as evo_plot_module
        return evo_plot_module
    except Exception as exc:  # noqa: BLE001 - any failure of evo's import means: draw without it
        warnings.warn(
            f"evo's plotting is unavailable ({type(exc).__name__}: {exc}); drawing the trajectory figures "
            "with matplotlib directly",
            PlotFallbackWarning,
            stacklevel=3,
        )
        return False


def draw_top_view(ax, positions: np.ndarray, style: str = "-", color=None, label: str = "", **line_kw):
    """Draw ``(N, 3)`` positions seen from above (x right, z up the page) into ``ax``.

    Through evo's ``plot.traj`` (``PlotMode.xz``) when evo's plotting is available, else
    with ``ax.plot``; ``line_kw`` (``linewidth``, ``zorder``, ...) is then set on the line.

    Returns:
        The matplotlib ``Line2D`` drawn.
    """
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    evo = evo_plot()
    if evo is not None and p.shape[0] > 0:
        from evo.core.trajectory import PosePath3D

        path = PosePath3D(positions_xyz=p, orientations_quat_wxyz=np.tile([1.0, 0.0, 0.0, 0.0], (p.shape[0], 1)))
        first = len(ax.lines)
        evo.traj(ax, evo.PlotMode.xz, path, style=style, color=color, label=label)
        line = ax.lines[first]
    else:
        (line,) = ax.plot(p[:, 0], p[:, 2], style, color=color, label=label)
    if line_kw:
        line.set(**line_kw)
    return line


def plot_evaluation(result, path: str | Path, title: str | None = None) -> Path:
    """Write ``path``: ground truth and aligned prediction seen from above (x-z plane,
    camera convention y down), and t_err / r_err per segment length, in the format its
    suffix names (see :func:`plot_format`).

    Args:
        result: a :class:`vo.eval.EvalResult`.
        path: output file (``.png``, ``.jpg``/``.jpeg``, ``.pdf`` or ``.svg``); its folder
            must exist.
        title: figure title.

    Returns:
        ``path`` as a Path.

    Raises:
        vo.errors.InputError: an unknown suffix (checked before drawing).
    """
    fmt = plot_format(path)
    fig = evaluation_figure(result, title)
    path = Path(path)
    fig.savefig(path, format=fmt)
    return path


def evaluation_figure(result, title: str | None = None):
    """The matplotlib ``Figure`` :func:`plot_evaluation` writes (headless, Agg canvas).
    The top view's axes say their unit (:func:`axis_units`)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    m = result.metrics
    gt = result.gt_rebased[:, :3, 3]
    pr = result.pred_aligned[:, :3, 3]
    fig = Figure(figsize=(12, 5), dpi=100)
    FigureCanvasAgg(fig)
    ax_traj = fig.add_subplot(1, 2, 1)
    draw_top_view(ax_traj, gt, "-", color="black", label="ground truth", linewidth=1.5)
    pred_label = "prediction (not aligned)" if m["align"] == "none" else f"prediction ({m['align']} aligned)"
    draw_top_view(ax_traj, pr, "-", color="tab:red", label=pred_label, linewidth=1.2)
    ax_traj.plot(gt[0, 0], gt[0, 2], "o", color="black", ms=5, label="start")
    unit = axis_units(m["align"])
    ax_traj.set_xlabel(f"x ({unit})")
    ax_traj.set_ylabel(f"z ({unit})")
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
    return fig
