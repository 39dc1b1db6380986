"""Optical-flow metrics against ground truth: EPE and Fl-all (``trianflow-vo eval-flow``).

Per image pair, over the pixels with valid ground truth:

* **EPE** (end-point error): ``|pred - gt|`` (Euclidean, pixels), averaged over the
  valid pixels;
* **Fl-all**: the percentage of valid pixels that are *outliers*, i.e. whose EPE is
  more than 3 px **and** more than 5 % of the ground-truth flow's length
  (``epe > 3`` and ``epe / |gt| > 0.05``: strictly; as the KITTI 2015 devkit).

Averaging over pairs, both reported:

* ``epe``, ``fl_all``: the per-pair values averaged over the pairs (every pair weighs
  the same): what the TrianFlow authors' ``eval_flow_avg`` reports;
* ``epe_pooled``, ``fl_all_pooled``: over all valid pixels of all pairs at once: the
  KITTI 2015 devkit's summary (it accumulates outlier and pixel counts over the
  images), i.e. the benchmark's Fl-all.

The prediction is first brought to the ground truth's grid by :func:`resize_flow`
(bilinear resize, values scaled by the size ratio), as the authors do.

Pure numpy (OpenCV only for the bilinear resize); no files here. The command is
:mod:`trianflow_vo.cli.eval_flow_cmd`.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from trianflow_vo.errors import InputError

#: an outlier's EPE exceeds this many pixels ...
FL_ABS_PX = 3.0
#: ... and this fraction of the ground-truth flow's length
FL_REL = 0.05

#: ``progress(done, name)``, called after each pair
Progress = Callable[[int, str], None]


# ---------------------------------------------------------------------------
# numerics

def _check_flow(flow: np.ndarray, what: str) -> np.ndarray:
    flow = np.asarray(flow)
    if flow.ndim != 3 or flow.shape[2] != 2 or flow.shape[0] < 1 or flow.shape[1] < 1:
        raise ValueError(f"{what} must be (H, W, 2) with H, W >= 1, got {flow.shape}")
    return flow


def resize_flow(flow: np.ndarray, size_hw: tuple[int, int]) -> np.ndarray:
    """A flow field on another pixel grid of the same image.

    Args:
        flow: ``(h, w, 2)`` flow in pixels of an ``h x w`` image, ``[..., 0]`` = dx.
        size_hw: the target ``(H, W)``.

    Returns:
        ``(H, W, 2)`` float32: bilinearly resized, dx multiplied by ``W / w`` and dy by
        ``H / h`` (a float32 copy when already that size).

    Raises:
        ValueError: ``flow`` not ``(h, w, 2)`` or a size < 1.
    """
    flow = _check_flow(flow, "flow").astype(np.float32)
    H, W = (int(v) for v in size_hw)
    if H < 1 or W < 1:
        raise ValueError(f"size must be at least 1x1, got {H}x{W}")
    h, w = flow.shape[:2]
    if (h, w) == (H, W):
        return flow.copy()
    out = cv2.resize(flow, (W, H), interpolation=cv2.INTER_LINEAR)
    out[..., 0] *= W / w
    out[..., 1] *= H / h
    return out


def epe_map(gt: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """``(H, W)`` float64 end-point error ``|pred - gt|`` of two ``(H, W, 2)`` flows.

    Raises:
        ValueError: not two ``(H, W, 2)`` flows of the same size.
    """
    gt = _check_flow(gt, "gt")
    pred = _check_flow(pred, "pred")
    if gt.shape != pred.shape:
        raise ValueError(f"gt and pred must have the same shape, got {gt.shape} and {pred.shape}")
    d = pred.astype(np.float64) - gt.astype(np.float64)
    return np.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2)


def outlier_mask(epe: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """``(H, W)`` bool: the Fl outliers, ``epe > 3`` and ``epe / |gt| > 0.05``.

    Args:
        epe: ``(H, W)`` end-point errors (:func:`epe_map`).
        gt: ``(H, W, 2)`` ground-truth flow (zero flow: any EPE above 3 px is an outlier).
    """
    gt = np.asarray(gt, dtype=np.float64)
    mag = np.sqrt(gt[..., 0] ** 2 + gt[..., 1] ** 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(mag > 0, epe / np.where(mag > 0, mag, 1.0), np.inf)
    return (epe > FL_ABS_PX) & (rel > FL_REL)


def flow_errors(gt: np.ndarray, valid: np.ndarray, pred: np.ndarray) -> dict:
    """EPE and Fl-all of one prediction over the valid ground-truth pixels.

    Args:
        gt: ``(H, W, 2)`` ground-truth flow, pixels.
        valid: ``(H, W)`` bool, where ``gt`` holds.
        pred: ``(H, W, 2)`` predicted flow on the same grid (see :func:`resize_flow`).

    Returns:
        ``{"epe": mean EPE (px), "fl_all": outliers / valid pixels (%), "n_valid",
        "n_outliers", "epe_sum"}``.

    Raises:
        ValueError: shapes that differ, no valid pixel, or a non-finite prediction or
            ground truth at a valid pixel.
    """
    epe = epe_map(gt, pred)
    valid = np.asarray(valid, dtype=bool)
    if valid.shape != epe.shape:
        raise ValueError(f"valid must be (H, W) = {epe.shape}, got {valid.shape}")
    n = int(valid.sum())
    if n == 0:
        raise ValueError("no valid ground-truth pixel")
    e = epe[valid]
    if not np.isfinite(e).all():
        raise ValueError("the flow is not finite at every valid ground-truth pixel")
    n_out = int(outlier_mask(epe, gt)[valid].sum())
    return {"epe": float(e.mean()), "fl_all": 100.0 * n_out / n, "n_valid": n, "n_outliers": n_out,
            "epe_sum": float(e.sum())}


def fl_all(gt: np.ndarray, valid: np.ndarray, pred: np.ndarray) -> float:
    """Fl-all (%) of one prediction (:func:`flow_errors`)."""
    return flow_errors(gt, valid, pred)["fl_all"]


# ---------------------------------------------------------------------------
# a whole evaluation

@dataclass(frozen=True)
class FlowReport:
    """Per-pair rows and the averages over pairs and over pixels.

    ``rows[i]``: ``{"name", "gt", "epe", "fl_all", "n_valid", "n_outliers", "epe_sum"}``.
    """

    rows: tuple[dict, ...]

    @property
    def n_pairs(self) -> int:
        return len(self.rows)

    @property
    def epe(self) -> float:
        """EPE (px) of each pair, averaged over the pairs (the TrianFlow authors)."""
        return float(np.mean([r["epe"] for r in self.rows]))

    @property
    def fl_all(self) -> float:
        """Fl-all (%) of each pair, averaged over the pairs (the TrianFlow authors)."""
        return float(np.mean([r["fl_all"] for r in self.rows]))

    @property
    def n_valid(self) -> int:
        return int(sum(r["n_valid"] for r in self.rows))

    @property
    def epe_pooled(self) -> float:
        """EPE (px) over all valid pixels of all pairs."""
        return float(sum(r["epe_sum"] for r in self.rows) / self.n_valid)

    @property
    def fl_all_pooled(self) -> float:
        """Outliers over all valid pixels of all pairs (%): the KITTI 2015 devkit's Fl-all."""
        return 100.0 * sum(r["n_outliers"] for r in self.rows) / self.n_valid

    def to_dict(self) -> dict:
        """JSON-ready summary (no per-pair rows)."""
        return {
            "metrics": {"epe": self.epe, "fl_all": self.fl_all, "epe_pooled": self.epe_pooled,
                        "fl_all_pooled": self.fl_all_pooled},
            "n_pairs": self.n_pairs,
            "n_valid_pixels": self.n_valid,
            "definitions": {
                "epe": "mean end-point error (px) over the valid pixels of each pair, averaged over pairs",
                "fl_all": "% of valid pixels with EPE > 3 px and > 5% of |gt| in each pair, averaged over pairs",
                "epe_pooled": "mean end-point error (px) over all valid pixels of all pairs",
                "fl_all_pooled": "% outliers over all valid pixels of all pairs (KITTI 2015 devkit)",
            },
        }


def evaluate_flow(triples: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]],
                  names: Sequence[str] | None = None, *, sources: Sequence[str] | None = None,
                  progress: Progress | None = None) -> FlowReport:
    """Evaluate predicted flows against ground truth.

    Args:
        triples: ``(gt, valid, pred)`` per pair: ``gt`` ``(H, W, 2)``, ``valid`` ``(H, W)``
            bool, ``pred`` ``(h, w, 2)`` on any grid of the same image (resized with
            :func:`resize_flow`). May be a generator: one is held at a time.
        names: the pair names (errors and rows); default ``pair 0``, ``pair 1``, ...
        sources: the ground-truth names for the rows (default: none).
        progress: called as ``progress(done, name)`` after each pair.

    Raises:
        InputError: naming the pair: bad shapes, no valid ground-truth pixel,
            non-finite flow; fewer names than pairs; or no pair at all.
    """
    rows: list[dict] = []
    for i, (gt, valid, pred) in enumerate(triples):
        if names is not None and i >= len(names):
            raise InputError(f"more flow pairs than names ({len(names)})")
        name = names[i] if names is not None else f"pair {i}"
        src = sources[i] if sources is not None else None
        try:
            gt = _check_flow(gt, "ground-truth flow")
            errs = flow_errors(gt, valid, resize_flow(pred, gt.shape[:2]))
        except ValueError as exc:
            raise InputError(str(exc) + (f" ({src})" if src else ""), name) from None
        rows.append({"name": name, "gt": src, **errs})
        if progress is not None:
            progress(i + 1, name)
    if not rows:
        raise InputError("no image pair to evaluate")
    return FlowReport(rows=tuple(rows))


# ---------------------------------------------------------------------------
# text outputs

def format_flow_report(report: FlowReport) -> str:
    """The table ``eval-flow`` prints."""
    r = report
    return "\n".join([
        f"flow: {r.n_pairs} pair{'s' * (r.n_pairs != 1)}, {r.n_valid} valid ground-truth pixels; "
        "outlier = EPE > 3 px and > 5% of |gt|",
        f"  {'':<26} {'EPE (px)':>10} {'Fl-all (%)':>10}",
        f"  {'mean over pairs (authors)':<26} {r.epe:>10.4f} {r.fl_all:>10.4f}",
        f"  {'over all pixels (KITTI)':<26} {r.epe_pooled:>10.4f} {r.fl_all_pooled:>10.4f}",
    ])


def flow_csv(report: FlowReport) -> str:
    """Per-pair CSV: ``pair,gt,n_valid,n_outliers,epe,fl_all``."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["pair", "gt", "n_valid", "n_outliers", "epe", "fl_all"])
    for row in report.rows:
        writer.writerow([row["name"], row["gt"] or "", row["n_valid"], row["n_outliers"],
                         repr(row["epe"]), repr(row["fl_all"])])
    return buf.getvalue()
