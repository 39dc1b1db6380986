"""`trianflow-vo train` end to end at a tiny size: outputs, resume, bad input, and DDP via torchrun."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("torch")
pytest.importorskip("tensorboard")

from click.testing import CliRunner  # noqa: E402

from trianflow_vo.cli.main import main  # noqa: E402

SIZE = "64x192"
# one torch thread: on a machine shared with other jobs, two OpenMP threads on two busy cores make an
# iteration 7-26x slower (measured); the behaviour tested does not depend on it
TINY = ["--size", SIZE, "--batch", "2", "--workers", "0", "--set", "runtime.threads=1",
        "--set", "schedule.log_every=1", "--set", "schedule.image_every=2", "--set", "schedule.checkpoint_every=2",
        "--set", "schedule.val_every=0"]


@pytest.fixture(scope="module")
def clip(tmp_path_factory) -> Path:
    """The first 6 frames of the KITTI sample (calib.txt, poses.txt kept)."""
    from conftest import SAMPLE

    if not SAMPLE.is_dir():
        pytest.skip(f"shipped sample missing at {SAMPLE}")
    d = tmp_path_factory.mktemp("clip") / "kitti00"
    src = Path(SAMPLE)
    shutil.copytree(src, d, ignore=lambda folder, names: [n for n in names if n.endswith(".jpg")
                                                         and int(Path(n).stem) >= 6])
    return d


def _train(args, **kw):
    return CliRunner().invoke(main, ["train", *args], catch_exceptions=False, **kw)


def _rows(out: Path) -> list[dict]:
    return list(csv.DictReader(open(out / "metrics.csv")))


def test_flow_stage_writes_everything_and_resumes(clip, tmp_path):
    out = tmp_path / "flow"
    res = _train(["--stage", "flow", str(clip), "--out", str(out), "--iters", "4", *TINY])
    assert res.exit_code == 0, res.output
    for name in ("checkpoint.pt", "metrics.csv", "config.yaml", "train.json"):
        assert (out / name).is_file(), name
    assert any((out / "tb").glob("events.out.tfevents.*"))
    status = json.loads((out / "train.json").read_text())
    assert status["status"] == "completed" and status["iteration"] == 4 and status["checkpoint_iteration"] == 4
    rows = _rows(out)
    assert [int(r["iteration"]) for r in rows] == [1, 2, 3, 4]
    assert all(float(r["total"]) > 0 for r in rows)
    res = _train(["--stage", "flow", str(clip), "--out", str(out), "--resume", "--iters", "6", *TINY])
    assert res.exit_code == 0, res.output
    assert [int(r["iteration"]) for r in _rows(out)] == [1, 2, 3, 4, 5, 6]
    assert json.loads((out / "train.json").read_text())["resumed_from"] == 4
    # the checkpoint exports directly and the networks run through `run`
    models = tmp_path / "m"
    res = CliRunner().invoke(main, ["export", "--checkpoint", str(out / "checkpoint.pt"), "--out-dir", str(models)])
    assert res.exit_code == 0, res.output
    run_out = tmp_path / "run"
    res = CliRunner().invoke(main, ["run", str(clip), "--flow-model", str(models / "flow.onnx"), "--out",
                                    str(run_out), "--quiet", "--no-plot"])
    assert res.exit_code == 0, res.output
    assert json.loads((run_out / "run.json").read_text())["status"] == "completed"


def test_resume_continues_exactly(clip, tmp_path):
    """4 iterations, then 2 more after a resume == 6 iterations in one go (same losses)."""
    a, b = tmp_path / "a", tmp_path / "b"
    assert _train(["--stage", "flow", str(clip), "--out", str(a), "--iters", "6", *TINY]).exit_code == 0
    assert _train(["--stage", "flow", str(clip), "--out", str(b), "--iters", "4", *TINY]).exit_code == 0
    assert _train(["--stage", "flow", str(clip), "--out", str(b), "--iters", "6", "--resume", *TINY]).exit_code == 0
    ta = [float(r["total"]) for r in _rows(a)]
    tb = [float(r["total"]) for r in _rows(b)]
    assert tb == pytest.approx(ta, rel=1e-4)


def test_depth_stage_needs_a_flow_network(clip, tmp_path):
    res = _train(["--stage", "depth", str(clip), "--out", str(tmp_path / "d"), "--iters", "1", *TINY])
    assert res.exit_code == 1
    assert "frozen flow network" in res.output and "--init" in res.output
    assert not (tmp_path / "d").exists()


@pytest.mark.parametrize("args,code,message", [
    (["--stage", "posenet"], 2, "posenet"),
    (["--stage", "flow", "--set", "losses.w_nope=1"], 2, "losses.w_nope"),
    (["--stage", "flow", "--config", "cityscapes"], 2, "no such file or preset"),
])
def test_bad_options_are_one_line(clip, tmp_path, args, code, message):
    res = _train([*args, str(clip), "--out", str(tmp_path / "o"), "--iters", "1", *TINY])
    assert res.exit_code == code, res.output
    assert message in res.output and "Traceback" not in res.output
    assert not (tmp_path / "o").exists()


def test_folder_without_images_and_wrong_checkpoint(tmp_path, clip):
    empty = tmp_path / "empty"
    empty.mkdir()
    res = _train(["--stage", "flow", str(empty), "--out", str(tmp_path / "o1"), "--iters", "1", *TINY])
    assert res.exit_code == 1 and str(empty) in res.output and "Traceback" not in res.output
    assert not (tmp_path / "o1").exists()
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    res = _train(["--stage", "flow", str(clip), "--out", str(tmp_path / "o2"), "--init", str(bad), "--iters", "1",
                  *TINY])
    assert res.exit_code == 1 and "bad.pt" in res.output
    assert not (tmp_path / "o2").exists()


def test_torchrun_two_cpu_processes(clip, tmp_path):
    torchrun = shutil.which("torchrun", path=str(Path(sys.executable).parent))
    exe = shutil.which("trianflow-vo", path=str(Path(sys.executable).parent))
    if torchrun is None or exe is None:
        pytest.skip("torchrun / trianflow-vo not installed beside this python")
    out = tmp_path / "ddp"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    res = subprocess.run([torchrun, "--standalone", "--nproc_per_node", "2", "--no-python", exe, "train",
                          "--stage", "flow", str(clip), "--out", str(out), "--iters", "3", "--quiet", *TINY],
                         capture_output=True, text=True, timeout=300, env=env)
    assert res.returncode == 0, res.stderr[:6000]
    status = json.loads((out / "train.json").read_text())
    assert status["world_size"] == 2 and status["batch_per_process"] == 1 and status["status"] == "completed"
    assert list(out.glob("checkpoint*.pt")) == [out / "checkpoint.pt"]
    assert len(_rows(out)) == 3


def test_init_from_the_authors_layout_and_depth_from_dis(clip, tmp_path):
    """--init reads the authors' .pth layouts (full: both nets; flow-only: the flow net); stage depth
    trains without a flow network with --flow-source dis; a flow-only file cannot start stage joint."""
    import torch

    from trianflow_vo.models.authors import LAYOUT_FLOW, LAYOUT_FULL, deterministic_checkpoint

    full, flow_only = tmp_path / "full.pth", tmp_path / "flow.pth"
    torch.save(deterministic_checkpoint(LAYOUT_FULL), full)
    torch.save(deterministic_checkpoint(LAYOUT_FLOW), flow_only)
    res = _train(["--stage", "joint", str(clip), "--out", str(tmp_path / "j"), "--init", str(full), "--iters", "1",
                  *TINY])
    assert res.exit_code == 0, res.output
    status = json.loads((tmp_path / "j" / "train.json").read_text())
    assert status["init_format"] == "trianflow-authors-full" and status["status"] == "completed"
    res = _train(["--stage", "depth", str(clip), "--out", str(tmp_path / "d"), "--init", str(flow_only), "--iters",
                  "1", *TINY])
    assert res.exit_code == 0, res.output
    res = _train(["--stage", "joint", str(clip), "--out", str(tmp_path / "j2"), "--init", str(flow_only), "--iters",
                  "1", *TINY])
    assert res.exit_code == 1 and "holds no depth network" in res.output
    assert not (tmp_path / "j2").exists()
    res = _train(["--stage", "depth", str(clip), "--out", str(tmp_path / "dis"), "--flow-source", "dis",
                  "--iters", "2", *TINY])
    assert res.exit_code == 0, res.output
    status = json.loads((tmp_path / "dis" / "train.json").read_text())
    assert any("OpenCV DIS" in w and "not the paper" in w for w in status["warnings"])
    assert status["config"]["model"]["flow_source"] == "dis"
    rows = _rows(tmp_path / "dis")
    assert len(rows) == 2 and float(rows[-1]["pt_depth"]) >= 0
    # the checkpoint of a DIS run holds the depth network only
    from trianflow_vo.models.checkpoint import load_checkpoint

    ck = load_checkpoint(tmp_path / "dis" / "checkpoint.pt")
    assert ck.flow is None and ck.depth is not None


def test_interrupt_writes_a_checkpoint_and_resume_continues(clip, tmp_path):
    """Ctrl-C during iteration 3: the checkpoint holds iteration 3, train.json says interrupted, and
    --resume continues from there."""
    from trianflow_vo.cli.train_cmd import build_train_config
    from trianflow_vo.train import loop

    out = tmp_path / "int"
    cfg = build_train_config("flow", None, ("schedule.log_every=1", "schedule.checkpoint_every=100",
                                            "schedule.image_every=0", "data.workers=0", "runtime.threads=1"),
                             {"iters": 6, "batch": 2, "size": (64, 192)})

    def stop(info):
        if info["iteration"] == 3:
            raise KeyboardInterrupt

    prep = loop.prepare(loop.TrainRequest(data=[clip], out_dir=out, config=cfg))
    result = loop.train(prep, on_progress=stop)
    assert result.status == "interrupted" and result.iteration == 3
    status = json.loads((out / "train.json").read_text())
    assert status["status"] == "interrupted" and status["checkpoint_iteration"] == 3
    assert not list(out.glob("*.tmp"))
    res = _train(["--stage", "flow", str(clip), "--out", str(out), "--resume", *TINY])
    assert res.exit_code == 0, res.output
    assert [int(r["iteration"]) for r in _rows(out)] == [1, 2, 3, 4, 5, 6]
