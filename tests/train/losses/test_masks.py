"""Visibility by forward splatting, forward-backward consistency and the score: known answers."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch", reason="needs torch (pip install 'trianflow-vo[train]')")

from trianflow_vo.errors import InputError  # noqa: E402
from trianflow_vo.train.losses.masks import (fb_consistency, fb_difference, score_map,  # noqa: E402
                                             splat_counts, splat_visibility, valid_mask)

H, W = 8, 16


def _uniform(dx, dy=0.0, n=1, h=H, w=W):
    f = torch.zeros(n, 2, h, w, dtype=torch.float64)
    f[:, 0] = dx
    f[:, 1] = dy
    return f


def test_zero_flow_is_visible_everywhere():
    v = splat_visibility(_uniform(0.0))
    assert v.shape == (1, 1, H, W)
    assert torch.equal(v, torch.ones_like(v))


@pytest.mark.parametrize("k", [1, 3])
def test_shift_right_leaves_the_first_columns_unseen(k):
    v = splat_visibility(_uniform(float(k)))[0, 0]
    assert torch.equal(v[:, :k], torch.zeros(H, k, dtype=v.dtype))
    assert torch.equal(v[:, k:], torch.ones(H, W - k, dtype=v.dtype))


def test_shift_up_leaves_the_last_rows_unseen():
    v = splat_visibility(_uniform(0.0, -2.0))[0, 0]
    assert torch.equal(v[-2:], torch.zeros(2, W, dtype=v.dtype))
    assert torch.equal(v[:-2], torch.ones(H - 2, W, dtype=v.dtype))


def test_half_pixel_shift_spreads_bilinear_weights():
    c = splat_counts(_uniform(0.5))[0, 0]
    assert torch.allclose(c[:, 0], torch.full((H,), 0.5, dtype=c.dtype))  # only pixel 0's left half
    assert torch.allclose(c[:, 1:], torch.ones(H, W - 1, dtype=c.dtype))  # last column: half of W-1 is lost


def test_two_pixels_landing_on_one_spot_are_clamped():
    f = _uniform(0.0)
    f[0, 0, 3, 5] = 1.0  # pixel (x=5, y=3) moves onto (6, 3), which also keeps its own
    c = splat_counts(f)[0, 0]
    v = splat_visibility(f)[0, 0]
    assert c[3, 6].item() == pytest.approx(2.0)
    assert v[3, 6].item() == 1.0
    assert v[3, 5].item() == 0.0  # nothing lands where the pixel left
    assert v.sum().item() == H * W - 1


def test_batches_do_not_leak_into_each_other_and_outside_targets_vanish():
    f = torch.cat((_uniform(2.0), _uniform(-1e6)), dim=0)  # second image: everything far off
    f[1, 0, 0, 0] = float("nan")
    v = splat_visibility(f)
    assert torch.equal(v[0, 0, :, :2], torch.zeros(H, 2, dtype=v.dtype))
    assert torch.equal(v[0, 0, :, 2:], torch.ones(H, W - 2, dtype=v.dtype))
    assert torch.equal(v[1], torch.zeros_like(v[1]))


def test_masks_carry_no_gradient():
    f12 = _uniform(1.3).requires_grad_()
    f21 = _uniform(-1.3).requires_grad_()
    assert not splat_visibility(f21).requires_grad
    assert not fb_consistency(f12, f21).requires_grad
    assert not valid_mask(f12, f21).requires_grad
    assert fb_difference(f12, f21).requires_grad  # the difference itself stays differentiable


def test_fb_difference_of_inverse_translations_is_zero_where_the_warp_lands_inside():
    k = 4
    d = fb_difference(_uniform(float(k)), _uniform(float(-k)))
    assert d.shape == (1, 2, H, W)
    assert d[..., : W - k].abs().max() < 1e-12
    # beyond the border the sampled backward flow is 0 (zero padding): the difference is flow12
    assert torch.allclose(d[0, 0, :, W - k:], torch.full((H, k), float(k), dtype=d.dtype))


def test_inverse_translations_are_consistent_exactly_where_the_warp_is_defined():
    k = 4  # > beta = 3 px, so the out-of-image part fails the test
    m = fb_consistency(_uniform(float(k)), _uniform(float(-k)))[0, 0]
    assert torch.equal(m[:, : W - k], torch.ones(H, W - k, dtype=m.dtype))
    assert torch.equal(m[:, W - k:], torch.zeros(H, k, dtype=m.dtype))


def test_corrupted_block_is_inconsistent_exactly_there():
    f12, f21 = _uniform(2.0, 1.0), _uniform(-2.0, -1.0)
    f12[0, 0, 2:5, 3:7] += 6.0  # still lands inside the image; |diff| = 6 > max(0.05 |f12|, 3)
    m = fb_consistency(f12, f21)[0, 0]
    expected = torch.ones(H, W, dtype=m.dtype)
    expected[2:5, 3:7] = 0.0
    # where x + flow12 leaves the image (last row, last 2 columns) |diff| = |flow12| = |(2, 1)| < 3 px:
    # still consistent, so only the block is 0
    assert torch.equal(m, expected)


def test_threshold_is_strict_and_relative_for_large_flow():
    # absolute floor: |diff| = 2.9 passes, 3.0 does not (strict <)
    assert fb_consistency(_uniform(0.0), _uniform(2.9)).min().item() == 1.0
    assert fb_consistency(_uniform(0.0), _uniform(3.0)).max().item() == 0.0
    # large motion: bound = 0.05 * 80 = 4 px, so 3.5 px error is accepted (where the warp lands inside)
    w = 128
    f12 = _uniform(80.0, w=w)
    m = fb_consistency(f12, _uniform(-76.5, w=w))[0, 0]
    assert torch.equal(m[:, : w - 80], torch.ones(H, w - 80, dtype=m.dtype))
    assert fb_consistency(f12, _uniform(-75.5, w=w))[0, 0, :, : w - 80].max().item() == 0.0  # 4.5 px
    # the parameters do what they say
    assert fb_consistency(f12, _uniform(-75.5, w=w), alpha=0.06)[0, 0, :, : w - 80].min().item() == 1.0
    assert fb_consistency(_uniform(0.0), _uniform(3.0), beta=3.1).min().item() == 1.0


def test_valid_mask_is_visibility_times_consistency():
    k = 4
    f12, f21 = _uniform(float(k)), _uniform(float(-k))
    v = valid_mask(f12, f21)[0, 0]
    # image-1 pixels: the last k columns are neither seen in image 2 nor consistent
    assert torch.equal(v[:, : W - k], torch.ones(H, W - k, dtype=v.dtype))
    assert torch.equal(v[:, W - k:], torch.zeros(H, k, dtype=v.dtype))
    # consistency off (NYUv2): visibility alone; make it differ by breaking consistency in a block
    f12b = f12.clone()
    f12b[0, 0, 2:4, 2:4] += 6.0
    assert valid_mask(f12b, f21)[0, 0, 2:4, 2:4].max().item() == 0.0
    assert torch.equal(valid_mask(f12b, f21, use_consistency=False), splat_visibility(f21))
    assert valid_mask(f12b, f21, use_consistency=False)[0, 0, 2:4, 2:4].min().item() == 1.0


def test_score_map_closed_form():
    valid = torch.ones(1, 1, 2, 3, dtype=torch.float64)
    valid[0, 0, 0, 0] = 0.0
    diff = torch.zeros(1, 2, 2, 3, dtype=torch.float64)
    diff[0, 0] = 0.3
    diff[0, 1] = -0.1  # mean |diff| = 0.2
    s = score_map(valid, diff)
    assert s.shape == (1, 1, 2, 3)
    assert s[0, 0, 0, 0].item() == 0.0
    assert torch.allclose(s[0, 0].flatten()[1:], torch.full((5,), 1 / 0.3, dtype=s.dtype))
    assert score_map(valid, torch.zeros_like(diff)).max().item() == pytest.approx(10.0)


def test_bad_shapes_raise_input_error():
    with pytest.raises(InputError):
        splat_visibility(torch.zeros(1, 3, 4, 4))
    with pytest.raises(InputError):
        fb_consistency(torch.zeros(1, 2, 4, 4), torch.zeros(1, 2, 4, 5))
    with pytest.raises(InputError):
        score_map(torch.zeros(1, 1, 4, 4), torch.zeros(1, 2, 4, 5))
