"""The ONNX runtime module: metadata schema (writer and reader), session, model input, errors.

Most tests are pure python (no onnxruntime, no torch). Those that open models use
small hand-built ONNX graphs with the right interface (no export, no torch).
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import cv2
import numpy as np
import pytest

from trianflow_vo.errors import DependencyError, ModelError
from trianflow_vo.nets import onnx_runtime as rt
from trianflow_vo.nets.onnx_runtime import (
    DEFAULT_RESIZE,
    KINDS,
    META_PREFIX,
    RESIZE_METHODS,
    ModelInfo,
    model_metadata,
    parse_metadata,
    to_model_input,
)

SIZE = (64, 192)
NORM = {"mean": [0.45, 0.45, 0.45], "std": [0.225, 0.225, 0.225]}


def _meta(kind="depth", size=SIZE, **kw) -> dict[str, str]:
    spec = KINDS[kind]
    extra = {"depth_range": [0.1, 100.0]} if kind == "depth" else None
    return model_metadata(kind, size, "RGB", NORM, list(spec.inputs), list(spec.outputs),
                          {"layers": 18}, extra, **kw)


def _image(h, w, seed):
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


# --- metadata schema: writer and reader ------------------------------------------------


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_metadata_written_parses_back(kind):
    meta = _meta(kind, resize="linear", version="9.9")
    assert all(k.startswith(META_PREFIX) and isinstance(v, str) for k, v in meta.items())
    assert meta["trianflow.kind"] == kind and meta["trianflow.format_version"] == rt.FORMAT_VERSION
    assert json.loads(meta["trianflow.input_names"]) == list(KINDS[kind].inputs)
    info = parse_metadata(meta, f"/m/{kind}.onnx", kind)
    assert info.kind == kind and info.input_size == SIZE and info.channel_order == "RGB"
    assert info.resize == "linear" and info.version == "9.9" and info.config == {"layers": 18}
    assert info.normalisation["applied"] == "in_graph" and info.normalisation["mean"] == NORM["mean"]
    assert info.normalisation["formula"] == "(x / 255 - mean) / std"
    assert info.meta == {k[len(META_PREFIX):]: v for k, v in meta.items()}
    assert str(info.path) == f"/m/{kind}.onnx"
    assert parse_metadata(meta, "x.onnx").kind == kind  # any kind
    if kind == "depth":
        assert json.loads(info.meta["depth_range"]) == [0.1, 100.0]


def test_metadata_defaults_and_foreign_keys():
    import trianflow_vo

    meta = _meta("flow")
    assert meta["trianflow.resize"] == DEFAULT_RESIZE == "area-down-linear-up"
    assert meta["trianflow.version"] == trianflow_vo.__version__
    info = parse_metadata({**meta, "producer": "someone", "other.key": "1"}, "f.onnx", "flow")
    assert "producer" not in info.meta and info.kind == "flow"
    frozen = parse_metadata(meta, "f.onnx", "flow")
    with pytest.raises(AttributeError):
        frozen.resize = "linear"  # ModelInfo is frozen


@pytest.mark.parametrize("change, match", [
    (dict(kind="pose"), "kind must be one of"),
    (dict(size_hw=(0, 192)), "size must be positive"),
    (dict(channel_order="GBR"), "channel_order must be one of"),
    (dict(input_names=["image1"]), "depth input names must be"),
    (dict(output_names=["disp"]), "depth output names lack"),
    (dict(resize="cubic"), "resize must be one of"),
    (dict(extra={"kind": "flow"}), "is a schema key"),
    (dict(normalisation={"mean": [0.5], "std": [1.0]}), "3 values"),
])
def test_model_metadata_rejects_what_the_reader_would(change, match):
    args = dict(kind="depth", size_hw=SIZE, channel_order="RGB", normalisation=NORM, input_names=["image"],
                output_names=["depth"], config={}, extra=None)
    change = dict(change)
    resize = change.pop("resize", DEFAULT_RESIZE)
    args.update(change)
    with pytest.raises(ValueError, match=match):
        model_metadata(**args, resize=resize)


def _edit(meta, **changes):
    out = dict(meta)
    for k, v in changes.items():
        if v is None:
            out.pop(META_PREFIX + k, None)
        else:
            out[META_PREFIX + k] = v
    return out


@pytest.mark.parametrize("changes, kind, match", [
    ({"kind": None}, "depth", "no trianflow-vo metadata; export the model with 'trianflow-vo export'"),
    ({}, "flow", "is a 'depth' model, expected a 'flow' model"),
    ({"kind": "pose"}, None, "unknown model kind 'pose'"),
    ({"format_version": "2"}, "depth", "unsupported metadata format_version '2'"),
    ({"format_version": None}, "depth", "unsupported metadata format_version None"),
    ({"input_size": None}, "depth", "metadata has no input_size"),
    ({"input_size": "64by192"}, "depth", "metadata input_size '64by192' is not 'HxW'"),
    ({"input_size": "0x192"}, "depth", "metadata input_size '0x192' is not positive"),
    ({"channel_order": "GBR"}, "depth", "metadata channel_order must be RGB or BGR, got 'GBR'"),
    ({"channel_order": None}, "depth", "metadata channel_order must be RGB or BGR, got None"),
    ({"normalisation": "{not json"}, "depth", "metadata 'trianflow.normalisation' is missing or not JSON"),
    ({"normalisation": None}, "depth", "metadata 'trianflow.normalisation' is missing or not JSON"),
    ({"normalisation": json.dumps({"applied": "runtime"})}, "depth", "normalisation must be applied in the graph"),
    ({"resize": "cubic"}, "depth", "metadata resize 'cubic' is not one of"),
    ({"config": "[1"}, "depth", "metadata 'trianflow.config' is missing or not JSON"),
    ({"config": "[1, 2]"}, "depth", "metadata 'trianflow.config' is not a JSON object"),
    ({"input_names": '["img"]'}, "depth", "metadata input_names"),
    ({"output_names": '["disp"]'}, "depth", "metadata output_names"),
])
def test_each_metadata_failure_is_one_line_naming_the_file(changes, kind, match):
    meta = _edit(_meta("depth"), **changes)
    with pytest.raises(ModelError) as exc:
        parse_metadata(meta, "/models/d.onnx", kind)
    msg = str(exc.value)
    assert msg.startswith("/models/d.onnx: ") and "\n" not in msg
    assert match in msg


def test_model_without_resize_key_reads_as_before():
    """Models exported before the resize key: INTER_AREA down in both directions, INTER_LINEAR otherwise."""
    meta = _edit(_meta("flow"), resize=None, config=None, version=None)
    info = parse_metadata(meta, "old.onnx", "flow")
    assert info.resize == DEFAULT_RESIZE == "area-down-linear-up"
    assert info.config == {} and info.version == "?"
    assert "resize" not in info.meta


def test_parse_metadata_rejects_unknown_kind_request():
    with pytest.raises(ValueError, match="kind must be one of"):
        parse_metadata(_meta("flow"), "f.onnx", "pose")


# --- model input ------------------------------------------------------------------------


def _info(resize=DEFAULT_RESIZE, order="RGB", size=SIZE) -> ModelInfo:
    return ModelInfo(path="m.onnx", kind="flow", input_size=size, channel_order=order, normalisation={},
                     resize=resize, version="?", config={}, meta={})


def _former_input(image, info):
    """What vo/flow/onnx_flow.to_model_input computed before the resize key existed."""
    H, W = info.input_size
    h, w = image.shape[:2]
    if (h, w) != (H, W):
        interp = cv2.INTER_AREA if (h > H and w > W) else cv2.INTER_LINEAR
        image = cv2.resize(image, (W, H), interpolation=interp)
    if info.channel_order == "RGB":
        image = image[:, :, ::-1]
    return np.ascontiguousarray(image.transpose(2, 0, 1)[None], dtype=np.float32)


@pytest.mark.parametrize("hw", [SIZE, (256, 832), (128, 160), (32, 96), (96, 320)])
@pytest.mark.parametrize("order", ["RGB", "BGR"])
def test_default_resize_is_the_former_conversion(hw, order):
    img = _image(*hw, 1)
    x = to_model_input(img, _info(order=order))
    assert x.shape == (1, 3, 64, 192) and x.dtype == np.float32 and x.flags.c_contiguous
    assert np.array_equal(x, _former_input(img, _info(order=order)))


def test_channel_order_and_identity_size():
    img = _image(*SIZE, 2)
    rgb = to_model_input(img, _info(order="RGB"))
    bgr = to_model_input(img, _info(order="BGR"))
    assert np.array_equal(rgb[0, 0], img[:, :, 2].astype(np.float32))
    assert np.array_equal(bgr[0, 0], img[:, :, 0].astype(np.float32))
    assert rgb.max() <= 255.0 and rgb.min() >= 0.0


def test_linear_resize_is_plain_bilinear():
    img = _image(256, 832, 3)
    x = to_model_input(img, _info(resize="linear", order="BGR"))
    want = cv2.resize(img, (192, 64), interpolation=cv2.INTER_LINEAR).transpose(2, 0, 1)[None].astype(np.float32)
    assert np.array_equal(x, want)
    assert not np.array_equal(x, to_model_input(img, _info(order="BGR")))  # area when shrinking
    up = _image(32, 96, 4)  # enlarging: both methods are bilinear
    assert np.array_equal(to_model_input(up, _info(resize="linear")), to_model_input(up, _info()))
    assert set(RESIZE_METHODS) >= {"area-down-linear-up", "linear"}


def test_model_input_rejects_other_images():
    for bad in (np.zeros((64, 192), np.uint8), np.zeros((64, 192, 3), np.float32), np.zeros((64, 192, 4), np.uint8)):
        with pytest.raises(ValueError, match=r"\(h, w, 3\) uint8 BGR"):
            to_model_input(bad, _info())
    with pytest.raises(ValueError, match="resize must be one of"):
        rt.resize_image(_image(128, 384, 0), SIZE, "cubic")


# --- imports ----------------------------------------------------------------------------


def test_inference_modules_do_not_import_torch():
    code = ("import sys, trianflow_vo.flow.onnx_flow, trianflow_vo.depth.onnx_depth, "
            "trianflow_vo.nets.onnx_runtime; "
            "assert 'torch' not in sys.modules, 'torch imported'; "
            "assert 'onnxruntime' not in sys.modules, 'onnxruntime imported at import time'")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


def test_module_imports_without_onnxruntime_and_opening_is_a_dependency_error(tmp_path):
    code = textwrap.dedent(f"""
        import sys
        sys.modules["onnxruntime"] = None  # import fails
        from trianflow_vo.nets import onnx_runtime as rt
        from trianflow_vo.flow.onnx_flow import OnnxFlow
        from trianflow_vo.depth.onnx_depth import OnnxDepthNet
        from trianflow_vo.errors import DependencyError
        meta = rt.model_metadata("flow", (64, 192), "RGB", {{"mean": [0] * 3, "std": [1] * 3}},
                                 ["image1", "image2"], ["flow_fw", "flow_bw"], {{}})
        assert rt.parse_metadata(meta, "f.onnx", "flow").resize == "area-down-linear-up"
        path = {str(tmp_path / "flow.onnx")!r}
        calls = {{"open_model": lambda: rt.open_model(path, "flow"), "open_session": lambda: rt.open_session(path),
                 "session_options": lambda: rt.session_options(2), "OnnxModel": lambda: rt.OnnxModel(path, "depth"),
                 "OnnxFlow": lambda: OnnxFlow(path), "OnnxDepthNet": lambda: OnnxDepthNet(path)}}
        for name, call in calls.items():
            try:
                call()
            except DependencyError as exc:
                assert "pip install onnxruntime" in str(exc), str(exc)
                assert "trianflow-vo[onnx]" in str(exc), str(exc)
            else:
                raise SystemExit(name + ": no DependencyError")
        print("ok")
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "ok"


# --- models opened with onnxruntime (hand-built graphs) ----------------------------------


def _write_graph(path, kind="depth", size=SIZE, meta=None, *, input_names=None, output_names=None,
                 out_channels=None):
    """A tiny graph with the interface of ``kind`` (flow: the first two channels of each image
    / 100; depth: the channel mean), ``meta`` as metadata_props (default: model_metadata)."""
    onnx = pytest.importorskip("onnx", reason="needs onnx to build test models")
    from onnx import TensorProto, helper, numpy_helper

    spec = KINDS[kind]
    h, w = size
    ins = list(input_names or spec.inputs)
    outs = list(output_names or spec.outputs)
    ch = out_channels or spec.output_channels
    inits = [numpy_helper.from_array(np.array(v, np.int64), n)
             for n, v in (("starts", [0]), ("ends", [ch]), ("axes", [1]))]
    inits.append(numpy_helper.from_array(np.array(0.01, np.float32), "scale"))
    nodes = []
    for i, (src, dst) in enumerate(zip(ins, outs)):
        if kind == "depth" and ch == 1:
            nodes.append(helper.make_node("ReduceMean", [src, "axes"], [dst], keepdims=1))
        else:
            nodes.append(helper.make_node("Slice", [src, "starts", "ends", "axes"], [f"s{i}"]))
            nodes.append(helper.make_node("Mul", [f"s{i}", "scale"], [dst]))
    graph = helper.make_graph(
        nodes, kind,
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, [1, 3, h, w]) for n in ins],
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, [1, ch, h, w]) for n in outs],
        initializer=inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 9
    for k, v in (_meta(kind, size) if meta is None else meta).items():
        prop = model.metadata_props.add()
        prop.key, prop.value = k, v
    onnx.checker.check_model(model)
    onnx.save_model(model, str(path))
    return path


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    pytest.importorskip("onnx", reason="needs onnx to build test models")
    pytest.importorskip("onnxruntime", reason="needs onnxruntime to open models")
    d = tmp_path_factory.mktemp("runtime")
    _write_graph(d / "flow.onnx", "flow")
    _write_graph(d / "depth.onnx", "depth")
    return d


def test_model_errors_name_the_file(models, tmp_path):
    import onnx

    from trianflow_vo.depth.onnx_depth import OnnxDepthNet
    from trianflow_vo.flow.onnx_flow import OnnxFlow

    d = models
    with pytest.raises(ModelError, match="missing.onnx: flow model file not found"):
        OnnxFlow(tmp_path / "missing.onnx")
    (tmp_path / "junk.onnx").write_bytes(b"\x00garbage")
    with pytest.raises(ModelError, match="junk.onnx: not a usable ONNX model"):
        OnnxFlow(tmp_path / "junk.onnx")
    with pytest.raises(ModelError, match="depth.onnx: is a 'depth' model, expected a 'flow' model"):
        OnnxFlow(d / "depth.onnx")
    with pytest.raises(ModelError, match="flow.onnx: is a 'flow' model"):
        OnnxDepthNet(d / "flow.onnx")

    model = onnx.load(str(d / "depth.onnx"))
    bare = onnx.ModelProto()
    bare.CopyFrom(model)
    del bare.metadata_props[:]
    onnx.save_model(bare, str(tmp_path / "bare.onnx"))
    with pytest.raises(ModelError, match="bare.onnx: no trianflow-vo metadata"):
        OnnxDepthNet(tmp_path / "bare.onnx")

    for p in model.metadata_props:
        if p.key == "trianflow.input_size":
            p.value = "128x384"
    onnx.save_model(model, str(tmp_path / "lying.onnx"))
    with pytest.raises(ModelError, match=r"lying.onnx: input 'image' has shape \[1, 3, 64, 192\]"):
        OnnxDepthNet(tmp_path / "lying.onnx")


def test_graph_failures_are_one_line_naming_the_file(models, tmp_path):
    cases = [
        (dict(input_names=["img"], meta=_edit(_meta("depth"), input_names=None)),
         r"graph inputs \['img'\] != expected \['image'\]"),
        (dict(output_names=["disp"], meta=_edit(_meta("depth"), output_names=None)),
         r"graph lacks outputs \['depth'\]"),
        (dict(out_channels=2), r"output 'depth' has shape \[1, 2, 64, 192\], expected \[1, 1, 64, 192\]"),
    ]
    for i, (kw, match) in enumerate(cases):
        path = _write_graph(tmp_path / f"bad{i}.onnx", "depth", **kw)
        with pytest.raises(ModelError, match=match) as exc:
            rt.open_model(path, "depth")
        msg = str(exc.value)
        assert msg.startswith(f"{path}: ") and "\n" not in msg
    (tmp_path / "junk.onnx").write_bytes(b"\x00garbage")
    with pytest.raises(ModelError) as exc:
        rt.open_session(tmp_path / "junk.onnx")
    assert "\n" not in str(exc.value) and "junk.onnx: not a usable ONNX model (" in str(exc.value)
    with pytest.raises(ModelError, match="nope.onnx: model file not found"):
        rt.open_session(tmp_path / "nope.onnx")
    with pytest.raises(ValueError, match="threads must be >= 1"):
        rt.open_model(models / "flow.onnx", "flow", threads=0)
    with pytest.raises(ValueError, match="kind must be one of"):
        rt.open_model(models / "flow.onnx", "pose")


def test_missing_onnxruntime_is_a_dependency_error(models, monkeypatch):
    from trianflow_vo.flow.onnx_flow import OnnxFlow

    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # import fails
    with pytest.raises(DependencyError, match="pip install onnxruntime"):
        OnnxFlow(models / "flow.onnx")
    with pytest.raises(DependencyError, match="pip install onnxruntime"):
        rt.require_onnxruntime()


def test_session_options_are_the_run_path_settings(models):
    import onnxruntime as ort

    opts = rt.session_options(3)
    assert opts.intra_op_num_threads == 3 and opts.inter_op_num_threads == 1
    assert opts.execution_mode == ort.ExecutionMode.ORT_SEQUENTIAL
    assert opts.graph_optimization_level == ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    assert opts.log_severity_level == 3
    assert opts.get_session_config_entry("session.intra_op.allow_spinning") == "0"
    sess = rt.open_session(models / "flow.onnx", threads=1)
    assert sess.get_providers() == ["CPUExecutionProvider"]
    assert rt.read_metadata(sess) == _meta("flow")


def test_open_model_and_onnx_model(models):
    sess, info = rt.open_model(models / "depth.onnx", "depth", threads=1)
    assert [i.name for i in sess.get_inputs()] == ["image"]
    assert info.kind == "depth" and info.input_size == SIZE and info.resize == DEFAULT_RESIZE
    assert info.path == models / "depth.onnx"
    m = rt.OnnxModel(models / "flow.onnx", "flow", threads=1)
    a, b = _image(*SIZE, 5), _image(*SIZE, 6)
    fw, bw = m.run(m.to_input(a), m.to_input(b))
    assert fw.shape == bw.shape == (1, 2, 64, 192) and m.n_inferences == 1
    assert np.allclose(fw[0, 0], a[:, :, 2] * 0.01)  # RGB: channel 0 is the red one
    with pytest.raises(ValueError, match="takes 2 inputs"):
        m.run(m.to_input(a))
    desc = m.describe()
    assert desc == {"path": str(models / "flow.onnx"), "input_size": [64, 192], "channel_order": "RGB",
                    "resize": DEFAULT_RESIZE, "threads": 1, "exported_with_version": info.version,
                    "config": {"layers": 18}}


@pytest.mark.parametrize("resize", [None, "area-down-linear-up", "linear"])
def test_resize_key_picks_the_interpolation(models, tmp_path, resize):
    """A model without the key behaves as before; "linear" resizes with plain INTER_LINEAR."""
    from trianflow_vo.depth.onnx_depth import OnnxDepthNet
    from trianflow_vo.flow.onnx_flow import OnnxFlow

    flow_meta = _edit(_meta("flow"), resize=resize)
    depth_meta = _edit(_meta("depth"), resize=resize)
    flow = OnnxFlow(_write_graph(tmp_path / "f.onnx", "flow", meta=flow_meta), threads=1)
    depth = OnnxDepthNet(_write_graph(tmp_path / "d.onnx", "depth", meta=depth_meta), threads=1)
    img = _image(256, 832, 7)
    assert flow.info.resize == depth.info.resize == (resize or "area-down-linear-up")
    if resize == "linear":
        small = cv2.resize(img, (192, 64), interpolation=cv2.INTER_LINEAR)
    else:
        small = cv2.resize(img, (192, 64), interpolation=cv2.INTER_AREA)
    assert np.array_equal(flow.prepare(img).tensor, small[:, :, ::-1].transpose(2, 0, 1)[None].astype(np.float32))
    if resize is None:
        assert np.array_equal(flow.prepare(img).tensor, _former_input(img, flow.info))
    got = depth.predict(img)
    want = cv2.resize(small.astype(np.float32).mean(axis=2), (832, 256), interpolation=cv2.INTER_LINEAR)
    assert got.shape == (256, 832) and np.allclose(got, want, atol=1e-4)
