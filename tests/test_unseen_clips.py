"""``benchmarks/unseen_clips.py``: the recipe that rebuilds the unseen clips from local clones."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest


@pytest.fixture(scope="module")
def uc(benchmark_module):
    return benchmark_module("unseen_clips")


def test_rotations_of_known_quaternions(uc):
    s = np.sqrt(0.5)
    gt = np.array([[1.0, 0, 0, 0, 0.0, 0.0, s, s], [2.0, 0, 0, 0, 0.0, 0.0, 0.0, 2.0]])  # 90 deg about z; identity unnormalised
    poses, _ = uc.nearest_poses(np.array([1.0, 2.0]), gt)
    assert np.allclose(poses[0, :, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    assert np.allclose(poses[1, :, :3], np.eye(3))


def test_nearest_poses_takes_the_closest_sample_and_reports_the_gap(uc):
    gt = np.array([[10.00, 1, 0, 0, 0, 0, 0, 1], [10.10, 2, 0, 0, 0, 0, 0, 1], [10.20, 3, 0, 0, 0, 0, 0, 1]])
    poses, gap = uc.nearest_poses(np.array([10.04, 10.06, 10.30]), gt[::-1])  # unsorted input
    assert poses.shape == (3, 3, 4)
    assert poses[:, 0, 3].tolist() == [1.0, 2.0, 3.0]
    assert gap == pytest.approx(0.10)
    with pytest.raises(ValueError, match=r"\(M, 8\)"):
        uc.nearest_poses(np.array([1.0]), np.zeros((3, 7)))


def _fake_teddy_clone(root: Path, uc) -> Path:
    d = root / "work" / uc.TEDDY_DIR
    (d / "rgb").mkdir(parents=True)
    lines = ["# color images", "# timestamp filename"]
    for i in range(205):
        name = f"rgb/{100 + i * 0.033:.6f}.png"
        (d / name).write_bytes(f"image {i}".encode())
        lines.append(f"{100 + i * 0.033:.6f} {name}")
    (d / "rgb.txt").write_text("\n".join(lines) + "\n")
    gt = [f"{100 + i * 0.01 + 0.004:.4f} {i} 0 0 0 0 0 1" for i in range(800)]
    (d / "groundtruth.txt").write_text("# ground truth\n" + "\n".join(gt) + "\n")
    return root / "work"


def test_teddy_from_a_work_tree_and_from_a_bare_clone(uc, tmp_path):
    work = _fake_teddy_clone(tmp_path, uc)
    seq, gap = uc.build_teddy(work, tmp_path / "out1")
    assert sorted(p.name for p in (seq / "color").iterdir())[:2] == ["000000.png", "000001.png"]
    assert len(list((seq / "color").iterdir())) == 196
    assert (seq / "color" / "000000.png").read_bytes() == b"image 4"  # position 4 of rgb.txt
    assert gap <= 0.005 + 1e-9
    poses = np.loadtxt(seq / "poses.txt").reshape(-1, 3, 4)
    assert len(poses) == 196 and np.allclose(poses[:, :, :3], np.eye(3))
    assert (seq / "calib.txt").read_text().startswith("P0: 535.4 0 320.1")
    # the same from a bare clone (no work tree): read through git
    git = ["git", "-c", "user.email=t@t", "-c", "user.name=t"]
    subprocess.run(git + ["init", "-q", str(work)], check=True)
    subprocess.run(git + ["-C", str(work), "add", "-A"], check=True)
    subprocess.run(git + ["-C", str(work), "commit", "-q", "-m", "data"], check=True)
    subprocess.run(["git", "clone", "-q", "--bare", str(work), str(tmp_path / "bare")], check=True)
    seq2, _ = uc.build_teddy(tmp_path / "bare", tmp_path / "out2")
    assert (seq2 / "poses.txt").read_text() == (seq / "poses.txt").read_text()
    assert (seq2 / "color" / "000195.png").read_bytes() == b"image 199"


def test_a_missing_file_is_a_one_line_error_naming_the_clone(uc, tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    subprocess.run(["git", "init", "-q", "--bare", str(empty)], check=True)
    assert uc.main(["--teddy-repo", str(empty), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and str(empty) in err and "rgb.txt" in err and err.count("\n") == 1
