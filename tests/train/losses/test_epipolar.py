"""F from a dense flow, epipolar distance, geometric band loss, rigid score, pose: known answers."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="needs torch (pip install 'trianflow-vo[train]')")
pytest.importorskip("cv2")

from trianflow_vo.errors import InputError  # noqa: E402
from trianflow_vo.geometry.se3 import rodrigues, rotation_log  # noqa: E402
from trianflow_vo.train.losses.epipolar import (epipolar_distance, essential_candidates,  # noqa: E402
                                                fundamental_from_flow, geometric_loss, geometric_loss_per_image,
                                                pose_from_fundamental, rigid_mask)
from trianflow_vo.train.losses.triangulation import sample_matches  # noqa: E402

DT = torch.float64
H, W = 64, 128
K = torch.tensor([[100.0, 0.0, 64.0], [0.0, 100.0, 32.0], [0.0, 0.0, 1.0]], dtype=DT)
R_TRUE = torch.from_numpy(rodrigues(np.array([0.01, 0.03, -0.02])))
T_TRUE = torch.tensor([0.2, -0.05, 1.0], dtype=DT)


def _skew(v):
    return torch.tensor([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]], dtype=DT)


def _true_F(R=R_TRUE, t=T_TRUE):
    Ki = torch.linalg.inv(K)
    return Ki.T @ _skew(t) @ R @ Ki


def _scene_flow(R=R_TRUE, t=T_TRUE, h=H, w=W):
    """Exact flow ``(1, 2, H, W)`` of a non-planar surface (depth 3..9) under ``X2 = R X1 + t``."""
    v, u = torch.meshgrid(torch.arange(h, dtype=DT), torch.arange(w, dtype=DT), indexing="ij")
    Z = 6.0 + 3.0 * torch.sin(u / 9.0) * torch.cos(v / 7.0)
    x = torch.stack((u, v, torch.ones_like(u)), 0).reshape(3, -1)
    X2 = R @ (torch.linalg.inv(K) @ x * Z.reshape(1, -1)) + t[:, None]
    p2 = (K @ X2)[:2] / X2[2:]
    return (p2 - x[:2]).reshape(1, 2, h, w)


def _gen(seed=0):
    return torch.Generator().manual_seed(seed)


def _angle(R_a, R_b):
    return float(np.linalg.norm(rotation_log((R_a.T @ R_b).numpy())))


def _dir_angle(a, b):
    a = a / a.norm()
    b = b / b.norm()
    return float(torch.arccos((a @ b).clamp(-1, 1)))


def test_true_F_gives_zero_distance_and_perpendicular_shift_gives_the_shift():
    flow = _scene_flow()
    F = _true_F()[None]
    d = epipolar_distance(F, flow)
    assert d.shape == (1, 1, H, W)
    assert d.max().item() < 1e-9
    # move every match along the unit normal of its epipolar line by 0.3 px
    v, u = torch.meshgrid(torch.arange(H, dtype=DT), torch.arange(W, dtype=DT), indexing="ij")
    x1 = torch.stack((u, v, torch.ones_like(u)), 0).reshape(3, -1)
    lines = F[0] @ x1
    normal = lines[:2] / lines[:2].norm(dim=0, keepdim=True)
    shifted = flow + 0.3 * normal.reshape(1, 2, H, W)
    d2 = epipolar_distance(F, shifted)
    norm = lines[:2].norm(dim=0).reshape(1, 1, H, W)
    assert torch.allclose(d2, 0.3 * norm / (norm + 1e-6), rtol=1e-9)  # the authors' 1e-6 guard
    assert torch.allclose(epipolar_distance(1e6 * F, shifted), torch.full_like(d2, 0.3), rtol=1e-6)


def test_epipolar_distance_is_differentiable_in_the_flow():
    flow = _scene_flow().clone().requires_grad_(True)
    shifted = flow + 0.2
    epipolar_distance(_true_F()[None], shifted).sum().backward()
    assert flow.grad is not None and flow.grad.abs().sum() > 0


def test_fundamental_from_exact_flow_recovers_the_geometry():
    flow = _scene_flow()
    score = torch.ones(1, 1, H, W, dtype=DT)
    F, valid = fundamental_from_flow(flow, score, generator=_gen())
    assert F.shape == (1, 3, 3) and F.dtype == DT and valid.tolist() == [True]
    assert epipolar_distance(F, flow).max().item() < 1e-3
    pts1, pts2, _ = sample_matches(flow, score, n=400, generator=_gen(1))
    R, t, ok = pose_from_fundamental(F, K[None], pts1, pts2)
    assert ok.tolist() == [True]
    assert _angle(R[0], R_TRUE) < 1e-3
    assert _dir_angle(t[0], T_TRUE) < 1e-3
    assert abs(t[0].norm().item() - 1.0) < 1e-9


def test_fundamental_draw_is_deterministic_with_a_generator():
    flow = _scene_flow() + 0.05 * torch.randn(1, 2, H, W, dtype=DT, generator=_gen(5))
    score = torch.rand(1, 1, H, W, dtype=DT, generator=_gen(6))
    F1, _ = fundamental_from_flow(flow, score, n_samples=800, generator=_gen(3))
    F2, _ = fundamental_from_flow(flow, score, n_samples=800, generator=_gen(3))
    assert torch.equal(F1, F2)


def test_moving_object_is_an_outlier_and_leaves_the_rigid_mask():
    flow = _scene_flow()
    flow[:, 1, 10:40, 20:60] += 4.0  # an object moving down (across the epipolar lines there): 1200 px
    F, valid = fundamental_from_flow(flow, torch.ones(1, 1, H, W, dtype=DT), generator=_gen())
    assert valid.tolist() == [True]
    d = epipolar_distance(F, flow)
    static = torch.ones(1, 1, H, W, dtype=torch.bool)
    static[:, :, 10:40, 20:60] = False
    assert d[static].max().item() < 1e-3
    r = rigid_mask(d)
    assert r[static].min().item() > 0.999
    assert (r[~static] == 0).float().mean().item() > 0.9  # most of the object is off its epipolar lines


def test_noisy_flow_still_gives_a_close_pose():
    flow = _scene_flow() + 0.03 * torch.randn(1, 2, H, W, dtype=DT, generator=_gen(7))
    score = torch.ones(1, 1, H, W, dtype=DT)
    F, valid = fundamental_from_flow(flow, score, generator=_gen())
    pts1, pts2, _ = sample_matches(flow, score, n=400, generator=_gen(1))
    R, t, ok = pose_from_fundamental(F, K[None], pts1, pts2)
    assert valid.all() and ok.all()
    assert _angle(R[0], R_TRUE) < 5e-3
    assert _dir_angle(t[0], T_TRUE) < 5e-2


def test_fundamental_fails_without_enough_scored_pixels():
    flow = _scene_flow().repeat(3, 1, 1, 1)
    score = torch.zeros(3, 1, H, W, dtype=DT)
    score[1] = 1.0
    score[2, 0, 5, :5] = 1.0  # 5 distinct pixels: fewer than 8
    F, valid = fundamental_from_flow(flow, score, n_samples=500, generator=_gen())
    assert valid.tolist() == [False, True, False]
    assert torch.equal(F[0], torch.zeros(3, 3, dtype=DT)) and torch.equal(F[2], torch.zeros(3, 3, dtype=DT))


def test_fundamental_fails_on_non_finite_flow():
    flow = _scene_flow()
    flow[:, :, :, :] = float("nan")
    _, valid = fundamental_from_flow(flow, torch.ones(1, 1, H, W, dtype=DT), n_samples=100, generator=_gen())
    assert valid.tolist() == [False]


def test_geometric_loss_counts_only_the_band():
    vals = torch.tensor([0.05, 0.1, 0.3, 0.49, 0.5, 2.0], dtype=DT)
    d = vals.view(1, 1, 2, 3).clone().requires_grad_(True)
    loss = geometric_loss(d)
    assert loss.item() == pytest.approx((0.1 + 0.3 + 0.49) / 3)
    loss.backward()
    expected = torch.tensor([0.0, 1 / 3, 1 / 3, 1 / 3, 0.0, 0.0], dtype=DT).view(1, 1, 2, 3)
    assert torch.allclose(d.grad, expected)


def test_geometric_loss_per_image_and_empty_band():
    d = torch.stack((torch.full((1, 4, 4), 0.2, dtype=DT), torch.full((1, 4, 4), 0.01, dtype=DT)))
    per = geometric_loss_per_image(d)
    assert per.tolist() == pytest.approx([0.2, 0.0])
    assert geometric_loss(d).item() == pytest.approx(0.1)
    assert geometric_loss_per_image(d, lo=0.0, hi=0.25).tolist() == pytest.approx([0.2, 0.01])


def test_rigid_mask_values():
    d = torch.tensor([0.0, 0.25, 0.49, 0.5, 1.0], dtype=DT).view(1, 1, 1, 5)
    assert rigid_mask(d).flatten().tolist() == pytest.approx([1.0, 0.8, 1 / 1.49, 0.0, 0.0])
    assert rigid_mask(d, thresh=1.5).flatten()[-1].item() == pytest.approx(0.5)


def test_essential_candidates_are_rotations_and_contain_the_truth():
    E = (K.T @ _true_F() @ K)[None]
    R, t = essential_candidates(E)
    assert R.shape == (1, 4, 3, 3) and t.shape == (1, 4, 3)
    for c in range(4):
        assert torch.allclose(R[0, c] @ R[0, c].T, torch.eye(3, dtype=DT), atol=1e-9)
        assert torch.linalg.det(R[0, c]).item() == pytest.approx(1.0)
    assert min(_angle(R[0, c], R_TRUE) for c in range(4)) < 1e-9
    assert min(_dir_angle(t[0, c], T_TRUE) for c in range(4)) < 1e-9


def test_pose_is_invalid_for_a_zero_F():
    pts = torch.rand(1, 50, 2, dtype=DT) * 50
    _, _, ok = pose_from_fundamental(torch.zeros(1, 3, 3, dtype=DT), K[None], pts, pts + 1)
    assert ok.tolist() == [False]


def test_shapes_are_checked():
    with pytest.raises(InputError):
        epipolar_distance(torch.eye(3)[None], torch.zeros(1, 3, 4, 4))
    with pytest.raises(InputError):
        epipolar_distance(torch.eye(3)[None].repeat(2, 1, 1), torch.zeros(1, 2, 4, 4))
    with pytest.raises(InputError):
        geometric_loss(torch.zeros(1, 2, 4, 4))
    with pytest.raises(InputError):
        geometric_loss(torch.zeros(1, 1, 4, 4), lo=0.5, hi=0.1)
    with pytest.raises(InputError):
        fundamental_from_flow(torch.zeros(1, 2, 4, 4), torch.ones(1, 1, 4, 5))
    with pytest.raises(InputError):
        pose_from_fundamental(torch.eye(3)[None], torch.eye(3)[None], torch.zeros(1, 5, 3), torch.zeros(1, 5, 3))
