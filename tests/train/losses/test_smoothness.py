"""Second-order flow and first-order disparity smoothness: zero cases, closed forms, edges."""

from __future__ import annotations

import math

import pytest

torch = pytest.importorskip("torch", reason="needs torch (pip install 'trianflow-vo[train]')")

from trianflow_vo.errors import InputError  # noqa: E402
from trianflow_vo.train.losses.smoothness import (depth_smoothness, depth_smoothness_per_image,  # noqa: E402
                                                  flow_smoothness, flow_smoothness_per_image)

H, W = 8, 12
DT = torch.float64


def _grid(h=H, w=W):
    ys, xs = torch.meshgrid(torch.arange(h, dtype=DT), torch.arange(w, dtype=DT), indexing="ij")
    return xs, ys


def _flat_img(n=1, h=H, w=W):
    return torch.full((n, 3, h, w), 0.5, dtype=DT)


def test_constant_and_affine_flow_cost_nothing():
    xs, ys = _grid()
    img = torch.rand(1, 3, H, W, generator=torch.Generator().manual_seed(0), dtype=DT)
    const = torch.stack((torch.full_like(xs, 3.0), torch.full_like(xs, -1.0)))[None]
    affine = torch.stack((1.0 + 0.3 * xs - 0.2 * ys, -2.0 + 0.1 * xs + 0.5 * ys))[None]
    assert flow_smoothness(const, img).item() == pytest.approx(0.0, abs=1e-12)
    assert flow_smoothness(affine, img).item() == pytest.approx(0.0, abs=1e-12)
    # only pure second differences (xx, yy) are penalised, not the mixed one
    mixed = torch.stack((0.1 * xs * ys, torch.zeros_like(xs)))[None]
    assert flow_smoothness(mixed, img).item() == pytest.approx(0.0, abs=1e-12)


def test_quadratic_flow_has_the_closed_form_value():
    xs, ys = _grid()
    c = 0.7
    # u = c x^2: u_xx = 2c everywhere, v = 0; on flow/20 and a flat image (weights 1):
    # mean over 2 channels of |2c/20| = c/20 for the x part, 0 for y, halved -> c/40
    flow = torch.stack((c * xs ** 2, torch.zeros_like(xs)))[None]
    assert flow_smoothness(flow, _flat_img()).item() == pytest.approx(c / 40, rel=1e-12)
    # the same curvature along y in v
    flow_y = torch.stack((torch.zeros_like(ys), c * ys ** 2))[None]
    assert flow_smoothness(flow_y, _flat_img()).item() == pytest.approx(c / 40, rel=1e-12)


def test_image_edge_reduces_the_penalty_exactly_where_the_weight_falls():
    xs, _ = _grid()
    c, alpha, e, step = 0.7, 10.0, 5, 0.4
    flow = torch.stack((c * xs ** 2, torch.zeros_like(xs)))[None]
    img = _flat_img().clone()
    img[..., e + 1:] += step  # vertical edge between columns e and e+1
    got = flow_smoothness(flow, img, alpha=alpha).item()
    # u_xx starting at column j is weighted by the image gradient between j+1 and j+2:
    # the edge hits j = e - 1 only
    expected = c / 40 * ((W - 3) + math.exp(-alpha * step)) / (W - 2)
    assert got == pytest.approx(expected, rel=1e-12)
    assert got < flow_smoothness(flow, _flat_img(), alpha=alpha).item()
    assert flow_smoothness(flow, img, alpha=0.0).item() == pytest.approx(c / 40, rel=1e-12)


def test_flow_smoothness_averages_the_batch_and_has_gradient():
    xs, _ = _grid()
    flows = torch.stack([torch.stack((c * xs ** 2, torch.zeros_like(xs))) for c in (0.2, 0.6)]).requires_grad_()
    per = flow_smoothness_per_image(flows, _flat_img(2))
    assert torch.allclose(per, torch.tensor([0.2 / 40, 0.6 / 40], dtype=DT))
    loss = flow_smoothness(flows, _flat_img(2))
    assert loss.item() == pytest.approx(0.4 / 40)
    loss.backward()
    assert flows.grad is not None and flows.grad.abs().sum() > 0


def test_depth_smoothness_zero_for_constant_and_scale_invariant():
    g = torch.Generator().manual_seed(1)
    img = torch.rand(2, 3, H, W, generator=g, dtype=DT)
    assert depth_smoothness(torch.full((2, 1, H, W), 0.3, dtype=DT), img).item() == pytest.approx(0.0, abs=1e-12)
    disp = 0.1 + torch.rand(2, 1, H, W, generator=g, dtype=DT)
    a = depth_smoothness(disp, img).item()
    assert a > 0
    assert depth_smoothness(disp * 7.5, img).item() == pytest.approx(a, rel=1e-9)


def test_depth_smoothness_closed_form_of_a_ramp_and_edge_weight():
    xs, _ = _grid()
    disp = (xs + 1.0)[None, None]  # mean (W + 1) / 2, so every x step is 2 / (W + 1) after normalising
    assert depth_smoothness(disp, _flat_img()).item() == pytest.approx(2 / (W + 1), rel=1e-12)
    img = _flat_img().clone()
    img[..., 6:] += 0.5  # one edge: the x step at column 5 is weighted exp(-0.5)
    expected = 2 / (W + 1) * ((W - 2) + math.exp(-0.5)) / (W - 1)
    per = depth_smoothness_per_image(disp, img)
    assert per.shape == (1,)
    assert per.item() == pytest.approx(expected, rel=1e-12)


def test_bad_shapes_raise_input_error():
    with pytest.raises(InputError):
        flow_smoothness(torch.zeros(1, 1, 4, 4), torch.zeros(1, 3, 4, 4))
    with pytest.raises(InputError):
        flow_smoothness(torch.zeros(1, 2, 4, 4), torch.zeros(1, 3, 4, 5))
    with pytest.raises(InputError):
        depth_smoothness(torch.zeros(1, 2, 4, 4), torch.zeros(1, 3, 4, 4))
