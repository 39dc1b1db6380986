"""ResNet18 encoder and DispNet decoder: shapes, depth range, parameter layout."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch", reason="needs torch (pip install 'trianflow-vo[torch]')")

from trianflow_vo.models.depth_net import DepthConfig, DepthNet, disp_to_depth  # noqa: E402
from trianflow_vo.models.resnet_encoder import ResNet18Encoder  # noqa: E402


def test_disp_to_depth_end_points_and_monotonic():
    sigma = torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64)
    d = disp_to_depth(sigma, 0.1, 100.0)
    assert d[0].item() == pytest.approx(100.0)
    assert d[2].item() == pytest.approx(0.1)
    # disparity is linear in sigma: 1/d(0.5) is the mean of 1/100 and 1/0.1
    assert (1.0 / d[1]).item() == pytest.approx(0.5 * (0.01 + 10.0))


def test_encoder_shapes_and_parameter_count():
    enc = ResNet18Encoder().eval()
    with torch.no_grad():
        feats = enc(torch.zeros(1, 3, 64, 192))
    shapes = [tuple(f.shape) for f in feats]
    assert shapes == [(1, 64, 32, 96), (1, 64, 16, 48), (1, 128, 8, 24), (1, 256, 4, 12), (1, 512, 2, 6)]
    # ResNet18 without the 1000-class fc layer (513000 parameters): 11689512 - 513000
    assert sum(p.numel() for p in enc.parameters()) == 11_176_512
    names = set(enc.state_dict())
    assert {"conv1.weight", "bn1.running_mean", "layer2.0.downsample.0.weight", "layer4.1.bn2.bias"} <= names


def test_depth_net_scales_and_range():
    torch.manual_seed(0)
    net = DepthNet(DepthConfig(scales=(0, 1, 2, 3))).eval()
    img = torch.randn(2, 3, 64, 192)
    with torch.no_grad():
        out = net(img)
        depth = net.depth(img)
    assert sorted(out) == [0, 1, 2, 3]
    for s, sigma in out.items():
        assert sigma.shape == (2, 1, 64 // 2 ** s, 192 // 2 ** s)
        assert torch.all((sigma > 0) & (sigma < 1))
    assert depth.shape == (2, 1, 64, 192)
    assert torch.all((depth >= 0.1) & (depth <= 100.0))


def test_default_is_the_authors_decoder():
    """Scale 0 only (their depth_scale: 1), their channel widths, depth = 1 / (0.01 + 9.99 sigma)."""
    net = DepthNet().eval()
    assert net.config.scales == (0,)
    names = set(net.state_dict())
    assert {"decoder.dispconv.0.conv.weight", "decoder.upconv0.0.conv.weight"} <= names
    assert not any(n.startswith("decoder.dispconv.1") for n in names)
    shapes = {k: tuple(v.shape) for k, v in net.state_dict().items()}
    assert shapes["decoder.upconv0.0.conv.weight"] == (256, 512, 3, 3)
    assert shapes["decoder.upconv1.3.conv.weight"] == (32, 96, 3, 3)  # 32 + 64 skip channels
    assert shapes["decoder.upconv1.4.conv.weight"] == (16, 16, 3, 3)  # no skip at full resolution
    sigma = torch.tensor([0.0, 0.25, 1.0])
    assert torch.allclose(disp_to_depth(sigma, 0.1, 100.0), 1.0 / (0.01 + 9.99 * sigma))
    with pytest.raises(ValueError, match="including 0"):
        DepthNet(DepthConfig(scales=(1, 2)))


def test_custom_depth_range_and_bad_size():
    net = DepthNet(DepthConfig(min_depth=1.0, max_depth=10.0)).eval()
    with torch.no_grad():
        d = net.depth(torch.randn(1, 3, 64, 64))
    assert torch.all((d >= 1.0) & (d <= 10.0))
    with pytest.raises(ValueError, match="multiple of 32"):
        net(torch.zeros(1, 3, 70, 64))
