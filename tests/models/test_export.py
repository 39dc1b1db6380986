"""Export to ONNX: parity with torch, single file, metadata, checkpoint errors, CLI."""

from __future__ import annotations

import json

import pytest

torch = pytest.importorskip("torch", reason="needs torch (pip install 'trianflow-vo[torch]')")
onnx = pytest.importorskip("onnx", reason="needs onnx to export and edit models")
pytest.importorskip("onnxruntime", reason="needs onnxruntime to run exported models")

from click.testing import CliRunner  # noqa: E402

import trianflow_vo  # noqa: E402
from trianflow_vo.cli.main import main  # noqa: E402
from trianflow_vo.models.checkpoint import (  # noqa: E402
    load_checkpoint,
    make_checkpoint,
    random_checkpoint,
    save_checkpoint,
)
from trianflow_vo.models.depth_net import DepthNet  # noqa: E402
from trianflow_vo.models.export import DepthGraph, FlowGraph, parity, random_images  # noqa: E402
from trianflow_vo.models.pwc import PWCNet  # noqa: E402
from trianflow_vo.errors import ModelError  # noqa: E402
from trianflow_vo.nets.onnx_runtime import parse_metadata  # noqa: E402

SIZE = (128, 384)


def _amplified_pwc(seed: int) -> PWCNet:
    """Default PWC-Net whose flow layers are scaled up so random weights give flows of
    several pixels (the default init gives ~0.2 px, too small for a meaningful parity)."""
    torch.manual_seed(seed)
    net = PWCNet()
    with torch.no_grad():
        for est in net.estimators:
            est.predict.weight.mul_(30.0)
        net.context.net[-1].weight.mul_(30.0)
    return net.eval()


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """One export through the CLI from a saved checkpoint (default architectures)."""
    d = tmp_path_factory.mktemp("export")
    torch.manual_seed(1)
    # not the defaults (BGR, linear: the authors'), to see that the checkpoint's values are recorded
    ckpt = make_checkpoint(_amplified_pwc(0), DepthNet().eval(), SIZE, channel_order="RGB",
                           resize="area-down-linear-up")
    save_checkpoint(d / "ckpt.pt", ckpt)
    result = CliRunner().invoke(main, ["export", "--checkpoint", str(d / "ckpt.pt"), "--out-dir", str(d / "out")])
    return d, result


def test_cli_export_reports_differences(exported):
    d, result = exported
    assert result.exit_code == 0, result.output
    lines = [ln for ln in result.output.splitlines() if ln.startswith(("flow:", "flow_split:", "depth:"))]
    assert len(lines) == 3  # flow.onnx, its encoder + decoder, depth.onnx
    for ln in lines:
        worst = float(ln.split("max |onnxruntime - torch| = ")[1].split()[0])
        assert worst <= 1e-4


def test_single_files_only(exported):
    d, _ = exported
    assert sorted(p.name for p in (d / "out").iterdir()) == ["depth.onnx", "flow.onnx", "flow_decoder.onnx",
                                                            "flow_encoder.onnx"]
    for p in (d / "out").iterdir():  # each self-contained (no external-data sidecar)
        model = onnx.load(str(p), load_external_data=False)
        assert not any(t.data_location == onnx.TensorProto.EXTERNAL for t in model.graph.initializer)


def test_split_graphs_equal_flow_onnx(exported):
    from trianflow_vo.models.export import split_parity

    d, _ = exported
    ckpt = load_checkpoint(d / "ckpt.pt")
    imgs = random_images(SIZE, 2, seed=11)
    diffs = split_parity(ckpt.flow.net, ckpt.flow.normalisation, SIZE, d / "out",
                         {"image1": imgs[0], "image2": imgs[1]})
    assert max(diffs.values()) <= 1e-4, diffs
    meta = {p.key: p.value for p in onnx.load(str(d / "out" / "flow_decoder.onnx")).metadata_props}
    assert json.loads(meta["trianflow.weights"])["file"] == "ckpt.pt"  # the parts carry the provenance too
    assert "trianflow.quantization" not in meta


def test_no_split_and_quantize_options(tmp_path):
    import cv2
    import numpy as np

    r = CliRunner().invoke(main, ["export", "--random-init", "--size", "64x192", "--no-split",
                                  "--out-dir", str(tmp_path / "a")])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["depth.onnx", "flow.onnx"]
    r = CliRunner().invoke(main, ["export", "--random-init", "--size", "64x192", "--quantize", "int8",
                                  "--out-dir", str(tmp_path / "b")])
    assert r.exit_code != 0 and "--calibration" in r.output
    frames = tmp_path / "frames"
    frames.mkdir()
    rng = np.random.default_rng(0)
    base = cv2.resize(rng.integers(0, 256, (16, 48, 3), dtype=np.uint8), (200, 70))
    for i in range(3):
        cv2.imwrite(str(frames / f"{i:06d}.png"), np.roll(base, 2 * i, axis=1))
    r = CliRunner().invoke(main, ["export", "--random-init", "--size", "64x192", "--quantize", "int8",
                                  "--calibration", str(frames), "--out-dir", str(tmp_path / "c")])
    assert r.exit_code == 0, r.output
    assert "flow_decoder_int8:" in r.output and "depth_int8:" in r.output
    from trianflow_vo.flow.onnx_flow import OnnxFlow

    src = OnnxFlow(tmp_path / "c" / "flow.onnx", threads=1)
    assert src.split and src.describe()["quantization"] == "int8-static-qdq"
    img = cv2.imread(str(frames / "000000.png"))
    fw, _ = src.flow_pair(src.prepare(img), src.prepare(img))
    assert fw.shape == (70, 200, 2) and np.isfinite(fw).all()
    nodes = {n.op_type for n in onnx.load(str(tmp_path / "c" / "depth.onnx")).graph.node}
    assert "QuantizeLinear" in nodes


def test_parity_on_new_inputs(exported):
    d, _ = exported
    ckpt = load_checkpoint(d / "ckpt.pt")
    imgs = random_images(SIZE, 2, seed=7)
    flow_graph = FlowGraph(ckpt.flow.net, ckpt.flow.normalisation).eval()
    with torch.no_grad():
        fw, _ = flow_graph(torch.from_numpy(imgs[0]), torch.from_numpy(imgs[1]))
    assert fw.abs().max() > 2.0  # the check is on flows of real magnitude, not ~0
    diffs = parity(flow_graph, d / "out" / "flow.onnx", {"image1": imgs[0], "image2": imgs[1]})
    assert max(diffs.values()) <= 1e-4, diffs
    depth_graph = DepthGraph(ckpt.depth.net, ckpt.depth.normalisation).eval()
    diffs = parity(depth_graph, d / "out" / "depth.onnx", {"image": imgs[1]})
    assert max(diffs.values()) <= 1e-4, diffs


def test_metadata_and_fixed_shapes(exported):
    d, _ = exported
    for kind, inputs, outputs in (("flow", ["image1", "image2"], ["flow_fw", "flow_bw"]),
                                  ("depth", ["image"], ["depth"])):
        model = onnx.load(str(d / "out" / f"{kind}.onnx"))
        meta = {p.key: p.value for p in model.metadata_props}
        assert meta["trianflow.kind"] == kind
        assert meta["trianflow.input_size"] == "128x384"
        assert meta["trianflow.channel_order"] == "RGB"
        assert meta["trianflow.version"] == trianflow_vo.__version__
        assert json.loads(meta["trianflow.output_names"]) == outputs
        norm = json.loads(meta["trianflow.normalisation"])
        assert norm["applied"] == "in_graph" and len(norm["mean"]) == 3
        assert max(op.version for op in model.opset_import if op.domain in ("", "ai.onnx")) >= 17
        assert [i.name for i in model.graph.input] == inputs
        for i in model.graph.input:
            assert [dim.dim_value for dim in i.type.tensor_type.shape.dim] == [1, 3, 128, 384]
        assert {n.domain for n in model.graph.node} <= {"", "ai.onnx"}  # no custom operators
        assert meta["trianflow.resize"] == "area-down-linear-up"  # what the run path does to images
        info = parse_metadata(meta, d / "out" / f"{kind}.onnx", kind)  # the reader's validation
        assert info.input_size == (128, 384) and info.resize == "area-down-linear-up"
        assert json.loads(meta["trianflow.train_input_size"]) == [128, 384]
        assert json.loads(meta["trianflow.weights"]) == {"source": "trianflow-vo-checkpoint", "file": "ckpt.pt"}
    flow_meta = {p.key: p.value for p in onnx.load(str(d / "out" / "flow.onnx")).metadata_props}
    assert json.loads(flow_meta["trianflow.config"])["search_range"] == 4
    depth_meta = {p.key: p.value for p in onnx.load(str(d / "out" / "depth.onnx")).metadata_props}
    assert json.loads(depth_meta["trianflow.depth_range"]) == [0.1, 100.0]


def test_checkpoint_round_trip(tmp_path):
    ckpt = random_checkpoint(3, (64, 192))
    save_checkpoint(tmp_path / "c.pt", ckpt)
    loaded = load_checkpoint(tmp_path / "c.pt")
    assert loaded.input_size == (64, 192)
    assert loaded.channel_order == "BGR" and loaded.resize == "linear"  # defaults: the authors' preprocessing
    assert ckpt["format_version"] == 2
    for k, v in ckpt["flow"]["state_dict"].items():
        assert torch.equal(loaded.flow.net.state_dict()[k], v)
    assert loaded.depth.normalisation == {"mean": [0.45] * 3, "std": [0.225] * 3}


def test_bad_checkpoints_name_the_file(tmp_path):
    with pytest.raises(ModelError, match="not found"):
        load_checkpoint(tmp_path / "missing.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ModelError, match="junk.pt: cannot read"):
        load_checkpoint(tmp_path / "junk.pt")
    torch.save({"flow": {}}, tmp_path / "foreign.pt")
    with pytest.raises(ModelError, match="foreign.pt: not a trianflow-vo checkpoint"):
        load_checkpoint(tmp_path / "foreign.pt")
    ckpt = random_checkpoint(0, (64, 192))
    ckpt["flow"]["config"]["search_range"] = 3  # weights were made for 81 cost channels
    save_checkpoint(tmp_path / "mismatch.pt", ckpt)
    with pytest.raises(ModelError, match="mismatch.pt: flow weights do not fit"):
        load_checkpoint(tmp_path / "mismatch.pt")


def test_cli_export_usage_errors(tmp_path):
    r = CliRunner().invoke(main, ["export", "--out-dir", str(tmp_path)])
    assert r.exit_code != 0 and "exactly one of" in r.output
    r = CliRunner().invoke(main, ["export", "--random-init", "--size", "100x200", "--out-dir", str(tmp_path)])
    assert r.exit_code != 0 and "multiples of 64" in r.output
    r = CliRunner().invoke(main, ["export", "--checkpoint", str(tmp_path / "nope.pt"), "--out-dir", str(tmp_path)])
    assert r.exit_code == 1 and "nope.pt: checkpoint not found" in r.output
    assert "Traceback" not in r.output
