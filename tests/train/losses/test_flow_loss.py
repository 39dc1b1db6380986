"""The composed flow loss L_f: a shifted image with its true flow, masks, gradients, shapes."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="needs torch (pip install 'trianflow-vo[train]')")
import torch.nn.functional as F  # noqa: E402

from trianflow_vo.errors import InputError  # noqa: E402
from trianflow_vo.models.pwc import PWCConfig, PWCNet  # noqa: E402
from trianflow_vo.train.losses.flow import FlowLossOutput, flow_loss  # noqa: E402
from trianflow_vo.train.losses.masks import splat_visibility  # noqa: E402

N, H, W, K = 2, 32, 64, 4  # K: shift in pixels, > the 3 px consistency floor, divisible by 2**2
DT = torch.float64


def _texture(seed=0, n=N, h=H, w=W):
    """Smooth random colour texture in [0, 1] (bilinear upsampling of coarse noise)."""
    g = torch.Generator().manual_seed(seed)
    coarse = torch.rand(n, 3, h // 4, w // 4, generator=g, dtype=DT)
    return F.interpolate(coarse, size=(h, w), mode="bilinear", align_corners=False)


def _shifted_pair(k=K, seed=0):
    """img2 = img1 moved right by k px (what enters on the left is other texture)."""
    img1 = _texture(seed)
    img2 = _texture(seed + 100)
    img2[..., k:] = img1[..., : W - k]
    return img1, img2


def _uniform_pyramid(dx, scales=4, n=N, h=H, w=W, grad=False):
    """Like PWCNet.multiscale: entry s at (h/2**s, w/2**s) in pixels of that resolution."""
    out = []
    for s in range(scales):
        f = torch.zeros(n, 2, h // 2 ** s, w // 2 ** s, dtype=DT)
        f[:, 0] = dx / 2 ** s
        out.append(f.requires_grad_(grad))
    return out


def test_true_flow_of_a_shift_gives_zero_photometric_and_the_expected_masks():
    img1, img2 = _shifted_pair()
    out = flow_loss(img1, img2, _uniform_pyramid(K), _uniform_pyramid(-K))
    assert isinstance(out, FlowLossOutput)
    assert out.photometric.item() == pytest.approx(0.0, abs=1e-9)
    assert out.flow_smooth.item() == pytest.approx(0.0, abs=1e-12)
    # image-1 pixels whose content leaves image 2 (last K columns) are invalid, the rest valid
    v12 = out.valid12[:, 0]
    assert torch.equal(v12[..., : W - K], torch.ones(N, H, W - K, dtype=DT))
    assert torch.equal(v12[..., W - K:], torch.zeros(N, H, K, dtype=DT))
    # image-2 pixels that came from outside image 1 (first K columns) are invalid
    v21 = out.valid21[:, 0]
    assert torch.equal(v21[..., :K], torch.zeros(N, H, K, dtype=DT))
    assert torch.equal(v21[..., K:], torch.ones(N, H, W - K, dtype=DT))
    # exact inverse flows: no forward-backward difference where valid, score 1 / 0.1 there
    assert out.fb_diff12[..., : W - K].abs().max() < 1e-12
    assert torch.allclose(out.score12, 10.0 * out.valid12)
    assert torch.allclose(out.score21, 10.0 * out.valid21)


def test_wrong_flows_cost_more_than_the_true_one():
    img1, img2 = _shifted_pair()
    true = flow_loss(img1, img2, _uniform_pyramid(K), _uniform_pyramid(-K)).photometric.item()
    zero = flow_loss(img1, img2, _uniform_pyramid(0.0), _uniform_pyramid(0.0)).photometric.item()
    half = flow_loss(img1, img2, _uniform_pyramid(K / 2), _uniform_pyramid(-K / 2)).photometric.item()
    assert true < 1e-9
    assert zero > 0.01 and half > 0.01
    assert zero > half  # further from the truth, larger error (smooth texture)


def test_noise_raises_the_loss_of_the_true_flow_a_little():
    img1, img2 = _shifted_pair()
    g = torch.Generator().manual_seed(5)
    noisy = (img2 + 0.02 * torch.randn(img2.shape, generator=g, dtype=DT)).clamp(0, 1)
    clean = flow_loss(img1, img2, _uniform_pyramid(K), _uniform_pyramid(-K)).photometric.item()
    dirty = flow_loss(img1, noisy, _uniform_pyramid(K), _uniform_pyramid(-K)).photometric.item()
    zero = flow_loss(img1, noisy, _uniform_pyramid(0.0), _uniform_pyramid(0.0)).photometric.item()
    assert clean < dirty < zero


def test_scales_are_summed_with_equal_weight():
    img1, img2 = _shifted_pair()
    f12, f21 = _uniform_pyramid(1.5), _uniform_pyramid(-0.5)
    one = flow_loss(img1, img2, f12, f21, n_scales=1).photometric.item()
    per_scale = []
    for s in range(3):
        i1 = F.adaptive_avg_pool2d(img1, (H // 2 ** s, W // 2 ** s))
        i2 = F.adaptive_avg_pool2d(img2, (H // 2 ** s, W // 2 ** s))
        per_scale.append(flow_loss(i1, i2, f12[s:], f21[s:], n_scales=1).photometric.item())
    assert per_scale[0] == pytest.approx(one, rel=1e-12)
    assert flow_loss(img1, img2, f12, f21, n_scales=3).photometric.item() == pytest.approx(sum(per_scale), rel=1e-9)


def test_gradients_reach_the_flows_of_the_scales_in_use_only():
    img1, img2 = _shifted_pair()
    f12 = _uniform_pyramid(K - 0.3, grad=True)
    f21 = _uniform_pyramid(-K + 0.6, grad=True)
    out = flow_loss(img1, img2, f12, f21, n_scales=3)
    assert out.total.requires_grad and out.photometric.requires_grad
    out.total.backward()
    for s in range(3):
        assert f12[s].grad is not None and f12[s].grad.abs().sum() > 0
        assert f21[s].grad is not None and f21[s].grad.abs().sum() > 0
    assert f12[3].grad is None and f21[3].grad is None
    for m in (out.valid12, out.valid21, out.fb_diff12, out.fb_diff21, out.score12, out.score21):
        assert not m.requires_grad


def test_output_shapes_and_the_weighted_total():
    img1, img2 = _shifted_pair()
    xs = torch.arange(W, dtype=DT)
    f12 = _uniform_pyramid(1.0)
    for s, f in enumerate(f12):
        f[:, 0] += 0.002 * (xs[: W // 2 ** s] * 2 ** s) ** 2 / 2 ** s  # curved: smoothness > 0
    out = flow_loss(img1, img2, f12, _uniform_pyramid(-1.0), w_flow_smooth=7.0)
    assert out.photometric.shape == () and out.flow_smooth.shape == ()
    assert out.flow_smooth.item() > 0
    assert out.total.item() == pytest.approx(out.photometric.item() + 7.0 * out.flow_smooth.item(), rel=1e-12)
    for m in (out.valid12, out.valid21, out.score12, out.score21):
        assert m.shape == (N, 1, H, W)
    assert out.fb_diff12.shape == (N, 2, H, W) and out.fb_diff21.shape == (N, 2, H, W)


def test_visibility_only_ignores_a_forward_backward_disagreement():
    img1, img2 = _shifted_pair()
    f12, f21 = _uniform_pyramid(K), _uniform_pyramid(-K)
    f12[0][:, 0, 8:16, 10:20] += 6.0  # breaks consistency in a block of image 1 (scale 0)
    with_c = flow_loss(img1, img2, f12, f21)
    without = flow_loss(img1, img2, f12, f21, use_consistency=False)
    assert with_c.valid12[:, :, 8:16, 10:20].max().item() == 0.0
    assert torch.equal(without.valid12, splat_visibility(f21[0]))
    assert without.valid12[:, :, 8:16, 10:20].min().item() == 1.0
    # the wrong block is masked out with consistency, so it costs less than when it counts
    assert with_c.photometric.item() < without.photometric.item()


def test_accepts_the_outputs_of_pwcnet_multiscale_and_trains_it():
    small = PWCConfig(pyramid_channels=(8, 16, 24, 32, 48, 64), estimator_channels=(16, 16, 12, 8, 8),
                      context_channels=(16, 16, 16, 12, 8, 8))
    torch.manual_seed(0)
    net = PWCNet(small)
    img1 = _texture(1, n=1, h=64, w=128).float()
    img2 = torch.roll(img1, shifts=2, dims=3)
    flows = net(torch.cat((img1, img2)), torch.cat((img2, img1)))
    ms = net.multiscale(flows, (64, 128))
    out = flow_loss(img1, img2, [f[:1] for f in ms], [f[1:] for f in ms])
    assert torch.isfinite(out.total)
    out.total.backward()
    grads = [p.grad for p in net.parameters() if p.grad is not None]
    assert grads and sum(g.abs().sum().item() for g in grads) > 0


def test_real_frames_with_dis_flow_cost_less_than_zero_flow(sample_seq):
    cv2 = pytest.importorskip("cv2")
    size = (192, 64)  # (w, h) for cv2
    a, b = (cv2.resize(cv2.imread(str(sample_seq / "image_0" / f"{i:06d}.jpg"), cv2.IMREAD_GRAYSCALE), size,
                       interpolation=cv2.INTER_AREA) for i in (0, 2))
    dis = cv2.DISOpticalFlow.create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    fw, bw = dis.calc(a, b, None), dis.calc(b, a, None)

    def pyramid(flow):
        f = torch.from_numpy(np.ascontiguousarray(flow.transpose(2, 0, 1)))[None].double()
        return [F.interpolate(f, size=(64 // 2 ** s, 192 // 2 ** s), mode="bilinear", align_corners=False) / 2 ** s
                for s in range(3)]

    def img(x):
        return torch.from_numpy(x).double().div(255.0)[None, None].expand(1, 3, 64, 192).contiguous()

    i1, i2 = img(a), img(b)
    out = flow_loss(i1, i2, pyramid(fw), pyramid(bw))
    zero = flow_loss(i1, i2, pyramid(0 * fw), pyramid(0 * bw))
    assert out.photometric.item() < 0.8 * zero.photometric.item()
    assert out.valid12.mean().item() > 0.6  # most of the image is seen and consistent


def test_bad_inputs_raise_input_error():
    img1, img2 = _shifted_pair()
    f = _uniform_pyramid(0.0)
    with pytest.raises(InputError):
        flow_loss(img1, img2[..., :32], f, f)
    with pytest.raises(InputError):
        flow_loss(img1, img2, f[:2], f[:2], n_scales=3)
    with pytest.raises(InputError):
        flow_loss(img1, img2, f, f, n_scales=0)
    with pytest.raises(InputError):
        flow_loss(img1, img2, [f[1]] + f[1:], f)  # scale 0 at the wrong size
