"""``trianflow-vo run`` with network models (random weights) on the shipped sample."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="needs torch (pip install 'trianflow-vo[torch]')")
pytest.importorskip("onnxruntime", reason="needs onnxruntime to run exported models")

from click.testing import CliRunner  # noqa: E402

from trianflow_vo.cli.main import main  # noqa: E402
from trianflow_vo.models.checkpoint import FLOW_NORM  # noqa: E402
from trianflow_vo.models.export import export_flow  # noqa: E402
from trianflow_vo.models.pwc import PWCConfig, PWCNet  # noqa: E402
from trianflow_vo.flow.onnx_flow import OnnxFlow  # noqa: E402

END = 6  # frames 0..5: the first frame and 5 pairs


@pytest.fixture(scope="module")
def random_models(tmp_path_factory):
    d = tmp_path_factory.mktemp("models")
    r = CliRunner().invoke(main, ["export", "--random-init", "--seed", "0", "--size", "64x192", "--out-dir", str(d)])
    assert r.exit_code == 0, r.output
    return d


def _run(seq, out, *model_args):
    r = CliRunner().invoke(main, ["run", str(seq), *model_args, "--end", str(END), "--out", str(out)])
    assert r.exit_code == 0, r.output
    lines = (out / "poses.txt").read_text().splitlines()
    assert len(lines) == END
    assert all(len(ln.split()) == 12 for ln in lines)
    info = json.loads((out / "run.json").read_text())
    counts = info["branch_counts"]
    assert sum(counts.values()) == END  # one branch for the first frame and for every pair
    assert counts["init"] == 1
    non_two_view = [e for e in info["degraded"] if e["branch"] != "init"]
    assert len(non_two_view) == END - 1 - counts["two-view"]  # every other pair is listed with its branch
    return info


def test_run_with_both_models(sample_seq, random_models, tmp_path):
    info = _run(sample_seq, tmp_path / "out", "--flow-model", str(random_models / "flow.onnx"),
                "--depth-model", str(random_models / "depth.onnx"))
    assert info["flow_source"]["name"] == "onnx-pwc"
    # the depth prior is the network prior, wrapping the ONNX depth network
    assert info["depth_source"]["name"] == "network"
    assert info["depth_source"]["net"]["name"] == "onnx-depth"
    assert info["config"]["depth"]["model"] == str(random_models / "depth.onnx")
    assert info["flow_source"]["input_size"] == [64, 192]  # resized to and from the working size


def test_run_with_each_model_alone(sample_seq, random_models, tmp_path):
    info = _run(sample_seq, tmp_path / "flow_only", "--flow-model", str(random_models / "flow.onnx"))
    assert info["flow_source"]["name"] == "onnx-pwc"
    assert info["depth_source"] == {"name": "triangulated"}  # no depth network: depth from triangulation
    info = _run(sample_seq, tmp_path / "depth_only", "--depth-model", str(random_models / "depth.onnx"))
    assert info["flow_source"]["name"] == "dis"
    assert info["depth_source"]["name"] == "network"
    assert info["depth_source"]["net"]["name"] == "onnx-depth"


def test_run_survives_large_random_flow(sample_seq, random_models, tmp_path):
    """Random flow of a hundred pixels and more (degenerate geometry) must not crash the run."""
    torch.manual_seed(5)
    net = PWCNet(PWCConfig(pyramid_channels=(8, 8, 16, 16, 16, 16), estimator_channels=(8, 8, 8, 8, 8),
                           context_channels=(8, 8, 8, 8, 8, 8), search_range=2,
                           estimator_connections="dense")).eval()  # this recipe's scale is tuned for it
    with torch.no_grad():
        for est in net.estimators:
            est.predict.weight.mul_(20.0)
    export_flow(net, FLOW_NORM, (64, 192), "RGB", tmp_path / "wild.onnx")
    src = OnnxFlow(tmp_path / "wild.onnx")
    ims = [cv2.resize(cv2.imread(str(sample_seq / "image_0" / f"00000{i}.jpg")), (832, 256)) for i in (0, 1)]
    fw, _ = src.flow_pair(src.prepare(ims[0]), src.prepare(ims[1]))
    assert np.median(np.abs(fw)) > 50.0  # really degenerate
    _run(sample_seq, tmp_path / "out", "--flow-model", str(tmp_path / "wild.onnx"),
         "--depth-model", str(random_models / "depth.onnx"))


def test_wrong_model_is_a_clear_error(sample_seq, random_models, tmp_path):
    r = CliRunner().invoke(main, ["run", str(sample_seq), "--flow-model", str(random_models / "depth.onnx"),
                                  "--end", "3", "--out", str(tmp_path / "o")])
    assert r.exit_code != 0
    assert "depth.onnx: is a 'depth' model, expected a 'flow' model" in r.output
    assert "Traceback" not in r.output
