"""Match sampling and mid-point triangulation: exact depths, filters, failure flags, gradcheck."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="needs torch (pip install 'trianflow-vo[train]')")

from trianflow_vo.errors import InputError  # noqa: E402
from trianflow_vo.geometry.se3 import rodrigues  # noqa: E402
from trianflow_vo.train.losses.triangulation import (midpoint_points, midpoint_triangulate,  # noqa: E402
                                                     sample_matches, sample_pixels, triangulate_matches)

DT = torch.float64
H, W = 48, 96
K = torch.tensor([[80.0, 0.0, 48.0], [0.0, 80.0, 24.0], [0.0, 0.0, 1.0]], dtype=DT)
K_INV = torch.linalg.inv(K)
R_TRUE = torch.from_numpy(rodrigues(np.array([0.02, -0.03, 0.01])))
T_TRUE = torch.tensor([0.3, 0.1, 1.2], dtype=DT)


def _scene(m=200, seed=0, R=R_TRUE, t=T_TRUE, inside2=True):
    """``m`` points (depth 3..12) seen inside image 1 and (``inside2``) inside image 2 or (not)
    right of it: pts1, pts2 ``(1, m, 2)``, z1, z2 ``(1, m)``."""
    g = np.random.default_rng(seed)
    p1, p2, z1, z2 = [], [], [], []
    Kn, Rn, tn = K.numpy(), R.numpy(), t.numpy()
    while len(p1) < m:
        uv = g.uniform([1, 1], [W - 1, H - 1])
        z = g.uniform(3, 12)
        X = z * np.linalg.inv(Kn) @ np.array([uv[0], uv[1], 1.0])
        X2 = Rn @ X + tn
        q = Kn @ X2
        q = q[:2] / q[2]
        if (1 < q[0] < W - 1 if inside2 else q[0] > W + 1) and 1 < q[1] < H - 1:
            p1.append(uv)
            p2.append(q)
            z1.append(z)
            z2.append(X2[2])
    f = lambda a: torch.tensor(np.array(a), dtype=DT)[None]  # noqa: E731
    return f(p1), f(p2), f(z1), f(z2)


def test_exact_matches_give_the_true_depths():
    pts1, pts2, z1, z2 = _scene()
    e1, e2, valid = midpoint_triangulate(pts1, pts2, K_INV[None], R_TRUE[None], T_TRUE[None], size=(H, W))
    assert valid.all()
    assert torch.allclose(e1, z1, rtol=1e-6) and torch.allclose(e2, z2, rtol=1e-6)


def test_depths_scale_with_t():
    pts1, pts2, z1, z2 = _scene()
    unit = T_TRUE / T_TRUE.norm()
    e1, e2, _ = midpoint_triangulate(pts1, pts2, K_INV[None], R_TRUE[None], unit[None])
    assert torch.allclose(e1 * T_TRUE.norm(), z1, rtol=1e-6)
    assert torch.allclose(e2 * T_TRUE.norm(), z2, rtol=1e-6)


def test_reprojections_of_exact_matches_are_the_matches():
    pts1, pts2, _, _ = _scene(50)
    tri = triangulate_matches(pts1, pts2, K_INV[None], R_TRUE[None], T_TRUE[None], size=(H, W))
    assert torch.allclose(tri.uv1, pts1, atol=1e-8) and torch.allclose(tri.uv2, pts2, atol=1e-8)
    assert tri.ok.tolist() == [True]


def test_noisy_matches_give_close_depths():
    pts1, pts2, z1, _ = _scene(300, seed=1)
    noisy = pts2 + 0.05 * torch.randn(pts2.shape, dtype=DT, generator=torch.Generator().manual_seed(0))
    e1, _, valid = midpoint_triangulate(pts1, noisy, K_INV[None], R_TRUE[None], T_TRUE[None])
    rel = ((e1 - z1).abs() / z1)[valid]
    assert valid.float().mean() > 0.95
    assert rel.median() < 0.02


def test_parallel_rays_are_dropped_and_fail_the_item():
    # pure sideways translation, no rotation: a match at the same pixel is a ray parallel to ray 1
    pts1, _, _, _ = _scene(40)
    R = torch.eye(3, dtype=DT)[None]
    t = torch.tensor([[1.0, 0.0, 0.0]], dtype=DT)
    X, cos = midpoint_points(pts1, pts1.clone(), K_INV[None], R, t)
    assert cos.abs().max() < 1e-3
    tri = triangulate_matches(pts1, pts1.clone(), K_INV[None], R, t, size=(H, W))
    assert not tri.valid.any() and tri.ok.tolist() == [False]


def test_rays_meeting_behind_the_camera_are_dropped():
    R = torch.eye(3, dtype=DT)[None]
    t = torch.tensor([[1.0, 0.0, 0.0]], dtype=DT)  # X2 = X1 + t: a point in front moves right in image 2
    pts1 = torch.tensor([[[40.0, 20.0], [40.0, 20.0]]], dtype=DT)
    pts2 = torch.tensor([[[50.0, 20.0], [30.0, 20.0]]], dtype=DT)  # the second moves the wrong way
    z1, z2, valid = midpoint_triangulate(pts1, pts2, K_INV[None], R, t)
    assert valid.tolist() == [[True, False]]
    assert z1[0, 0].item() == pytest.approx(80.0 / 10.0)  # f * baseline / disparity
    assert z1[0, 1].item() < 0


def test_points_outside_an_image_are_dropped_only_with_a_size():
    pts1, pts2, _, _ = _scene(10)
    pts1 = pts1.clone()
    pts2 = pts2.clone()
    pts2[0, 0] = pts2[0, 0] + torch.tensor([W, 0.0], dtype=DT)  # its reprojection lands right of image 2
    R, t = R_TRUE[None], T_TRUE[None]
    _, _, with_size = midpoint_triangulate(pts1, pts2, K_INV[None], R, t, size=(H, W))
    _, _, no_size = midpoint_triangulate(pts1, pts2, K_INV[None], R, t)
    assert not with_size[0, 0] and with_size[0, 1:].all()
    assert no_size[0, 1:].all()


def test_failure_flags_follow_the_ten_percent_rule():
    R, t = torch.eye(3, dtype=DT)[None], torch.tensor([[1.5, 0.0, 0.0]], dtype=DT)  # sideways: 10..40 px
    inside = _scene(20, seed=5, R=R[0], t=t[0])
    outside = _scene(20, seed=6, R=R[0], t=t[0], inside2=False)  # exact matches, but right of image 2

    def ok_with(k_inside):
        pts1 = torch.cat((inside[0][:, :k_inside], outside[0][:, k_inside:]), dim=1)
        pts2 = torch.cat((inside[1][:, :k_inside], outside[1][:, k_inside:]), dim=1)
        tri = triangulate_matches(pts1, pts2, K_INV[None], R, t, size=(H, W))
        assert tri.valid.sum().item() == k_inside
        return tri.ok.item()

    assert ok_with(20) and ok_with(2)  # 10 % kept: still ok
    assert not ok_with(1) and not ok_with(0)  # 5 %, 0 %: the item fails


def test_batch_items_are_independent():
    a = _scene(30, seed=2)
    b = _scene(30, seed=3, R=torch.eye(3, dtype=DT), t=torch.tensor([0.0, 0.0, 1.0], dtype=DT))
    pts1 = torch.cat((a[0], b[0]))
    pts2 = torch.cat((a[1], b[1]))
    R = torch.stack((R_TRUE, torch.eye(3, dtype=DT)))
    t = torch.stack((T_TRUE, torch.tensor([0.0, 0.0, 1.0], dtype=DT)))
    z1, _, valid = midpoint_triangulate(pts1, pts2, K_INV[None].repeat(2, 1, 1), R, t)
    assert valid.all()
    assert torch.allclose(z1, torch.cat((a[2], b[2])), rtol=1e-6)


def test_gradcheck_float64():
    pts1, pts2, _, _ = _scene(4, seed=4)
    pts1 = pts1.clone().requires_grad_(True)
    pts2 = pts2.clone().requires_grad_(True)
    t = T_TRUE[None].clone().requires_grad_(True)
    R = R_TRUE[None].clone().requires_grad_(True)

    def f(p1, p2, R_, t_):
        z1, z2, _ = midpoint_triangulate(p1, p2, K_INV[None], R_, t_)
        return z1, z2

    assert torch.autograd.gradcheck(f, (pts1, pts2, R, t), eps=1e-6, atol=1e-6)
    # and with matches that do not meet exactly (the mid-point proper)
    off = (pts2 + torch.tensor([0.3, -0.4], dtype=DT)).detach().requires_grad_(True)
    assert torch.autograd.gradcheck(f, (pts1, off, R, t), eps=1e-6, atol=1e-6)


def test_triangulated_uv_are_differentiable():
    pts1, pts2, _, _ = _scene(5)
    pts2 = pts2.clone().requires_grad_(True)
    tri = triangulate_matches(pts1, pts2, K_INV[None], R_TRUE[None], T_TRUE[None], size=(H, W))
    (tri.uv1.sum() + tri.z1.sum()).backward()
    assert pts2.grad.abs().sum() > 0


def test_sample_pixels_keeps_the_top_ratio():
    w = torch.arange(100, dtype=DT).view(1, 1, 10, 10)  # weight = flat index
    idx, ok = sample_pixels(w, top_ratio=0.2, n=500, generator=torch.Generator().manual_seed(0))
    assert idx.shape == (1, 500) and ok.tolist() == [True]
    assert idx.min() >= 80  # the 20 largest
    assert len(torch.unique(idx)) == 20  # all of them drawn (500 draws of 20)


def test_sample_pixels_only_draws_positive_weights():
    w = torch.zeros(2, 1, 10, 10, dtype=DT)
    w[0, 0, 3, 4] = 1.0
    w[0, 0, 7, 1] = 0.5
    idx, ok = sample_pixels(w, top_ratio=0.2, n=50, generator=torch.Generator().manual_seed(0))
    assert ok.tolist() == [True, False]
    assert set(idx[0].tolist()) == {34, 71}
    assert torch.equal(idx[1], torch.zeros(50, dtype=torch.long))


def test_sample_pixels_is_deterministic():
    w = torch.rand(2, 1, 16, 16, generator=torch.Generator().manual_seed(1))
    a, _ = sample_pixels(w, n=100, generator=torch.Generator().manual_seed(9))
    b, _ = sample_pixels(w, n=100, generator=torch.Generator().manual_seed(9))
    c, _ = sample_pixels(w, n=100, generator=torch.Generator().manual_seed(10))
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_sample_matches_pairs_pixels_with_their_flow_and_keeps_its_gradient():
    flow = torch.randn(1, 2, 8, 12, dtype=DT, generator=torch.Generator().manual_seed(0)).requires_grad_(True)
    w = torch.rand(1, 1, 8, 12, dtype=DT, generator=torch.Generator().manual_seed(1))
    pts1, pts2, ok = sample_matches(flow, w, top_ratio=0.5, n=30, generator=torch.Generator().manual_seed(2))
    assert pts1.shape == pts2.shape == (1, 30, 2) and ok.all()
    u, v = pts1[0, :, 0].long(), pts1[0, :, 1].long()
    assert torch.equal(pts1[0], pts1[0].round())
    assert torch.allclose(pts2[0] - pts1[0], flow[0, :, v, u].T.detach())
    pts2.sum().backward()
    assert flow.grad.abs().sum() > 0


def test_shapes_are_checked():
    p = torch.zeros(1, 5, 2)
    eye = torch.eye(3)[None]
    with pytest.raises(InputError):
        midpoint_triangulate(p, torch.zeros(1, 4, 2), eye, eye, torch.zeros(1, 3))
    with pytest.raises(InputError):
        midpoint_triangulate(p, p, eye, eye, torch.zeros(1, 4))
    with pytest.raises(InputError):
        sample_pixels(torch.zeros(1, 2, 4, 4))
    with pytest.raises(InputError):
        sample_pixels(torch.zeros(1, 1, 4, 4), top_ratio=0.0)
    with pytest.raises(InputError):
        sample_matches(torch.zeros(1, 2, 4, 4), torch.zeros(1, 1, 4, 5))
