"""PWC-Net building blocks (exact small cases), output shapes, and a tiny overfit."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="needs torch (pip install 'trianflow-vo[torch]')")
import torch.nn.functional as F  # noqa: E402

from trianflow_vo.models.losses import photometric_error, smoothness  # noqa: E402
from trianflow_vo.models.pwc import PWCConfig, PWCNet, cost_volume, upsample_flow, warp  # noqa: E402

SMALL = PWCConfig(pyramid_channels=(8, 16, 24, 32, 48, 64), estimator_channels=(32, 32, 24, 16, 8),
                  context_channels=(32, 32, 32, 24, 16, 8))


def test_warp_integer_shift_is_exact():
    feat = torch.arange(2 * 5 * 7, dtype=torch.float64).view(1, 2, 5, 7)
    flow = torch.zeros(1, 2, 5, 7, dtype=torch.float64)
    flow[:, 0] = 2.0  # sample 2 px to the right
    flow[:, 1] = -1.0  # and 1 px up
    out = warp(feat, flow)
    assert torch.allclose(out[:, :, 1:, :5], feat[:, :, :4, 2:], atol=1e-9)
    assert torch.allclose(out[:, :, 0], torch.zeros(1)[0].double(), atol=1e-9)  # above the image: zeros
    assert out[:, :, :, 5:].abs().max() < 1e-9


def test_cost_volume_matches_naive_loop():
    g = torch.Generator().manual_seed(0)
    f1 = torch.randn(2, 3, 5, 6, generator=g, dtype=torch.float64)
    f2 = torch.randn(2, 3, 5, 6, generator=g, dtype=torch.float64)
    d = 2
    cv = cost_volume(f1, f2, d)
    assert cv.shape == (2, 25, 5, 6)
    ref = torch.zeros_like(cv)
    for k, (dy, dx) in enumerate((dy, dx) for dy in range(-d, d + 1) for dx in range(-d, d + 1)):
        for y in range(5):
            for x in range(6):
                if 0 <= y + dy < 5 and 0 <= x + dx < 6:
                    ref[:, k, y, x] = (f1[:, :, y, x] * f2[:, :, y + dy, x + dx]).mean(dim=1)
    assert torch.allclose(cv, ref, atol=1e-12)


def test_gradients_through_warp_and_cost_volume():
    g = torch.Generator().manual_seed(1)
    f1 = torch.randn(1, 2, 4, 5, generator=g, dtype=torch.float64, requires_grad=True)
    f2 = torch.randn(1, 2, 4, 5, generator=g, dtype=torch.float64, requires_grad=True)
    # away from integer positions: bilinear sampling is smooth there
    flow = (0.3 + 0.4 * torch.rand(1, 2, 4, 5, generator=g, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b, f: cost_volume(a, warp(b, f), 1), (f1, f2, flow))


def test_upsample_flow_scales_values():
    flow = torch.ones(1, 2, 4, 6)
    up = upsample_flow(flow, (8, 12))
    assert up.shape == (1, 2, 8, 12)
    assert torch.allclose(up, torch.full_like(up, 2.0))
    up = upsample_flow(flow, (8, 24))  # x by 4, y by 2
    assert torch.allclose(up[:, 0], torch.full_like(up[:, 0], 4.0))
    assert torch.allclose(up[:, 1], torch.full_like(up[:, 1], 2.0))


def _textured(h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    small = rng.uniform(0, 1, (3, h // 4, w // 4)).astype(np.float32)
    return np.stack([cv2.resize(c, (w, h), interpolation=cv2.INTER_CUBIC) for c in small])


def test_shifted_pair_gives_finite_flow_at_every_scale():
    torch.manual_seed(0)
    net = PWCNet().eval()
    h, w, shift = 64, 192, 3
    big = _textured(h, w + shift, 0)
    img1 = torch.from_numpy(big[:, :, shift:].copy())[None]  # frame 2 = frame 1 moved 3 px right
    img2 = torch.from_numpy(big[:, :, :w].copy())[None]
    with torch.no_grad():
        flows = net(img1, img2)
        fw, bw = net.forward_backward(img1, img2)
    assert len(flows) == 5  # levels 2..6
    for k, f in enumerate(flows):
        assert f.shape == (1, 2, h // 2 ** (2 + k), w // 2 ** (2 + k))
        assert torch.isfinite(f).all()
    assert fw.shape == bw.shape == (1, 2, h, w)
    assert torch.isfinite(fw).all() and torch.isfinite(bw).all()
    # the batched forward-backward decoding equals two separate calls
    with torch.no_grad():
        fw1 = net.full_flow(net(img1, img2)[0], (h, w))
        bw1 = net.full_flow(net(img2, img1)[0], (h, w))
    assert torch.allclose(fw, fw1, atol=1e-5) and torch.allclose(bw, bw1, atol=1e-5)


def test_size_not_multiple_of_64_is_rejected():
    net = PWCNet(SMALL)
    with pytest.raises(ValueError, match="multiple of 64"):
        net(torch.zeros(1, 3, 100, 192), torch.zeros(1, 3, 100, 192))


def test_overfit_one_real_pair_reduces_warping_error(sample_seq):
    """A few hundred Adam steps on one KITTI pair: gradients reach the network through
    warping and the cost volume. Reduced channel widths (SMALL) keep it fast; same structure."""
    h, w = 64, 192

    def load(name):
        im = cv2.imread(str(sample_seq / "image_0" / name), cv2.IMREAD_GRAYSCALE)
        im = cv2.resize(im, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
        return torch.from_numpy(np.repeat(im[None], 3, axis=0))[None]

    img1, img2 = load("000000.jpg"), load("000001.jpg")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # a shared machine: OpenMP spin-waiting with 2 threads is 10x slower
    try:
        torch.manual_seed(0)
        net = PWCNet(SMALL)
        opt = torch.optim.Adam(net.parameters(), lr=1e-3)
        with torch.no_grad():
            err_zero = float(photometric_error(img1, img2, torch.zeros(1, 2, h, w)))
            err_init = float(photometric_error(img1, img2, net.full_flow(net(img1, img2)[0], (h, w))))
        for _ in range(150):
            flows = net(img1, img2)
            loss = photometric_error(img1, img2, net.full_flow(flows[0], (h, w))) + 0.05 * smoothness(flows[0])
            opt.zero_grad()
            loss.backward()
            opt.step()
        with torch.no_grad():
            err_final = float(photometric_error(img1, img2, net.full_flow(net(img1, img2)[0], (h, w))))
    finally:
        torch.set_num_threads(threads)
    # seen on this pair: ~0.29 of the zero-flow error, ~0.22 of the initial error
    assert err_final < 0.5 * err_zero, (err_final, err_zero)
    assert err_final < 0.5 * err_init, (err_final, err_init)


@pytest.mark.parametrize("connections", ["pairwise", "dense"])
def test_estimator_connections(connections):
    """Both estimator variants give flow of the right shape at every scale; the
    pairwise one (TrianFlow's released variant, the default) is the lighter."""
    cfg = PWCConfig(pyramid_channels=SMALL.pyramid_channels, estimator_channels=SMALL.estimator_channels,
                    estimator_connections=connections)
    net = PWCNet(cfg).eval()
    x = torch.rand(1, 3, 64, 128)
    with torch.no_grad():
        flows = net(x, x)
    assert [tuple(f.shape) for f in flows] == [(1, 2, 64 // 2 ** k, 128 // 2 ** k) for k in range(2, 7)]
    assert all(torch.isfinite(f).all() for f in flows)
    n_params = sum(p.numel() for p in net.parameters())
    other = "dense" if connections == "pairwise" else "pairwise"
    other_net = PWCNet(PWCConfig.from_dict({**cfg.to_dict(), "estimator_connections": other}))
    n_other = sum(p.numel() for p in other_net.parameters())
    assert (n_params < n_other) == (connections == "pairwise")


def test_unknown_connections_rejected():
    with pytest.raises(ValueError, match="estimator_connections"):
        PWCNet(PWCConfig(estimator_connections="sparse"))


def test_default_is_the_authors_flow_network():
    """Pyramid 16..196, estimator inputs 81 / 81 + C_l + 2, context input 2 + 32: the
    parameter count of their flow model (fpyramid + pwc_model, 5,134,324)."""
    net = PWCNet()
    assert net.config.pyramid_channels == (16, 32, 64, 96, 128, 196)
    assert net.config.estimator_connections == "pairwise"
    assert sum(p.numel() for p in net.parameters()) == 5_134_324
    sd = net.state_dict()
    assert tuple(sd["estimators.0.convs.0.0.weight"].shape) == (128, 81, 3, 3)  # level 6: cost volume only
    assert tuple(sd["estimators.1.convs.0.0.weight"].shape) == (128, 81 + 128 + 2, 3, 3)
    assert tuple(sd["estimators.4.convs.0.0.weight"].shape) == (128, 81 + 32 + 2, 3, 3)
    assert tuple(sd["context.net.0.0.weight"].shape) == (128, 34, 3, 3)


def test_decoder_wiring_is_the_authors():
    """Hooks on the estimators and the context network: level 6 sees the raw cost volume (no
    activation, negative values kept), level 5 sees [cost(f1, warp(f2, up)), f1, up] with
    up = 2 x bilinear of the level-6 flow, the context sees [flow2, x4] and is added to flow2."""
    torch.manual_seed(0)
    net = PWCNet().eval()
    h, w = 64, 128
    g = torch.Generator().manual_seed(1)
    chans = net.config.pyramid_channels
    f1 = [torch.randn(1, c, h // 2 ** (i + 1), w // 2 ** (i + 1), generator=g) for i, c in enumerate(chans)]
    f2 = [torch.randn(1, c, h // 2 ** (i + 1), w // 2 ** (i + 1), generator=g) for i, c in enumerate(chans)]
    seen = {}
    hooks = [net.estimators[k].register_forward_hook(
        lambda m, i, o, k=k: seen.__setitem__(f"est{k}", (i[0], o))) for k in (0, 1, 4)]
    hooks.append(net.context.register_forward_hook(lambda m, i, o: seen.__setitem__("ctx", (i[0], o))))
    with torch.no_grad():
        flows = net.decode(f1, f2)
    for hk in hooks:
        hk.remove()
    x6, (_, flow6) = seen["est0"]
    cost6 = cost_volume(f1[5], f2[5], 4)
    assert (cost6 < 0).any()
    assert torch.equal(x6, cost6)
    assert torch.equal(flows[4], flow6)  # level 6: the prediction is the flow
    x5, (_, res5) = seen["est1"]
    up6 = F.interpolate(flow6, scale_factor=2.0, mode="bilinear", align_corners=False) * 2.0
    assert torch.allclose(x5[:, :81], cost_volume(f1[4], warp(f2[4], up6), 4), atol=1e-6)
    assert torch.equal(x5[:, 81:81 + 128], f1[4])
    assert torch.allclose(x5[:, 81 + 128:], up6, atol=1e-6)
    assert torch.allclose(flows[3], res5 + up6, atol=1e-6)
    ctx_in, ctx_out = seen["ctx"]
    (feat2, res2) = seen["est4"][1]
    assert ctx_in.shape[1] == 2 + 32
    assert torch.equal(ctx_in[:, 2:], feat2)  # x4 of the level-2 estimator, after the flow
    assert torch.allclose(flows[0], ctx_in[:, :2] + ctx_out, atol=1e-6)


def test_multiscale_outputs_as_the_authors():
    """Their outputs: flow_(2+k) x 4 resized to (H / 2**k, W / 2**k); output 0 = full_flow."""
    torch.manual_seed(0)
    net = PWCNet(SMALL).eval()
    x1, x2 = torch.rand(1, 3, 64, 128), torch.rand(1, 3, 64, 128)
    with torch.no_grad():
        flows = net(x1, x2)
        outs = net.multiscale(flows, (64, 128))
        fw, _ = net.forward_backward(x1, x2)
    assert [tuple(o.shape) for o in outs] == [(1, 2, 64 // 2 ** k, 128 // 2 ** k) for k in range(4)]
    assert torch.allclose(outs[0], net.full_flow(flows[0], (64, 128)), atol=1e-6)
    assert torch.allclose(outs[0], fw, atol=1e-5)
    assert torch.allclose(outs[1], F.interpolate(flows[1] * 4.0, size=(32, 64), mode="bilinear"), atol=1e-6)
