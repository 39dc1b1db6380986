"""``trianflow-vo eval-depth`` and ``eval-flow`` end to end, with one-line errors.

The models are small random-weight exports (``trianflow-vo export --random-init``).
Known answers come from ground truth made *of the network's own output*, computed here
independently (a plain onnxruntime session fed as the metadata says, the resize done
with OpenCV here): ground truth = 100 x the predicted depth gives zero error with median
scaling and abs rel 0.99 without; ground truth = the predicted flow gives EPE 0 (up to
the 1/64 px of KITTI PNGs), and + 4 px gives EPE 4 and Fl-all 100 %. The tests check
that a mismatched pairing would have given other numbers (for depth through the
network's output, which differs between images; for flow through ground truth offset
per pair, since a random network's flow hardly depends on the images).
"""

from __future__ import annotations

import csv
import functools
import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

pytest.importorskip("torch", reason="needs torch to export the test models (pip install 'trianflow-vo[torch]')")
pytest.importorskip("onnx", reason="needs onnx to export the test models (pip install 'trianflow-vo[torch]')")
ort = pytest.importorskip("onnxruntime", reason="needs onnxruntime to run exported models")

from click.testing import CliRunner  # noqa: E402

from trianflow_vo.cli.main import main  # noqa: E402
from trianflow_vo.io.depth_png import write_depth_png  # noqa: E402
from trianflow_vo.io.flo import write_flo  # noqa: E402
from trianflow_vo.io.kitti_flow import write_kitti_flow  # noqa: E402

IMAGE_HW = (100, 300)  # the model is 64x192


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    d = tmp_path_factory.mktemp("models")
    r = CliRunner().invoke(main, ["export", "--random-init", "--seed", "0", "--size", "64x192", "--no-split",
                                   "--out-dir", str(d)])
    assert r.exit_code == 0, r.output
    return {"depth": d / "depth.onnx", "flow": d / "flow.onnx"}


def _image(seed, hw=IMAGE_HW):
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 256, (hw[0] // 4, hw[1] // 4, 3), dtype=np.uint8)
    return cv2.resize(img, (hw[1], hw[0]), interpolation=cv2.INTER_CUBIC)


# --------------------------------------------------------------------------- independent reference


@functools.cache
def _session(model):
    return ort.InferenceSession(str(model), providers=["CPUExecutionProvider"])


def _input(path, meta):
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    H, W = (int(v) for v in meta["trianflow.input_size"].split("x"))
    method = meta.get("trianflow.resize", "area-down-linear-up")
    if method == "linear":
        interp = cv2.INTER_LINEAR
    else:
        assert method == "area-down-linear-up", method
        interp = cv2.INTER_AREA if (img.shape[0] > H and img.shape[1] > W) else cv2.INTER_LINEAR
    img = cv2.resize(img, (W, H), interpolation=interp)
    if meta["trianflow.channel_order"] == "RGB":
        img = img[:, :, ::-1]
    return np.ascontiguousarray(img.transpose(2, 0, 1)[None], dtype=np.float32)


def _ref_depth(model, path, hw):
    """The network's depth of ``path`` resized (bilinear) to ``hw``."""
    s = _session(model)
    d = s.run(["depth"], {"image": _input(path, s.get_modelmeta().custom_metadata_map)})[0][0, 0]
    return cv2.resize(d, (hw[1], hw[0]), interpolation=cv2.INTER_LINEAR)


def _ref_flow(model, p1, p2, hw):
    """The network's forward flow resized to ``hw`` with its values scaled to those pixels."""
    s = _session(model)
    meta = s.get_modelmeta().custom_metadata_map
    fw = s.run(["flow_fw"], {"image1": _input(p1, meta), "image2": _input(p2, meta)})[0][0].transpose(1, 2, 0)
    h, w = fw.shape[:2]
    out = cv2.resize(np.ascontiguousarray(fw), (hw[1], hw[0]), interpolation=cv2.INTER_LINEAR)
    out[..., 0] *= hw[1] / w
    out[..., 1] *= hw[0] / h
    return out


def _abs_rel_median_scaled(gt, pred):
    p = pred * np.median(gt) / np.median(pred)
    return float(np.mean(np.abs(gt - p) / gt))


def _invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def _one_line_error(r, code, *words):
    assert r.exit_code == code, r.output
    assert isinstance(r.exception, SystemExit)
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: "), r.output
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


# --------------------------------------------------------------------------- fixtures


@pytest.fixture
def frames(tmp_path):
    """img/f10.png, f1.png, f2.png (natural order f1, f2, f10)."""
    d = tmp_path / "img"
    d.mkdir()
    for seed, name in ((10, "f10"), (1, "f1"), (2, "f2")):
        cv2.imwrite(str(d / f"{name}.png"), _image(seed))
    return d


def _depth_gt(models, frames, dest, hw, kind="npy", scale=100.0, order=("f1", "f2", "f10")):
    """Ground truth = ``scale`` x the network's depth at ``hw``; ``order`` maps the ground truth
    file named ``f1``, ``f2``, ``f10`` to the image it is made from."""
    dest.mkdir()
    maps = {}
    for name, src in zip(("f1", "f2", "f10"), order):
        maps[name] = scale * _ref_depth(models["depth"], frames / f"{src}.png", hw)
        if kind == "npy":
            np.save(dest / f"{name}.npy", maps[name])
        else:
            write_depth_png(dest / f"{name}.png", maps[name])
    return maps


# --------------------------------------------------------------------------- eval-depth


def test_listed_in_main_help():
    r = CliRunner().invoke(main, ["--help"])
    assert r.exit_code == 0 and "eval-depth" in r.output and "eval-flow" in r.output


def test_help_does_not_import_onnxruntime():
    code = (
        "import sys\n"
        "from click.testing import CliRunner\n"
        "from trianflow_vo.cli.main import main\n"
        "for cmd in ('eval-depth', 'eval-flow'):\n"
        "    r = CliRunner().invoke(main, [cmd, '--help'])\n"
        "    assert r.exit_code == 0, r.output\n"
        "    assert 'Examples' in r.output\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('onnxruntime', 'torch', 'evo'))\n"
        "assert not bad, bad\n"
        "print('ok')\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and "ok" in res.stdout, res.stdout + res.stderr


def test_crop_choices_match_the_library():
    from trianflow_vo.cli.eval_depth_cmd import CROP_CHOICES
    from trianflow_vo.eval.depth_metrics import CROPS

    assert set(CROP_CHOICES) == set(CROPS)


def test_depth_known_answer_folder_npy(models, frames, tmp_path):
    gt = tmp_path / "gt"
    _depth_gt(models, frames, gt, IMAGE_HW)
    out = tmp_path / "out"
    r = _invoke("eval-depth", "--depth-model", models["depth"], frames, "--gt-depth", gt, "--out", out,
                "--crop", "none")
    assert r.exit_code == 0, r.output
    summary = json.loads((out / "depth_metrics.json").read_text())
    m = summary["metrics"]
    assert m["abs_rel"] < 1e-5 and m["rmse_log"] < 1e-5 and m["a1"] == 1.0
    assert summary["n_images"] == 3
    assert summary["median_scaling"]["ratio_median"] == pytest.approx(100.0, rel=1e-5)
    assert summary["median_scaling"]["ratio_rel_std"] < 1e-5
    assert summary["settings"]["crop"] == "none" and summary["model"]["input_size"] == [64, 192]
    rows = list(csv.DictReader((out / "depth_per_image.csv").open()))
    assert [r_["image"] for r_ in rows] == [str(frames / f"{n}.png") for n in ("f1", "f2", "f10")]
    assert [r_["gt"] for r_ in rows] == [str(gt / f"{n}.npy") for n in ("f1", "f2", "f10")]
    assert all(int(r_["n_pixels"]) == IMAGE_HW[0] * IMAGE_HW[1] for r_ in rows)
    assert "abs_rel" in r.stdout and "3 images" in r.stdout and "crop none" in r.stdout
    # the pairing matters: the ground truth of another image is measurably worse
    a, b = (_ref_depth(models["depth"], frames / f"{n}.png", IMAGE_HW) for n in ("f1", "f2"))
    assert _abs_rel_median_scaled(100 * a, b) > 1e-3


def test_depth_png_ground_truth_of_another_size(models, frames, tmp_path):
    gt = tmp_path / "gt"
    _depth_gt(models, frames, gt, (50, 150), kind="png")  # half the image size, 1/256 m steps
    r = _invoke("eval-depth", "-q", "--depth-model", models["depth"], frames / "f2.png", frames / "f1.png",
                "--gt-depth", gt, "--out", tmp_path / "out")
    assert r.exit_code == 0, r.output
    m = json.loads((tmp_path / "out" / "depth_metrics.json").read_text())["metrics"]
    assert m["abs_rel"] < 2e-4 and m["a1"] == 1.0  # ~20 m depths stored to 1/256 m
    assert r.stderr == ""


def test_depth_swapped_ground_truth_is_detected(models, frames, tmp_path):
    gt = tmp_path / "gt"
    _depth_gt(models, frames, gt, IMAGE_HW, order=("f2", "f1", "f10"))
    r = _invoke("eval-depth", "-q", "--depth-model", models["depth"], frames, "--gt-depth", gt, "--crop", "none",
                "--out", tmp_path / "out")
    assert r.exit_code == 0, r.output
    rows = list(csv.DictReader((tmp_path / "out" / "depth_per_image.csv").open()))
    assert float(rows[0]["abs_rel"]) > 1e-3 and float(rows[1]["abs_rel"]) > 1e-3
    assert float(rows[2]["abs_rel"]) < 1e-5


def test_depth_stack_no_median_scaling_and_progress(models, frames, tmp_path):
    maps = _depth_gt(models, frames, tmp_path / "gt", IMAGE_HW)
    np.savez(tmp_path / "gt_depths.npz", data=np.stack([maps[n] for n in ("f1", "f2", "f10")]))
    r = _invoke("eval-depth", "--depth-model", models["depth"], frames, "--gt-depth", tmp_path / "gt_depths.npz",
                "--no-median-scaling", "--crop", "garg")
    assert r.exit_code == 0, r.output
    table = r.stdout.splitlines()
    assert "median scaling off" in table[0] and not any("scaling ratio" in t for t in table)
    values = [float(v) for v in table[-1].split()]
    assert values[0] == pytest.approx(0.99, abs=1e-5)  # pred = gt / 100: |gt - pred| / gt
    assert values[4:] == [0.0, 0.0, 0.0]
    assert r.stderr.splitlines() == ["depth 1/3 f1.png", "depth 2/3 f2.png", "depth 3/3 f10.png"]


def test_depth_object_array_stack_needs_allow_pickle(models, frames, tmp_path):
    maps = np.empty(1, dtype=object)
    maps[0] = 100 * _ref_depth(models["depth"], frames / "f1.png", (40, 120))
    np.savez(tmp_path / "gt_depths.npz", data=maps)
    args = ["eval-depth", "--depth-model", models["depth"], frames / "f1.png", "--gt-depth",
            tmp_path / "gt_depths.npz"]
    _one_line_error(_invoke(*args), 1, "gt_depths.npz", "--allow-pickle")
    r = _invoke(*args, "--allow-pickle")
    assert r.exit_code == 0, r.output
    assert "1 image," in r.stdout


# --------------------------------------------------------------------------- eval-depth errors


def test_depth_error_missing_ground_truth(models, frames, tmp_path):
    gt = tmp_path / "gt"
    _depth_gt(models, frames, gt, IMAGE_HW)
    (gt / "f2.npy").unlink()
    _one_line_error(_invoke("eval-depth", "--depth-model", models["depth"], frames, "--gt-depth", gt,
                            "--out", tmp_path / "out"), 1, str(frames / "f2.png"), "no ground-truth depth")
    assert not (tmp_path / "out").exists()  # checked before any work


def test_depth_error_unreadable_ground_truth_png(models, frames, tmp_path):
    gt = tmp_path / "gt"
    _depth_gt(models, frames, gt, IMAGE_HW, kind="png")
    data = (gt / "f1.png").read_bytes()
    (gt / "f1.png").write_bytes(data[: len(data) // 3])
    out = tmp_path / "out"
    _one_line_error(_invoke("eval-depth", "-q", "--depth-model", models["depth"], frames, "--gt-depth", gt,
                            "--out", out), 1, str(gt / "f1.png"), "cannot decode")
    assert not list(out.iterdir())  # nothing written
    cv2.imwrite(str(gt / "f1.png"), np.zeros((10, 10), np.uint8))
    _one_line_error(_invoke("eval-depth", "-q", "--depth-model", models["depth"], frames, "--gt-depth", gt),
                    1, str(gt / "f1.png"), "not a KITTI depth PNG: uint8")


def test_depth_error_unreadable_image(models, frames, tmp_path):
    gt = tmp_path / "gt"
    _depth_gt(models, frames, gt, IMAGE_HW)
    data = (frames / "f1.png").read_bytes()
    (frames / "f1.png").write_bytes(data[: len(data) // 3])
    _one_line_error(_invoke("eval-depth", "-q", "--depth-model", models["depth"], frames, "--gt-depth", gt),
                    1, str(frames / "f1.png"), "decode")


def test_depth_error_empty_folder_and_missing_paths(models, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    _one_line_error(_invoke("eval-depth", "--depth-model", models["depth"], empty, "--gt-depth", empty),
                    1, str(empty), "no images")
    frames = tmp_path / "one"
    frames.mkdir()
    cv2.imwrite(str(frames / "a.png"), _image(0))
    _one_line_error(_invoke("eval-depth", "--depth-model", models["depth"], frames, "--gt-depth",
                            tmp_path / "nope.npz"), 1, str(tmp_path / "nope.npz"), "no such file")
    _one_line_error(_invoke("eval-depth", "--depth-model", tmp_path / "none.onnx", frames, "--gt-depth",
                            frames / "a.png"), 1, "none.onnx", "not found")


def test_depth_error_stack_length_and_ground_truth_without_pixels(models, frames, tmp_path):
    np.save(tmp_path / "two.npy", np.ones((2, 10, 30), np.float32))
    _one_line_error(_invoke("eval-depth", "--depth-model", models["depth"], frames, "--gt-depth",
                            tmp_path / "two.npy"), 1, "two.npy", "holds 2 depth map(s) for 3 image(s)")
    np.save(tmp_path / "far.npy", np.full((1, 10, 30), 200.0, np.float32))
    _one_line_error(_invoke("eval-depth", "-q", "--depth-model", models["depth"], frames / "f1.png",
                            "--gt-depth", tmp_path / "far.npy"),
                    1, str(frames / "f1.png"), "no ground-truth depth in (0.001, 80) m")


def test_depth_error_bad_options(models, frames, tmp_path):
    _one_line_error(_invoke("eval-depth", "--depth-model", models["depth"], frames, "--gt-depth", frames,
                            "--min-depth", "10", "--max-depth", "5"), 2, "--min-depth (10) must be below")
    _one_line_error(_invoke("eval-depth", "--depth-model", models["flow"], frames, "--gt-depth", frames),
                    1, "is a 'flow' model, expected a 'depth' model")


# --------------------------------------------------------------------------- eval-flow


def _kitti_flow_folder(models, root, offsets=((0.0, 0.0), (0.0, 0.0)), gt_hw=IMAGE_HW):
    """training/image_2/00000{0,1}_1{0,1}.png, flow_occ/00000i_10.png = the network's flow of pair i
    + ``offsets[i]`` at ``gt_hw``."""
    (root / "image_2").mkdir(parents=True)
    (root / "flow_occ").mkdir()
    refs = {}
    for i in (0, 1):
        p1, p2 = root / "image_2" / f"00000{i}_10.png", root / "image_2" / f"00000{i}_11.png"
        base = _image(20 + i)
        cv2.imwrite(str(p1), base)
        cv2.imwrite(str(p2), np.roll(base, 2 + i, axis=1))
        refs[i] = _ref_flow(models["flow"], p1, p2, gt_hw)
        write_kitti_flow(root / "flow_occ" / f"00000{i}_10.png", refs[i] + np.asarray(offsets[i], np.float32))
    return refs


def test_flow_known_answer_kitti_folder(models, tmp_path):
    root = tmp_path / "training"
    _kitti_flow_folder(models, root)
    out = tmp_path / "out"
    r = _invoke("eval-flow", "--flow-model", models["flow"], root, "--out", out)
    assert r.exit_code == 0, r.output
    summary = json.loads((out / "flow_metrics.json").read_text())
    m = summary["metrics"]
    assert m["epe"] < 0.012 and m["epe_pooled"] < 0.012  # 1/64 px steps of the PNG (<= 0.011 px)
    assert m["fl_all"] == 0.0 and m["fl_all_pooled"] == 0.0
    assert summary["n_pairs"] == 2 and summary["n_valid_pixels"] == 2 * IMAGE_HW[0] * IMAGE_HW[1]
    assert summary["gt"] == str(root / "flow_occ")
    rows = list(csv.DictReader((out / "flow_per_pair.csv").open()))
    assert [r_["pair"] for r_ in rows] == [str(root / "image_2" / f"00000{i}_10.png") for i in (0, 1)]
    assert "EPE (px)" in r.stdout and "Fl-all (%)" in r.stdout and "2 pairs" in r.stdout
    assert r.stderr.splitlines() == ["flow 1/2 000000_10.png", "flow 2/2 000001_10.png"]


def test_flow_ground_truth_matched_to_its_pair(models, tmp_path):
    """The random network's flow hardly depends on the images, so the pairing is checked
    through the ground truth instead: pair 1's is offset by 4 px, pair 0's is not."""
    root = tmp_path / "training"
    _kitti_flow_folder(models, root, offsets=((0.0, 0.0), (0.0, 4.0)))
    r = _invoke("eval-flow", "-q", "--flow-model", models["flow"], root, "--out", tmp_path / "out")
    assert r.exit_code == 0, r.output
    rows = list(csv.DictReader((tmp_path / "out" / "flow_per_pair.csv").open()))
    assert [r_["gt"] for r_ in rows] == [str(root / "flow_occ" / f"00000{i}_10.png") for i in (0, 1)]
    assert float(rows[0]["epe"]) < 0.012 and float(rows[0]["fl_all"]) == 0.0
    assert float(rows[1]["epe"]) == pytest.approx(4.0, abs=0.012) and float(rows[1]["fl_all"]) == 100.0
    m = json.loads((tmp_path / "out" / "flow_metrics.json").read_text())["metrics"]
    assert m["fl_all"] == pytest.approx(50.0) and m["epe"] == pytest.approx(2.0, abs=0.012)


def test_flow_constant_4px_offset_and_gt_of_another_size(models, tmp_path):
    root = tmp_path / "training"
    _kitti_flow_folder(models, root, offsets=((4.0, 0.0), (-4.0, 0.0)), gt_hw=(50, 150))
    r = _invoke("eval-flow", "-q", "--flow-model", models["flow"], root, "--out", tmp_path / "out")
    assert r.exit_code == 0, r.output
    m = json.loads((tmp_path / "out" / "flow_metrics.json").read_text())["metrics"]
    assert m["epe"] == pytest.approx(4.0, abs=0.012)
    assert m["fl_all"] == 100.0 and m["fl_all_pooled"] == 100.0  # |gt| ~ 4 px: 4 px is > 5% of it


def test_flow_pair_list_with_flo_ground_truth(models, tmp_path):
    root = tmp_path / "training"
    refs = _kitti_flow_folder(models, root)
    write_flo(tmp_path / "gt0.flo", refs[0])
    lst = tmp_path / "pairs.txt"
    lst.write_text("# image1 image2 gt\ntraining/image_2/000000_10.png training/image_2/000000_11.png gt0.flo\n")
    r = _invoke("eval-flow", "-q", "--flow-model", models["flow"], lst, "--out", tmp_path / "out")
    assert r.exit_code == 0, r.output
    m = json.loads((tmp_path / "out" / "flow_metrics.json").read_text())["metrics"]
    assert m["epe"] < 1e-5 and m["fl_all"] == 0.0
    _one_line_error(_invoke("eval-flow", "--flow-model", models["flow"], lst, "--gt-flow", root / "flow_occ"),
                    2, "--gt-flow is for a KITTI folder")


def test_flow_gt_flow_option_picks_the_folder(models, tmp_path):
    root = tmp_path / "training"
    refs = _kitti_flow_folder(models, root)
    noc = root / "flow_noc"
    noc.mkdir()
    for i in (0, 1):
        valid = np.zeros(IMAGE_HW, bool)
        valid[:, :10] = True
        write_kitti_flow(noc / f"00000{i}_10.png", refs[i] + np.float32(10.0), valid)
    r = _invoke("eval-flow", "-q", "--flow-model", models["flow"], root, "--gt-flow", noc)
    assert r.exit_code == 0, r.output
    assert f"2 pairs, {2 * 10 * IMAGE_HW[0]} valid" in r.stdout
    assert "100.0000" in r.stdout  # every noc pixel is 10 px off


# --------------------------------------------------------------------------- eval-flow errors


def test_flow_error_missing_second_image_and_gt(models, tmp_path):
    root = tmp_path / "training"
    _kitti_flow_folder(models, root)
    (root / "flow_occ" / "000001_10.png").unlink()
    _one_line_error(_invoke("eval-flow", "--flow-model", models["flow"], root, "--out", tmp_path / "out"),
                    1, str(root / "image_2" / "000001_10.png"), "no ground-truth flow")
    assert not (tmp_path / "out").exists()
    (root / "image_2" / "000000_11.png").unlink()
    _one_line_error(_invoke("eval-flow", "--flow-model", models["flow"], root),
                    1, str(root / "image_2" / "000000_10.png"), "no second image 000000_11.png")


def test_flow_error_unreadable_gt_png(models, tmp_path):
    root = tmp_path / "training"
    _kitti_flow_folder(models, root)
    bad = root / "flow_occ" / "000000_10.png"
    data = bad.read_bytes()
    bad.write_bytes(data[: len(data) // 3])
    out = tmp_path / "out"
    _one_line_error(_invoke("eval-flow", "-q", "--flow-model", models["flow"], root, "--out", out),
                    1, str(bad), "cannot decode the flow PNG")
    assert not list(out.iterdir())
    cv2.imwrite(str(bad), np.zeros((4, 4, 3), np.uint8))
    _one_line_error(_invoke("eval-flow", "-q", "--flow-model", models["flow"], root),
                    1, str(bad), "not a KITTI flow PNG: uint8")


def test_flow_error_empty_missing_and_wrong_model(models, tmp_path):
    empty = tmp_path / "empty"
    (empty / "image_2").mkdir(parents=True)
    _one_line_error(_invoke("eval-flow", "--flow-model", models["flow"], empty),
                    1, str(empty / "image_2"), "no first images")
    _one_line_error(_invoke("eval-flow", "--flow-model", models["flow"], tmp_path / "nope"),
                    1, str(tmp_path / "nope"), "no such file or folder")
    lst = tmp_path / "pairs.txt"
    lst.write_text("a.png b.png\n")
    _one_line_error(_invoke("eval-flow", "--flow-model", models["flow"], lst), 1, f"{lst}:1", "got 2 field")
    root = tmp_path / "training"
    _kitti_flow_folder(models, root)
    _one_line_error(_invoke("eval-flow", "--flow-model", models["depth"], root),
                    1, "is a 'depth' model, expected a 'flow' model")
