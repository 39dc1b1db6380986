"""What a training run writes to watch it: ``metrics.csv`` and TensorBoard event files.

``metrics.csv``: one row per logged iteration, columns ``iteration``, ``seconds`` (mean
wall time per iteration since the previous row), ``lr``, every loss term (weighted, as
summed into the total; means over the iterations since the previous row), ``total``,
``depth_failed`` (batches so far whose depth terms were zeroed because pose or
triangulation failed) and ``skipped`` (unreadable samples so far; both summed over the
processes), then the validation figures (``val_*``, filled on validation rows only). On ``--resume`` the file
is cut back to the checkpoint's iteration and continued, so the curve has no repeats.

TensorBoard (``tb/``): every column above as a scalar (``loss/<term>``, ``val/<name>``,
``lr``, ``time/iteration_s``), and images every ``schedule.image_every`` iterations: flow
colour, disparity, valid and rigid masks of the first pair of the batch.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

BASE_COLUMNS = ("iteration", "seconds", "lr")
TAIL_COLUMNS = ("total", "depth_failed", "skipped")


def truncate_metrics(path: Path, last_iteration: int) -> list[str] | None:
    """Keep the rows of ``path`` up to ``last_iteration`` (resume); returns its header (None: no file)."""
    if not path.is_file():
        return None
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    if not rows:
        return None
    header, body = rows[0], rows[1:]
    kept = [r for r in body if r and r[0].isdigit() and int(r[0]) <= last_iteration]
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(kept)
    tmp.replace(path)
    return header


class MetricsCSV:
    """Append-only ``metrics.csv`` with a fixed header (loss terms and validation names)."""

    def __init__(self, path: Path, terms: list[str], val_names: list[str], header: list[str] | None = None):
        self.path = Path(path)
        self.header = header or [*BASE_COLUMNS, *terms, *TAIL_COLUMNS, *(f"val_{n}" for n in val_names)]
        new = not self.path.is_file() or self.path.stat().st_size == 0
        self._f = open(self.path, "a", newline="")
        self._w = csv.writer(self._f)
        if new:
            self._w.writerow(self.header)
            self._f.flush()

    def write(self, row: dict) -> None:
        out = []
        for c in self.header:
            v = row.get(c, "")
            if isinstance(v, float):
                v = "" if not math.isfinite(v) else f"{v:.6g}"
            out.append(v)
        self._w.writerow(out)
        self._f.flush()

    def close(self) -> None:
        self._f.close()


def _disp_image(disp: np.ndarray) -> np.ndarray:
    """``(H, W)`` disparity -> ``(H, W, 3)`` uint8, magma-like via OpenCV's colormap."""
    import cv2

    d = disp.astype(np.float32)
    lo, hi = np.percentile(d, 1), np.percentile(d, 99)
    u8 = np.clip((d - lo) / max(hi - lo, 1e-9) * 255, 0, 255).astype(np.uint8)
    return cv2.cvtColor(cv2.applyColorMap(u8, cv2.COLORMAP_MAGMA), cv2.COLOR_BGR2RGB)


class TensorBoard:
    """A thin wrapper of ``torch.utils.tensorboard.SummaryWriter`` (needs the ``tensorboard`` package)."""

    def __init__(self, log_dir: Path, purge_step: int | None = None):
        from torch.utils.tensorboard import SummaryWriter

        self.w = SummaryWriter(str(log_dir), purge_step=purge_step)

    def scalars(self, it: int, values: dict[str, float], prefix: str) -> None:
        for k, v in values.items():
            if v is not None and math.isfinite(float(v)):
                self.w.add_scalar(f"{prefix}{k}", float(v), it)

    def images(self, it: int, visuals: dict) -> None:
        """``visuals``: tensors of the first pair: flow12 (2,H,W), disp1 (1,H,W), valid12 / rigid12 (1,H,W)."""
        from trianflow_vo.viz.flow_color import flow_to_rgb

        if "flow12" in visuals:
            rgb, _ = flow_to_rgb(visuals["flow12"].float().cpu().numpy().transpose(1, 2, 0))
            self.w.add_image("flow12", rgb, it, dataformats="HWC")
        if "disp1" in visuals:
            self.w.add_image("disparity1", _disp_image(visuals["disp1"].float().cpu().numpy()[0]), it,
                             dataformats="HWC")
        for name in ("valid12", "rigid12"):
            if name in visuals:
                m = visuals[name].float().cpu().clamp(0, 1).numpy()
                self.w.add_image(name, m, it, dataformats="CHW")

    def flush(self) -> None:
        self.w.flush()

    def close(self) -> None:
        self.w.close()
