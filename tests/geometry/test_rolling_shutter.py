"""Rolling-shutter pixels moved to the middle row's instant (``geometry/rolling_shutter``)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from trianflow_vo.geometry.rolling_shutter import dense_inverse_depth, row_time, to_global_shutter, twist_per_frame

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
H = 480


def _scene(n: int = 400, seed: int = 0) -> np.ndarray:
    """``(n, 3)`` points in front of the camera at the middle row's instant, 1-5 m deep."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(1.0, 5.0, n)
    uv = np.c_[rng.uniform(20, 620, n), rng.uniform(20, 460, n)]
    return np.c_[(uv - K[:2, 2]) / 500.0 * z[:, None], z]


def _rolling_pixels(X0: np.ndarray, readout: float, omega: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Where a rolling shutter sees the points ``X0``: the camera at time ``tau`` is rotated by
    ``exp(tau omega)`` and displaced by ``tau v`` (exactly, not to first order), and a point is
    seen at the time of the row it projects to (found by fixed-point iteration)."""
    tau = np.zeros(len(X0))
    for _ in range(30):
        out = np.empty((len(X0), 2))
        for i, (X, t) in enumerate(zip(X0, tau)):
            R = cv2.Rodrigues(t * omega)[0]
            Xt = R.T @ (X - t * v)
            x = K @ Xt
            out[i] = x[:2] / x[2]
        tau = row_time(out[:, 1], H, readout)
    return out


def _global(X0: np.ndarray) -> np.ndarray:
    x = X0 @ K.T
    return x[:, :2] / x[:, 2:]


def test_row_time_is_zero_at_the_middle_row_and_spans_the_readout():
    t = row_time(np.array([0.0, (H - 1) / 2, H - 1.0]), H, 0.5)
    assert t[1] == 0.0
    assert t[2] - t[0] == pytest.approx(0.5 * (H - 1) / H)


def test_rotation_and_translation_are_undone_to_second_order():
    X0 = _scene()
    omega, v, readout = np.array([0.01, -0.03, 0.005]), np.array([0.02, -0.01, 0.015]), 0.6
    seen = _rolling_pixels(X0, readout, omega, v)
    truth = _global(X0)
    before = np.abs(seen - truth).max()
    assert before > 2.0  # the shutter moves the outer rows by pixels
    fixed = to_global_shutter(seen, K, H, readout, omega, v, 1.0 / X0[:, 2])
    assert np.abs(fixed - truth).max() < 0.1
    # rotation only leaves the translation's share (about f tau |v| / z)
    rot_only = to_global_shutter(seen, K, H, readout, omega)
    assert 0.3 < np.abs(rot_only - truth).max() < before


def test_pure_rotation_needs_no_depth():
    X0 = _scene(seed=1)
    omega = np.array([0.0, 0.04, 0.0])
    seen = _rolling_pixels(X0, 1.0, omega, np.zeros(3))
    assert np.abs(seen - _global(X0)).max() > 5.0
    assert np.abs(to_global_shutter(seen, K, H, 1.0, omega) - _global(X0)).max() < 0.1


def test_global_shutter_and_empty_input_are_returned_unchanged():
    pts = np.array([[10.0, 20.0], [300.0, 400.0]])
    out = to_global_shutter(pts, K, H, 0.0, np.array([0.1, 0.2, 0.3]))
    assert np.array_equal(out, pts) and out is not pts
    assert to_global_shutter(np.zeros((0, 2)), K, H, 0.5, np.zeros(3)).shape == (0, 2)


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        to_global_shutter(np.zeros((3, 3)), K, H, 0.5, np.zeros(3))


def test_twist_per_frame_is_the_rotation_vector_and_the_step_per_interval():
    T = np.eye(4)
    rv = np.array([0.02, -0.05, 0.01])
    T[:3, :3] = cv2.Rodrigues(rv)[0]
    T[:3, 3] = [0.3, -0.6, 0.9]
    omega, v = twist_per_frame(T, 3.0)
    assert np.allclose(omega, rv / 3.0, atol=1e-12)
    assert np.allclose(v, [0.1, -0.2, 0.3])
    omega0, v0 = twist_per_frame(np.eye(4), 1.0)
    assert np.array_equal(omega0, np.zeros(3)) and np.array_equal(v0, np.zeros(3))


def test_dense_inverse_depth_fills_a_slanted_plane_from_sparse_samples():
    h, w = 120, 160
    gy = np.arange(h, dtype=np.float64)[:, None] * np.ones((1, w))
    inv_true = 1.0 / (1.0 + gy / 40.0)  # a floor: depth 1 m at the top row to 4 m at the bottom
    rng = np.random.default_rng(0)
    depth = np.zeros((h, w))
    keep = rng.random((h, w)) < 0.03
    keep[60:, 100:] = False  # a corner without any depth
    depth[keep] = 1.0 / inv_true[keep]
    inv = dense_inverse_depth(depth, cell_px=16)
    assert np.array_equal(inv[keep], inv_true[keep])  # measured pixels keep their own depth
    rel = np.abs(inv / inv_true - 1.0)
    assert np.median(rel) < 0.05 and rel[:60].max() < 0.25
    assert np.all(np.isfinite(inv)) and np.all(inv > 0)
    assert rel[60:, 100:].max() < 0.5  # filled from its neighbours, not left empty


def test_dense_inverse_depth_needs_some_depth():
    with pytest.raises(ValueError, match="no pixel"):
        dense_inverse_depth(np.zeros((8, 8)))
    with pytest.raises(ValueError, match=r"\(h, w\)"):
        dense_inverse_depth(np.zeros(8))
