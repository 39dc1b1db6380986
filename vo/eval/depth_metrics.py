"""Single-image depth metrics on the KITTI Eigen-split conventions (``trianflow-vo eval-depth``).

The protocol of monodepth2's evaluation and of the TrianFlow authors'
``core/evaluation/evaluate_depth.py``, per image:

1. the predicted depth is resized (bilinear) to the ground truth's size;
2. the pixels used are those with ground truth in ``(min_depth, max_depth)``
   (defaults 1e-3, 80 m) inside the crop (:func:`eigen_crop_mask`): ``garg`` (the
   default; the crop of Garg et al. ECCV 2016 that monodepth2 and the TrianFlow
   authors apply on the Eigen split), ``eigen`` (the crop of monodepth v1's
   ``--eigen_crop``, reproducing Eigen et al. NIPS 2014) or ``none``;
3. median scaling (monocular depth has no scale): the prediction is multiplied by
   ``ratio = median(gt) / median(pred)`` over those pixels; the ratios are reported
   (median and spread over the images; a small spread = a consistent scale);
4. the prediction is clamped to ``[min_depth, max_depth]``;
5. :func:`depth_errors`: abs rel, sq rel, RMSE, RMSE log, and the fractions of
   pixels with ``max(gt / pred, pred / gt)`` below 1.25, 1.25², 1.25³.

Metrics are computed per image and **averaged over images** (every image weighs the
same, however many ground-truth pixels it has), as both references do.

Pure numpy (OpenCV only for the bilinear resize); no files here. The command is
:mod:`trianflow_vo.cli.eval_depth_cmd`.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from trianflow_vo.errors import InputError

#: metric keys, in table order
DEPTH_METRICS = ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3")
#: column titles of the table
METRIC_TITLES = {"abs_rel": "abs_rel", "sq_rel": "sq_rel", "rmse": "rmse", "rmse_log": "rmse_log",
                 "a1": "d<1.25", "a2": "d<1.25^2", "a3": "d<1.25^3"}
#: lower is better for these; higher for the others (the a* fractions)
LOWER_IS_BETTER = frozenset({"abs_rel", "sq_rel", "rmse", "rmse_log"})
DELTA = 1.25

CROPS = ("garg", "eigen", "none")
DEFAULT_CROP = "garg"
#: crop as fractions of the ground-truth size: (top, bottom, left, right); rows
#: [int(top*h), int(bottom*h)), columns [int(left*w), int(right*w)) (truncated to int)
CROP_FRACTIONS = {
    "garg": (0.40810811, 0.99189189, 0.03594771, 0.96405229),
    "eigen": (0.3324324, 0.91351351, 0.0359477, 0.96405229),
}
MIN_DEPTH = 1e-3
MAX_DEPTH = 80.0

#: ``progress(done, name)``, called after each image
Progress = Callable[[int, str], None]


# ---------------------------------------------------------------------------
# numerics

def depth_errors(gt: np.ndarray, pred: np.ndarray) -> dict[str, float]:
    """The seven depth metrics of matched ground-truth and predicted depths.

    Args:
        gt: ``(N,)`` (or any shape) ground-truth depths, all > 0.
        pred: predicted depths, the shape of ``gt``, all > 0.

    Returns:
        ``{"abs_rel": mean(|gt - pred| / gt), "sq_rel": mean((gt - pred)² / gt),
        "rmse": sqrt(mean((gt - pred)²)), "rmse_log": sqrt(mean((log gt - log pred)²)),
        "a1" / "a2" / "a3": fraction of max(gt / pred, pred / gt) < 1.25, 1.25², 1.25³}``
        (float64 arithmetic).

    Raises:
        ValueError: different shapes, no element, or a depth that is not finite and > 0.
    """
    if np.shape(gt) != np.shape(pred):
        raise ValueError(f"gt and pred must have the same shape, got {np.shape(gt)} and {np.shape(pred)}")
    gt = np.asarray(gt, dtype=np.float64).ravel()
    pred = np.asarray(pred, dtype=np.float64).ravel()
    if gt.size == 0:
        raise ValueError("no depth to compare")
    if not (np.isfinite(gt).all() and np.isfinite(pred).all() and (gt > 0).all() and (pred > 0).all()):
        raise ValueError("depths must be finite and > 0")
    diff = gt - pred
    ratio = np.maximum(gt / pred, pred / gt)
    return {
        "abs_rel": float(np.mean(np.abs(diff) / gt)),
        "sq_rel": float(np.mean(diff ** 2 / gt)),
        "rmse": float(np.sqrt(np.mean(diff ** 2))),
        "rmse_log": float(np.sqrt(np.mean((np.log(gt) - np.log(pred)) ** 2))),
        "a1": float(np.mean(ratio < DELTA)),
        "a2": float(np.mean(ratio < DELTA ** 2)),
        "a3": float(np.mean(ratio < DELTA ** 3)),
    }


def eigen_crop_mask(h: int, w: int, kind: str = DEFAULT_CROP) -> np.ndarray:
    """``(h, w)`` bool mask of the evaluation crop of an ``h x w`` ground-truth map.

    ``kind``: ``"garg"``, ``"eigen"`` (rectangles of :data:`CROP_FRACTIONS`) or
    ``"none"`` (every pixel).

    Raises:
        ValueError: unknown ``kind`` or a size < 1.
    """
    h, w = int(h), int(w)
    if h < 1 or w < 1:
        raise ValueError(f"size must be at least 1x1, got {h}x{w}")
    mask = np.zeros((h, w), dtype=bool)
    if kind == "none":
        mask[:] = True
        return mask
    if kind not in CROP_FRACTIONS:
        raise ValueError(f"crop must be one of {list(CROPS)}, got {kind!r}")
    top, bottom, left, right = CROP_FRACTIONS[kind]
    r0, r1 = int(top * h), int(bottom * h)
    c0, c1 = int(left * w), int(right * w)
    mask[r0:r1, c0:c1] = True
    return mask


def resize_depth(depth: np.ndarray, size_hw: tuple[int, int]) -> np.ndarray:
    """``depth`` ``(h, w)`` resized bilinearly to ``size_hw`` = ``(H, W)``: ``(H, W)``, float64
    for float64 input, float32 otherwise (not copied when already that size and dtype)."""
    depth = np.asarray(depth)
    depth = depth.astype(np.float64 if depth.dtype == np.float64 else np.float32)
    H, W = (int(v) for v in size_hw)
    if depth.shape == (H, W):
        return depth
    return cv2.resize(depth, (W, H), interpolation=cv2.INTER_LINEAR)


def _check_settings(min_depth: float, max_depth: float, crop: str) -> None:
    if not (0 < float(min_depth) < float(max_depth) < math.inf):
        raise ValueError(f"need 0 < min_depth < max_depth < inf, got {min_depth} and {max_depth}")
    if crop not in CROPS:
        raise ValueError(f"crop must be one of {list(CROPS)}, got {crop!r}")


def image_depth_errors(gt: np.ndarray, pred: np.ndarray, min_depth: float = MIN_DEPTH,
                       max_depth: float = MAX_DEPTH, crop: str = DEFAULT_CROP,
                       median_scaling: bool = True) -> tuple[dict, bool]:
    """The protocol of this module on one image.

    Args:
        gt: ``(H, W)`` ground-truth depth, metres; <= 0 or non-finite = no ground truth.
        pred: ``(h, w)`` predicted depth (resized to ``(H, W)`` when the sizes differ).
        min_depth, max_depth: ground truth used in the open interval; prediction clamped to it.
        crop: :data:`CROPS`.
        median_scaling: scale the prediction by ``median(gt) / median(pred)``.

    Returns:
        ``(row, valid)``: ``row`` = ``{"n_pixels", "ratio", **metrics}`` (``ratio`` None
        without median scaling); ``valid`` False when no pixel is left (then the metrics
        are NaN) or when the prediction there is not finite and > 0.

    Raises:
        ValueError: bad settings, or arrays that are not 2-D.
    """
    _check_settings(min_depth, max_depth, crop)
    gt = np.asarray(gt, dtype=np.float64)
    pred = np.asarray(pred)
    if gt.ndim != 2 or pred.ndim != 2 or gt.size == 0 or pred.size == 0:
        raise ValueError(f"gt and pred must be non-empty 2-D maps, got {gt.shape} and {pred.shape}")
    pred = resize_depth(pred, gt.shape).astype(np.float64)
    with np.errstate(invalid="ignore"):
        mask = np.isfinite(gt) & (gt > min_depth) & (gt < max_depth)
    mask &= eigen_crop_mask(*gt.shape, crop)
    g, p = gt[mask], pred[mask]
    nan_row = {"n_pixels": int(g.size), "ratio": None, **{k: math.nan for k in DEPTH_METRICS}}
    if g.size == 0 or not (np.isfinite(p).all() and (p > 0).all()):
        return nan_row, False
    ratio = None
    if median_scaling:
        ratio = float(np.median(g) / np.median(p))
        p = p * ratio
    p = np.clip(p, min_depth, max_depth)
    return {"n_pixels": int(g.size), "ratio": ratio, **depth_errors(g, p)}, True


# ---------------------------------------------------------------------------
# a whole evaluation

@dataclass(frozen=True)
class DepthReport:
    """Per-image rows and their mean, with the settings they were computed with.

    ``rows[i]``: ``{"name", "gt", "n_pixels", "ratio", **metrics}``; ``mean``: each
    metric averaged over the images; ``ratios``: the median-scaling ratios, in image
    order (empty without median scaling).
    """

    rows: tuple[dict, ...]
    mean: dict
    ratios: tuple[float, ...]
    min_depth: float
    max_depth: float
    crop: str
    median_scaling: bool

    @property
    def n_images(self) -> int:
        return len(self.rows)

    @property
    def ratio_median(self) -> float | None:
        """Median of the scaling ratios (None without median scaling)."""
        return float(np.median(self.ratios)) if self.ratios else None

    @property
    def ratio_std(self) -> float | None:
        """Standard deviation of the scaling ratios (None without median scaling)."""
        return float(np.std(self.ratios)) if self.ratios else None

    @property
    def ratio_rel_std(self) -> float | None:
        """std(ratios / median ratio), the spread monodepth2 prints (None without median scaling)."""
        return float(np.std(np.asarray(self.ratios) / self.ratio_median)) if self.ratios else None

    def to_dict(self) -> dict:
        """JSON-ready summary (no per-image rows): metrics, image count, scaling, settings."""
        return {
            "metrics": dict(self.mean),
            "n_images": self.n_images,
            "n_pixels": int(sum(r["n_pixels"] for r in self.rows)),
            "median_scaling": {"enabled": self.median_scaling, "ratio_median": self.ratio_median,
                               "ratio_std": self.ratio_std, "ratio_rel_std": self.ratio_rel_std},
            "settings": {"min_depth": self.min_depth, "max_depth": self.max_depth, "crop": self.crop,
                         "averaging": "per image, then mean over images"},
        }


def evaluate_depth(pairs: Iterable[tuple[np.ndarray, np.ndarray]], names: Sequence[str] | None = None, *,
                   sources: Sequence[str] | None = None, min_depth: float = MIN_DEPTH,
                   max_depth: float = MAX_DEPTH, crop: str = DEFAULT_CROP, median_scaling: bool = True,
                   progress: Progress | None = None) -> DepthReport:
    """Evaluate predicted depth maps against ground truth (the protocol of this module).

    Args:
        pairs: ``(gt, pred)`` per image: ``gt`` ``(H, W)`` metres (<= 0 = none),
            ``pred`` ``(h, w)`` (any size; resized to ``(H, W)``). May be a generator:
            one pair is held at a time.
        names: the image names (errors and rows); default ``image 0``, ``image 1``, ...
        sources: the ground-truth names for the rows (default: none).
        min_depth, max_depth, crop, median_scaling: see :func:`image_depth_errors`.
        progress: called as ``progress(done, name)`` after each image.

    Returns:
        :class:`DepthReport`.

    Raises:
        ValueError: bad settings.
        InputError: naming the image: not 2-D maps, no ground-truth pixel left in
            ``(min_depth, max_depth)`` and the crop, a prediction there that is not
            finite and > 0, fewer names than pairs; or no pair at all.
    """
    _check_settings(min_depth, max_depth, crop)
    rows: list[dict] = []
    ratios: list[float] = []
    for i, (gt, pred) in enumerate(pairs):
        if names is not None and i >= len(names):
            raise InputError(f"more depth pairs than names ({len(names)})")
        name = names[i] if names is not None else f"image {i}"
        try:
            row, valid = image_depth_errors(gt, pred, min_depth, max_depth, crop, median_scaling)
        except ValueError as exc:
            raise InputError(str(exc), name) from None
        if not valid:
            if row["n_pixels"] == 0:
                raise InputError(f"no ground-truth depth in ({min_depth:g}, {max_depth:g}) m inside the "
                                 f"{crop} crop" + (f" ({sources[i]})" if sources is not None else ""), name)
            raise InputError("the predicted depth is not finite and > 0 at every ground-truth pixel", name)
        rows.append({"name": name, "gt": sources[i] if sources is not None else None, **row})
        if row["ratio"] is not None:
            ratios.append(row["ratio"])
        if progress is not None:
            progress(i + 1, name)
    if not rows:
        raise InputError("no image to evaluate")
    mean = {k: float(np.mean([r[k] for r in rows])) for k in DEPTH_METRICS}
    return DepthReport(rows=tuple(rows), mean=mean, ratios=tuple(ratios), min_depth=float(min_depth),
                       max_depth=float(max_depth), crop=crop, median_scaling=bool(median_scaling))


# ---------------------------------------------------------------------------
# text outputs

def format_depth_report(report: DepthReport) -> str:
    """The table ``eval-depth`` prints: settings, scaling ratios, then the mean metrics."""
    r = report
    out = [f"depth: {r.n_images} image{'s' * (r.n_images != 1)}, ground truth in ({r.min_depth:g}, "
           f"{r.max_depth:g}) m, crop {r.crop}, median scaling {'on' if r.median_scaling else 'off'}, "
           "metrics averaged over images"]
    if r.median_scaling:
        out.append(f"scaling ratio: median {r.ratio_median:.4f}, std {r.ratio_std:.4f} "
                   f"(std of ratio / median {r.ratio_rel_std:.4f})")
    out.append("  " + " ".join(f"{METRIC_TITLES[k]:>10}" for k in DEPTH_METRICS))
    out.append("  " + " ".join(f"{r.mean[k]:>10.4f}" for k in DEPTH_METRICS))
    return "\n".join(out)


def depth_csv(report: DepthReport) -> str:
    """Per-image CSV: ``image,gt,n_pixels,ratio,abs_rel,...,a3`` (ratio empty without scaling)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["image", "gt", "n_pixels", "ratio", *DEPTH_METRICS])
    for row in report.rows:
        writer.writerow([row["name"], row["gt"] or "", row["n_pixels"],
                         "" if row["ratio"] is None else repr(row["ratio"]),
                         *(repr(row[k]) for k in DEPTH_METRICS)])
    return buf.getvalue()
