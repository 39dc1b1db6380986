"""The matrix-product cost volume (``pwc.cost_volume``) against its definition.

Known answers first (a naive per-pixel loop in float64, an image pair shifted by a known
amount), then random inputs against ``cost_volume_reference`` (the slice/multiply/mean loop
the network was written with): values, borders, tile edge cases, gradients, inside PWCNet,
and in an exported ONNX graph run by onnxruntime.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="needs torch (pip install 'trianflow-vo[torch]')")

from trianflow_vo.models import pwc  # noqa: E402
from trianflow_vo.models.pwc import (  # noqa: E402
    COST_TILE,
    PWCConfig,
    PWCNet,
    cost_volume,
    cost_volume_reference,
)


def naive_cost_volume(f1: np.ndarray, f2: np.ndarray, d: int) -> np.ndarray:
    """Pixel by pixel, float64: ``(N, C, H, W)`` x2 -> ``(N, (2d+1)**2, H, W)``, dy major."""
    n, c, h, w = f1.shape
    k = 2 * d + 1
    out = np.zeros((n, k * k, h, w))
    for ky, dy in enumerate(range(-d, d + 1)):
        for kx, dx in enumerate(range(-d, d + 1)):
            for y in range(h):
                for x in range(w):
                    if 0 <= y + dy < h and 0 <= x + dx < w:
                        out[:, ky * k + kx, y, x] = (f1[:, :, y, x] * f2[:, :, y + dy, x + dx]).mean(axis=1)
    return out


def _pair(shape, seed, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(*shape, generator=g, dtype=dtype), torch.randn(*shape, generator=g, dtype=dtype)


# shapes (N, C, H, W) and search ranges chosen around the tile width T = COST_TILE: W below,
# equal to, not a multiple of, and a multiple of T; d = 0; 2d > T (windows over 3 blocks);
# H and W smaller than 2d + 1 (every shift partly outside the image)
CASES = [
    ((1, 1, 1, 1), 0),
    ((2, 3, 5, 6), 2),
    ((1, 4, 7, COST_TILE), 1),
    ((2, 2, 4, COST_TILE + 3), 4),
    ((1, 3, 6, 3 * COST_TILE), 3),
    ((1, 2, 3, 4), 4),
    ((1, 2, 9, 2 * COST_TILE + 5), COST_TILE + 1),
]


@pytest.mark.parametrize("shape,d", CASES)
def test_equals_the_definition_pixel_by_pixel(shape, d):
    f1, f2 = _pair(shape, seed=sum(shape) + d)
    want = naive_cost_volume(f1.numpy(), f2.numpy(), d)
    got = cost_volume(f1, f2, d)
    assert got.shape == want.shape
    np.testing.assert_allclose(got.numpy(), want, rtol=0, atol=1e-12)
    np.testing.assert_allclose(cost_volume_reference(f1, f2, d).numpy(), want, rtol=0, atol=1e-12)


def test_known_shift_peaks_at_the_right_channel_and_zero_outside():
    # f2 is f1 moved by (+2, -1) px: f2[y, x] = f1[y + 1, x - 2]; then f1[y, x] = f2[y - 1, x + 2],
    # so the channel (dx, dy) = (2, -1) holds mean_c f1**2 wherever (y - 1, x + 2) is inside.
    d, (dx, dy) = 3, (2, -1)
    g = torch.Generator().manual_seed(3)
    f1 = torch.randn(1, 5, 12, 20, generator=g)
    f1 = f1 / f1.norm(dim=1, keepdim=True)  # unit vectors: only the true shift reaches mean_c f1**2 = 1/C
    f2 = torch.zeros_like(f1)
    f2[:, :, :-1, 2:] = f1[:, :, 1:, :-2]
    cv = cost_volume(f1, f2, d)
    k = 2 * d + 1
    ch = (dy + d) * k + (dx + d)
    inside = (slice(1, 12), slice(0, 20 - 2))
    assert torch.allclose(cv[0, ch][inside], torch.full((11, 18), 1 / 5), atol=1e-6)
    assert torch.all(cv[0, ch, 0] == 0) and torch.all(cv[0, ch, :, -2:] == 0)  # shifted off the image
    # where the true shift and f2's content are inside, it wins against every other shift
    assert torch.all(cv[0].argmax(dim=0)[d:-d, d:-d] == ch)
    # shifts that leave the image give exact zeros: dy = -d at row 0, dx = +d at the last d columns
    assert torch.all(cv[0, :k, 0] == 0)
    assert torch.all(cv[0, (k - 1)::k, :, -d:] == 0)


@pytest.mark.parametrize("d", [1, 2, 4, 6])
@pytest.mark.parametrize("shape", [(2, 32, 16, 52), (1, 64, 8, 26), (2, 16, 5, 13)])
def test_equals_the_reference_in_float32(shape, d):
    f1, f2 = _pair(shape, seed=d, dtype=torch.float32)
    f1, f2 = 3.0 * f1, 3.0 * f2  # feature magnitudes of a few units, as after the pyramid
    got, ref = cost_volume(f1, f2, d), cost_volume_reference(f1, f2, d)
    assert got.dtype == torch.float32 and got.shape == ref.shape
    assert float((got - ref).abs().max()) <= 1e-6 * max(1.0, float(ref.abs().max()))


def test_gradients_equal_the_reference_and_pass_gradcheck():
    f1, f2 = _pair((2, 3, 5, COST_TILE + 3), seed=7)
    up = torch.randn(2, 25, 5, COST_TILE + 3, generator=torch.Generator().manual_seed(8), dtype=torch.float64)
    grads = []
    for fn in (cost_volume, cost_volume_reference):
        a, b = f1.clone().requires_grad_(), f2.clone().requires_grad_()
        (fn(a, b, 2) * up).sum().backward()
        grads.append((a.grad, b.grad))
    (ga, gb), (ra, rb) = grads
    assert float(ra.abs().max()) > 0.1 and float(rb.abs().max()) > 0.1
    assert torch.allclose(ga, ra, atol=1e-12) and torch.allclose(gb, rb, atol=1e-12)
    a, b = _pair((1, 2, 3, 5), seed=9)
    assert torch.autograd.gradcheck(lambda x, y: cost_volume(x, y, 2),
                                    (a.requires_grad_(), b.requires_grad_()))


def _saved_bytes(fn, f1, f2, d) -> int:
    """Bytes of the distinct storages autograd keeps for the backward pass of ``fn``."""
    seen = {}

    def pack(x):
        seen[x.untyped_storage().data_ptr()] = x.untyped_storage().nbytes()
        return x

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda x: x):
        fn(f1, f2, d)
    return sum(seen.values())


def test_backward_keeps_about_as_much_memory_as_the_reference():
    # the reference keeps f1 and the padded f2 (its per-shift slices are views); the matrix
    # form keeps its tile and window copies (~1.6x here), not one copy per dy (~11x)
    f1, f2 = (x.float().requires_grad_() for x in _pair((2, 8, 16, 52), seed=12))
    ref = _saved_bytes(cost_volume_reference, f1, f2, 4)
    new = _saved_bytes(cost_volume, f1, f2, 4)
    assert ref >= 2 * f1.numel() * 4  # the measurement sees f1 and f2p
    assert new <= 2 * ref


def test_rejects_bad_inputs():
    f = torch.zeros(1, 2, 4, 4)
    with pytest.raises(ValueError, match="same shape"):
        cost_volume(f, torch.zeros(1, 2, 4, 5), 1)
    with pytest.raises(ValueError, match="same shape"):
        cost_volume(f[0], f[0], 1)
    with pytest.raises(ValueError, match="search_range"):
        cost_volume(f, f, -1)


def test_pwcnet_flow_unchanged_against_the_reference_cost_volume(monkeypatch):
    cfg = PWCConfig(pyramid_channels=(8, 16, 24, 32, 48, 64), estimator_channels=(32, 32, 24, 16, 8),
                    context_channels=(32, 32, 32, 24, 16, 8))
    torch.manual_seed(0)
    net = PWCNet(cfg).eval()
    g = torch.Generator().manual_seed(1)
    img1, img2 = torch.rand(1, 3, 64, 128, generator=g), torch.rand(1, 3, 64, 128, generator=g)
    with torch.no_grad():
        fw, bw = net.forward_backward(img1, img2)
        monkeypatch.setattr(pwc, "cost_volume", cost_volume_reference)
        rfw, rbw = net.forward_backward(img1, img2)
    assert float(rfw.abs().max()) > 1e-3  # a flow that is not trivially zero
    assert torch.allclose(fw, rfw, atol=1e-5) and torch.allclose(bw, rbw, atol=1e-5)


class _CostVolume(torch.nn.Module):
    def __init__(self, fn, d: int):
        super().__init__()
        self.fn, self.d = fn, d

    def forward(self, f1, f2):
        return self.fn(f1, f2, self.d)


@pytest.mark.parametrize("shape,d", [((2, 32, 16, 52), 4), ((1, 8, 5, 13), 2)])
def test_exported_onnx_graph_equals_torch(tmp_path, shape, d):
    onnx = pytest.importorskip("onnx")
    ort = pytest.importorskip("onnxruntime")
    from trianflow_vo.models.export import OPSET

    f1, f2 = _pair(shape, seed=11, dtype=torch.float32)
    path = tmp_path / "cv.onnx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(_CostVolume(cost_volume, d).eval(), (f1, f2), str(path), input_names=["f1", "f2"],
                          output_names=["cost"], opset_version=OPSET, dynamo=False)
    ops = [node.op_type for node in onnx.load(str(path)).graph.node]
    assert ops.count("MatMul") == 2 * d + 1 and "ReduceMean" not in ops  # the new formulation was exported
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    got = sess.run(None, {"f1": f1.numpy(), "f2": f2.numpy()})[0]
    ref = cost_volume_reference(f1, f2, d).numpy()
    assert got.shape == ref.shape
    assert float(np.abs(got - ref).max()) <= 1e-6
