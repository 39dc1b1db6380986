"""Depth metrics (KITTI/Eigen protocol) and the ground-truth depth files.

Known answers first: identical depths, a doubled prediction with and without median
scaling (closed forms), a 2x2 case computed by hand for every metric (with the 1.25
threshold hit exactly), the crop rectangles at the KITTI size; then the protocol's
rules (invalid ground truth ignored, 80 m cap, clamping, resizing, ratios), then the
KITTI depth PNG and the ground-truth sources (folder, stacks, object arrays).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from trianflow_vo.errors import InputError
from trianflow_vo.eval.depth_metrics import (
    CROPS,
    DEPTH_METRICS,
    DepthReport,
    depth_csv,
    depth_errors,
    eigen_crop_mask,
    evaluate_depth,
    format_depth_report,
    image_depth_errors,
    resize_depth,
)
from trianflow_vo.io.depth_png import (
    decode_depth_png,
    encode_depth_png,
    open_gt_depth,
    read_depth_file,
    read_depth_png,
    write_depth_png,
)


def _gt(h=20, w=30, seed=0, lo=1.0, hi=30.0):
    return np.random.default_rng(seed).uniform(lo, hi, (h, w))


def _one(gt, pred, **kw):
    kw.setdefault("crop", "none")
    report = evaluate_depth([(gt, pred)], **kw)
    return report.mean, report


# --------------------------------------------------------------------------- closed forms


def test_identical_depths_are_perfect():
    gt = _gt()
    for scaling in (True, False):
        m, rep = _one(gt, gt.copy(), median_scaling=scaling)
        for k in ("abs_rel", "sq_rel", "rmse", "rmse_log"):
            assert m[k] == pytest.approx(0.0, abs=1e-12), k
        assert m["a1"] == m["a2"] == m["a3"] == 1.0
    assert rep.rows[0]["n_pixels"] == gt.size


def test_doubled_prediction_with_median_scaling_is_perfect():
    gt = _gt()
    m, rep = _one(gt, 2 * gt)
    assert m["abs_rel"] == pytest.approx(0.0, abs=1e-12)
    assert m["rmse"] == pytest.approx(0.0, abs=1e-10)
    assert m["a1"] == 1.0
    assert rep.ratios == (pytest.approx(0.5),)


def test_doubled_prediction_without_median_scaling_closed_form():
    gt = _gt()  # at most 30 m: 2 * gt stays below the 80 m clamp
    m, rep = _one(gt, 2 * gt, median_scaling=False)
    assert m["abs_rel"] == pytest.approx(1.0)
    assert m["sq_rel"] == pytest.approx(gt.mean())  # (gt - 2gt)^2 / gt = gt
    assert m["rmse"] == pytest.approx(math.sqrt((gt ** 2).mean()))
    assert m["rmse_log"] == pytest.approx(math.log(2.0))
    assert m["a1"] == m["a2"] == m["a3"] == 0.0  # ratio 2 > 1.25^3 = 1.953
    assert rep.ratios == () and rep.ratio_median is None and rep.rows[0]["ratio"] is None


def test_hand_computed_2x2():
    gt = np.array([[2.0, 4.0], [5.0, 10.0]])
    pred = np.array([[1.0, 4.0], [10.0, 8.0]])
    # gt - pred = 1, 0, -5, 2 ; max(gt/pred, pred/gt) = 2, 1, 2, 1.25
    want = {
        "abs_rel": (1 / 2 + 0 + 5 / 5 + 2 / 10) / 4,  # 0.425
        "sq_rel": (1 / 2 + 0 + 25 / 5 + 4 / 10) / 4,  # 1.475
        "rmse": math.sqrt((1 + 0 + 25 + 4) / 4),
        "rmse_log": math.sqrt((math.log(2) ** 2 + 0 + math.log(2) ** 2 + math.log(1.25) ** 2) / 4),
        "a1": 0.25,  # only the exact pixel: 1.25 is not < 1.25
        "a2": 0.5,  # 1 and 1.25 < 1.5625
        "a3": 0.5,  # 2 is not < 1.953125
    }
    got = depth_errors(gt, pred)
    assert set(got) == set(DEPTH_METRICS)
    for k, v in want.items():
        assert got[k] == pytest.approx(v, rel=1e-12), k
    m, _ = _one(gt, pred, median_scaling=False)
    for k, v in want.items():
        assert m[k] == pytest.approx(v, rel=1e-12), k
    # median scaling: median(gt) = 4.5, median(pred) = 6 -> ratio 0.75
    _, rep = _one(gt, pred)
    assert rep.rows[0]["ratio"] == pytest.approx(0.75)
    assert rep.mean["abs_rel"] == pytest.approx(depth_errors(gt, 0.75 * pred)["abs_rel"])


def test_depth_errors_rejects_bad_input():
    with pytest.raises(ValueError, match="same shape"):
        depth_errors(np.ones(3), np.ones(4))
    with pytest.raises(ValueError, match="no depth"):
        depth_errors(np.ones(0), np.ones(0))
    with pytest.raises(ValueError, match="finite and > 0"):
        depth_errors(np.array([1.0, 0.0]), np.array([1.0, 1.0]))


# --------------------------------------------------------------------------- crops


def test_crop_rectangles_at_kitti_size():
    h, w = 375, 1242
    garg = eigen_crop_mask(h, w, "garg")
    # rows int(0.40810811*375)=153 .. int(0.99189189*375)=371; columns int(0.03594771*1242)=44 .. 1197
    rows, cols = np.nonzero(garg)
    assert (rows.min(), rows.max() + 1, cols.min(), cols.max() + 1) == (153, 371, 44, 1197)
    assert garg.sum() == 218 * 1153
    eigen = eigen_crop_mask(h, w, "eigen")
    # rows int(0.3324324*375)=124 .. int(0.91351351*375)=342
    rows, cols = np.nonzero(eigen)
    assert (rows.min(), rows.max() + 1, cols.min(), cols.max() + 1) == (124, 342, 44, 1197)
    assert eigen_crop_mask(h, w, "none").all()
    # fractions of the area: (0.99189189 - 0.40810811) * (0.96405229 - 0.03594771) = 0.5418, a bit
    # less after truncation to whole pixels (218 * 1153 / (375 * 1242) = 0.5397)
    assert garg.mean() == pytest.approx(0.5418, abs=3e-3)
    assert eigen.mean() == pytest.approx((0.91351351 - 0.3324324) * 0.92810458, abs=3e-3)
    assert set(CROPS) == {"garg", "eigen", "none"}
    with pytest.raises(ValueError, match="crop must be one of"):
        eigen_crop_mask(h, w, "monodepth")


def test_crop_excludes_pixels_outside():
    h, w = 100, 200
    gt = np.full((h, w), 10.0)
    pred = gt.copy()
    pred[:30] = 1.0  # wrong only above the garg crop (starts at row 40)
    m, _ = _one(gt, pred, crop="garg", median_scaling=False)
    assert m["abs_rel"] == 0.0
    m, _ = _one(gt, pred, crop="none", median_scaling=False)
    assert m["abs_rel"] == pytest.approx(0.3 * 0.9)


# --------------------------------------------------------------------------- protocol rules


def test_invalid_ground_truth_is_ignored():
    gt = _gt()
    pred = 1.5 * gt
    bad = gt.copy()
    bad[::3, ::2] = 0.0
    bad[1, 1] = np.nan
    bad[2, 5] = -4.0
    keep = np.isfinite(bad) & (bad > 0)
    m, rep = _one(bad, np.where(keep, pred, 1e-6), median_scaling=False)  # garbage where gt is invalid
    want = depth_errors(gt[keep], pred[keep])
    for k in DEPTH_METRICS:
        assert m[k] == pytest.approx(want[k], rel=1e-12), k
    assert rep.rows[0]["n_pixels"] == keep.sum()


def test_cap_at_80_m_and_clamp():
    gt = np.full((10, 10), 40.0)
    gt[0] = 80.0  # not < 80: excluded
    gt[1] = 120.0  # beyond the cap: excluded
    pred = np.full((10, 10), 200.0)
    m, rep = _one(gt, pred, median_scaling=False)
    assert rep.rows[0]["n_pixels"] == 80
    assert m["abs_rel"] == pytest.approx(1.0)  # prediction clamped to 80 against 40
    m, rep = _one(gt, pred, median_scaling=False, max_depth=50.0)
    assert m["abs_rel"] == pytest.approx(0.25)  # clamped to 50
    m, _ = _one(gt, np.full((10, 10), 1e-6), median_scaling=False, min_depth=1.0)
    assert m["abs_rel"] == pytest.approx(39.0 / 40.0)  # clamped up to min_depth = 1


def test_prediction_resized_to_ground_truth_size():
    gt = np.full((60, 80), 10.0)
    m, rep = _one(gt, np.full((15, 20), 5.0), median_scaling=False)
    assert m["abs_rel"] == pytest.approx(0.5)
    m, rep = _one(gt, np.full((15, 20), 5.0))
    assert m["abs_rel"] == pytest.approx(0.0, abs=1e-7) and rep.rows[0]["n_pixels"] == 60 * 80
    # a horizontal ramp at half resolution: bilinear resize keeps it linear away from the borders
    x = np.arange(40, dtype=np.float32)
    small = np.tile(1.0 + x, (10, 1))
    big = resize_depth(small, (20, 80))
    assert big.shape == (20, 80) and big.dtype == np.float32
    np.testing.assert_allclose(big[:, 2:-2], np.tile(1.0 + (np.arange(80) - 0.5) / 2, (20, 1))[:, 2:-2], atol=1e-5)


def test_scale_invariance_with_median_scaling_and_noise():
    rng = np.random.default_rng(3)
    gt = _gt(seed=3)
    pred = gt * np.exp(rng.normal(0, 0.1, gt.shape))
    a, ra = _one(gt, pred)
    b, rb = _one(gt, 7.0 * pred)
    for k in DEPTH_METRICS:
        assert a[k] == pytest.approx(b[k], rel=1e-9), k
    assert rb.ratios[0] == pytest.approx(ra.ratios[0] / 7.0)
    assert 0.05 < a["abs_rel"] < 0.15 and 0.5 < a["a1"] < 1.0  # ~10% log-normal noise


def test_mean_over_images_and_ratio_statistics():
    g1, g2 = _gt(seed=1), _gt(h=10, w=10, seed=2)
    pred1, pred2 = 2.0 * g1, 4.0 * g2 * np.where(np.arange(100).reshape(10, 10) % 2, 1.1, 1.0)
    rep = evaluate_depth([(g1, pred1), (g2, pred2)], ["a.png", "b.png"], crop="none")
    per = [r["abs_rel"] for r in rep.rows]
    assert per[0] == pytest.approx(0.0, abs=1e-12) and per[1] > 0.01
    assert rep.mean["abs_rel"] == pytest.approx(sum(per) / 2)  # images weigh the same, not pixels
    r1, r2 = rep.ratios
    assert r1 == pytest.approx(0.5)
    assert rep.ratio_median == pytest.approx((r1 + r2) / 2)
    assert rep.ratio_std == pytest.approx(abs(r1 - r2) / 2)
    assert rep.ratio_rel_std == pytest.approx(abs(r1 - r2) / 2 / ((r1 + r2) / 2))
    d = rep.to_dict()
    assert d["n_images"] == 2 and d["median_scaling"]["ratio_median"] == rep.ratio_median
    assert d["settings"]["crop"] == "none"
    text = format_depth_report(rep)
    assert "2 images" in text and "d<1.25" in text and "median" in text
    lines = depth_csv(rep).splitlines()
    assert lines[0].split(",") == ["image", "gt", "n_pixels", "ratio", *DEPTH_METRICS]
    assert lines[1].startswith("a.png,,") and len(lines) == 3
    assert float(lines[2].split(",")[4]) == rep.rows[1]["abs_rel"]


def test_generator_input_and_progress():
    calls = []
    gen = ((g, 3 * g) for g in (_gt(seed=s) for s in range(3)))
    rep = evaluate_depth(gen, ["x", "y", "z"], crop="none", progress=lambda done, name: calls.append((done, name)))
    assert isinstance(rep, DepthReport) and rep.n_images == 3
    assert calls == [(1, "x"), (2, "y"), (3, "z")]


def test_errors_name_the_image():
    gt = np.zeros((10, 10))
    with pytest.raises(InputError, match=r"^b\.png: no ground-truth depth in \(0\.001, 80\) m inside the none crop"):
        evaluate_depth([(_gt(), _gt()), (gt, _gt(h=10, w=10))], ["a.png", "b.png"], crop="none")
    pred = _gt()
    pred[3, 3] = np.nan
    with pytest.raises(InputError, match=r"^a\.png: the predicted depth is not finite"):
        evaluate_depth([(_gt(), pred)], ["a.png"], crop="none")
    with pytest.raises(InputError, match="a.png: gt and pred must be non-empty 2-D"):
        evaluate_depth([(np.ones((2, 2, 2)), np.ones((2, 2)))], ["a.png"])
    with pytest.raises(InputError, match="no image to evaluate"):
        evaluate_depth([])
    with pytest.raises(ValueError, match="min_depth < max_depth"):
        evaluate_depth([(_gt(), _gt())], min_depth=10, max_depth=5)
    with pytest.raises(ValueError, match="crop must be one of"):
        image_depth_errors(_gt(), _gt(), crop="bad")
    row, valid = image_depth_errors(np.zeros((4, 4)), np.ones((4, 4)))
    assert not valid and row["n_pixels"] == 0 and math.isnan(row["abs_rel"])


# --------------------------------------------------------------------------- KITTI depth PNG


def test_depth_png_round_trip_and_layout(tmp_path):
    depth = _gt(seed=4, lo=0.5, hi=90.0).astype(np.float32)
    depth[0, :5] = 0.0
    depth[1, 0] = np.nan
    p = write_depth_png(tmp_path / "d.png", depth)
    raw = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16 and raw.shape == depth.shape
    assert raw[2, 3] == round(float(depth[2, 3]) * 256)
    assert raw[0, 0] == 0 and raw[1, 0] == 0
    back = read_depth_png(p)
    assert back.dtype == np.float32
    ok = np.isfinite(depth) & (depth > 0)
    assert np.abs(back[ok] - depth[ok]).max() <= 0.5 / 256 + 1e-6
    assert (back[~ok] == 0).all()
    assert list(tmp_path.iterdir()) == [p]


def test_depth_png_hand_made_values(tmp_path):
    raw = np.array([[0, 256, 512], [1, 20480, 65535]], dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "d.png"), raw)
    np.testing.assert_array_equal(read_depth_png(tmp_path / "d.png"),
                                  np.array([[0, 1, 2], [1 / 256, 80, 65535 / 256]], dtype=np.float32))


def test_depth_png_errors(tmp_path):
    with pytest.raises(InputError, match="nope.png: no such file"):
        read_depth_png(tmp_path / "nope.png")
    cv2.imwrite(str(tmp_path / "u8.png"), np.zeros((4, 4), np.uint8))
    with pytest.raises(InputError, match="u8.png: not a KITTI depth PNG: uint8"):
        read_depth_png(tmp_path / "u8.png")
    cv2.imwrite(str(tmp_path / "rgb16.png"), np.zeros((4, 4, 3), np.uint16))
    with pytest.raises(InputError, match="rgb16.png: not a KITTI depth PNG: uint16 with 3 channel"):
        read_depth_png(tmp_path / "rgb16.png")
    data = encode_depth_png(np.ones((30, 40)))
    with pytest.raises(InputError, match="cut.png: cannot decode"):
        decode_depth_png(data[: len(data) // 2], "cut.png")
    with pytest.raises(InputError, match="x.tiff: unknown ground-truth depth format"):
        read_depth_file(tmp_path / "x.tiff")


# --------------------------------------------------------------------------- ground-truth sources


def _images(tmp_path, stems):
    d = tmp_path / "img"
    d.mkdir(exist_ok=True)
    return [d / f"{s}.png" for s in stems]


def test_gt_folder_matched_by_stem(tmp_path):
    images = _images(tmp_path, ["0000000005", "0000000010"])
    gt = tmp_path / "gt"
    gt.mkdir()
    write_depth_png(gt / "0000000010.png", np.full((4, 5), 10.0))
    np.save(gt / "0000000005.npy", np.full((4, 5), 5.0, np.float64))
    srcs = open_gt_depth(gt, images)
    assert [s for s, _ in srcs] == [str(gt / "0000000005.npy"), str(gt / "0000000010.png")]
    assert srcs[0][1]().dtype == np.float32
    assert srcs[0][1]()[0, 0] == 5.0 and srcs[1][1]()[0, 0] == 10.0
    (gt / "0000000005.npy").unlink()
    with pytest.raises(InputError, match=r"0000000005.png: no ground-truth depth for this image "
                                         r"\(looked for 0000000005.png and 0000000005.npy"):
        open_gt_depth(gt, images)


def test_gt_stacks(tmp_path):
    images = _images(tmp_path, ["a", "b", "c"])
    stack = np.stack([np.full((4, 5), float(i + 1)) for i in range(3)]).astype(np.float32)
    stack[2, 0, 0] = np.inf
    np.savez(tmp_path / "gt_depths.npz", data=stack)
    np.savez(tmp_path / "other_key.npz", depths=stack)
    np.save(tmp_path / "stack.npy", stack)
    for f in ("gt_depths.npz", "other_key.npz", "stack.npy"):
        srcs = open_gt_depth(tmp_path / f, images)
        assert [s for s, _ in srcs] == [f"{tmp_path / f}[{i}]" for i in range(3)]
        assert [float(load()[1, 1]) for _, load in srcs] == [1.0, 2.0, 3.0]
        assert srcs[2][1]()[0, 0] == 0.0  # non-finite = no ground truth
    with pytest.raises(InputError, match=r"stack.npy: holds 3 depth map\(s\) for 2 image\(s\)"):
        open_gt_depth(tmp_path / "stack.npy", images[:2])
    np.savez(tmp_path / "two.npz", a=stack, b=stack)
    with pytest.raises(InputError, match="two.npz: no array named 'data'"):
        open_gt_depth(tmp_path / "two.npz", images)
    one = tmp_path / "one.npy"
    np.save(one, stack[0])
    assert open_gt_depth(one, images[:1])[0][1]().shape == (4, 5)


def test_gt_object_array_needs_allow_pickle(tmp_path):
    """The Eigen-split gt_depths.npz: maps of several sizes in an object array."""
    images = _images(tmp_path, ["a", "b"])
    maps = np.empty(2, dtype=object)
    maps[0], maps[1] = np.full((4, 5), 3.0), np.full((6, 7), 4.0)
    np.savez(tmp_path / "gt_depths.npz", data=maps)
    with pytest.raises(InputError, match="gt_depths.npz: holds Python objects.*--allow-pickle"):
        open_gt_depth(tmp_path / "gt_depths.npz", images)
    srcs = open_gt_depth(tmp_path / "gt_depths.npz", images, allow_pickle=True)
    assert [load().shape for _, load in srcs] == [(4, 5), (6, 7)]


def test_gt_source_errors(tmp_path):
    images = _images(tmp_path, ["a", "b"])
    with pytest.raises(InputError, match="missing.npz: no such file or folder"):
        open_gt_depth(tmp_path / "missing.npz", images)
    (tmp_path / "gt.txt").write_text("1 2 3\n")
    with pytest.raises(InputError, match="gt.txt: unknown ground-truth depth"):
        open_gt_depth(tmp_path / "gt.txt", images)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="junk.npz: not a readable"):
        open_gt_depth(tmp_path / "junk.npz", images)
    np.save(tmp_path / "s4.npy", np.zeros((2, 3, 4, 5)))
    with pytest.raises(InputError, match=r"s4.npy: expected \(N, H, W\) depth maps"):
        open_gt_depth(tmp_path / "s4.npy", images)
