"""The batch summary: ``DIR/summary.csv``, ``DIR/summary.md`` and ``DIR/summary.json``.

One row per job (the result rows of :func:`trianflow_vo.batch.jobs.run_job`) and one overall
row (``name`` = ``ALL``). The overall row sums frames, branch counts and run times; its ``fps``
is the batch's throughput (frames processed by this batch, i.e. not of resumed runs, over the
batch's wall time), its ``task_s`` that wall time,
its ``peak_rss_mb`` the largest of the runs; ATE, RPE, t_err and r_err are means over the
sequences that have them (the KITTI metric of the whole set would weight segments instead).
Rendering is pure (:func:`summary_rows`, :func:`overall_row`, :func:`render_csv`,
:func:`render_markdown`); :func:`write_summary` writes the files atomically.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path


COLUMNS = ("name", "sweep", "status", "reason", "resumed", "frames", "frames_skipped", "elapsed_s", "fps",
           "task_s", "peak_rss_mb", "two_view", "pnp", "rotation", "identity", "failed_frames", "ate_rmse",
           "rpe_trans", "rpe_rot", "t_err", "r_err", "lengths", "num_segments", "out_dir", "seq")
_BRANCH_COLUMN = {"two-view": "two_view", "pnp": "pnp", "rotation": "rotation", "identity": "identity",
                  "failed": "failed_frames"}
_METRICS = ("ate_rmse", "rpe_trans", "rpe_rot", "t_err", "r_err")
OVERALL = "ALL"


def _sweep_text(sweep: Mapping | None) -> str:
    return ",".join(f"{k}={v}" for k, v in (sweep or {}).items())


def _lengths_text(lengths) -> str:
    return " ".join(f"{x:g}" for x in lengths) if lengths else ""


def summary_rows(results: Sequence[Mapping]) -> list[dict]:
    """One flat row (:data:`COLUMNS`) per result; missing values are None."""
    rows = []
    for r in results:
        counts = r.get("branch_counts") or {}
        ev = r.get("eval") or {}
        row = {
            "name": r.get("name"), "sweep": _sweep_text(r.get("sweep")), "status": r.get("status"),
            "reason": r.get("reason"), "resumed": bool(r.get("resumed")), "frames": r.get("frames"),
            "frames_skipped": r.get("frames_skipped"), "elapsed_s": r.get("elapsed_s"), "fps": r.get("fps"),
            "task_s": r.get("task_s"), "peak_rss_mb": r.get("peak_rss_mb"),
            **{col: (counts.get(b) if counts else None) for b, col in _BRANCH_COLUMN.items()},
            **{k: ev.get(k) for k in _METRICS},
            "lengths": _lengths_text(ev.get("lengths")), "num_segments": ev.get("num_segments"),
            "out_dir": r.get("out_dir"), "seq": r.get("seq"),
        }
        rows.append(row)
    return rows


def _num(v) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) else None


def _sum(rows, key) -> int | float | None:
    vals = [_num(r[key]) for r in rows if _num(r[key]) is not None]
    return sum(vals) if vals else None


def _mean(rows, key) -> float | None:
    vals = [_num(r[key]) for r in rows if _num(r[key]) is not None]
    return sum(vals) / len(vals) if vals else None


def overall_row(rows: Sequence[Mapping], wall_s: float | None) -> dict:
    """The ``ALL`` row of :func:`summary_rows` rows; ``wall_s`` = the batch's wall time (None if unknown)."""
    n = len(rows)
    done = sum(r["status"] == "completed" for r in rows)
    frames = _sum(rows, "frames")
    ran = _sum([r for r in rows if not r["resumed"]], "frames")  # frames processed by this batch
    out = {c: None for c in COLUMNS}
    out.update({
        "name": OVERALL, "sweep": "", "status": f"{done}/{n} completed",
        "reason": None if done == n else f"{n - done} not completed",
        "resumed": sum(bool(r["resumed"]) for r in rows),
        "frames": None if frames is None else int(frames),
        "frames_skipped": None if _sum(rows, "frames_skipped") is None else int(_sum(rows, "frames_skipped")),
        "elapsed_s": _sum(rows, "elapsed_s"),
        "fps": (ran / wall_s) if ran and wall_s else None,
        "task_s": wall_s,
        "peak_rss_mb": max((_num(r["peak_rss_mb"]) for r in rows if _num(r["peak_rss_mb"]) is not None),
                           default=None),
        "lengths": "", "out_dir": "", "seq": "",
    })
    for col in _BRANCH_COLUMN.values():
        s = _sum(rows, col)
        out[col] = None if s is None else int(s)
    for k in _METRICS:
        out[k] = _mean(rows, k)
    segs = _sum(rows, "num_segments")
    out["num_segments"] = None if segs is None else int(segs)
    return out


def _csv_cell(v) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


def render_csv(rows: Sequence[Mapping], overall: Mapping) -> str:
    """``summary.csv``: a header of :data:`COLUMNS`, the rows, the overall row last."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(COLUMNS)
    for r in [*rows, overall]:
        w.writerow([_csv_cell(r.get(c)) for c in COLUMNS])
    return buf.getvalue()


def _f(v, digits: int) -> str:
    v = _num(v)
    return "–" if v is None else f"{v:.{digits}f}"


def _i(v) -> str:
    v = _num(v)
    return "–" if v is None else str(int(v))


def _md(text) -> str:
    return "" if text is None else str(text).replace("|", "\\|").replace("\n", " ")


def render_markdown(rows: Sequence[Mapping], overall: Mapping, meta: Mapping | None = None) -> str:
    """``summary.md``: what ran (``meta``: ``command``, ``started``, ``workers``, ``ray``, ``wall_s``), one
    table (a row per job, the overall row in bold) and the failures with their reasons."""
    meta = dict(meta or {})
    lines = ["# Batch summary", ""]
    for key, label in (("command", "command"), ("started", "started"), ("ray", "Ray"), ("workers", "workers")):
        if meta.get(key) is not None:
            val = f"`{meta[key]}`" if key == "command" else str(meta[key])
            lines.append(f"- {label}: {val}")
    n = len(rows)
    fails = [r for r in rows if r["status"] != "completed"]
    resumed = sum(bool(r["resumed"]) for r in rows)
    wall = overall.get("task_s")
    lines.append(f"- {n} runs: {n - len(fails)} completed ({resumed} already completed, not run again), "
                 f"{len(fails)} not completed" + (f"; wall time {wall:.1f} s" if _num(wall) is not None else "")
                 + (f"; {overall['frames']} frames, {_f(overall['fps'], 1)} frames/s processed overall"
                    if overall.get("frames") is not None else ""))
    swept = any(r["sweep"] for r in rows)
    head = ["name", *(["sweep"] if swept else []), "status", "frames", "fps", "two-view", "pnp", "rotation", "static",
            "failed frames", "ATE (m)", "RPE t (m)", "RPE r (deg)", "t_err (%)", "r_err (deg/100 m)", "lengths (m)",
            "peak RSS (MB)"]
    lines += ["", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]

    def cells(r, bold=False):
        c = [_md(r["name"]), *([_md(r["sweep"])] if swept else []),
             _md(r["status"]) + (" (resumed)" if r["resumed"] is True else ""),
             _i(r["frames"]), _f(r["fps"], 1), _i(r["two_view"]), _i(r["pnp"]), _i(r["rotation"]),
             _i(r["identity"]), _i(r["failed_frames"]), _f(r["ate_rmse"], 3), _f(r["rpe_trans"], 3),
             _f(r["rpe_rot"], 3), _f(r["t_err"], 2), _f(r["r_err"], 2), _md(r["lengths"]) or "–",
             _f(r["peak_rss_mb"], 0)]
        if bold:
            c = [f"**{x}**" if x not in ("", "–") else x for x in c]
        return "| " + " | ".join(c) + " |"

    lines += [cells(r) for r in rows]
    lines.append(cells(overall, bold=True))
    lines += ["", "fps: frames per second of each run (from its run.json); in the overall row, the frames this batch "
                  "processed (resumed runs not counted) over its wall time. ATE/RPE (RMSE after 7-DoF alignment) and "
                  "KITTI t_err/r_err (over the lengths shown) as `trianflow-vo eval` computes them; overall: means over "
                  "the runs that have them."]
    if fails:
        lines += ["", "## Not completed", ""]
        lines += [f"- {_md(r['name'])}{' [' + _md(r['sweep']) + ']' if r['sweep'] else ''}: {r['status']} — "
                  f"{_md(r['reason']) or 'no reason given'}" for r in fails]
    return "\n".join(lines) + "\n"


def write_summary(out_root: str | Path, results: Sequence[Mapping], meta: Mapping | None = None,
                  wall_s: float | None = None) -> list[Path]:
    """Write ``summary.csv``, ``summary.md`` and ``summary.json`` (meta, rows, overall, the full results with
    per-length metrics) into ``out_root``, each atomically. Returns their paths."""
    from trianflow_vo.io.atomic import write_atomic

    out_root = Path(out_root)
    rows = summary_rows(results)
    overall = overall_row(rows, wall_s)
    meta = {**(meta or {}), "wall_s": wall_s}
    doc = {"meta": meta, "overall": overall, "rows": rows, "results": list(results)}
    return [
        write_atomic(out_root / "summary.csv", render_csv(rows, overall).encode()),
        write_atomic(out_root / "summary.md", render_markdown(rows, overall, meta).encode()),
        write_atomic(out_root / "summary.json", json.dumps(doc, indent=2, default=str).encode()),
    ]
