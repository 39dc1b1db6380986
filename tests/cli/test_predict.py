"""``trianflow-vo predict``: depth/flow files against direct onnxruntime calls, and one-line errors.

The models are small random-weight exports (``trianflow-vo export --random-init``); the
tests rely only on the export command and the ONNX metadata, never on the networks'
internals. References are computed independently here: the image is resized as the
metadata's ``trianflow.resize`` says, put in ``trianflow.channel_order`` and fed to a
plain onnxruntime session.
"""

from __future__ import annotations

import os
import struct

import cv2
import numpy as np
import pytest

pytest.importorskip("torch", reason="needs torch to export the test models (pip install 'trianflow-vo[torch]')")
onnx = pytest.importorskip("onnx", reason="needs onnx to export the test models (pip install 'trianflow-vo[torch]')")
ort = pytest.importorskip("onnxruntime", reason="needs onnxruntime to run exported models")

from click.testing import CliRunner  # noqa: E402

import trianflow_vo.predict as P  # noqa: E402
from trianflow_vo.cli.main import main  # noqa: E402
from trianflow_vo.errors import InputError  # noqa: E402
from trianflow_vo.io.flo import read_flo  # noqa: E402
from trianflow_vo.nets.onnx_runtime import OnnxModel  # noqa: E402

SIZE = (64, 192)
IMAGE_HW = (100, 300)  # larger than SIZE in both directions, by a non-integer ratio: area != linear


def _set_resize(src, dst, method):
    m = onnx.load(str(src))
    props = {p.key: p for p in m.metadata_props}
    if "trianflow.resize" in props:
        props["trianflow.resize"].value = method
    else:
        onnx.helper.set_model_props(m, {**{k: p.value for k, p in props.items()}, "trianflow.resize": method})
    onnx.save(m, str(dst))
    return dst


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """``{"depth", "flow"}``: the exported models; ``{"depth-linear", "flow-linear"}`` and
    ``{"depth-area", "flow-area"}``: the same graphs with ``trianflow.resize`` set to ``linear``
    (the TrianFlow authors' preprocessing) and to ``area-down-linear-up``."""
    d = tmp_path_factory.mktemp("models")
    r = CliRunner().invoke(main, ["export", "--random-init", "--seed", "0", "--size", "64x192", "--out-dir", str(d)])
    assert r.exit_code == 0, r.output
    out = {"depth": d / "depth.onnx", "flow": d / "flow.onnx"}
    for kind in ("depth", "flow"):
        out[kind + "-linear"] = _set_resize(out[kind], d / f"{kind}-linear.onnx", "linear")
        out[kind + "-area"] = _set_resize(out[kind], d / f"{kind}-area.onnx", "area-down-linear-up")
    return out


def _image(seed, hw=IMAGE_HW):
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 256, (hw[0] // 4, hw[1] // 4, 3), dtype=np.uint8)
    img = cv2.resize(img, (hw[1], hw[0]), interpolation=cv2.INTER_CUBIC)  # smooth texture
    return cv2.add(img, rng.integers(0, 40, img.shape, dtype=np.uint8))


@pytest.fixture
def frames(tmp_path):
    """A folder with img10.png, img1.png, img2.png (written in that order)."""
    d = tmp_path / "frames"
    d.mkdir()
    for seed, name in ((10, "img10"), (1, "img1"), (2, "img2")):
        cv2.imwrite(str(d / f"{name}.png"), _image(seed))
    (d / "notes.txt").write_text("not an image, not listed\n")
    return d


# ---------------------------------------------------------------------------
# independent reference


def _meta(model):
    return dict(ort.InferenceSession(str(model), providers=["CPUExecutionProvider"])
                .get_modelmeta().custom_metadata_map)


def _reference_input(path, meta, method=None):
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    H, W = (int(v) for v in meta["trianflow.input_size"].split("x"))
    method = method or meta.get("trianflow.resize", "area-down-linear-up")
    if method == "linear":
        interp = cv2.INTER_LINEAR
    else:
        assert method == "area-down-linear-up"
        interp = cv2.INTER_AREA if (img.shape[0] > H and img.shape[1] > W) else cv2.INTER_LINEAR
    img = cv2.resize(img, (W, H), interpolation=interp)
    if meta["trianflow.channel_order"] == "RGB":
        img = img[:, :, ::-1]
    return np.ascontiguousarray(img.transpose(2, 0, 1)[None], dtype=np.float32)


def _session(model):
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 2
    return ort.InferenceSession(str(model), sess_options=opts, providers=["CPUExecutionProvider"])


def _ref_depth(model, path, method=None):
    x = _reference_input(path, _meta(model), method)
    return _session(model).run(["depth"], {"image": x})[0][0, 0]


def _ref_flow(model, p1, p2):
    meta = _meta(model)
    fw = _session(model).run(["flow_fw"], {"image1": _reference_input(p1, meta),
                                           "image2": _reference_input(p2, meta)})[0]
    return fw[0].transpose(1, 2, 0)


def _invoke(*args):
    return CliRunner().invoke(main, ["predict", *map(str, args)])


def _no_tmp(out):
    assert not [p for p in out.rglob("*") if p.name.endswith(".tmp")]


# ---------------------------------------------------------------------------
# outputs


def test_listed_in_main_help():
    r = CliRunner().invoke(main, ["--help"])
    assert r.exit_code == 0 and "predict" in r.output


def test_help_documents_choices():
    r = _invoke("--help")
    assert r.exit_code == 0
    for words in ("magma", "inverse depth", "consecutive", "With both models", "Middlebury", "resize"):
        assert words in r.output


@pytest.mark.parametrize("kind", ["depth", "depth-linear"])
def test_depth_matches_onnxruntime_at_input_size(models, frames, tmp_path, kind):
    out = tmp_path / "out"
    img = frames / "img1.png"
    r = _invoke("--depth-model", models[kind], img, "--out", out)
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in out.iterdir()) == ["img1.depth.npy", "img1.depth.png"]
    d = np.load(out / "img1.depth.npy")
    assert d.dtype == np.float32 and d.shape == SIZE
    ref = _ref_depth(models[kind], img)
    np.testing.assert_allclose(d, ref, rtol=0, atol=1e-6)
    lo, hi = (float(v) for v in _meta(models[kind])["trianflow.depth_range"].strip("[]").split(","))
    assert np.all((d >= lo - 1e-4) & (d <= hi + 1e-4))  # the network's units
    png = cv2.imread(str(out / "img1.depth.png"), cv2.IMREAD_UNCHANGED)
    assert png is not None and png.shape == SIZE + (3,) and png.dtype == np.uint8
    _no_tmp(out)


def test_resize_method_comes_from_metadata(models, frames):
    """The two resize methods give different inputs here; each model's output follows its own."""
    img = frames / "img1.png"
    meta = _meta(models["depth-area"])
    assert meta["trianflow.resize"] == "area-down-linear-up"
    assert _meta(models["depth-linear"])["trianflow.resize"] == "linear"
    area_in, lin_in = (_reference_input(img, meta, m) for m in ("area-down-linear-up", "linear"))
    assert np.abs(area_in - lin_in).max() > 10
    lin = P.run_depth(OnnxModel(models["depth-linear"], "depth"), cv2.imread(str(img)))
    area = P.run_depth(OnnxModel(models["depth-area"], "depth"), cv2.imread(str(img)))
    np.testing.assert_allclose(lin, _ref_depth(models["depth"], img, "linear"), rtol=0, atol=1e-6)
    np.testing.assert_allclose(area, _ref_depth(models["depth"], img, "area-down-linear-up"), rtol=0, atol=1e-6)
    assert np.abs(lin - area).max() > 1e-5  # the check above can tell the two methods apart


@pytest.mark.parametrize("kind", ["flow", "flow-linear"])
def test_flow_pair_npy_flo_png(models, frames, tmp_path, kind):
    out = tmp_path / "out"
    a, b = frames / "img2.png", frames / "img10.png"
    r = _invoke("--flow-model", models[kind], a, b, "--out", out)
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in out.iterdir()) == ["img2.flo", "img2.flow.npy", "img2.flow.png"]
    f = np.load(out / "img2.flow.npy")
    assert f.dtype == np.float32 and f.shape == SIZE + (2,)
    np.testing.assert_allclose(f, _ref_flow(models[kind], a, b), rtol=0, atol=1e-6)
    data = (out / "img2.flo").read_bytes()
    assert struct.unpack("<f", data[:4])[0] == 202021.25
    assert struct.unpack("<ii", data[4:12]) == (SIZE[1], SIZE[0])
    np.testing.assert_array_equal(read_flo(out / "img2.flo"), f)
    png = cv2.imread(str(out / "img2.flow.png"), cv2.IMREAD_UNCHANGED)
    assert png is not None and png.shape == SIZE + (3,) and png.dtype == np.uint8
    _no_tmp(out)


def test_folder_both_models_consecutive_natural_order(models, frames, tmp_path):
    out = tmp_path / "out"
    r = _invoke("--depth-model", models["depth"], "--flow-model", models["flow"], frames,
                "--pairs", "consecutive", "--out", out)
    assert r.exit_code == 0, r.output
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted([f"{n}.depth.{e}" for n in ("img1", "img2", "img10") for e in ("npy", "png")]
                           + [f"{n}{s}" for n in ("img1", "img2") for s in (".flow.npy", ".flo", ".flow.png")])
    # natural order: img1 -> img2 -> img10 (img2.flow is the flow img2 -> img10)
    np.testing.assert_allclose(np.load(out / "img2.flow.npy"),
                               _ref_flow(models["flow"], frames / "img2.png", frames / "img10.png"), rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.load(out / "img1.flow.npy"),
                               _ref_flow(models["flow"], frames / "img1.png", frames / "img2.png"), rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.load(out / "img10.depth.npy"), _ref_depth(models["depth"], frames / "img10.png"),
                               rtol=0, atol=1e-6)
    # progress: plain lines on stderr (not a terminal), in natural order
    assert r.stderr.splitlines() == ["depth 1/3 img1.png", "depth 2/3 img2.png", "depth 3/3 img10.png",
                                     "flow 1/2 img1.png", "flow 2/2 img2.png"]
    assert r.stdout.strip() == f"wrote depth of 3 images and flow of 2 pairs (12 files) to {out}"
    _no_tmp(out)


def test_both_models_two_images(models, frames, tmp_path):
    out = tmp_path / "out"
    r = _invoke("--depth-model", models["depth"], "--flow-model", models["flow"],
                frames / "img1.png", frames / "img2.png", "--out", out)
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in out.iterdir()) == ["img1.depth.npy", "img1.depth.png", "img1.flo",
                                                      "img1.flow.npy", "img1.flow.png",
                                                      "img2.depth.npy", "img2.depth.png"]
    assert r.stderr == ""  # no folder given: no progress


def test_quiet_folder(models, frames, tmp_path):
    r = _invoke("-q", "--depth-model", models["depth"], frames, "--out", tmp_path / "out")
    assert r.exit_code == 0, r.output
    assert r.output == ""
    assert len(list((tmp_path / "out").iterdir())) == 6


def test_library_api(models, frames, tmp_path):
    calls = []
    images = P.collect_images([frames])
    assert [p.name for p in images] == ["img1.png", "img2.png", "img10.png"]
    written = P.predict_depth(images, models["depth"], tmp_path / "lib", 1, progress=lambda *a: calls.append(a))
    assert [p.name for p in written] == [f"{n}.depth.{e}" for n in ("img1", "img2", "img10") for e in ("npy", "png")]
    assert calls == [(1, 3, "img1.png"), (2, 3, "img2.png"), (3, 3, "img10.png")]
    written = P.predict_flow(P.flow_pairs(images[:2]), models["flow"], tmp_path / "lib")
    assert [p.name for p in written] == ["img1.flow.npy", "img1.flo", "img1.flow.png"]
    with pytest.raises(InputError, match="exactly 2 images, got 3"):
        P.flow_pairs(images)
    assert P.flow_pairs(images, "consecutive") == [(images[0], images[1]), (images[1], images[2])]


def test_interrupted_run_leaves_only_complete_files(models, frames, tmp_path):
    out = tmp_path / "out"

    def stop(done, total, name):
        if done == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        P.predict_depth(P.collect_images([frames]), models["depth"], out, progress=stop)
    assert sorted(p.name for p in out.iterdir()) == ["img1.depth.npy", "img1.depth.png",
                                                      "img2.depth.npy", "img2.depth.png"]


def test_failed_write_leaves_no_file(tmp_path, monkeypatch):
    target = tmp_path / "a.depth.npy"

    def boom(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(P.os, "replace", boom)
    with pytest.raises(OSError):
        P.write_atomic(target, b"x" * 100)
    assert not list(tmp_path.iterdir())


def test_depth_colour_map():
    depth = np.linspace(1, 50, 64 * 192, dtype=np.float32).reshape(SIZE)
    depth[0, 0] = np.nan
    depth[0, 1] = 0
    bgr = P.depth_to_color(depth)
    assert bgr.shape == SIZE + (3,) and bgr.dtype == np.uint8
    assert (bgr[0, 0] == 0).all() and (bgr[0, 1] == 0).all()
    assert bgr[1, 0].astype(int).sum() > bgr[-1, -1].astype(int).sum()  # near (small depth) is brighter
    assert P.depth_to_color(np.full(SIZE, 3.0, np.float32)).shape == SIZE + (3,)  # constant depth


# ---------------------------------------------------------------------------
# errors: one line, non-zero exit, no traceback, nothing written


def _one_line_error(r, code, *words):
    assert r.exit_code == code, r.output
    assert isinstance(r.exception, SystemExit)
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: "), r.output
    assert "Traceback" not in r.output
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


def test_error_neither_model(frames, tmp_path):
    _one_line_error(_invoke(frames / "img1.png", "--out", tmp_path / "out"), 2, "--depth-model", "--flow-model")
    assert not (tmp_path / "out").exists()


def test_error_missing_path(models, tmp_path):
    _one_line_error(_invoke("--depth-model", models["depth"], tmp_path / "nope.png", "--out", tmp_path / "out"),
                    1, str(tmp_path / "nope.png"), "no such file or folder")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("name, content", [("notes.txt", b"hello\n"), ("fake.png", b"not a png at all")])
def test_error_not_an_image(models, frames, tmp_path, name, content):
    bad = tmp_path / name
    bad.write_bytes(content)
    _one_line_error(_invoke("--depth-model", models["depth"], frames / "img1.png", bad, "--out", tmp_path / "out"),
                    1, str(bad), "not an image")
    assert not (tmp_path / "out").exists()


def test_error_truncated_image_is_named(models, frames, tmp_path):
    good = (frames / "img1.png").read_bytes()
    bad = tmp_path / "cut.png"
    bad.write_bytes(good[: len(good) // 3])
    line = _one_line_error(_invoke("--depth-model", models["depth"], bad, "--out", tmp_path / "out"), 1, str(bad))
    assert "decode" in line
    _no_tmp(tmp_path)


def test_error_folder_without_images(models, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "readme.txt").write_text("x")
    _one_line_error(_invoke("--depth-model", models["depth"], empty, "--out", tmp_path / "out"),
                    1, str(empty), "no images")


@pytest.mark.parametrize("n", [1, 3])
def test_error_flow_needs_two_images(models, frames, tmp_path, n):
    imgs = [frames / f"img{i}.png" for i in (1, 2, 10)][:n]
    _one_line_error(_invoke("--flow-model", models["flow"], *imgs, "--out", tmp_path / "out"),
                    2, f"exactly 2 images, got {n}", "--pairs consecutive")
    # a folder of 3 images too (even with a depth model: nothing is written)
    _one_line_error(_invoke("--depth-model", models["depth"], "--flow-model", models["flow"], frames,
                            "--out", tmp_path / "out"), 2, "exactly 2 images, got 3")
    assert not (tmp_path / "out").exists()


def test_error_consecutive_needs_two_images(models, frames, tmp_path):
    _one_line_error(_invoke("--flow-model", models["flow"], frames / "img1.png", "--pairs", "consecutive",
                            "--out", tmp_path / "out"), 2, "at least 2 images, got 1")


def test_error_pairs_without_flow_model(models, frames, tmp_path):
    _one_line_error(_invoke("--depth-model", models["depth"], frames, "--pairs", "consecutive",
                            "--out", tmp_path / "out"), 2, "--pairs consecutive needs --flow-model")


@pytest.mark.parametrize("option, model, found, wanted", [
    ("--depth-model", "flow", "flow", "depth"),
    ("--flow-model", "depth", "depth", "flow"),
])
def test_error_wrong_kind(models, frames, tmp_path, option, model, found, wanted):
    args = [frames / "img1.png", frames / "img2.png"]
    _one_line_error(_invoke(option, models[model], *args, "--out", tmp_path / "out"),
                    1, str(models[model]), f"is a '{found}' model, expected a '{wanted}' model")
    assert not (tmp_path / "out").exists()


def test_error_wrong_kind_with_both_models_writes_nothing(models, frames, tmp_path):
    _one_line_error(_invoke("--depth-model", models["depth"], "--flow-model", models["depth"],
                            frames / "img1.png", frames / "img2.png", "--out", tmp_path / "out"),
                    1, "expected a 'flow'")
    assert not (tmp_path / "out").exists()


def test_error_model_missing_or_not_onnx(models, frames, tmp_path):
    _one_line_error(_invoke("--depth-model", tmp_path / "none.onnx", frames / "img1.png", "--out", tmp_path / "o"),
                    1, "none.onnx", "not found")
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"junk")
    _one_line_error(_invoke("--depth-model", junk, frames / "img1.png", "--out", tmp_path / "o"),
                    1, "junk.onnx", "not a usable ONNX model")


def test_error_out_not_creatable(models, frames, tmp_path):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    _one_line_error(_invoke("--depth-model", models["depth"], frames / "img1.png", "--out", a_file),
                    1, str(a_file), "not a folder")
    _one_line_error(_invoke("--depth-model", models["depth"], frames / "img1.png", "--out", a_file / "sub"),
                    1, str(a_file / "sub"), "cannot create the output folder")


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="needs a non-root POSIX user")
def test_error_out_not_writable(models, frames, tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        _one_line_error(_invoke("--depth-model", models["depth"], frames / "img1.png", "--out", ro / "sub"),
                        1, "cannot create the output folder")
    finally:
        ro.chmod(0o700)


def test_error_same_stem_twice(models, frames, tmp_path):
    other = tmp_path / "other"
    other.mkdir()
    cv2.imwrite(str(other / "img1.jpg"), _image(5))
    _one_line_error(_invoke("--depth-model", models["depth"], frames / "img1.png", other / "img1.jpg",
                            "--out", tmp_path / "out"), 1, "img1.depth.npy", "rename one")
    assert not (tmp_path / "out").exists()
