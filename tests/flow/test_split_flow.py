"""The flow network split into encoder (per frame) and decoder (per pair) graphs."""

from __future__ import annotations

import json
import logging
import shutil

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="needs torch to export the flow network")
onnx = pytest.importorskip("onnx", reason="needs onnx to export the flow network")
pytest.importorskip("onnxruntime", reason="needs onnxruntime to run the exported flow network")

from trianflow_vo.errors import ModelError  # noqa: E402
from trianflow_vo.flow.onnx_flow import OnnxFlow  # noqa: E402
from trianflow_vo.models.export import (  # noqa: E402
    FLOW_DECODER_FILE,
    FLOW_ENCODER_FILE,
    FlowDecoderGraph,
    FlowEncoderGraph,
    FlowGraph,
    export_flow,
)
from trianflow_vo.models.pwc import PWCConfig, PWCNet  # noqa: E402
from trianflow_vo.nets.onnx_runtime import OnnxModel, parse_metadata  # noqa: E402

SIZE = (64, 192)
TINY = PWCConfig(pyramid_channels=(8, 8, 16, 16, 16, 16), estimator_channels=(8, 8, 8, 8, 8),
                 context_channels=(8, 8, 8, 8, 8, 8), search_range=2)
NORM = {"mean": [0.0, 0.0, 0.0], "std": [1.0, 1.0, 1.0]}


def _net(seed=0):
    torch.manual_seed(seed)
    net = PWCNet(TINY).eval()
    with torch.no_grad():
        for est in net.estimators:
            est.predict.weight.mul_(5.0)  # flows of a few pixels, not ~0
    return net


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    net = _net()
    split_dir = tmp_path_factory.mktemp("split")
    export_flow(net, NORM, SIZE, "BGR", split_dir / "flow.onnx", split=True)
    old_dir = tmp_path_factory.mktemp("single")  # as exported before the split existed
    export_flow(net, NORM, SIZE, "BGR", old_dir / "flow.onnx")
    return net, split_dir, old_dir


def _image(h, w, seed):
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def test_files_and_metadata(models):
    _, split_dir, old_dir = models
    assert sorted(p.name for p in split_dir.iterdir()) == sorted(["flow.onnx", FLOW_ENCODER_FILE, FLOW_DECODER_FILE])
    metas = {name: {p.key: p.value for p in onnx.load(str(split_dir / name)).metadata_props}
             for name in ("flow.onnx", FLOW_ENCODER_FILE, FLOW_DECODER_FILE)}
    split = json.loads(metas["flow.onnx"]["trianflow.split"])
    assert split["encoder"] == FLOW_ENCODER_FILE and split["decoder"] == FLOW_DECODER_FILE
    enc = parse_metadata(metas[FLOW_ENCODER_FILE], FLOW_ENCODER_FILE, "flow_encoder")
    dec = parse_metadata(metas[FLOW_DECODER_FILE], FLOW_DECODER_FILE, "flow_decoder")
    assert enc.split["id"] == dec.split["id"] == split["id"]
    assert enc.output_names == ["pyr2", "pyr3", "pyr4", "pyr5", "pyr6"]
    assert enc.features == dec.features
    assert dict(enc.features)["pyr2"] == (1, 8, 16, 48) and dict(enc.features)["pyr6"] == (1, 16, 1, 3)
    assert dec.input_names[0] == "image1_pyr2" and dec.input_names[5] == "image2_pyr2"
    assert dec.output_names == ["flow_fw", "flow_bw"]
    assert enc.input_size == dec.input_size == SIZE and enc.channel_order == "BGR"
    with pytest.raises(ModelError, match="is a 'flow_encoder' model"):
        parse_metadata(metas[FLOW_ENCODER_FILE], FLOW_ENCODER_FILE, "flow")
    old = {p.key: p.value for p in onnx.load(str(old_dir / "flow.onnx")).metadata_props}
    assert "trianflow.split" not in old


def test_split_equals_single_graph(models):
    net, split_dir, old_dir = models
    split = OnnxFlow(split_dir / "flow.onnx", threads=1)
    single = OnnxFlow(split_dir / "flow.onnx", threads=1, split=False)
    old = OnnxFlow(old_dir / "flow.onnx", threads=1)
    assert split.split and not single.split and not old.split
    a, b = _image(*SIZE, 0), _image(*SIZE, 1)
    pa, pb = split.prepare(a), split.prepare(b)
    assert pa.features is not None and len(pa.features) == 5
    fw, bw = split.flow_pair(pa, pb)
    assert split.n_inferences == 1 and split.encoder.n_inferences == 2
    sfw, sbw = single.flow_pair(single.prepare(a), single.prepare(b))
    ofw, obw = old.flow_pair(old.prepare(a), old.prepare(b))
    assert np.abs(sfw).max() > 1.0  # flows of real magnitude
    assert np.abs(fw - sfw).max() <= 1e-4 and np.abs(bw - sbw).max() <= 1e-4
    assert np.abs(fw - ofw).max() <= 1e-4 and np.abs(bw - obw).max() <= 1e-4
    # and torch's split modules equal torch's single graph
    to_t = lambda im: torch.from_numpy(im.transpose(2, 0, 1).astype(np.float32).copy())[None]  # noqa: E731
    with torch.no_grad():
        tfw, tbw = FlowGraph(net, NORM).eval()(to_t(a), to_t(b))
        enc = FlowEncoderGraph(net, NORM).eval()
        dfw, dbw = FlowDecoderGraph(net, SIZE).eval()(*enc(to_t(a)), *enc(to_t(b)))
    assert torch.allclose(tfw, dfw, atol=1e-5) and torch.allclose(tbw, dbw, atol=1e-5)
    assert np.abs(fw - tfw[0].numpy().transpose(1, 2, 0)).max() <= 1e-4
    # the reverse pair, at another working size (resized to and from the model size)
    c, d = _image(128, 320, 2), _image(128, 320, 3)
    fw2, bw2 = split.flow_pair(split.prepare(d), split.prepare(c))
    sfw2, sbw2 = single.flow_pair(single.prepare(d), single.prepare(c))
    assert fw2.shape == (128, 320, 2)
    assert np.abs(fw2 - sfw2).max() <= 1e-4 and np.abs(bw2 - sbw2).max() <= 1e-4


def test_describe_and_api(models):
    _, split_dir, old_dir = models
    split = OnnxFlow(split_dir / "flow.onnx", threads=1)
    desc = split.describe()
    assert desc["name"] == "onnx-pwc" and desc["graphs"] == "encoder+decoder"
    assert desc["path"] == str(split_dir / "flow.onnx") and desc["input_size"] == list(SIZE)
    assert desc["encoder"].endswith(FLOW_ENCODER_FILE) and desc["threads"] == 1
    assert split.info.kind == "flow" and split.info.split is not None
    assert OnnxFlow(old_dir / "flow.onnx").describe()["graphs"] == "single"
    frame = split.prepare(_image(*SIZE, 4))
    with pytest.raises(ValueError, match="different working sizes"):
        split.flow_pair(frame, split.prepare(_image(128, 320, 5)))
    bare = OnnxFlow(old_dir / "flow.onnx").prepare(_image(*SIZE, 4))  # no features
    with pytest.raises(ValueError, match="without pyramid features"):
        split.flow_pair(frame, bare)


def test_missing_parts_fall_back_to_the_single_graph(models, tmp_path, caplog):
    _, split_dir, _ = models
    shutil.copy(split_dir / "flow.onnx", tmp_path / "flow.onnx")  # flow.onnx alone, copied elsewhere
    with caplog.at_level(logging.WARNING, logger="trianflow_vo"):
        src = OnnxFlow(tmp_path / "flow.onnx")
    assert not src.split and "not beside it" in caplog.text
    fw, _ = src.flow_pair(src.prepare(_image(*SIZE, 0)), src.prepare(_image(*SIZE, 1)))
    assert fw.shape == (64, 192, 2)


def test_parts_of_another_export_are_refused(models, tmp_path):
    _, split_dir, _ = models
    export_flow(_net(1), NORM, SIZE, "BGR", tmp_path / "flow.onnx", split=True)
    shutil.copy(split_dir / FLOW_DECODER_FILE, tmp_path / FLOW_DECODER_FILE)  # a stale decoder
    with pytest.raises(ModelError, match="split id differs"):
        OnnxFlow(tmp_path / "flow.onnx")


def test_part_models_open_with_their_kind(models):
    _, split_dir, _ = models
    enc = OnnxModel(split_dir / FLOW_ENCODER_FILE, "flow_encoder", threads=1)
    feats = enc.run(np.zeros((1, 3, *SIZE), np.float32))
    assert [f.shape for f in feats] == [sh for _, sh in enc.info.features]
    with pytest.raises(ModelError, match="expected a 'flow' model"):
        OnnxModel(split_dir / FLOW_ENCODER_FILE, "flow")
