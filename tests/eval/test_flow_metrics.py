"""Flow metrics: EPE and Fl-all on known answers, the outlier thresholds' edges, resizing,
and the two averagings (over pairs, over pixels)."""

from __future__ import annotations

import numpy as np
import pytest

from trianflow_vo.errors import InputError
from trianflow_vo.eval.flow_metrics import (
    FL_ABS_PX,
    FL_REL,
    FlowReport,
    epe_map,
    evaluate_flow,
    fl_all,
    flow_csv,
    flow_errors,
    format_flow_report,
    outlier_mask,
    resize_flow,
)


def _flow(h=12, w=16, seed=0, scale=0.5):
    return np.random.default_rng(seed).uniform(-scale, scale, (h, w, 2)).astype(np.float32)


def _all(shape):
    return np.ones(shape[:2], dtype=bool)


def test_identical_flow_is_perfect():
    gt = _flow(scale=20)
    e = flow_errors(gt, _all(gt.shape), gt.copy())
    assert e["epe"] == 0.0 and e["fl_all"] == 0.0 and e["n_outliers"] == 0
    assert e["n_valid"] == gt.shape[0] * gt.shape[1]


def test_constant_4px_error_small_gt():
    gt = _flow(scale=0.5)  # |gt| < 0.71 px: 4 px is far more than 5% of it
    rng = np.random.default_rng(1)
    theta = rng.uniform(0, 2 * np.pi, gt.shape[:2])
    pred = gt.astype(np.float64) + 4.0 * np.stack([np.cos(theta), np.sin(theta)], axis=2)
    e = flow_errors(gt, _all(gt.shape), pred)
    assert e["epe"] == pytest.approx(4.0, abs=1e-6)
    assert e["fl_all"] == 100.0
    assert fl_all(gt, _all(gt.shape), pred) == 100.0
    np.testing.assert_allclose(epe_map(gt, pred), 4.0, atol=1e-6)


def test_outlier_threshold_edges():
    # one row per case: (gt u, pred u) with v = 0, so EPE = |pred - gt| exactly
    cases = [
        ((0.0, 3.0), False),  # EPE = 3 is not > 3
        ((0.0, 3.0 + 1e-6), True),  # just above 3 px, |gt| = 0
        ((100.0, 105.0), False),  # EPE 5 = 5% of 100, not > 5%
        ((100.0, 105.01), True),  # just above 5%
        ((100.0, 104.0), False),  # > 3 px but only 4%
        ((40.0, 42.9), False),  # 7% but < 3 px
        ((60.0, 63.0), False),  # both edges at once: 3 px and exactly 5% of 60
        ((60.0, 63.5), True),
    ]
    gt = np.zeros((1, len(cases), 2))
    pred = np.zeros_like(gt)
    for i, ((g, p), _) in enumerate(cases):
        gt[0, i, 0], pred[0, i, 0] = g, p
    got = outlier_mask(epe_map(gt, pred), gt)[0]
    assert got.tolist() == [want for _, want in cases]
    e = flow_errors(gt, np.ones((1, len(cases)), bool), pred)
    assert e["n_outliers"] == 3 and e["fl_all"] == pytest.approx(100 * 3 / len(cases))
    assert (FL_ABS_PX, FL_REL) == (3.0, 0.05)


def test_invalid_pixels_ignored():
    gt = _flow(scale=10)
    valid = np.random.default_rng(2).random(gt.shape[:2]) < 0.4
    pred = gt.copy()
    pred[~valid] += 1000.0  # garbage where there is no ground truth
    pred[valid] += np.array([0.0, 1.0], np.float32)
    e = flow_errors(gt, valid, pred)
    assert e["epe"] == pytest.approx(1.0, abs=1e-5) and e["fl_all"] == 0.0
    assert e["n_valid"] == valid.sum()
    assert e["epe_sum"] == pytest.approx(valid.sum(), rel=1e-5)


def test_resize_flow_scales_values():
    flow = np.empty((4, 6, 2), np.float32)
    flow[..., 0], flow[..., 1] = 2.0, 1.0
    out = resize_flow(flow, (8, 18))  # x3 wide, x2 high
    assert out.shape == (8, 18, 2) and out.dtype == np.float32
    np.testing.assert_allclose(out[..., 0], 6.0)
    np.testing.assert_allclose(out[..., 1], 2.0)
    down = resize_flow(out, (4, 6))
    np.testing.assert_allclose(down, flow, atol=1e-6)
    same = resize_flow(flow, (4, 6))
    np.testing.assert_array_equal(same, flow)
    assert same is not flow
    with pytest.raises(ValueError, match=r"\(H, W, 2\)"):
        resize_flow(np.zeros((4, 6, 3)), (8, 8))


def test_evaluate_flow_resizes_prediction_to_gt():
    gt = np.empty((20, 40, 2), np.float32)
    gt[..., 0], gt[..., 1] = 4.0, -2.0
    pred = np.empty((10, 10, 2), np.float32)  # half height, quarter width: values halved/quartered
    pred[..., 0], pred[..., 1] = 1.0, -1.0
    rep = evaluate_flow([(gt, _all(gt.shape), pred)], ["p"])
    assert rep.epe == pytest.approx(0.0, abs=1e-6) and rep.fl_all == 0.0


def test_mean_over_pairs_vs_over_pixels():
    gt_a = np.zeros((2, 2, 2))
    valid_a = np.array([[True, False], [False, False]])  # 1 pixel, EPE 10 (outlier)
    pred_a = gt_a.copy()
    pred_a[..., 0] = 10.0
    gt_b = np.zeros((1, 3, 2))  # 3 pixels, EPE 0
    rep = evaluate_flow([(gt_a, valid_a, pred_a), (gt_b, _all(gt_b.shape), gt_b.copy())], ["a", "b"],
                        sources=["a.png", "b.png"])
    assert isinstance(rep, FlowReport) and rep.n_pairs == 2 and rep.n_valid == 4
    assert rep.epe == pytest.approx(5.0) and rep.fl_all == pytest.approx(50.0)  # per pair, then the mean
    assert rep.epe_pooled == pytest.approx(2.5) and rep.fl_all_pooled == pytest.approx(25.0)  # all pixels
    d = rep.to_dict()
    assert d["metrics"] == {"epe": 5.0, "fl_all": 50.0, "epe_pooled": 2.5, "fl_all_pooled": 25.0}
    assert "KITTI 2015 devkit" in d["definitions"]["fl_all_pooled"]
    text = format_flow_report(rep)
    assert "2 pairs" in text and "5.0000" in text and "25.0000" in text
    lines = flow_csv(rep).splitlines()
    assert lines == ["pair,gt,n_valid,n_outliers,epe,fl_all", "a,a.png,1,1,10.0,100.0", "b,b.png,3,0,0.0,0.0"]


def test_noise_gives_expected_epe():
    rng = np.random.default_rng(5)
    gt = _flow(h=200, w=200, scale=30)
    pred = gt + rng.normal(0, 1.0, gt.shape).astype(np.float32)
    e = flow_errors(gt, _all(gt.shape), pred)
    assert e["epe"] == pytest.approx(np.sqrt(np.pi / 2), rel=0.02)  # Rayleigh mean, sigma 1
    # outliers: EPE > 3 (P = exp(-4.5) = 1.1%) and > 5% of |gt| (true for most of them)
    assert 0.5 < e["fl_all"] < 1.2


def test_errors_name_the_pair():
    gt = _flow()
    with pytest.raises(InputError, match=r"^b: no valid ground-truth pixel \(b\.png\)"):
        evaluate_flow([(gt, _all(gt.shape), gt), (gt, np.zeros(gt.shape[:2], bool), gt)], ["a", "b"],
                      sources=["a.png", "b.png"])
    bad = gt.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(InputError, match="^a: the flow is not finite"):
        evaluate_flow([(gt, _all(gt.shape), bad)], ["a"])
    with pytest.raises(InputError, match=r"^a: ground-truth flow must be \(H, W, 2\)"):
        evaluate_flow([(gt[..., 0], _all(gt.shape), gt)], ["a"])
    with pytest.raises(InputError, match="no image pair"):
        evaluate_flow([])
    with pytest.raises(ValueError, match="same shape"):
        epe_map(gt, gt[:-1])
    with pytest.raises(ValueError, match="valid must be"):
        flow_errors(gt, np.ones((3, 3), bool), gt)
