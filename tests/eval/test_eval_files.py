"""Eval on files (trianflow_vo.eval.evaluate_files): association by frame index (13
columns, frames.txt) and by timestamp (TUM), then the published KITTI numbers on
../shared (skipped without it). Refusals and the printed report: test_eval_cli.py."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from trianflow_vo.errors import InputError
from trianflow_vo.eval import evaluate, evaluate_files, match_timestamps
from trianflow_vo.eval.report import format_report
from trianflow_vo.io.trajectory import format_kitti_line, format_tum_line

# KITTI segment metric of kitti-odometry-eval/pred/dfvo_example_1 (see ../shared/README.md)
PUBLISHED = {"09": (2.527535077, 0.287707222), "10": (2.221192217, 0.369334674)}


def pose(R=None, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    T[:3, 3] = t
    return T


def winding(n: int, seed: int = 0) -> np.ndarray:
    """``(n, 4, 4)`` a smooth 3-D drive: ~1 m forward per frame, turning about all axes."""
    rng = np.random.default_rng(seed)
    out = [np.eye(4)]
    for _ in range(n - 1):
        R = Rotation.from_rotvec(rng.normal(0.0, [0.01, 0.04, 0.01])).as_matrix()
        out.append(out[-1] @ pose(R, (rng.normal(0, 0.05), rng.normal(0, 0.02), 1.0 + rng.normal(0, 0.1))))
    return np.stack(out)


def straight(frames, step=1.0) -> np.ndarray:
    """Poses at the given frame indices of a camera moving ``step`` m/frame along z."""
    T = np.tile(np.eye(4), (len(frames), 1, 1))
    T[:, 2, 3] = step * np.asarray(frames, float)
    return T


def scaled(T: np.ndarray, s: float) -> np.ndarray:
    out = T.copy()
    out[:, :3, 3] *= s
    return out


RIGID = pose(Rotation.from_rotvec([0.3, -1.2, 0.7]).as_matrix(), (12.0, -3.0, 40.0))


def write_kitti(path, poses, frames=None):
    with open(path, "w") as fh:
        for i, T in enumerate(poses):
            prefix = "" if frames is None else f"{int(frames[i])} "
            fh.write(prefix + format_kitti_line(T) + "\n")
    return path


def write_tum(path, times, poses):
    with open(path, "w") as fh:
        fh.write("# timestamp tx ty tz qx qy qz qw\n")
        for t, T in zip(times, poses):
            fh.write(format_tum_line(t, T) + "\n")
    return path


# --------------------------------------------------------------------------- frame index


@pytest.mark.parametrize("case", ["winding-shuffled", "straight-every-7th-missing"])
def test_13_column_prediction_with_missing_frames(tmp_path, case):
    """13 columns with frames missing: only the present frames are compared and a
    half-scale (rigidly moved) copy is exact after 7dof (scale 2). Shuffled lines of a
    winding drive (file precision: 10 digits), or a straight drive without every 7th
    frame (exact zeros in the file); with noise, the file gives the numbers of the arrays."""
    if case == "winding-shuffled":
        n = 120
        gt = winding(n, seed=7)
        rng = np.random.default_rng(0)
        keep = np.sort(rng.choice(n, 80, replace=False))
        order = rng.permutation(keep)
        pred = scaled(RIGID @ gt, 0.5)
        tol_t, tol_ate = 1e-7, 1e-6
    else:
        n = 100
        gt = straight(range(n))
        keep = np.array([f for f in range(n) if f % 7 != 3])
        order = keep
        pred = straight(range(n), 0.5)
        tol_t, tol_ate = 1e-9, 1e-9
    gt_file = write_kitti(tmp_path / "gt.txt", gt)
    f = write_kitti(tmp_path / "pred13.txt", pred[order], frames=order)
    r = evaluate_files(f, gt_file, lengths=(10, 20))
    m = r.metrics
    assert m["num_frames"] == keep.size and m["num_pred_frames"] == keep.size and m["num_gt_frames"] == n
    assert m["matched_by"] == "frame index"
    assert m["t_err"] == pytest.approx(0.0, abs=tol_t)
    assert m["ate_rmse"] == pytest.approx(0.0, abs=tol_ate)
    assert m["scale"] == pytest.approx(2.0)
    np.testing.assert_array_equal(r.frames, keep)

    if case == "winding-shuffled":
        noisy = pred.copy()
        noisy[:, :3, 3] += rng.normal(0, 0.05, (n, 3))
        noisy[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.01, (n, 3))).as_matrix() @ noisy[:, :3, :3]
        f2 = write_kitti(tmp_path / "pred13n.txt", noisy[order], frames=order)
        r2 = evaluate_files(f2, gt_file, lengths=(10, 20))
        ref = evaluate(noisy[keep], keep, gt, lengths=(10, 20))
        for key in ("t_err", "r_err", "ate_rmse", "rpe_trans", "rpe_rot"):
            assert r2.metrics[key] == pytest.approx(ref[key], rel=1e-6), key
            assert r2.metrics[key] > 0


# --------------------------------------------------------------------------- timestamps


def test_tum_prediction_against_tum_ground_truth_by_timestamp(tmp_path):
    """TUM gt at 10 Hz (absolute Unix-like times); prediction every other gt frame with up
    to 4 ms of clock jitter and 3 extra poses after the gt ends: 50 pairs, matched by
    time, and a scaled copy is exact."""
    gt = winding(100, seed=8)
    t0 = 1305031102.0
    tg = t0 + 0.1 * np.arange(100)
    gt_file = write_tum(tmp_path / "gt.tum", tg, gt)
    idx = np.arange(0, 100, 2)
    rng = np.random.default_rng(1)
    tp = np.r_[tg[idx] + rng.uniform(-0.004, 0.004, idx.size), tg[-1] + [1.0, 1.1, 1.2]]
    pred = scaled(RIGID @ np.concatenate([gt[idx], gt[:3]]), 2.5)
    pred_file = write_tum(tmp_path / "pred.tum", tp, pred)
    m = evaluate_files(pred_file, gt_file, lengths=(10, 20)).metrics
    assert m["matched_by"] == "timestamp"
    assert m["num_frames"] == 50
    assert m["t_err"] == pytest.approx(0.0, abs=1e-6)
    assert m["ate_rmse"] == pytest.approx(0.0, abs=1e-6)
    # a clock offset beyond --max-time-diff leaves nothing in common
    late = write_tum(tmp_path / "late.tum", tp + 0.05, pred)
    with pytest.raises(InputError, match="only 0 frame"):
        evaluate_files(late, gt_file)


def test_timestamp_association_uses_each_ground_truth_pose_once():
    """Two predictions 4 ms and 6 ms around each ground-truth time: evo's nearest-neighbour
    search proposes the same ground-truth pose for both; the closer one wins, so the pairs
    are one-to-one (here the +4 ms ones). A prediction exactly half-way is given to the
    earlier time; beyond max_diff nothing is matched."""
    tg = 100.0 + 0.1 * np.arange(10)
    tp = np.sort(np.r_[tg + 0.004, tg - 0.006])
    pi, gi = match_timestamps(tp, tg, 0.02)
    assert gi.tolist() == list(range(10))
    np.testing.assert_allclose(tp[pi] - tg[gi], 0.004, atol=1e-9)
    tb = 100.0 + 0.125 * np.arange(4)  # binary fractions: the half-way time is exact
    pi, gi = match_timestamps(np.array([100.0625, 105.0]), tb, 0.07)
    assert pi.tolist() == [0] and gi.tolist() == [0]
    assert match_timestamps(tg + 0.03, tg, 0.02)[0].size == 0


def test_tum_prediction_against_kitti_ground_truth_by_frame_index(tmp_path):
    """A run's trajectory.tum carries the frame index as timestamp when the source has no
    times: matched to KITTI gt by frame index. Real timestamps need a frames.txt."""
    gt = winding(60, seed=9)
    gt_file = write_kitti(tmp_path / "gt.txt", gt)
    kept = np.arange(0, 60, 2)
    pred = scaled(gt[kept], 0.1)
    f = write_tum(tmp_path / "traj.tum", kept.astype(float), pred)
    m = evaluate_files(f, gt_file, lengths=(10,)).metrics
    assert m["matched_by"] == "frame index" and m["num_frames"] == 30
    assert "30 common" in format_report(m)
    assert m["t_err"] == pytest.approx(0.0, abs=1e-6)

    sub = tmp_path / "withframes"
    sub.mkdir()
    f2 = write_tum(sub / "traj.tum", 1000.0 + 0.1 * kept, pred)
    with pytest.raises(InputError, match="TUM timestamps cannot be matched.*frames.txt"):
        evaluate_files(f2, gt_file)
    (sub / "frames.txt").write_text("".join(f"{i}\n" for i in kept))
    m2 = evaluate_files(f2, gt_file, lengths=(10,)).metrics
    assert m2["num_frames"] == 30
    assert m2["t_err"] == pytest.approx(0.0, abs=1e-6)


def test_tum_lines_out_of_time_order_keep_their_frames_txt_index(tmp_path):
    """frames.txt follows the lines of the file; the reader sorts TUM rows by time, so the
    indices must be re-attached to the right rows (here lines in reverse time order)."""
    gt = winding(40, seed=12)
    gt_file = write_kitti(tmp_path / "gt.txt", gt)
    kept = np.arange(0, 40, 2)[::-1]  # file order: newest first
    write_tum(tmp_path / "traj.tum", 50.0 + 0.1 * kept, scaled(gt[kept], 2.0))
    (tmp_path / "frames.txt").write_text("".join(f"{i}\n" for i in kept))
    m = evaluate_files(tmp_path / "traj.tum", gt_file, lengths=(5,)).metrics
    assert m["num_frames"] == 20
    assert m["ate_rmse"] == pytest.approx(0.0, abs=1e-6)


def test_run_folder_prefers_tum_for_tum_ground_truth(tmp_path):
    gt = winding(40, seed=10)
    tg = 100.0 + 0.05 * np.arange(40)
    gt_file = write_tum(tmp_path / "gt.tum", tg, gt)
    run = tmp_path / "run"
    run.mkdir()
    write_kitti(run / "poses.txt", gt)
    (run / "frames.txt").write_text("".join(f"{i}\n" for i in range(40)))
    write_tum(run / "trajectory.tum", tg, scaled(gt, 3.0))
    m = evaluate_files(run, gt_file, lengths=(5,)).metrics
    assert m["matched_by"] == "timestamp" and m["num_frames"] == 40
    assert "trajectory.tum" in m["pred"]
    report = format_report(m)
    assert "trajectory.tum" in report and "matched by timestamp" in report
    assert m["scale"] == pytest.approx(1 / 3.0, rel=1e-6)


# --------------------------------------------------------------------------- real data


@pytest.mark.parametrize("seq", sorted(PUBLISHED))
def test_published_kitti_numbers(shared_data, seq):
    """dfvo_example_1 on KITTI 09/10: the numbers the community's devkit protocol gives."""
    root = shared_data / "kitti-odometry-eval"
    m = evaluate_files(root / "pred" / "dfvo_example_1" / f"{seq}.txt", root / "gt_poses" / f"{seq}.txt").metrics
    t_ref, r_ref = PUBLISHED[seq]
    assert m["t_err"] == pytest.approx(t_ref, rel=1e-6)
    assert m["r_err"] == pytest.approx(r_ref, rel=1e-6)
    # and to all the 9 decimals published
    assert round(m["t_err"], 9) == t_ref and round(m["r_err"], 9) == r_ref
    assert m["align"] == "7dof" and m["matched_by"] == "line number"
    assert m["num_frames"] == m["num_gt_frames"]
    assert m["num_segments"] > 400
    assert sum(r["num_segments"] for r in m["per_length"]) == m["num_segments"]
    # ATE after Sim(3) alignment of a published method: metres, not millimetres or km
    assert 0.5 < m["ate_rmse"] < 50.0
