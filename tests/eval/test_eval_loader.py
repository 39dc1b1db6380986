"""Files to evo trajectories (trianflow_vo.eval.loader): the one ground-truth loader, run
folders and frames.txt. Association and its refusals are tested through evaluate_files
(test_eval_files.py) and the CLI (test_eval_cli.py)."""

from __future__ import annotations

import numpy as np
import pytest
from evo.core.trajectory import PosePath3D, PoseTrajectory3D
from scipy.spatial.transform import Rotation

from trianflow_vo.errors import InputError
from trianflow_vo.eval import load_ground_truth as exported_loader
from trianflow_vo.eval.loader import load_ground_truth, load_prediction
from trianflow_vo.io.trajectory import format_kitti_line, format_tum_line, read_frame_indices


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    T[:, :3, 3] = rng.normal(0, 50, (n, 3))
    return T


def test_load_ground_truth_gives_poses_and_frames_for_every_format(tmp_path):
    """The one ground-truth loader (eval and run --gt): ``.poses`` (N, 4, 4), ``.frames``
    (N,) int64 -- 0..N-1 for KITTI, the first column (sorted) for 13 columns, None for
    TUM, whose rows are identified by ``.timestamps`` -- and evo's type in ``.traj``."""
    assert exported_loader is load_ground_truth
    T = random_poses(6, seed=1)
    kitti = tmp_path / "gt.txt"
    kitti.write_text("".join(format_kitti_line(x) + "\n" for x in T))
    gt = load_ground_truth(kitti)
    assert gt.poses.shape == (6, 4, 4) and gt.poses.dtype == np.float64
    assert gt.frames.dtype == np.int64 and gt.frames.tolist() == list(range(6))
    assert type(gt.traj) is PosePath3D and gt.timestamps is None
    np.testing.assert_allclose(gt.poses, T, atol=1e-9)

    indexed = tmp_path / "gt13.txt"
    indexed.write_text("".join(f"{f} {format_kitti_line(x)}\n" for f, x in zip([40, 10, 30], T[:3])))
    gt = load_ground_truth(indexed)
    assert gt.frames.tolist() == [10, 30, 40]
    np.testing.assert_allclose(gt.poses, T[[1, 2, 0]], atol=1e-9)

    tum = tmp_path / "gt.tum"
    tum.write_text("".join(format_tum_line(t, x) + "\n" for t, x in zip([0.2, 0.1, 0.3], T[:3])))
    gt = load_ground_truth(tum)
    assert gt.frames is None and isinstance(gt.traj, PoseTrajectory3D)
    np.testing.assert_allclose(gt.timestamps, [0.1, 0.2, 0.3])
    np.testing.assert_allclose(gt.poses, T[[1, 0, 2]], atol=1e-8)

    bad = tmp_path / "bad.txt"
    bad.write_text(format_kitti_line(T[0]) + "\n1 2 3\n")
    with pytest.raises(InputError) as exc:
        load_ground_truth(bad)
    assert str(exc.value).startswith(f"{bad}:2: ")


def test_frames_file_and_run_folder(tmp_path):
    T = random_poses(4, seed=5)
    run = tmp_path / "run"
    run.mkdir()
    (run / "poses.txt").write_text("".join(format_kitti_line(x) + "\n" for x in T))
    (run / "frames.txt").write_text("0\n3\n6\n9\n")
    traj, desc = load_prediction(run)
    np.testing.assert_array_equal(traj.frames, [0, 3, 6, 9])
    assert "poses.txt" in desc and "frames.txt" in desc
    idx, lines = read_frame_indices(run / "frames.txt")
    np.testing.assert_array_equal(idx, [0, 3, 6, 9])


def test_frames_file_out_of_order_reorders_evo_path(tmp_path):
    """frames.txt need not be increasing: poses are sorted by frame, the evo path with them."""
    T = random_poses(3, seed=6)
    (tmp_path / "p.txt").write_text("".join(format_kitti_line(x) + "\n" for x in T))
    (tmp_path / "frames.txt").write_text("8\n2\n5\n")
    traj, _ = load_prediction(tmp_path / "p.txt")
    assert traj.frames.tolist() == [2, 5, 8] and traj.lines.tolist() == [2, 3, 1]
    np.testing.assert_allclose(traj.poses, T[[1, 2, 0]], atol=1e-9)
    np.testing.assert_array_equal(np.array(traj.traj.poses_se3), traj.poses)


def test_prediction_path_missing(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        load_prediction(tmp_path / "nope")
    (tmp_path / "empty_run").mkdir()
    with pytest.raises(InputError, match="not a run folder"):
        load_prediction(tmp_path / "empty_run")
