"""Eval maths on synthetic trajectories with closed-form answers, then noise vs evo."""

from __future__ import annotations

import numpy as np
import pytest

from trianflow_vo.errors import InputError
from trianflow_vo.eval import align_trajectory, evaluate, umeyama
from trianflow_vo.eval.align import apply_alignment, estimate_alignment
from trianflow_vo.eval.ate_rpe import ate_errors, rpe_errors
from trianflow_vo.eval.evaluate import evaluate_associated, suggest_lengths
from trianflow_vo.eval.segments import path_distances, rotation_angle, segment_errors


def rot(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def pose(R=None, t=(0, 0, 0)):
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    T[:3, 3] = t
    return T


def chain(steps):
    """``(N+1, 4, 4)`` camera-to-world poses from relative motions (first = identity)."""
    out = [np.eye(4)]
    for M in steps:
        out.append(out[-1] @ M)
    return np.array(out)


def straight(n, step=1.0):
    """Camera moving forward along z, ``step`` m per frame, ``n`` frames."""
    return chain([pose(t=(0, 0, step))] * (n - 1))


def wiggly(n, seed=0):
    """A curvy, non-planar drive: forward ~1 m/frame with varying yaw and pitch."""
    rng = np.random.default_rng(seed)
    steps = []
    for i in range(n - 1):
        R = rot([0, 1, 0], 0.05 * np.sin(i / 15)) @ rot([1, 0, 0], 0.01 * np.cos(i / 9))
        steps.append(pose(R, (0.05 * rng.normal(), 0.02 * rng.normal(), 1.0 + 0.1 * np.sin(i / 7))))
    return chain(steps)


def sim3(T, s, R, t):
    return apply_alignment(T, s, R, t)


# ----------------------------------------------------------------------------- alignment


def test_umeyama_recovers_known_similarity():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(50, 3)) * 5
    R = rot([1, 2, 3], 0.7)
    dst = 2.5 * src @ R.T + [1, -2, 3]
    (s, R_est, t), ok = umeyama(src, dst, True)
    assert ok
    assert s == pytest.approx(2.5, rel=1e-12)
    np.testing.assert_allclose(R_est, R, atol=1e-12)
    np.testing.assert_allclose(t, [1, -2, 3], atol=1e-10)


def test_estimate_alignment_modes_and_degenerate():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(20, 3))
    (s, R, t), ok = estimate_alignment(src, 3 * src, "scale")
    assert ok and s == pytest.approx(3.0) and np.allclose(R, np.eye(3)) and np.allclose(t, 0)
    (s, R, t), ok = estimate_alignment(src, 3 * src, "6dof")
    assert ok and s == 1.0
    (s, _, _), ok = estimate_alignment(src, 3 * src, "none")
    assert ok and s == 1.0
    same = np.ones((10, 3))
    for mode in ("7dof", "6dof", "scale"):
        assert not estimate_alignment(same, src[:10], mode)[1]
        assert not estimate_alignment(src[:10], same, mode)[1]
        assert not estimate_alignment(src[:2], src[:2], mode)[1]
    assert estimate_alignment(same, src[:10], "none")[1]


def test_align_trajectory_undoes_similarity_in_gt_frame():
    gt = wiggly(80)
    G0 = pose(rot([0, 0, 1], 0.3), (5, 1, -2))
    gt_world = G0 @ gt  # ground truth not starting at identity
    pred = sim3(gt, 0.37, rot([1, -1, 0.5], 1.1), [3, 4, 5])
    aligned = align_trajectory(pred, gt_world, "7dof")
    np.testing.assert_allclose(aligned, gt_world, atol=1e-9)
    with pytest.raises(InputError, match="--align none"):
        align_trajectory(np.tile(np.eye(4), (5, 1, 1)), gt_world[:5])


# ----------------------------------------------------------------------------- segment metric


def test_path_distances_and_rotation_angle():
    np.testing.assert_allclose(path_distances(np.array([[0, 0, 0], [3, 4, 0], [3, 4, 1.0]])), [0, 5, 6])
    assert rotation_angle(rot([1, 1, 0], 0.4)) == pytest.approx(0.4)
    assert rotation_angle(np.eye(3)) == 0.0


def test_pure_scale_gives_zero_error_after_7dof():
    gt = wiggly(400)
    pred = sim3(gt, 0.25, np.eye(3), np.zeros(3))  # monocular: everything 4x too small
    m = evaluate(pred, None, gt, None, align="7dof", lengths=[50, 100, 200])
    assert m["num_segments"] > 30
    # r_err uses the devkit's arccos of the trace, whose resolution near 0 is ~1e-8 rad
    assert m["t_err"] < 1e-9 and m["r_err"] < 1e-5 and m["ate_rmse"] < 1e-9
    assert m["rpe_trans"] < 1e-9 and m["rpe_rot"] < 1e-6
    assert m["scale"] == pytest.approx(4.0)
    # without scale correction the same prediction is 75 % wrong on every segment
    m6 = evaluate(pred, None, gt, None, align="6dof", lengths=[50, 100, 200])
    assert m6["t_err"] > 50


def test_constant_scale_drift_known_t_err():
    # gt: 1 m/frame straight; pred: 1.03 m/frame. Segment of length L ends at the first frame
    # more than L m further, i.e. L+1 frames later: error 0.03 (L+1) m, t_err = 3 (L+1)/L %.
    n, e = 200, 0.03
    gt = straight(n, 1.0)
    pred = straight(n, 1.0 + e)
    lengths = [10, 20, 50]
    m = evaluate(pred, None, gt, None, align="none", lengths=lengths)
    for row in m["per_length"]:
        L = row["length"]
        assert row["t_err"] == pytest.approx(100 * e * (L + 1) / L, rel=1e-9)
        assert row["r_err"] == 0
        # first frames 0, 10, ...; valid when first + L + 1 <= n - 1
        assert row["num_segments"] == len([a for a in range(0, n, 10) if a + L + 1 <= n - 1])
    counts = [r["num_segments"] for r in m["per_length"]]
    expected = sum(100 * e * (L + 1) / L * c for L, c in zip(lengths, counts)) / sum(counts)
    assert m["t_err"] == pytest.approx(expected, rel=1e-9)
    assert m["num_segments"] == sum(counts)
    # ATE: frame i is off by e*i
    assert m["ate_rmse"] == pytest.approx(e * np.sqrt(np.mean(np.arange(n) ** 2)), rel=1e-9)
    assert m["rpe_trans"] == pytest.approx(e, rel=1e-9)
    # and 7dof removes it completely
    assert evaluate(pred, None, gt, None, align="7dof", lengths=lengths)["t_err"] < 1e-9


def test_constant_yaw_drift_known_r_err():
    # pred turns by w rad per frame while gt goes straight: over L+1 frames the rotation error
    # is (L+1) w, r_err = (L+1) w / L rad/m.
    n, w = 120, 1e-3
    gt = straight(n)
    pred = chain([pose(rot([0, 1, 0], w), (0, 0, 1))] * (n - 1))
    m = evaluate(pred, None, gt, None, align="none", lengths=[10, 40])
    for row in m["per_length"]:
        L = row["length"]
        assert row["r_err"] == pytest.approx((L + 1) * w / L * 180 / np.pi * 100, rel=1e-9)
    assert m["rpe_rot"] == pytest.approx(np.degrees(w), rel=1e-9)


def test_segment_step_and_strict_end_frame():
    gt = straight(31)  # distances 0..30
    seg = segment_errors(gt, gt, lengths=[10], step=10)
    # firsts 0, 10, 20; end = first frame with distance > first + 10 -> 11, 21; 31 does not exist
    assert seg.first.tolist() == [0, 10] and seg.last.tolist() == [11, 21]
    seg = segment_errors(gt, gt, lengths=[10], step=5)
    assert seg.first.tolist() == [0, 5, 10, 15]


def test_missing_frames_are_dropped_by_index():
    gt = wiggly(300)
    keep = np.setdiff1d(np.arange(300), [5, 6, 7, 100, 250])
    pred = sim3(gt[keep], 2.0, rot([0, 1, 0], 0.5), [1, 2, 3])
    m = evaluate(pred, keep, gt, None, lengths=[20, 50])
    assert m["num_frames"] == keep.size
    assert m["t_err"] < 1e-9 and m["ate_rmse"] < 1e-9


def test_no_segment_is_reported_not_nan():
    gt = straight(30)
    m = evaluate(gt, None, gt, None)
    assert m["t_err"] is None and m["r_err"] is None and m["num_segments"] == 0
    assert "29.0 m" in m["note"] and "--lengths 2,4,6,8,10,12,14,16" in m["note"]
    assert all(r["t_err"] is None for r in m["per_length"])


def test_suggest_lengths():
    assert suggest_lengths(110) == [10, 20, 30, 40, 50, 60, 70, 80]
    assert suggest_lengths(60) == [5, 10, 15, 20, 25, 30, 35, 40]
    assert suggest_lengths(0) == []


def test_too_few_frames_and_degenerate():
    gt = straight(10)
    with pytest.raises(InputError, match="at least 3"):
        evaluate(gt[:2], [0, 1], gt, None)
    with pytest.raises(InputError, match="at least 3"):
        evaluate(gt[:5], [20, 21, 22, 23, 24], gt, None)
    with pytest.raises(InputError, match="degenerate|cannot estimate"):
        evaluate(np.tile(np.eye(4), (10, 1, 1)), None, gt, None)
    with pytest.raises(InputError, match="unknown alignment"):
        evaluate_associated(gt, gt, align="8dof")


# ----------------------------------------------------------------------------- vs evo


def _noisy(gt, seed):
    rng = np.random.default_rng(seed)
    steps = [np.linalg.inv(gt[i]) @ gt[i + 1] for i in range(len(gt) - 1)]
    noisy = []
    for M in steps:
        N = pose(rot(rng.normal(size=3), 0.004 * abs(rng.normal())), 0.03 * rng.normal(size=3))
        noisy.append(M @ N)
    return sim3(chain(noisy), 0.6, rot([1, 0, 1], 0.4), [2, 0, 1])


def test_alignment_ate_rpe_agree_with_evo():
    pytest.importorskip("evo")
    from evo.core import metrics
    from evo.core.trajectory import PosePath3D

    gt = wiggly(250, seed=4)
    pred = _noisy(gt, seed=5)
    result = evaluate_associated(pred, gt, align="7dof", lengths=[20, 50])
    m = result.metrics

    ref = PosePath3D(poses_se3=list(result.gt_rebased))
    est = PosePath3D(poses_se3=list(np.linalg.inv(pred[0]) @ pred))
    est.align(ref, correct_scale=True)
    np.testing.assert_allclose(np.array(est.poses_se3), result.pred_aligned, atol=1e-8)

    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    assert m["ate_rmse"] == pytest.approx(ape.get_statistic(metrics.StatisticsType.rmse), rel=1e-9)
    assert m["ate_mean"] == pytest.approx(ape.get_statistic(metrics.StatisticsType.mean), rel=1e-9)

    for relation, key, key_mean in [
        (metrics.PoseRelation.translation_part, "rpe_trans", "rpe_trans_mean"),
        (metrics.PoseRelation.rotation_angle_deg, "rpe_rot", "rpe_rot_mean"),
    ]:
        rpe = metrics.RPE(relation, delta=1, delta_unit=metrics.Unit.frames, all_pairs=False)
        rpe.process_data((ref, est))
        assert m[key] == pytest.approx(rpe.get_statistic(metrics.StatisticsType.rmse), rel=1e-7)
        assert m[key_mean] == pytest.approx(rpe.get_statistic(metrics.StatisticsType.mean), rel=1e-7)
    assert m["t_err"] > 0.1  # the noise is visible in the segment metric


def test_ate_rpe_shapes():
    gt = straight(5)
    assert ate_errors(gt, gt).shape == (5,)
    t, r = rpe_errors(gt, gt, delta=2)
    assert t.shape == (3,) and r.shape == (3,)
    t, r = rpe_errors(gt[:1], gt[:1])
    assert t.size == 0
