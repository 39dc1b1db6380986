"""Scale alignment, L_d, projected depth and flow error on scenes with known answers."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="needs torch (pip install 'trianflow-vo[train]')")

from trianflow_vo.errors import InputError  # noqa: E402
from trianflow_vo.geometry.se3 import rodrigues  # noqa: E402
from trianflow_vo.train.losses.depth import (align_scale, flow_error_loss, projected_depth_loss,  # noqa: E402
                                             rigid_projection, sample_depth, triangulation_depth_loss)
from trianflow_vo.train.losses.triangulation import Triangulation, triangulate_matches  # noqa: E402

DT = torch.float64
H, W = 32, 64
K = torch.tensor([[50.0, 0.0, 32.0], [0.0, 50.0, 16.0], [0.0, 0.0, 1.0]], dtype=DT)
K_INV = torch.linalg.inv(K)
R_TRUE = torch.from_numpy(rodrigues(np.array([0.01, 0.02, -0.01])))
T_TRUE = torch.tensor([0.1, 0.0, 0.5], dtype=DT)
PLANE_N = torch.tensor([0.1, -0.2, 1.0], dtype=DT)  # plane n . X = D in camera 1
PLANE_D = 8.0


def _grid():
    v, u = torch.meshgrid(torch.arange(H, dtype=DT), torch.arange(W, dtype=DT), indexing="ij")
    return torch.stack((u, v, torch.ones_like(u)), 0).reshape(3, -1)


def _plane_depth(n, d):
    """Depth ``(1, 1, H, W)`` of the plane ``n . X = d`` seen by a camera with intrinsics K."""
    rays = K_INV @ _grid()
    return (d / (n @ rays)).reshape(1, 1, H, W)


def _plane_scene():
    """Depth maps of the plane in both cameras and the exact flow 1 -> 2."""
    depth1 = _plane_depth(PLANE_N, PLANE_D)
    n2 = R_TRUE @ PLANE_N  # in camera 2: n2 . X2 = d + n2 . t
    depth2 = _plane_depth(n2, PLANE_D + float(n2 @ T_TRUE))
    x = _grid()
    X2 = R_TRUE @ (K_INV @ x * depth1.reshape(1, -1)) + T_TRUE[:, None]
    p2 = (K @ X2)[:2] / X2[2:]
    return depth1, depth2, (p2 - x[:2]).reshape(1, 2, H, W)


def _tri_at_pixels(z, pix):
    """A Triangulation whose points sit exactly on integer pixels ``pix`` ``(M, 2)`` in both images."""
    uv = pix.to(DT)[None]
    valid = torch.ones_like(z, dtype=torch.bool)
    return Triangulation(z1=z, z2=z, uv1=uv, uv2=uv, valid=valid, ok=torch.ones(1, dtype=torch.bool))


def _pixels(m, seed=0):
    g = torch.Generator().manual_seed(seed)
    flat = torch.randperm(H * W, generator=g)[:m]
    return torch.stack((flat % W, flat // W), dim=1)


def _depth_at(pix, values):
    d = torch.ones(1, 1, H, W, dtype=DT)
    d[0, 0, pix[:, 1], pix[:, 0]] = values
    return d


def test_sample_depth_is_exact_at_pixel_centres_and_bilinear_between():
    d = torch.arange(H * W, dtype=DT).view(1, 1, H, W)
    uv = torch.tensor([[[3.0, 2.0], [3.5, 2.0], [3.0, 2.25]]], dtype=DT)
    got = sample_depth(d, uv)
    assert got[0].tolist() == pytest.approx([2 * W + 3, 2 * W + 3.5, 2 * W + 3 + 0.25 * W])


def test_align_scale_of_a_scaled_depth_is_exact():
    z = torch.rand(1, 100, dtype=DT, generator=torch.Generator().manual_seed(0)) * 10 + 1
    valid = torch.ones_like(z, dtype=torch.bool)
    s, a = align_scale(3.7 * z, z, valid)
    assert s.item() == pytest.approx(3.7)
    assert a.item() == pytest.approx(1.0)
    assert torch.allclose(a * 3.7 * z / s, z)


def test_align_scale_ignores_invalid_matches_and_has_no_gradient():
    z = torch.rand(1, 50, dtype=DT, generator=torch.Generator().manual_seed(1)) * 5 + 1
    d = (2.0 * z).clone()
    valid = torch.ones_like(z, dtype=torch.bool)
    valid[0, :10] = False
    d[0, :10] = 1000.0
    d.requires_grad_(True)
    s, a = align_scale(d, z, valid)
    assert s.item() == pytest.approx(2.0) and a.item() == pytest.approx(1.0)
    assert not s.requires_grad and not a.requires_grad
    s0, a0 = align_scale(d, z, torch.zeros_like(valid))
    assert s0.item() == 1.0 and a0.item() == 1.0


def test_ld_is_zero_for_a_scaled_depth():
    pix = _pixels(60)
    z = torch.rand(1, 60, dtype=DT, generator=torch.Generator().manual_seed(2)) * 10 + 2
    tri = _tri_at_pixels(z, pix)
    loss, s1, s2 = triangulation_depth_loss(_depth_at(pix, 4.0 * z[0]), _depth_at(pix, 0.5 * z[0]), tri)
    assert loss.item() == pytest.approx(0.0, abs=1e-20)
    assert s1.item() == pytest.approx(0.25) and s2.item() == pytest.approx(2.0)


@pytest.mark.parametrize("eps", [0.05, 0.2])
def test_ld_of_a_known_perturbation(eps):
    # d = c z (1 +- eps), half each: a d'/z = (1 +- eps) / (1 + eps^2), L = eps^2 / (1 + eps^2) per frame
    m = 40
    pix = _pixels(m, seed=3)
    z = torch.rand(1, m, dtype=DT, generator=torch.Generator().manual_seed(4)) * 10 + 2
    sign = torch.tensor([1.0, -1.0] * (m // 2), dtype=DT)
    d = 3.0 * z[0] * (1 + eps * sign)
    tri = _tri_at_pixels(z, pix)
    loss, _, _ = triangulation_depth_loss(_depth_at(pix, d), _depth_at(pix, d), tri)
    assert loss.item() == pytest.approx(2 * eps ** 2 / (1 + eps ** 2), rel=1e-9)
    # invalid matches do not count, whatever their values
    tri2 = Triangulation(z1=torch.cat((z, torch.full((1, 5), 0.001, dtype=DT)), 1),
                         z2=torch.cat((z, torch.full((1, 5), 0.001, dtype=DT)), 1),
                         uv1=torch.cat((tri.uv1, torch.zeros(1, 5, 2, dtype=DT)), 1),
                         uv2=torch.cat((tri.uv2, torch.zeros(1, 5, 2, dtype=DT)), 1),
                         valid=torch.cat((tri.valid, torch.zeros(1, 5, dtype=torch.bool)), 1), ok=tri.ok)
    loss2, _, _ = triangulation_depth_loss(_depth_at(pix, d), _depth_at(pix, d), tri2)
    assert loss2.item() == pytest.approx(loss.item(), rel=1e-12)


def test_ld_gradients_reach_the_depth_and_the_triangulation():
    pix = _pixels(20, seed=5)
    z = (torch.rand(1, 20, dtype=DT, generator=torch.Generator().manual_seed(6)) * 5 + 2).requires_grad_(True)
    d1 = _depth_at(pix, 2.0 * z[0].detach() * 1.1).requires_grad_(True)
    d2 = _depth_at(pix, 2.0 * z[0].detach())
    tri = _tri_at_pixels(z, pix)
    pert = torch.linspace(0.9, 1.1, 20, dtype=DT)[None]
    tri = Triangulation(z1=z * pert, z2=z, uv1=tri.uv1, uv2=tri.uv2, valid=tri.valid, ok=tri.ok)
    loss, _, _ = triangulation_depth_loss(d1, d2, tri)
    loss.sum().backward()
    assert d1.grad.abs().sum() > 0 and z.grad.abs().sum() > 0


def test_ld_on_a_triangulated_plane_is_zero_up_to_interpolation():
    depth1, depth2, flow = _plane_scene()
    pix = _pixels(200, seed=7)
    pts1 = pix.to(DT)[None]
    pts2 = pts1 + flow[0, :, pix[:, 1], pix[:, 0]].T[None]
    unit = T_TRUE / T_TRUE.norm()
    tri = triangulate_matches(pts1, pts2, K_INV[None], R_TRUE[None], unit[None], size=(H, W))
    assert tri.ok.all() and tri.valid.float().mean() > 0.5
    loss, s1, s2 = triangulation_depth_loss(5.0 * depth1, 0.2 * depth2, tri)
    assert loss.item() < 1e-6
    assert s1.item() == pytest.approx(1 / (5.0 * T_TRUE.norm().item()), rel=1e-3)
    assert s2.item() == pytest.approx(1 / (0.2 * T_TRUE.norm().item()), rel=1e-3)


def test_rigid_projection_is_the_flow_of_the_scene():
    depth1, depth2, flow = _plane_scene()
    uv2, z2, inside = rigid_projection(depth1, K[None], K_INV[None], R_TRUE[None], T_TRUE[None])
    grid = _grid()[:2].reshape(1, 2, H, W)
    assert torch.allclose(uv2 - grid, flow, atol=1e-9)
    assert inside.sum() > 0.5 * H * W
    assert torch.allclose(z2[inside > 0], sample_depth(depth2, uv2.reshape(1, 2, -1).transpose(1, 2))
                          .reshape(1, 1, H, W)[inside > 0], rtol=1e-3)


def test_projected_depth_loss_zero_for_consistent_depths_and_known_for_a_scaled_one():
    depth1, depth2, _ = _plane_scene()
    ones = torch.ones(1, 1, H, W, dtype=DT)
    args = (K[None], K_INV[None], R_TRUE[None], T_TRUE[None], ones, ones)
    assert projected_depth_loss(depth1, depth2, *args).item() < 1e-4
    # frame 2 predicted 10 % too far: |1 - z2 / (1.1 z2)| = 0.1 / 1.1 wherever the pixel lands inside
    assert projected_depth_loss(depth1, 1.1 * depth2, *args).item() == pytest.approx(0.1 / 1.1, abs=1e-4)


def test_projected_depth_loss_weights_pixels_by_rigid_and_validity():
    depth1, depth2, _ = _plane_scene()
    bad2 = depth2.clone()
    bad2[:, :, :, : W // 2] *= 2.0
    ones = torch.ones(1, 1, H, W, dtype=DT)
    keep_right = ones.clone()
    keep_right[:, :, :, : W // 2 + 8] = 0.0  # pixels of frame 1 that land on the wrong half are not counted
    args = (K[None], K_INV[None], R_TRUE[None], T_TRUE[None])
    assert projected_depth_loss(depth1, bad2, *args, keep_right, ones).item() < 1e-4
    assert projected_depth_loss(depth1, bad2, *args, ones, keep_right).item() < 1e-4
    assert projected_depth_loss(depth1, bad2, *args, ones, ones).item() > 0.05


def test_projected_depth_loss_gradients_reach_both_depths():
    depth1, depth2, _ = _plane_scene()
    d1 = depth1.clone().requires_grad_(True)
    d2 = (1.1 * depth2).requires_grad_(True)
    ones = torch.ones(1, 1, H, W, dtype=DT)
    projected_depth_loss(d1, d2, K[None], K_INV[None], R_TRUE[None], T_TRUE[None], ones, ones).sum().backward()
    assert d1.grad.abs().sum() > 0 and d2.grad.abs().sum() > 0


def test_flow_error_zero_for_the_rigid_flow_and_known_for_an_offset():
    depth1, _, flow = _plane_scene()
    ones = torch.ones(1, 1, H, W, dtype=DT)
    args = (K[None], K_INV[None], R_TRUE[None], T_TRUE[None], ones)
    assert flow_error_loss(flow, depth1, *args).item() < 1e-9
    off = flow + torch.tensor([0.6, 0.0], dtype=DT).view(1, 2, 1, 1)
    # the authors average |error| over both channels: 0.6 px in one of them -> 0.3
    assert flow_error_loss(off, depth1, *args).item() == pytest.approx(0.3, rel=1e-9)
    half = ones.clone()
    half[:, :, : H // 2] = 0.0
    off2 = flow.clone()
    off2[:, 1, : H // 2] += 5.0  # wrong only where the rigid score is 0
    assert flow_error_loss(off2, depth1, K[None], K_INV[None], R_TRUE[None], T_TRUE[None], half).item() < 1e-9


def test_flow_error_gradient_reaches_only_the_flow():
    depth1, _, flow = _plane_scene()
    f = (flow + 0.5).requires_grad_(True)
    d1 = depth1.clone().requires_grad_(True)
    ones = torch.ones(1, 1, H, W, dtype=DT)
    flow_error_loss(f, d1, K[None], K_INV[None], R_TRUE[None], T_TRUE[None], ones).sum().backward()
    assert f.grad.abs().sum() > 0
    assert d1.grad is None


def test_shapes_are_checked():
    d = torch.ones(1, 1, 4, 4)
    with pytest.raises(InputError):
        sample_depth(d, torch.zeros(1, 3, 3))
    with pytest.raises(InputError):
        align_scale(torch.ones(1, 3), torch.ones(1, 4), torch.ones(1, 3, dtype=torch.bool))
    with pytest.raises(InputError):
        rigid_projection(d, torch.eye(3)[None], torch.eye(3)[None], torch.eye(3)[None], torch.zeros(1, 4))
    with pytest.raises(InputError):
        flow_error_loss(torch.zeros(1, 2, 4, 4), torch.ones(1, 1, 4, 5), torch.eye(3)[None], torch.eye(3)[None],
                        torch.eye(3)[None], torch.zeros(1, 3), torch.ones(1, 1, 4, 4))
