"""Trajectory evaluation (issue 3): the KITTI segment metric, ATE, RPE and alignment.

Synthetic trajectories whose errors are known in closed form come first, then the
file-level association cases (13 columns, strided run folders, TUM), then the
published KITTI numbers on ../shared (skipped without it) and a cross-check with evo.

Conventions used by the closed-form cases: ground truth moving along +z in 1 m steps,
so cumulative distances are exact integers. The KITTI devkit's end frame of a segment
of length L starting at frame a is the first frame *more than* L further along the
path, i.e. ``a + L + 1`` with 1 m steps: a segment covers ``L + 1`` metres of ground
truth while its error is divided by the nominal ``L``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from trianflow_vo.errors import InputError
from trianflow_vo.eval import align_trajectory, evaluate, evaluate_associated, evaluate_files
from trianflow_vo.io.trajectory import format_kitti_line, format_tum_line

DEG100 = 180.0 / math.pi * 100.0  # rad/m -> deg/100 m
# Rotation angles come from acos((trace - 1) / 2), as in the KITTI devkit: ~1.5e-8 rad of
# float noise near zero, i.e. up to ~1e-5 deg/100 m over a 10 m segment, ~1e-6 deg per frame.
R_ERR_ZERO = 1e-4  # deg/100 m
ROT_ZERO = 1e-5  # deg


# --------------------------------------------------------------------------- builders


def pose(R=None, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    T[:3, 3] = t
    return T


def chain(steps: list[np.ndarray]) -> np.ndarray:
    """``(N + 1, 4, 4)`` camera-to-world poses, starting at identity, composing ``steps``."""
    out = [np.eye(4)]
    for S in steps:
        out.append(out[-1] @ S)
    return np.stack(out)


def straight(n: int, step: float = 1.0) -> np.ndarray:
    """``(n, 4, 4)``: identity rotations, positions ``(0, 0, step * i)``."""
    return chain([pose(t=(0.0, 0.0, step))] * (n - 1))


def winding(n: int, seed: int = 0) -> np.ndarray:
    """``(n, 4, 4)`` a smooth 3-D drive: ~1 m forward per frame, turning about all axes."""
    rng = np.random.default_rng(seed)
    steps = []
    for _ in range(n - 1):
        R = Rotation.from_rotvec(rng.normal(0.0, [0.01, 0.04, 0.01])).as_matrix()
        steps.append(pose(R, (rng.normal(0, 0.05), rng.normal(0, 0.02), 1.0 + rng.normal(0, 0.1))))
    return chain(steps)


def scaled(T: np.ndarray, s: float) -> np.ndarray:
    out = T.copy()
    out[:, :3, 3] *= s
    return out


RIGID = pose(Rotation.from_rotvec([0.3, -1.2, 0.7]).as_matrix(), (12.0, -3.0, 40.0))


# --------------------------------------------------------------------------- alignment


def test_pure_scale_is_zero_after_7dof_but_not_after_6dof_or_none():
    """pred = A @ (gt with positions x 0.37), A rigid: the Sim(3) alignment undoes it
    exactly, so every error vanishes; without scale (6dof, none) the motion is 0.37 times
    too short and the segment error is large (about 63 % of the travelled distance)."""
    gt = winding(150)
    pred = RIGID @ scaled(gt, 0.37)
    lengths = (10, 20, 40)
    m7 = evaluate(pred, None, gt, align="7dof", lengths=lengths)
    assert m7["num_segments"] > 20
    assert m7["t_err"] == pytest.approx(0.0, abs=1e-9)
    assert m7["r_err"] == pytest.approx(0.0, abs=R_ERR_ZERO)
    assert m7["ate_rmse"] == pytest.approx(0.0, abs=1e-9)
    assert m7["rpe_trans"] == pytest.approx(0.0, abs=1e-9)
    assert m7["rpe_rot"] == pytest.approx(0.0, abs=ROT_ZERO)
    assert m7["scale"] == pytest.approx(1 / 0.37, rel=1e-9)
    for mode in ("6dof", "none"):
        m = evaluate(pred, None, gt, align=mode, lengths=lengths)
        assert m["t_err"] > 40.0, mode
        assert m["ate_rmse"] > 1.0, mode
    # "scale" alone also undoes a pure scale (the rigid part is removed by re-basing)
    assert evaluate(pred, None, gt, align="scale", lengths=lengths)["t_err"] == pytest.approx(0.0, abs=1e-9)


def test_pure_scale_with_none_alignment_on_straight_path():
    """Straight gt, pred 2x longer steps, no alignment: a segment from a to a + L + 1
    has ground-truth motion L + 1 and predicted motion 2 (L + 1), error L + 1, so
    t_err = (L + 1) / L (in %: 100 (L + 1) / L)."""
    gt = straight(121)
    m = evaluate(scaled(gt, 2.0), None, gt, align="none", lengths=(10, 50))
    per = {r["length"]: r for r in m["per_length"]}
    assert per[10.0]["t_err"] == pytest.approx(110.0, rel=1e-12)
    assert per[50.0]["t_err"] == pytest.approx(102.0, rel=1e-12)
    assert m["scale"] == 1.0


def test_rigid_transform_of_whole_trajectory():
    """pred = A @ gt: re-basing to the first frame removes A, and the 6dof alignment then
    has nothing left to do (identity); errors are zero for 6dof, 7dof and none."""
    gt = winding(120, seed=1)
    pred = RIGID @ gt
    for mode in ("6dof", "7dof", "none"):
        m = evaluate(pred, None, gt, align=mode, lengths=(10, 30))
        assert m["t_err"] == pytest.approx(0.0, abs=1e-9), mode
        assert m["r_err"] == pytest.approx(0.0, abs=R_ERR_ZERO), mode
        assert m["ate_rmse"] == pytest.approx(0.0, abs=1e-9), mode


def test_6dof_removes_a_rotation_of_the_positions_only_7dof_the_scale():
    """Rotate the re-based positions by B (orientations untouched) and scale them by 3:
    the 6dof alignment recovers B (ATE of the unscaled case is zero), 7dof recovers B and 3."""
    gt = winding(100, seed=2)
    B = Rotation.from_rotvec([0.0, 0.5, 0.1]).as_matrix()
    pred = gt.copy()
    pred[:, :3, 3] = gt[:, :3, 3] @ B.T
    m6 = evaluate(pred, None, gt, align="6dof", lengths=(10,))
    assert m6["ate_rmse"] == pytest.approx(0.0, abs=1e-9)
    assert m6["scale"] == 1.0
    assert evaluate(pred, None, gt, align="none", lengths=(10,))["ate_rmse"] > 1.0
    m7 = evaluate(scaled(pred, 3.0), None, gt, align="7dof", lengths=(10,))
    assert m7["ate_rmse"] == pytest.approx(0.0, abs=1e-9)
    assert m7["scale"] == pytest.approx(1 / 3.0, rel=1e-9)
    assert evaluate(scaled(pred, 3.0), None, gt, align="6dof", lengths=(10,))["ate_rmse"] > 1.0


def test_align_trajectory_maps_prediction_onto_ground_truth_world():
    """For drawing: a scaled, rigidly moved copy of gt comes back onto gt itself."""
    gt = RIGID @ winding(60, seed=3)  # gt not starting at identity
    pred = pose(Rotation.from_rotvec([1.0, 0.2, 0.0]).as_matrix(), (5, 5, 5)) @ scaled(gt, 0.2)
    np.testing.assert_allclose(align_trajectory(pred, gt, "7dof"), gt, atol=1e-8)
    with pytest.raises(InputError, match="7dof"):
        align_trajectory(np.tile(np.eye(4), (10, 1, 1)), gt[:10], "7dof")


def test_umeyama_never_returns_a_reflection_and_matches_evo():
    """dst = a mirror image of src: the best proper rotation needs the det correction
    (S = diag(1, 1, -1)), which also enters the scale; evo's Umeyama is the reference."""
    from evo.core.geometry import umeyama_alignment

    from trianflow_vo.eval.align import umeyama

    rng = np.random.default_rng(5)
    src = rng.normal(0, 1, (40, 3)) * [5.0, 2.0, 0.5]
    dst = 1.7 * src * [1.0, 1.0, -1.0] + [3.0, 0.0, -2.0] + rng.normal(0, 0.05, (40, 3))
    (s, R, t), valid = umeyama(src, dst)
    assert valid
    assert np.linalg.det(R) == pytest.approx(1.0)
    R_evo, t_evo, s_evo = umeyama_alignment(src.T, dst.T, with_scale=True)
    np.testing.assert_allclose(R, R_evo, atol=1e-9)
    np.testing.assert_allclose(t, t_evo, atol=1e-9)
    assert s == pytest.approx(s_evo, rel=1e-9)
    assert s < 1.7  # a mirror cannot be matched fully: the scale shrinks


# --------------------------------------------------------------------------- known drift


def test_constant_length_drift_gives_known_t_err_per_length():
    """Straight 400 m gt (401 frames), pred steps 1.01 m, no alignment.

    Segment (a, L) ends at b = a + L + 1: error |1.01 - 1| (L + 1), so t_err(L) =
    1 % x (L + 1) / L: 1.01 % at 100 m, 1.005 % at 200 m, 1.00333 % at 300 m.
    First frames 0, 10, ..., and b <= 400 gives a <= 399 - L: 30, 20, 10 segments.
    Overall t_err is the mean over the 60 segments; r_err is 0."""
    gt = straight(401)
    pred = straight(401, 1.01)
    lengths = (100, 200, 300, 400)
    m = evaluate(pred, None, gt, align="none", lengths=lengths)
    per = {r["length"]: r for r in m["per_length"]}
    counts = {100: 30, 200: 20, 300: 10}
    for L, c in counts.items():
        assert per[float(L)]["num_segments"] == c
        assert per[float(L)]["t_err"] == pytest.approx((L + 1) / L, rel=1e-9)
        assert per[float(L)]["r_err"] == pytest.approx(0.0, abs=1e-12)
    # 400 m: the end frame (401) does not exist -> no segment, None (not NaN)
    assert per[400.0]["num_segments"] == 0
    assert per[400.0]["t_err"] is None and per[400.0]["r_err"] is None
    expected = sum(c * (L + 1) / L for L, c in counts.items()) / 60
    assert m["num_segments"] == 60
    assert m["t_err"] == pytest.approx(expected, rel=1e-9)
    assert m["r_err"] == pytest.approx(0.0, abs=1e-12)
    assert m["path_length"] == pytest.approx(400.0)
    # the same drift is pure scale: 7dof removes it
    assert evaluate(pred, None, gt, align="7dof", lengths=lengths)["t_err"] == pytest.approx(0.0, abs=1e-9)


def test_constant_yaw_drift_gives_known_r_err():
    """pred turns by delta = 1e-3 rad about y every frame while gt goes straight; the
    segment (a, L) spans L + 1 frames, so its rotation error is (L + 1) delta and
    r_err(L) = (L + 1) delta / L rad/m = that x (180/pi) x 100 deg/100 m."""
    delta = 1e-3
    gt = straight(251)
    step = pose(Rotation.from_rotvec([0.0, delta, 0.0]).as_matrix(), (0.0, 0.0, 1.0))
    pred = chain([step] * 250)
    m = evaluate(pred, None, gt, align="none", lengths=(50, 100))
    per = {r["length"]: r for r in m["per_length"]}
    for L in (50, 100):
        assert per[float(L)]["r_err"] == pytest.approx((L + 1) * delta / L * DEG100, rel=1e-7)
    # RPE between consecutive frames: exactly delta in rotation
    assert m["rpe_rot"] == pytest.approx(math.degrees(delta), rel=1e-7)
    assert m["t_err"] > 0.0


def test_ate_and_rpe_of_one_displaced_frame():
    """pred = gt except frame k, displaced by d (|d| = 0.5 m), no alignment.

    ATE: one frame off by 0.5 -> rmse 0.5 / sqrt(N), mean 0.5 / N, max 0.5.
    RPE: the pairs (k-1, k) and (k, k+1) each have translation error |d| (d is rotated,
    not shortened), the others 0 -> rmse sqrt(2 x 0.25 / (N - 1)); rotation error 0."""
    n, k = 50, 17
    gt = winding(n, seed=4)
    pred = gt.copy()
    d = np.array([0.3, 0.0, 0.4])
    pred[k, :3, 3] += d
    m = evaluate(pred, None, gt, align="none", lengths=(10,))
    assert m["ate_rmse"] == pytest.approx(0.5 / math.sqrt(n), rel=1e-9)
    assert m["ate_mean"] == pytest.approx(0.5 / n, rel=1e-9)
    assert m["ate_max"] == pytest.approx(0.5, rel=1e-9)
    assert m["rpe_trans"] == pytest.approx(math.sqrt(2 * 0.25 / (n - 1)), rel=1e-9)
    assert m["rpe_trans_mean"] == pytest.approx(2 * 0.5 / (n - 1), rel=1e-9)
    assert m["rpe_rot"] == pytest.approx(0.0, abs=ROT_ZERO)
    assert m["num_frames"] == n


# --------------------------------------------------------------------------- protocol details


def test_frames_matched_by_index_and_rebased_to_first_common_frame():
    """Prediction frames 5..59 of a 60-frame gt (and an extra frame 80 the gt lacks): only
    the 55 common frames count, re-based at frame 5; a scaled copy gives zero error."""
    gt = winding(60, seed=5)
    frames = np.r_[np.arange(5, 60), 80]
    pred = scaled(RIGID @ np.concatenate([gt[5:], gt[:1]]), 4.0)
    m = evaluate(pred, frames, gt, align="7dof", lengths=(10, 20))
    assert m["num_frames"] == 55
    assert m["t_err"] == pytest.approx(0.0, abs=1e-9)
    assert m["ate_rmse"] == pytest.approx(0.0, abs=1e-9)


def test_short_sequence_has_no_segment_and_suggests_lengths():
    """A 50 m sequence with the default 100..800 m lengths: no segment, t_err/r_err None,
    a note suggesting --lengths that fit (5..40 m: eight 1-2-5 steps below 50/8 m)."""
    gt = straight(51)
    pred = straight(51, 1.02)
    m = evaluate(pred, None, gt, align="none")
    assert m["num_segments"] == 0
    assert m["t_err"] is None and m["r_err"] is None
    assert all(r["t_err"] is None for r in m["per_length"])
    assert "50.0 m" in m["note"] and "--lengths 5,10,15,20,25,30,35,40" in m["note"]
    assert m["ate_rmse"] > 0 and math.isfinite(m["ate_rmse"])
    m2 = evaluate(pred, None, gt, align="none", lengths=[5, 10, 15, 20, 25, 30, 35, 40])
    assert m2["num_segments"] == 5 + 4 + 4 + 3 + 3 + 2 + 2 + 1  # first frames 0, 10, .., end a + L + 1 <= 50
    for row in m2["per_length"]:
        assert row["t_err"] == pytest.approx(2.0 * (row["length"] + 1) / row["length"], rel=1e-9)


def test_too_few_common_frames_and_degenerate_alignment_raise():
    gt = winding(30, seed=6)
    with pytest.raises(InputError, match="only 2 frame"):
        evaluate(gt[:2], np.array([3, 4]), gt)
    with pytest.raises(InputError, match="only 0 frame"):
        evaluate(gt[:5], np.arange(100, 105), gt)
    still = np.tile(pose(t=(1.0, 2.0, 3.0)), (30, 1, 1))
    for mode in ("7dof", "6dof", "scale"):
        with pytest.raises(InputError, match="all predicted"):
            evaluate(still, None, gt, align=mode)
        with pytest.raises(InputError, match="cannot estimate"):
            evaluate(gt, None, still, align=mode)
    # without alignment there is nothing to estimate: a standing camera is evaluated
    m = evaluate(still, None, gt, align="none", lengths=(5,))
    assert m["ate_rmse"] > 1.0


def test_evaluate_associated_rejects_bad_lengths_and_mode():
    gt = winding(20)
    with pytest.raises(InputError, match="lengths"):
        evaluate_associated(gt, gt, "7dof", lengths=[10, -5])
    with pytest.raises(InputError, match="alignment"):
        evaluate_associated(gt, gt, "sim3")


# --------------------------------------------------------------------------- files


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


def test_13_column_prediction_with_missing_frames(tmp_path):
    """13 columns, frames in shuffled order with 40 of 120 missing: only the 80 present
    frames are compared (a scaled copy is exact); with noise, the file gives the same
    numbers as the arrays of those frames."""
    gt = winding(120, seed=7)
    gt_file = write_kitti(tmp_path / "gt.txt", gt)
    rng = np.random.default_rng(0)
    keep = np.sort(rng.choice(120, 80, replace=False))
    order = rng.permutation(keep)
    pred = scaled(RIGID @ gt, 0.5)
    f = write_kitti(tmp_path / "pred13.txt", pred[order], frames=order)
    r = evaluate_files(f, gt_file, lengths=(10, 20))
    assert r.metrics["num_frames"] == 80
    assert r.metrics["matched_by"] == "frame index"
    assert r.metrics["t_err"] == pytest.approx(0.0, abs=1e-7)  # file precision: 10 digits
    assert r.metrics["ate_rmse"] == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_array_equal(r.frames, keep)

    noisy = pred.copy()
    noisy[:, :3, 3] += rng.normal(0, 0.05, (120, 3))
    noisy[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.01, (120, 3))).as_matrix() @ noisy[:, :3, :3]
    f2 = write_kitti(tmp_path / "pred13n.txt", noisy[order], frames=order)
    r2 = evaluate_files(f2, gt_file, lengths=(10, 20))
    ref = evaluate(noisy[keep], keep, gt, lengths=(10, 20))
    for key in ("t_err", "r_err", "ate_rmse", "rpe_trans", "rpe_rot"):
        assert r2.metrics[key] == pytest.approx(ref[key], rel=1e-6), key
        assert r2.metrics[key] > 0


def test_strided_run_folder_with_frames_txt(tmp_path):
    """A `run --stride 3` folder: poses.txt holds frames 0, 3, ..., 300 of a straight
    300 m gt, with 1 % too long motion. The segment metric works on the 101 kept frames
    (3 m apart): L = 30 ends 11 kept frames later (33 m), L = 60 21 later (63 m), so
    t_err = 1 % x 33/30 = 1.1 % and 1 % x 63/60 = 1.05 % with 9 and 8 segments
    (first kept frames 0, 10, ... with end <= 100)."""
    gt = straight(301)
    gt_file = write_kitti(tmp_path / "gt.txt", gt)
    run = tmp_path / "run"
    run.mkdir()
    kept = np.arange(0, 301, 3)
    write_kitti(run / "poses.txt", straight(301, 1.01)[kept])
    (run / "frames.txt").write_text("".join(f"{i}\n" for i in kept))
    r = evaluate_files(run, gt_file, align="none", lengths=(30, 60))
    m = r.metrics
    assert m["num_frames"] == 101 and m["num_pred_frames"] == 101 and m["num_gt_frames"] == 301
    assert "frames.txt" in m["pred"]
    per = {row["length"]: row for row in m["per_length"]}
    assert per[30.0]["num_segments"] == 9 and per[60.0]["num_segments"] == 8
    assert per[30.0]["t_err"] == pytest.approx(1.1, rel=1e-6)
    assert per[60.0]["t_err"] == pytest.approx(1.05, rel=1e-6)
    # 7dof removes the drift
    assert evaluate_files(run, gt_file, lengths=(30, 60)).metrics["t_err"] == pytest.approx(0.0, abs=1e-6)


def test_strided_prediction_without_frames_txt_is_refused(tmp_path):
    gt_file = write_kitti(tmp_path / "gt.txt", straight(30))
    pred = write_kitti(tmp_path / "pred.txt", straight(30)[::3])
    with pytest.raises(InputError, match="frames.txt") as exc:
        evaluate_files(pred, gt_file)
    assert "10 poses" in str(exc.value) and "30" in str(exc.value)
    assert str(exc.value).startswith(str(pred))


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
    assert m["t_err"] == pytest.approx(0.0, abs=1e-6)

    sub = tmp_path / "withframes"
    sub.mkdir()
    f2 = write_tum(sub / "traj.tum", 1000.0 + 0.1 * kept, pred)
    with pytest.raises(InputError, match="frames.txt"):
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
    assert m["scale"] == pytest.approx(1 / 3.0, rel=1e-6)


# --------------------------------------------------------------------------- real data


@pytest.mark.parametrize(
    "seq, t_err, r_err",
    [("09", 2.527535077, 0.287707222), ("10", 2.221192217, 0.369334674)],
)
def test_published_kitti_numbers(shared_data, seq, t_err, r_err):
    """dfvo_example_1 on KITTI 09/10: the numbers the community's devkit protocol gives."""
    root = shared_data / "kitti-odometry-eval"
    r = evaluate_files(root / "pred" / "dfvo_example_1" / f"{seq}.txt", root / "gt_poses" / f"{seq}.txt")
    m = r.metrics
    assert m["t_err"] == pytest.approx(t_err, rel=1e-6)
    assert m["r_err"] == pytest.approx(r_err, rel=1e-6)
    assert m["align"] == "7dof" and m["matched_by"] == "line number"
    assert m["num_segments"] > 400
    # ATE after Sim(3) alignment of a published method: metres, not millimetres or km
    assert 0.5 < m["ate_rmse"] < 50.0


# --------------------------------------------------------------------------- evo


def test_ate_and_rpe_agree_with_evo():
    """A noisy, scaled, rigidly moved prediction: our ATE RMSE (7dof) equals evo's APE
    (translation part) after its Sim(3) Umeyama alignment, and our RPE (1 frame) equals
    evo's RPE on the aligned trajectory (translation and rotation angle, RMSE)."""
    from evo.core import lie_algebra, metrics, trajectory

    gt = winding(200, seed=11)
    rng = np.random.default_rng(2)
    steps = []
    for i in range(199):
        rel = np.linalg.inv(gt[i]) @ gt[i + 1]
        noise = pose(Rotation.from_rotvec(rng.normal(0, 0.003, 3)).as_matrix(), rng.normal(0, 0.03, 3))
        steps.append(rel @ noise)
    pred = RIGID @ scaled(chain(steps), 0.6)
    ours = evaluate(pred, None, gt, align="7dof", lengths=(20,))

    ref = trajectory.PosePath3D(poses_se3=list(gt))
    est = trajectory.PosePath3D(poses_se3=[lie_algebra.se3(T[:3, :3], T[:3, 3]) for T in pred])
    est.align(ref, correct_scale=True)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    assert ours["ate_rmse"] == pytest.approx(ape.get_statistic(metrics.StatisticsType.rmse), rel=1e-6)
    assert ours["ate_rmse"] > 0.1

    for relation, key in (
        (metrics.PoseRelation.translation_part, "rpe_trans"),
        (metrics.PoseRelation.rotation_angle_deg, "rpe_rot"),
    ):
        rpe = metrics.RPE(relation, delta=1, delta_unit=metrics.Unit.frames, all_pairs=False)
        rpe.process_data((ref, est))
        assert ours[key] == pytest.approx(rpe.get_statistic(metrics.StatisticsType.rmse), rel=1e-6), key
        assert ours[key] > 0
