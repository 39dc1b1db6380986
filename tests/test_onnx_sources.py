"""OnnxFlow / OnnxDepth: shapes, resizing, agreement with torch, depth cache, errors."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")

from trianflow_vo.models.depth_net import DepthNet  # noqa: E402
from trianflow_vo.models.export import DepthGraph, FlowGraph, export_depth, export_flow  # noqa: E402
from trianflow_vo.models.pwc import PWCConfig, PWCNet  # noqa: E402
from trianflow_vo.depth.onnx_depth import OnnxDepth  # noqa: E402
from trianflow_vo.errors import DependencyError, ModelError  # noqa: E402
from trianflow_vo.flow.onnx_flow import OnnxFlow, _flow_to_working  # noqa: E402

SIZE = (64, 192)
# narrow widths and search range 2 keep the export quick; the structure is the default one
TINY = PWCConfig(pyramid_channels=(8, 8, 16, 16, 16, 16), estimator_channels=(8, 8, 8, 8, 8),
                 context_channels=(8, 8, 8, 8, 8, 8), search_range=2)
NORM_FLOW = {"mean": [0.0, 0.0, 0.0], "std": [1.0, 1.0, 1.0]}
NORM_DEPTH = {"mean": [0.45, 0.45, 0.45], "std": [0.225, 0.225, 0.225]}


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    d = tmp_path_factory.mktemp("onnx")
    torch.manual_seed(0)
    flow_net = PWCNet(TINY).eval()
    with torch.no_grad():
        for est in flow_net.estimators:
            est.predict.weight.mul_(5.0)
    depth_net = DepthNet().eval()
    export_flow(flow_net, NORM_FLOW, SIZE, "RGB", d / "flow.onnx")
    export_depth(depth_net, NORM_DEPTH, SIZE, "RGB", d / "depth.onnx")
    return d, flow_net, depth_net


def _image(h, w, seed):
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, (h, w, 3), dtype=np.uint8)


def test_flow_shapes_and_agreement_with_torch(models):
    d, flow_net, _ = models
    src = OnnxFlow(d / "flow.onnx", threads=1)
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


def test_flow_at_other_working_size(models):
    d, _, _ = models
    src = OnnxFlow(d / "flow.onnx")
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


def test_depth_once_per_frame_and_agreement(models):
    d, _, depth_net = models
    src = OnnxDepth(d / "depth.onnx", threads=1)
    assert src.is_metric_prior is True
    imgs = {i: _image(*SIZE, 10 + i) for i in range(5)}
    d0 = src.predict(0, imgs[0])
    assert d0.shape == SIZE and d0.dtype == np.float32
    assert np.all((d0 >= 0.1) & (d0 <= 100.0))
    assert src.predict(0, imgs[0]) is d0  # pair (0, 1) then pair (1, 2): no recomputation
    src.predict(1, imgs[1])
    src.predict(1, imgs[1])
    assert src.n_inferences == 2
    src.forget(0)
    src.predict(0, imgs[0])
    assert src.n_inferences == 3
    for i in (2, 3, 4):  # cache of 3: frame 1 falls out
        src.predict(i, imgs[i])
    src.predict(1, imgs[1])
    assert src.n_inferences == 7
    src.observe(1, np.zeros((3, 2)), np.ones(3), np.ones(3))  # a no-op
    graph = DepthGraph(depth_net, NORM_DEPTH).eval()
    with torch.no_grad():
        ref = graph(torch.from_numpy(imgs[0][:, :, ::-1].transpose(2, 0, 1).astype(np.float32).copy())[None])
    assert np.allclose(d0, ref[0, 0].numpy(), rtol=1e-4, atol=1e-4)
    with pytest.raises(ValueError):
        d0[0, 0] = 1.0  # the cached map is read-only


def test_depth_at_other_working_size(models):
    d, _, _ = models
    src = OnnxDepth(d / "depth.onnx")
    out = src.predict(0, _image(96, 320, 0))
    assert out.shape == (96, 320)


def test_model_errors_name_the_file(models, tmp_path):
    d, _, _ = models
    with pytest.raises(ModelError, match="missing.onnx: flow model file not found"):
        OnnxFlow(tmp_path / "missing.onnx")
    (tmp_path / "junk.onnx").write_bytes(b"\x00garbage")
    with pytest.raises(ModelError, match="junk.onnx: not a usable ONNX model"):
        OnnxFlow(tmp_path / "junk.onnx")
    with pytest.raises(ModelError, match="depth.onnx: is a 'depth' model, expected a 'flow' model"):
        OnnxFlow(d / "depth.onnx")
    with pytest.raises(ModelError, match="flow.onnx: is a 'flow' model"):
        OnnxDepth(d / "flow.onnx")

    model = onnx.load(str(d / "depth.onnx"))
    bare = onnx.ModelProto()
    bare.CopyFrom(model)
    del bare.metadata_props[:]
    onnx.save_model(bare, str(tmp_path / "bare.onnx"))
    with pytest.raises(ModelError, match="bare.onnx: no trianflow-vo metadata"):
        OnnxDepth(tmp_path / "bare.onnx")

    for p in model.metadata_props:
        if p.key == "trianflow.input_size":
            p.value = "128x384"
    onnx.save_model(model, str(tmp_path / "lying.onnx"))
    with pytest.raises(ModelError, match=r"lying.onnx: input 'image' has shape \[1, 3, 64, 192\]"):
        OnnxDepth(tmp_path / "lying.onnx")


def test_missing_onnxruntime_is_a_dependency_error(models, monkeypatch):
    d, _, _ = models
    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # import fails
    with pytest.raises(DependencyError, match="pip install onnxruntime"):
        OnnxFlow(d / "flow.onnx")


def test_inference_modules_do_not_import_torch():
    code = ("import sys, trianflow_vo.flow.onnx_flow, trianflow_vo.depth.onnx_depth; "
            "assert 'torch' not in sys.modules, 'torch imported'")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
