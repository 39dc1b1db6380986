"""OnnxFlow on an exported (tiny) PWC-Net: shapes, resizing, agreement with torch."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="needs torch to export the flow network")
pytest.importorskip("onnx", reason="needs onnx to export the flow network")
pytest.importorskip("onnxruntime", reason="needs onnxruntime to run the exported flow network")

from trianflow_vo.flow.onnx_flow import OnnxFlow, PreparedFrame, _flow_to_working  # noqa: E402
from trianflow_vo.models.export import FlowGraph, export_flow  # noqa: E402
from trianflow_vo.models.pwc import PWCConfig, PWCNet  # noqa: E402

SIZE = (64, 192)
# narrow widths and search range 2 keep the export quick; the structure is the default one
TINY = PWCConfig(pyramid_channels=(8, 8, 16, 16, 16, 16), estimator_channels=(8, 8, 8, 8, 8),
                 context_channels=(8, 8, 8, 8, 8, 8), search_range=2)
NORM_FLOW = {"mean": [0.0, 0.0, 0.0], "std": [1.0, 1.0, 1.0]}


@pytest.fixture(scope="module")
def flow_model(tmp_path_factory):
    d = tmp_path_factory.mktemp("onnx_flow")
    torch.manual_seed(0)
    flow_net = PWCNet(TINY).eval()
    with torch.no_grad():
        for est in flow_net.estimators:
            est.predict.weight.mul_(5.0)
    export_flow(flow_net, NORM_FLOW, SIZE, "RGB", d / "flow.onnx")
    return d / "flow.onnx", flow_net


def _image(h, w, seed):
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, (h, w, 3), dtype=np.uint8)


def test_flow_shapes_and_agreement_with_torch(flow_model):
    path, flow_net = flow_model
    src = OnnxFlow(path, threads=1)
    a, b = _image(*SIZE, 0), _image(*SIZE, 1)
    fw, bw = src.flow_pair(src.prepare(a), src.prepare(b))
    assert fw.shape == bw.shape == (64, 192, 2)
    assert fw.dtype == bw.dtype == np.float32
    assert src.n_inferences == 1  # both directions from one call
    graph = FlowGraph(flow_net, NORM_FLOW).eval()
    to_t = lambda im: torch.from_numpy(im[:, :, ::-1].transpose(2, 0, 1).astype(np.float32).copy())[None]  # noqa: E731
    with torch.no_grad():
        tfw, tbw = graph(to_t(a), to_t(b))  # RGB, as the metadata says
    assert np.abs(tfw[0].numpy().transpose(1, 2, 0)).max() > 1.0
    assert np.allclose(fw, tfw[0].numpy().transpose(1, 2, 0), rtol=1e-5, atol=1e-4)
    assert np.allclose(bw, tbw[0].numpy().transpose(1, 2, 0), rtol=1e-5, atol=1e-4)
    desc = src.describe()
    assert desc["input_size"] == [64, 192] and desc["threads"] == 1


def test_flow_source_api(flow_model):
    path, _ = flow_model
    src = OnnxFlow(path, threads=1)
    assert src.name == "onnx-pwc"
    assert src.info.kind == "flow" and src.info.input_size == SIZE and src.info.channel_order == "RGB"
    frame = src.prepare(_image(*SIZE, 4))
    assert isinstance(frame, PreparedFrame) and frame.hw == SIZE
    assert frame.tensor.shape == (1, 3, 64, 192) and frame.tensor.dtype == np.float32
    desc = src.describe()
    assert desc["name"] == "onnx-pwc" and desc["path"] == str(path) and desc["channel_order"] == "RGB"
    assert desc["resize"] == "area-down-linear-up" and desc["config"]["search_range"] == 2
    with pytest.raises(ValueError, match="different working sizes"):
        src.flow_pair(frame, src.prepare(_image(128, 320, 5)))
    assert src.n_inferences == 0
    src.flow_pair(frame, frame)
    src.flow_pair(frame, frame)
    assert src.n_inferences == 2


def test_flow_at_other_working_size(flow_model):
    path, _ = flow_model
    src = OnnxFlow(path)
    a, b = _image(128, 320, 2), _image(128, 320, 3)
    fw, bw = src.flow_pair(src.prepare(a), src.prepare(b))
    assert fw.shape == bw.shape == (128, 320, 2)
    assert np.isfinite(fw).all() and np.isfinite(bw).all()


def test_flow_rescaled_to_working_pixels():
    const = np.zeros((2, 64, 192), np.float32)
    const[0], const[1] = 1.0, 2.0
    out = _flow_to_working(const, (128, 320))  # x scaled by 320/192, y by 2
    assert out.shape == (128, 320, 2)
    assert np.allclose(out[..., 0], 320 / 192) and np.allclose(out[..., 1], 4.0)
    same = _flow_to_working(const, (64, 192))
    assert np.array_equal(same[..., 1], const[1])
