"""OnnxDepthNet on an exported depth network: shapes, resizing, agreement with torch."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="needs torch to export the depth network")
pytest.importorskip("onnx", reason="needs onnx to export the depth network")
pytest.importorskip("onnxruntime", reason="needs onnxruntime to run the exported depth network")

from trianflow_vo.depth.onnx_depth import OnnxDepthNet  # noqa: E402
from trianflow_vo.models.depth_net import DepthNet  # noqa: E402
from trianflow_vo.models.export import DepthGraph, export_depth  # noqa: E402

SIZE = (64, 192)
NORM_DEPTH = {"mean": [0.45, 0.45, 0.45], "std": [0.225, 0.225, 0.225]}


@pytest.fixture(scope="module")
def depth_model(tmp_path_factory):
    d = tmp_path_factory.mktemp("onnx_depth")
    torch.manual_seed(0)
    depth_net = DepthNet().eval()
    export_depth(depth_net, NORM_DEPTH, SIZE, "RGB", d / "depth.onnx")
    return d / "depth.onnx", depth_net


def _former_input(image, info):
    """The model input as vo/flow/onnx_flow.to_model_input computed it before the resize key."""
    H, W = info.input_size
    h, w = image.shape[:2]
    if (h, w) != (H, W):
        interp = cv2.INTER_AREA if (h > H and w > W) else cv2.INTER_LINEAR
        image = cv2.resize(image, (W, H), interpolation=interp)
    if info.channel_order == "RGB":
        image = image[:, :, ::-1]
    return np.ascontiguousarray(image.transpose(2, 0, 1)[None], dtype=np.float32)


def _image(h, w, seed):
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, (h, w, 3), dtype=np.uint8)


def test_depth_every_call_runs_the_network_and_agrees_with_torch(depth_model):
    path, depth_net = depth_model
    src = OnnxDepthNet(path, threads=1)
    imgs = {i: _image(*SIZE, 10 + i) for i in range(3)}
    d0 = src.predict(imgs[0])
    assert d0.shape == SIZE and d0.dtype == np.float32
    assert np.all((d0 >= 0.1) & (d0 <= 100.0))
    assert src.n_inferences == 1
    src.predict(imgs[1])
    src.predict(imgs[2])
    assert src.n_inferences == 3  # one graph call per image
    again = src.predict(imgs[0])  # no cache in the network wrapper
    assert src.n_inferences == 4
    assert again is not d0 and np.array_equal(again, d0)
    graph = DepthGraph(depth_net, NORM_DEPTH).eval()
    with torch.no_grad():
        ref = graph(torch.from_numpy(imgs[0][:, :, ::-1].transpose(2, 0, 1).astype(np.float32).copy())[None])
    assert np.allclose(d0, ref[0, 0].numpy(), rtol=1e-4, atol=1e-4)


def test_depth_at_other_working_size(depth_model):
    path, _ = depth_model
    src = OnnxDepthNet(path)
    out = src.predict(_image(96, 320, 0))
    assert out.shape == (96, 320)


@pytest.mark.parametrize("hw", [SIZE, (96, 320), (256, 832), (48, 160)])
def test_depth_identical_to_the_former_onnx_depth(depth_model, hw):
    """Bit for bit what OnnxDepth.predict computed: model input, one run, bilinear back."""
    path, _ = depth_model
    src = OnnxDepthNet(path, threads=1)
    img = _image(*hw, 3)
    (raw,) = src.session.run(["depth"], {"image": _former_input(img, src.info)})
    want = np.ascontiguousarray(raw[0, 0], dtype=np.float32)
    if want.shape != hw:
        want = cv2.resize(want, (hw[1], hw[0]), interpolation=cv2.INTER_LINEAR)
    got = src.predict(img)
    assert got.dtype == np.float32 and got.shape == hw
    assert np.array_equal(got, want)


def test_depth_net_api(depth_model):
    path, _ = depth_model
    src = OnnxDepthNet(path, threads=1)
    assert src.name == "onnx-depth"
    assert src.info.kind == "depth" and src.info.input_size == SIZE
    assert not hasattr(src, "observe") and not hasattr(src, "forget")  # caching is the caller's
    desc = src.describe()
    assert desc["name"] == "onnx-depth" and desc["path"] == str(path) and desc["threads"] == 1
    assert desc["input_size"] == [64, 192] and desc["channel_order"] == "RGB"
    assert desc["depth_range"] == "[0.1, 100.0]" and desc["resize"] == "area-down-linear-up"
    with pytest.raises(ValueError, match="uint8 BGR"):
        src.predict(np.zeros((64, 192), np.uint8))
    assert src.n_inferences == 0
