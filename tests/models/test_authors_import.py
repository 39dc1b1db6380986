"""Importing the TrianFlow authors' checkpoints: layout, equivalence with their code, errors.

The expected outputs in ``tests/fixtures/authors_expected.npz`` come from the authors' own
code run once on :func:`deterministic_checkpoint` weights (``tests/fixtures/README.md``);
here the same weights go through ``trianflow-vo export`` and onnxruntime.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="needs torch (pip install 'trianflow-vo[torch]')")
onnx = pytest.importorskip("onnx", reason="needs onnx to export models")
pytest.importorskip("onnxruntime", reason="needs onnxruntime to run exported models")

from click.testing import CliRunner  # noqa: E402

from trianflow_vo.cli.main import main  # noqa: E402
from trianflow_vo.errors import ModelError  # noqa: E402
from trianflow_vo.models import authors  # noqa: E402
from trianflow_vo.models.checkpoint import make_checkpoint, save_checkpoint  # noqa: E402
from trianflow_vo.models.depth_net import DepthNet  # noqa: E402
from trianflow_vo.models.pwc import PWCConfig, PWCNet  # noqa: E402
from trianflow_vo.nets.onnx_runtime import open_model, to_model_input  # noqa: E402

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "authors_expected.npz"
MANIFEST = "trianflow_state_dict_manifest.json"
SIZE = "64x192"
FLOW_TOL_PX = 1e-3
DEPTH_TOL_REL = 1e-4
TINY = PWCConfig(pyramid_channels=(8, 8, 16, 16, 16, 16), estimator_channels=(8, 8, 8, 8, 8),
                 context_channels=(8, 8, 8, 8, 8, 8), search_range=2)


def _save_theirs(path: Path, layout: str) -> Path:
    torch.save(authors.deterministic_checkpoint(layout), str(path))
    return path


def _export(ckpt: Path, out: Path, *extra: str):
    return CliRunner().invoke(main, ["export", "--checkpoint", str(ckpt), "--size", SIZE, "--out-dir", str(out),
                                     *extra])


@pytest.fixture(scope="module")
def expected():
    if not FIXTURE.is_file():
        pytest.skip(f"{FIXTURE} missing (made by tests/fixtures/make_authors_expected.py)")
    return dict(np.load(FIXTURE))


@pytest.fixture(scope="module")
def frames(expected):
    """The fixture's image pair as the run path feeds it: full-size BGR frames."""
    sample = Path(__file__).resolve().parents[2] / "sample" / "kitti00" / "image_0"
    ims = [cv2.imread(str(sample / n)) for n in ("000000.jpg", "000001.jpg")]
    if any(im is None for im in ims):
        pytest.skip(f"shipped sample missing at {sample}")
    h, w = (int(v) for v in expected["size_hw"])
    small = [cv2.resize(im, (w, h), interpolation=cv2.INTER_LINEAR) for im in ims]
    hashes = [hashlib.sha256(np.ascontiguousarray(s).tobytes()).hexdigest() for s in small]
    assert hashes == list(expected["image_sha256"]), "the resized inputs differ from the fixture's (OpenCV?)"
    return ims


@pytest.fixture(scope="module")
def full_export(tmp_path_factory):
    d = tmp_path_factory.mktemp("authors_full")
    result = _export(_save_theirs(d / "their_full.pth", "full"), d / "out")
    return d / "out", result


def _flows(model_dir: Path, frames):
    sess, info = open_model(model_dir / "flow.onnx", "flow")
    fw, bw = sess.run(["flow_fw", "flow_bw"], {"image1": to_model_input(frames[0], info),
                                               "image2": to_model_input(frames[1], info)})
    return fw, bw, info


def test_generated_layout_equals_manifest(shared_data):
    path = shared_data.parent / "reference" / MANIFEST
    if not path.is_file():
        pytest.skip(f"{path} not found")
    manifest = json.loads(path.read_text())
    want = [(e["name"], tuple(e["shape"]), e["dtype"]) for e in manifest["state_dict"]]
    full = authors.deterministic_state_dict("full")
    assert [(k, tuple(v.shape), str(v.dtype).replace("torch.", "")) for k, v in full.items()] == want
    want_flow = [(e["name"], tuple(e["shape"])) for e in manifest["flow_only_checkpoint_keys"]]
    assert [(k, tuple(v.shape)) for k, v in authors.deterministic_state_dict("flow").items()] == want_flow
    assert [(n, s) for n, s, _ in authors.their_layout("full")] == [(n, s) for n, s, _ in want]


def test_deterministic_weights_are_reproducible_and_sane():
    a = authors.deterministic_state_dict("flow")
    b = authors.deterministic_state_dict("flow")
    assert all(torch.equal(a[k], b[k]) for k in a)
    full = authors.deterministic_state_dict("full")
    for k, v in a.items():  # the flow net gets the same values in both layouts
        assert torch.equal(full[authors.FULL_FLOW_PREFIX + k], v)
    w = full["model_pose.model_flow.pwc_model.conv2_0.0.weight"]
    assert abs(float(w.std()) * (115 * 9) ** 0.5 - 2 ** 0.5) < 0.05  # std = sqrt(2 / fan_in)
    var = [v for k, v in full.items() if k.endswith("running_var")]
    assert var and all(float(v.min()) >= 0.5 for v in var)
    assert full["depth_net.encoder.encoder.bn1.num_batches_tracked"].dtype == torch.int64
    # a known value pins the definition (numpy PCG64 seeded from sha256 of the name)
    assert float(a["fpyramid.conv1.0.bias"][0]) == pytest.approx(float(authors.deterministic_tensor(
        "fpyramid.conv1.0.bias", (16,))[0]))


def test_mapping_round_trip_and_layout_detection():
    theirs = authors.deterministic_state_dict("full")
    assert authors.detect_layout(theirs) == "full"
    flow_sd, depth_sd = authors.their_to_ours(theirs)
    assert set(flow_sd) == set(PWCNet().state_dict())
    assert set(depth_sd) == set(DepthNet().state_dict())  # fc.* dropped
    back = authors.ours_to_theirs(flow_sd, depth_sd)
    assert list(back) == list(theirs)
    for k, v in back.items():
        if ".fc." in k:
            assert not v.any()
        else:
            assert torch.equal(v, theirs[k])
    flow_only = authors.ours_to_theirs(flow_sd)
    assert list(flow_only) == list(authors.deterministic_state_dict("flow"))
    assert authors.detect_layout(flow_only) == "flow"
    assert authors.detect_layout({"model_flow." + k: v for k, v in flow_only.items()}) == "flow"
    assert authors.detect_layout({"module." + k: v for k, v in theirs.items()}) == "full"
    assert authors.their_to_ours({"module." + k: v for k, v in flow_only.items()})[1] is None
    assert authors.detect_layout({"conv1.weight": torch.zeros(1)}) is None


def test_full_import_matches_the_authors_code(full_export, expected, frames):
    out, result = full_export
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in out.iterdir()) == ["depth.onnx", "flow.onnx", "flow_decoder.onnx", "flow_encoder.onnx"]
    fw, bw, info = _flows(out, frames)
    assert np.abs(expected["flow_fw"]).mean() > 1.0  # flows of a few pixels, not ~0
    assert np.abs(fw - expected["flow_fw"]).max() <= FLOW_TOL_PX
    assert np.abs(bw - expected["flow_bw"]).max() <= FLOW_TOL_PX
    sess, dinfo = open_model(out / "depth.onnx", "depth")
    (depth,) = sess.run(["depth"], {"image": to_model_input(frames[0], dinfo)})
    want = expected["depth1"]
    assert want.max() / want.min() > 2.0  # depth varies over the image
    assert (np.abs(depth - want) / want).max() <= DEPTH_TOL_REL
    # the authors' preprocessing is in the metadata
    for i, kind in ((info, "flow"), (dinfo, "depth")):
        assert i.channel_order == "BGR" and i.resize == "linear" and i.input_size == (64, 192)
        assert json.loads(i.meta["train_input_size"]) == [256, 832]
        assert json.loads(i.meta["weights"]) == {"source": "trianflow-authors-full", "file": "their_full.pth"}
    assert info.normalisation["mean"] == [0.0] * 3 and info.normalisation["std"] == [1.0] * 3
    assert dinfo.normalisation["mean"] == [0.45] * 3 and dinfo.normalisation["std"] == [0.225] * 3
    assert "trianflow-authors-full layout; input BGR, resize linear, trained at 256x832" in result.output


def test_flow_only_import_writes_only_flow(tmp_path, expected, frames):
    result = _export(_save_theirs(tmp_path / "their_flow.pth", "flow"), tmp_path / "out")
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["flow.onnx", "flow_decoder.onnx", "flow_encoder.onnx"]  # no depth.onnx
    fw, bw, info = _flows(tmp_path / "out", frames)
    assert np.abs(fw - expected["flow_fw"]).max() <= FLOW_TOL_PX
    assert np.abs(bw - expected["flow_bw"]).max() <= FLOW_TOL_PX
    assert json.loads(info.meta["weights"])["source"] == "trianflow-authors-flow"


def _flow_only_file(tmp_path: Path, edit=None) -> Path:
    ckpt = authors.deterministic_checkpoint("flow")
    if edit is not None:
        edit(ckpt["model_state_dict"])
    path = tmp_path / "bad.pth"
    torch.save(ckpt, str(path))
    return path


def _junk(tmp_path):
    (tmp_path / "bad.pth").write_bytes(b"this is not a checkpoint\n" * 10)
    return tmp_path / "bad.pth"


def _truncated(tmp_path):
    path = _flow_only_file(tmp_path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


def _missing(tmp_path):
    return _flow_only_file(tmp_path, lambda sd: sd.pop("pwc_model.conv3_2.0.weight"))


def _misshaped(tmp_path):
    def edit(sd):
        sd["fpyramid.conv11.0.weight"] = torch.zeros(192, 128, 3, 3)  # the old 192-channel pyramid
    return _flow_only_file(tmp_path, edit)


def _unexpected(tmp_path):
    return _flow_only_file(tmp_path, lambda sd: sd.__setitem__("pwc_model.conv1_0.0.weight", torch.zeros(1)))


def _foreign(tmp_path):
    torch.save({"weights": {"a": torch.zeros(2)}}, str(tmp_path / "bad.pth"))
    return tmp_path / "bad.pth"


def _pickled_object(tmp_path):
    torch.save({"model_state_dict": {"fpyramid.conv1.0.weight": np.zeros(3)}}, str(tmp_path / "bad.pth"))
    return tmp_path / "bad.pth"


@pytest.mark.parametrize("make, message", [
    (_junk, "bad.pth: cannot read checkpoint: not a torch checkpoint file, or corrupt or truncated"),
    (_truncated, "bad.pth: cannot read checkpoint: not a torch checkpoint file, or corrupt or truncated "
                 "(RuntimeError: failed finding central directory"),
    (_missing, "bad.pth: missing tensor 'pwc_model.conv3_2.0.weight'"),
    (_misshaped, "bad.pth: tensor 'fpyramid.conv11.0.weight' has shape [192, 128, 3, 3], expected [196, 128, 3, 3]"),
    (_unexpected, "bad.pth: unexpected tensor 'pwc_model.conv1_0.0.weight'"),
    (_foreign, "bad.pth: not a trianflow-vo checkpoint"),
    (_pickled_object, "bad.pth: cannot read checkpoint safely"),
])
def test_bad_files_are_one_line_and_write_nothing(tmp_path, make, message):
    path = make(tmp_path)
    out = tmp_path / "out"
    result = _export(path, out)
    assert result.exit_code == 1, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1, result.output
    assert message in lines[0] and str(path) in lines[0], lines[0]
    assert "Traceback" not in result.output
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.pth"]  # no temporary leftovers


def test_failure_midway_leaves_the_directory_as_it_was(tmp_path, monkeypatch):
    """flow.onnx is written and checked, then the depth export fails: nothing reaches DIR."""
    import trianflow_vo.models.export as export_mod

    torch.manual_seed(0)
    save_checkpoint(tmp_path / "ours.pt", make_checkpoint(PWCNet(TINY), DepthNet(), (64, 192)))
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")

    def fail(*args, **kwargs):
        raise ModelError("simulated depth export failure")

    monkeypatch.setattr(export_mod, "export_depth", fail)
    result = _export(tmp_path / "ours.pt", out)
    assert result.exit_code == 1 and "simulated depth export failure" in result.output
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ours.pt", "out"]


def test_old_version_of_our_checkpoint_is_refused(tmp_path):
    torch.manual_seed(0)
    ckpt = make_checkpoint(PWCNet(TINY), None, (64, 192))
    ckpt["format_version"] = 1
    del ckpt["resize"]
    save_checkpoint(tmp_path / "old.pt", ckpt)
    result = _export(tmp_path / "old.pt", tmp_path / "out")
    assert result.exit_code == 1
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and "old.pt: checkpoint format_version 1 is no longer supported" in lines[0]
    assert "re-create it" in lines[0] and "trianflow-vo export --checkpoint their.pth" in lines[0]
    assert not (tmp_path / "out").exists()
