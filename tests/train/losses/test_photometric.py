"""SSIM dissimilarity and the masked photometric loss: closed forms, then noise."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch", reason="needs torch (pip install 'trianflow-vo[train]')")

from trianflow_vo.errors import InputError  # noqa: E402
from trianflow_vo.train.losses.photometric import (SSIM_C1, SSIM_C2, photometric_loss,  # noqa: E402
                                                   photometric_loss_per_image, photometric_map,
                                                   ssim_dissimilarity)


def _rand(*shape, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(*shape, generator=g, dtype=torch.float64)


def _ssim_const(a, b, k):
    """SSIM of constant images a, b in a window with k of 9 pixels inside (zero padding counts)."""
    mx, my = a * k / 9, b * k / 9
    vx, vy, cxy = a * a * k / 9 - mx * mx, b * b * k / 9 - my * my, a * b * k / 9 - mx * my
    return (2 * mx * my + SSIM_C1) * (2 * cxy + SSIM_C2) / ((mx * mx + my * my + SSIM_C1) * (vx + vy + SSIM_C2))


def test_ssim_of_an_image_with_itself_is_zero():
    x = _rand(2, 3, 8, 12)
    d = ssim_dissimilarity(x, x)
    assert d.shape == (2, 3, 8, 12)
    assert d.abs().max() < 1e-12


def test_ssim_of_constant_images_matches_closed_form_inside_and_at_the_borders():
    a, b = 0.8, 0.3
    x = torch.full((1, 1, 6, 7), a, dtype=torch.float64)
    y = torch.full((1, 1, 6, 7), b, dtype=torch.float64)
    d = ssim_dissimilarity(x, y)[0, 0]
    inside = (1 - _ssim_const(a, b, 9)) / 2  # = (1 - (2ab + C1) / (a^2 + b^2 + C1)) / 2
    assert inside == pytest.approx((1 - (2 * a * b + SSIM_C1) / (a * a + b * b + SSIM_C1)) / 2)
    assert torch.allclose(d[1:-1, 1:-1], torch.full((4, 5), inside, dtype=torch.float64), atol=1e-12)
    # the 3x3 average pool counts the zero padding: corner windows hold 4 pixels, edges 6
    assert d[0, 0].item() == pytest.approx((1 - _ssim_const(a, b, 4)) / 2, abs=1e-12)
    assert d[0, 3].item() == pytest.approx((1 - _ssim_const(a, b, 6)) / 2, abs=1e-12)
    assert d[0, 0].item() != pytest.approx(inside, abs=1e-6)


def test_ssim_dissimilarity_is_clamped_to_unit_range():
    x = _rand(1, 3, 8, 8, seed=1)
    d = ssim_dissimilarity(x, 1.0 - x)
    assert d.min() >= 0 and d.max() <= 1
    assert d.mean() > 0.3  # anti-correlated images are very dissimilar


def test_photometric_map_with_zero_ssim_weight_is_l1():
    x, y = _rand(2, 3, 5, 6, seed=2), _rand(2, 3, 5, 6, seed=3)
    m = photometric_map(x, y, w_ssim=0.0)
    assert m.shape == (2, 1, 5, 6)
    assert torch.allclose(m, (x - y).abs().mean(dim=1, keepdim=True), atol=1e-12)


def test_photometric_map_mixes_l1_and_ssim():
    x, y = _rand(1, 3, 5, 6, seed=4), _rand(1, 3, 5, 6, seed=5)
    m = photometric_map(x, y, w_ssim=0.85)
    ref = (0.15 * (x - y).abs() + 0.85 * ssim_dissimilarity(x, y)).mean(dim=1, keepdim=True)
    assert torch.allclose(m, ref, atol=1e-12)
    assert torch.allclose(photometric_map(x, y, 1.0), ssim_dissimilarity(x, y).mean(1, keepdim=True))


def test_photometric_loss_normalises_by_the_mask_mean():
    x = torch.zeros(1, 3, 6, 8, dtype=torch.float64)
    y = torch.full_like(x, 0.5)
    valid = torch.zeros(1, 1, 6, 8, dtype=torch.float64)
    valid[..., :, :4] = 1.0  # left half valid
    # L1 only: masked mean of 0.5 over the valid half, divided by the mask mean 1/2 -> 0.5
    assert photometric_loss(x, y, valid, w_ssim=0.0).item() == pytest.approx(0.5, abs=1e-9)
    # full SSIM: the masked images are compared, so windows straddling the mask edge count too
    full = photometric_loss(x, y, valid, w_ssim=1.0)
    ref = ssim_dissimilarity(x * valid, y * valid).mean() / (valid.mean() + 1e-12)
    assert full.item() == pytest.approx(ref.item(), rel=1e-12)
    # the same errors under a full mask: mask mean 1
    ones = torch.ones_like(valid)
    assert photometric_loss(x, y, ones, w_ssim=0.0).item() == pytest.approx(0.5, abs=1e-9)


def test_photometric_loss_is_zero_for_matching_images_even_outside_the_mask_and_averages_the_batch():
    x = _rand(2, 3, 8, 8, seed=6)
    y = x.clone()
    y[..., :, 5:] = 1.0 - y[..., :, 5:]  # differs only where masked out
    valid = torch.ones(2, 1, 8, 8, dtype=torch.float64)
    valid[..., :, 5:] = 0.0
    assert photometric_loss(x, y, valid).item() == pytest.approx(0.0, abs=1e-12)
    assert photometric_loss(x, y, torch.ones_like(valid)).item() > 0.05
    per = photometric_loss_per_image(x, _rand(2, 3, 8, 8, seed=7), torch.ones_like(valid))
    assert per.shape == (2,)
    assert photometric_loss(x, _rand(2, 3, 8, 8, seed=7), torch.ones_like(valid)).item() == \
        pytest.approx(per.mean().item(), rel=1e-12)


def test_empty_mask_gives_zero_not_nan():
    x, y = _rand(1, 3, 4, 4, seed=8), _rand(1, 3, 4, 4, seed=9)
    loss = photometric_loss(x, y, torch.zeros(1, 1, 4, 4, dtype=torch.float64))
    assert torch.isfinite(loss) and loss.item() == 0.0


def test_photometric_loss_grows_with_noise():
    x = _rand(1, 3, 16, 16, seed=10)
    valid = torch.ones(1, 1, 16, 16, dtype=torch.float64)
    g = torch.Generator().manual_seed(11)
    losses = [photometric_loss(x, (x + s * torch.randn(x.shape, generator=g, dtype=x.dtype)).clamp(0, 1), valid).item()
              for s in (0.0, 0.02, 0.1)]
    assert losses[0] < 1e-12 < losses[1] < losses[2]


def test_bad_inputs_raise_input_error():
    x = torch.zeros(1, 3, 4, 4)
    with pytest.raises(InputError):
        ssim_dissimilarity(x, torch.zeros(1, 3, 4, 5))
    with pytest.raises(InputError):
        photometric_loss(x, x, torch.ones(1, 3, 4, 4))
    with pytest.raises(InputError):
        photometric_map(x, x, w_ssim=1.5)
