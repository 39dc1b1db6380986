"""Frozen run configuration. The CLI builds one; library users may too."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class RunConfig:
    """Everything ``vo.pipeline.run`` needs. Paths are not resolved here."""

    seq: Path
    out_dir: Path
    # frame selection
    start: int = 0
    end: int | None = None  # exclusive source index; None = to the end
    stride: int = 1
    # camera
    intrinsics: tuple[float, float, float, float] | None = None  # fx, fy, cx, cy at source resolution
    calib: Path | None = None
    size: tuple[int, int] | None = None  # working (h, w); None = automatic
    # models (None = weight-free: OpenCV DIS flow, depth from triangulation)
    flow_model: Path | None = None
    depth_model: Path | None = None
    threads: int = 2
    # method parameters
    seed: int = 0
    n_samples: int = 6000
    top_ratio: float = 0.2
    dis_preset: str = "medium"
    ransac_threshold_px: float = 0.25
    refine: bool = True
    min_parallax_px: float = 3.0
    min_flow_px: float = 5.0
    min_inliers: int = 100
    ransac_method: str = "ransac"
    depth_fusion: bool = True
    depth_decay: float = 0.8
    pnp_check_ratio: float = 1.5
    # outputs
    rerun: Path | None = None
    rerun_spawn: bool = False
    gt: Path | None = None
    plot: bool = True
    quiet: bool = False

    def to_dict(self) -> dict:
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            out[f.name] = str(v) if isinstance(v, Path) else (list(v) if isinstance(v, tuple) else v)
        return out
