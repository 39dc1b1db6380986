"""Weight-free dense flow: OpenCV's DIS optical flow (Kroeger et al. 2016)."""

from __future__ import annotations

import cv2
import numpy as np

# name -> (OpenCV preset, overrides). "fine" runs the medium preset down to full
# resolution (finest scale 0) with variational refinement; see benchmarks/README.md.
DIS_PRESETS = {
    "fast": (cv2.DISOPTICAL_FLOW_PRESET_FAST, {}),
    "medium": (cv2.DISOPTICAL_FLOW_PRESET_MEDIUM, {}),
    "fine": (cv2.DISOPTICAL_FLOW_PRESET_MEDIUM, {"FinestScale": 0}),
}


class DisFlow:
    """:class:`vo.flow.base.FlowSource` backed by ``cv2.DISOpticalFlow``."""

    name = "dis"

    def __init__(self, preset: str = "medium"):
        if preset not in DIS_PRESETS:
            raise ValueError(f"unknown DIS preset {preset!r}; choose from {sorted(DIS_PRESETS)}")
        self.preset = preset
        base, overrides = DIS_PRESETS[preset]
        self._dis = cv2.DISOpticalFlow.create(base)
        for key, value in overrides.items():
            getattr(self._dis, "set" + key)(value)

    def clone(self) -> DisFlow:
        """A second source with the same settings (one DIS object serves one thread at a time)."""
        return DisFlow(self.preset)

    def prepare(self, image: np.ndarray) -> np.ndarray:
        """Grey ``(h, w)`` uint8, contiguous (DIS requires it), from ``(h, w, 3)`` BGR."""
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        return np.ascontiguousarray(image)

    def flow_pair(self, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        fw = self._dis.calc(a, b, None)
        bw = self._dis.calc(b, a, None)
        return fw, bw

    def describe(self) -> dict:
        return {
            "name": self.name,
            "preset": self.preset,
            "finest_scale": int(self._dis.getFinestScale()),
            "patch_size": int(self._dis.getPatchSize()),
            "patch_stride": int(self._dis.getPatchStride()),
            "gradient_descent_iterations": int(self._dis.getGradientDescentIterations()),
            "variational_refinement_iterations": int(self._dis.getVariationalRefinementIterations()),
        }
