"""Masks from forward/backward flow: forward-backward distance, score M_s, occlusion M_o."""

from __future__ import annotations

import cv2
import numpy as np


def _check_flow(flow: np.ndarray, name: str) -> None:
    if flow.ndim != 3 or flow.shape[2] != 2:
        raise ValueError(f"{name} must be (H, W, 2), got {flow.shape}")


def warp_by_flow(field: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """Sample ``field`` ``(H, W, C)`` at ``x + flow(x)`` (bilinear, border replicate)."""
    h, w = flow.shape[:2]
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    map_x = np.ascontiguousarray(gx + flow[..., 0])
    map_y = np.ascontiguousarray(gy + flow[..., 1])
    return cv2.remap(field, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def fb_distance(flow_fw: np.ndarray, flow_bw: np.ndarray) -> np.ndarray:
    """Forward-backward distance ``(H, W)``: ``|f(x) + b(x + f(x))|`` in pixels.

    Args:
        flow_fw: ``(H, W, 2)`` flow a -> b.
        flow_bw: ``(H, W, 2)`` flow b -> a.
    """
    _check_flow(flow_fw, "flow_fw")
    _check_flow(flow_bw, "flow_bw")
    bw_at_fw = warp_by_flow(np.ascontiguousarray(flow_bw, dtype=np.float32), flow_fw)
    d = flow_fw + bw_at_fw
    return np.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2)


def range_map(flow_bw: np.ndarray) -> np.ndarray:
    """How many pixels of frame b land on each pixel of frame a under ``flow_bw``
    (bilinear forward splatting, Wang et al. 2018). ``(H, W)`` float32."""
    _check_flow(flow_bw, "flow_bw")
    h, w = flow_bw.shape[:2]
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    x = (gx + flow_bw[..., 0]).ravel()
    y = (gy + flow_bw[..., 1]).ravel()
    x0 = np.floor(x)
    y0 = np.floor(y)
    idx_all, w_all = [], []
    for dx in (0, 1):
        for dy in (0, 1):
            xi = x0 + dx
            yi = y0 + dy
            wgt = (1.0 - np.abs(x - xi)) * (1.0 - np.abs(y - yi))
            ok = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
            idx_all.append(yi[ok].astype(np.int64) * w + xi[ok].astype(np.int64))
            w_all.append(wgt[ok])
    out = np.bincount(np.concatenate(idx_all), weights=np.concatenate(w_all), minlength=h * w)
    return out.reshape(h, w).astype(np.float32)


def occlusion_mask(flow_fw: np.ndarray, flow_bw: np.ndarray, range_threshold: float = 0.5,
                   downsample: int = 2) -> np.ndarray:
    """Validity mask M_o ``(H, W)`` float32 in {0, 1} for pixels of frame a.

    A pixel is valid when some pixel of b maps onto it (range map above
    ``range_threshold``) and its forward flow lands inside frame b. The range map
    is computed at ``1/downsample`` resolution (4x cheaper at 2; occluded regions
    are blobs, not single pixels) and upsampled by nearest neighbour.
    """
    h, w = flow_fw.shape[:2]
    if downsample > 1 and h % downsample == 0 and w % downsample == 0:
        small = cv2.resize(flow_bw, (w // downsample, h // downsample), interpolation=cv2.INTER_AREA) / downsample
        vis_small = (range_map(np.ascontiguousarray(small, dtype=np.float32)) > range_threshold).astype(np.uint8)
        visible = cv2.resize(vis_small, (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)
    else:
        visible = range_map(flow_bw) > range_threshold
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    xt = gx + flow_fw[..., 0]
    yt = gy + flow_fw[..., 1]
    inside = (xt >= 0) & (xt <= w - 1) & (yt >= 0) & (yt <= h - 1)
    return (visible & inside).astype(np.float32)


def flow_scores(flow_fw: np.ndarray, flow_bw: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(D_fb, M_s, M_o)``, each ``(H, W)`` float32, with ``M_s = 1 / (0.1 + D_fb)``."""
    d_fb = fb_distance(flow_fw, flow_bw).astype(np.float32)
    m_s = 1.0 / (0.1 + d_fb)
    m_o = occlusion_mask(flow_fw, flow_bw)
    return d_fb, m_s.astype(np.float32), m_o
