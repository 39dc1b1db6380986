"""Eval maths on arrays: alignment, the KITTI segment metric, ATE, RPE.

Synthetic trajectories whose errors are known in closed form come first (these are
independent of evo, which now does the alignment and ATE), then cross-checks against
evo where our code is not evo (the re-basing + alignment pipeline, RPE), and the reasons
some pieces are not evo's.

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
from trianflow_vo.eval import align_trajectory, evaluate, evaluate_associated, umeyama
from trianflow_vo.eval.align import apply_alignment, estimate_alignment
from trianflow_vo.eval.ate_rpe import ate_errors, rpe_errors
from trianflow_vo.eval.evaluate import suggest_lengths
from trianflow_vo.eval.segments import path_distances, rotation_angle, segment_errors

DEG100 = 180.0 / math.pi * 100.0  # rad/m -> deg/100 m
# Rotation angles come from acos((trace - 1) / 2), as in the KITTI devkit: ~1.5e-8 rad of
# float noise near zero, i.e. up to ~1e-5 deg/100 m over a 10 m segment, ~1e-6 deg per frame.
R_ERR_ZERO = 1e-5  # deg/100 m
ROT_ZERO = 1e-6  # deg


# --------------------------------------------------------------------------- builders


def pose(R=None, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    T[:3, 3] = t
    return T


def rot(axis, angle) -> np.ndarray:
    axis = np.asarray(axis, dtype=float)
    return Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()


def chain(steps) -> np.ndarray:
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


def wiggly(n: int, seed: int = 0) -> np.ndarray:
    """A curvy, non-planar drive: forward ~1 m/frame with varying yaw and pitch."""
    rng = np.random.default_rng(seed)
    steps = []
    for i in range(n - 1):
        R = rot([0, 1, 0], 0.05 * np.sin(i / 15)) @ rot([1, 0, 0], 0.01 * np.cos(i / 9))
        steps.append(pose(R, (0.05 * rng.normal(), 0.02 * rng.normal(), 1.0 + 0.1 * np.sin(i / 7))))
    return chain(steps)


def scaled(T: np.ndarray, s: float) -> np.ndarray:
    out = T.copy()
    out[:, :3, 3] *= s
    return out


RIGID = pose(Rotation.from_rotvec([0.3, -1.2, 0.7]).as_matrix(), (12.0, -3.0, 40.0))


# --------------------------------------------------------------------------- alignment


@pytest.mark.parametrize(
    "gt, pred, s_true",
    [
        (winding(150), RIGID @ scaled(winding(150), 0.37), 0.37),  # moved rigidly and scaled
        (wiggly(400), scaled(wiggly(400), 0.25), 0.25),  # monocular: everything 4x too small
    ],
    ids=["rigid+0.37", "0.25"],
)
def test_pure_scale_is_zero_after_7dof_but_not_after_6dof_or_none(gt, pred, s_true):
    """pred = A @ (gt with positions x s), A rigid: the Sim(3) alignment undoes it exactly,
    so every error vanishes; without scale (6dof, none) the motion is s times too short and
    the segment error is large (1 - s of the travelled distance: 63 %, 75 %)."""
    lengths = (10, 20, 40) if s_true == 0.37 else (50, 100, 200)
    m7 = evaluate(pred, None, gt, align="7dof", lengths=lengths)
    assert m7["num_segments"] > 20 and (s_true != 0.25 or m7["num_segments"] > 30)
    assert m7["t_err"] == pytest.approx(0.0, abs=1e-9)
    assert m7["r_err"] == pytest.approx(0.0, abs=R_ERR_ZERO)
    assert m7["ate_rmse"] == pytest.approx(0.0, abs=1e-9)
    assert m7["rpe_trans"] == pytest.approx(0.0, abs=1e-9)
    assert m7["rpe_rot"] == pytest.approx(0.0, abs=ROT_ZERO)
    assert m7["scale"] == pytest.approx(1 / s_true, rel=1e-9)
    for mode in ("6dof", "none"):
        m = evaluate(pred, None, gt, align=mode, lengths=lengths)
        assert m["t_err"] > 50.0, mode
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


@pytest.mark.parametrize("case", ["rigid-scaled", "similarity"])
def test_align_trajectory_maps_prediction_onto_ground_truth_world(case):
    """For drawing: a scaled, rigidly moved copy of gt (gt not starting at identity) comes
    back onto gt itself; a standing camera cannot be aligned."""
    if case == "rigid-scaled":
        gt = RIGID @ winding(60, seed=3)
        pred = pose(Rotation.from_rotvec([1.0, 0.2, 0.0]).as_matrix(), (5, 5, 5)) @ scaled(gt, 0.2)
    else:
        base = wiggly(80)
        gt = pose(rot([0, 0, 1], 0.3), (5, 1, -2)) @ base
        pred = apply_alignment(base, 0.37, rot([1, -1, 0.5], 1.1), np.array([3.0, 4.0, 5.0]))
    np.testing.assert_allclose(align_trajectory(pred, gt, "7dof"), gt, atol=1e-9)
    with pytest.raises(InputError) as exc:
        align_trajectory(np.tile(np.eye(4), (10, 1, 1)), gt[:10])
    assert "7dof" in str(exc.value) and "--align none" in str(exc.value)


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


def test_umeyama_never_returns_a_reflection():
    """dst = a mirror image of src: the best proper rotation needs the det correction
    (S = diag(1, 1, -1)), which also enters the scale. Independent reference: scipy's
    Kabsch (``Rotation.align_vectors``) on the centred points, and the closed-form scale
    given that rotation."""
    rng = np.random.default_rng(5)
    src = rng.normal(0, 1, (40, 3)) * [5.0, 2.0, 0.5]
    dst = 1.7 * src * [1.0, 1.0, -1.0] + [3.0, 0.0, -2.0] + rng.normal(0, 0.05, (40, 3))
    (s, R, t), valid = umeyama(src, dst)
    assert valid
    assert np.linalg.det(R) == pytest.approx(1.0)
    xs, xd = src - src.mean(0), dst - dst.mean(0)
    R_ref = Rotation.align_vectors(xd, xs)[0].as_matrix()
    np.testing.assert_allclose(R, R_ref, atol=1e-9)
    s_ref = float(np.sum(xd * (xs @ R_ref.T)) / np.sum(xs * xs))
    assert s == pytest.approx(s_ref, rel=1e-9)
    np.testing.assert_allclose(t, dst.mean(0) - s * R @ src.mean(0), atol=1e-9)
    assert s < 1.7  # a mirror cannot be matched fully: the scale shrinks


@pytest.mark.parametrize("direction", [1.0, -1.0])
def test_umeyama_on_a_line_which_evo_refuses(direction):
    """Positions on a line (a straight drive) have a rank-1 covariance: evo's Umeyama raises,
    ours solves it in closed form (the rotation about the line is free and changes no
    metric). dst = 2.5 x src along the line (or reversed), shifted."""
    from evo.core.geometry import GeometryException, umeyama_alignment

    src = np.zeros((20, 3))
    src[:, 2] = np.arange(20.0)
    dst = direction * 2.5 * src + [1.0, -2.0, 3.0]
    with pytest.raises(GeometryException):
        umeyama_alignment(src.T, dst.T, True)
    (s, R, t), valid = umeyama(src, dst)
    assert valid and s == pytest.approx(2.5, rel=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0) and np.allclose(R.T @ R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(s * src @ R.T + t, dst, atol=1e-9)
    # and end to end: a straight prediction 0.8x too short is exact after 7dof
    gt = straight(60)
    m = evaluate(scaled(gt, 0.8), None, gt, align="7dof", lengths=(10,))
    assert m["t_err"] == pytest.approx(0.0, abs=1e-9) and m["scale"] == pytest.approx(1.25, rel=1e-12)


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


def test_scale_mode_is_least_squares_about_the_first_frame_not_evos_only_scale():
    """"scale": s = sum(dst . src) / sum(src . src) about the origin (the first frame after
    re-basing). evo's ``align(correct_only_scale=True)`` keeps the scale of the full Sim(3)
    fit instead, which is another number once there is noise: that is why it is ours."""
    from evo.core.trajectory import PosePath3D

    rng = np.random.default_rng(7)
    src = np.cumsum(rng.normal(0, 1, (50, 3)), axis=0)
    src -= src[0]
    dst = 1.3 * src @ rot([0, 1, 0], 0.2).T + rng.normal(0, 0.3, (50, 3))
    dst -= dst[0]
    (s, R, t), ok = estimate_alignment(src, dst, "scale")
    assert ok and s == pytest.approx(float(np.sum(dst * src) / np.sum(src * src)), rel=1e-12)
    np.testing.assert_array_equal(R, np.eye(3))
    est = PosePath3D(positions_xyz=src, orientations_quat_wxyz=np.tile([1.0, 0, 0, 0], (50, 1)))
    ref = PosePath3D(positions_xyz=dst, orientations_quat_wxyz=np.tile([1.0, 0, 0, 0], (50, 1)))
    _, _, s_evo = est.align(ref, correct_only_scale=True)
    assert abs(s_evo - s) > 1e-3


# --------------------------------------------------------------------------- segment metric


def test_path_distances_and_rotation_angle():
    np.testing.assert_allclose(path_distances(np.array([[0, 0, 0], [3, 4, 0], [3, 4, 1.0]])), [0, 5, 6])
    assert rotation_angle(rot([1, 1, 0], 0.4)) == pytest.approx(0.4)
    assert rotation_angle(np.eye(3)) == 0.0


@pytest.mark.parametrize(
    "n, e, lengths, counts",
    [
        # 400 m, 1 %: first frames 0, 10, ... and b = a + L + 1 <= 400 -> 30, 20, 10 segments, none at 400 m
        (401, 0.01, (100, 200, 300, 400), {100: 30, 200: 20, 300: 10, 400: 0}),
        (200, 0.03, (10, 20, 50), None),  # counts from the rule below
    ],
)
def test_constant_length_drift_gives_known_t_err_per_length(n, e, lengths, counts):
    """Straight gt, 1 m per frame; pred (1 + e) m per frame, no alignment. Segment (a, L)
    ends at b = a + L + 1: error e (L + 1), so t_err(L) = 100 e (L + 1) / L %. Overall
    t_err is the mean over all segments; r_err is 0. ATE: frame i is off by e i; RPE
    between consecutive frames: e. A length without segment gives None (not NaN)."""
    gt = straight(n)
    pred = straight(n, 1.0 + e)
    m = evaluate(pred, None, gt, align="none", lengths=lengths)
    per = {r["length"]: r for r in m["per_length"]}
    rule = {L: len([a for a in range(0, n, 10) if a + L + 1 <= n - 1]) for L in lengths}
    if counts is not None:
        assert rule == counts
    total = 0.0
    for L in lengths:
        row = per[float(L)]
        assert row["num_segments"] == rule[L]
        if rule[L] == 0:
            assert row["t_err"] is None and row["r_err"] is None
            continue
        assert row["t_err"] == pytest.approx(100 * e * (L + 1) / L, rel=1e-9)
        assert row["r_err"] == pytest.approx(0.0, abs=1e-12)
        total += rule[L] * 100 * e * (L + 1) / L
    assert m["num_segments"] == sum(rule.values())
    assert m["t_err"] == pytest.approx(total / m["num_segments"], rel=1e-9)
    assert m["r_err"] == pytest.approx(0.0, abs=1e-12)
    assert m["path_length"] == pytest.approx(n - 1.0)
    assert m["ate_rmse"] == pytest.approx(e * np.sqrt(np.mean(np.arange(n) ** 2)), rel=1e-9)
    assert m["rpe_trans"] == pytest.approx(e, rel=1e-9)
    # the same drift is pure scale: 7dof removes it
    assert evaluate(pred, None, gt, align="7dof", lengths=lengths)["t_err"] == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("n, lengths", [(251, (50, 100)), (120, (10, 40))])
def test_constant_yaw_drift_gives_known_r_err(n, lengths):
    """pred turns by delta = 1e-3 rad about y every frame while gt goes straight; the
    segment (a, L) spans L + 1 frames, so its rotation error is (L + 1) delta and
    r_err(L) = (L + 1) delta / L rad/m = that x (180/pi) x 100 deg/100 m."""
    delta = 1e-3
    gt = straight(n)
    pred = chain([pose(rot([0, 1, 0], delta), (0.0, 0.0, 1.0))] * (n - 1))
    m = evaluate(pred, None, gt, align="none", lengths=lengths)
    per = {r["length"]: r for r in m["per_length"]}
    for L in lengths:
        assert per[float(L)]["r_err"] == pytest.approx((L + 1) * delta / L * DEG100, rel=1e-9)
    # RPE between consecutive frames: exactly delta in rotation
    assert m["rpe_rot"] == pytest.approx(math.degrees(delta), rel=1e-9)
    assert m["t_err"] > 0.0


def test_segment_step_and_strict_end_frame():
    gt = straight(31)  # distances 0..30
    seg = segment_errors(gt, gt, lengths=[10], step=10)
    # firsts 0, 10, 20; end = first frame with distance > first + 10 -> 11, 21; 31 does not exist
    assert seg.first.tolist() == [0, 10] and seg.last.tolist() == [11, 21]
    seg = segment_errors(gt, gt, lengths=[10], step=5)
    assert seg.first.tolist() == [0, 5, 10, 15]


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


def test_ate_rpe_shapes():
    gt = straight(5)
    assert ate_errors(gt, gt).shape == (5,)
    t, r = rpe_errors(gt, gt, delta=2)
    assert t.shape == (3,) and r.shape == (3,)
    t, r = rpe_errors(gt[:1], gt[:1])
    assert t.size == 0


# --------------------------------------------------------------------------- protocol details


@pytest.mark.parametrize("case", ["shifted+extra", "holes"])
def test_frames_matched_by_index_and_rebased_to_first_common_frame(case):
    """Only the common frames count, re-based at the first of them; a similar copy of
    those frames gives zero error. Prediction frames 5..59 of a 60-frame gt plus a
    frame 80 the gt lacks (55 common), or 300 frames with 5 missing (295 common)."""
    if case == "shifted+extra":
        gt = winding(60, seed=5)
        frames = np.r_[np.arange(5, 60), 80]
        pred = scaled(RIGID @ np.concatenate([gt[5:], gt[:1]]), 4.0)
        lengths, n_common = (10, 20), 55
    else:
        gt = wiggly(300)
        frames = np.setdiff1d(np.arange(300), [5, 6, 7, 100, 250])
        pred = apply_alignment(gt[frames], 2.0, rot([0, 1, 0], 0.5), np.array([1.0, 2.0, 3.0]))
        lengths, n_common = (20, 50), 295
    m = evaluate(pred, frames, gt, align="7dof", lengths=lengths)
    assert m["num_frames"] == n_common
    assert m["t_err"] == pytest.approx(0.0, abs=1e-9)
    assert m["ate_rmse"] == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize(
    "n, step, align, note_words",
    [
        (51, 1.02, "none", ("50.0 m", "--lengths 5,10,15,20,25,30,35,40")),
        (30, 1.0, "7dof", ("29.0 m", "--lengths 2,4,6,8,10,12,14,16")),
    ],
)
def test_short_sequence_has_no_segment_and_suggests_lengths(n, step, align, note_words):
    """A 50 m (29 m) sequence with the default 100..800 m lengths: no segment, t_err/r_err
    None (not NaN), a note suggesting --lengths that fit (eight 1-2-5 steps below path/8)."""
    gt = straight(n)
    pred = straight(n, step)
    m = evaluate(pred, None, gt, None, align=align)
    assert m["num_segments"] == 0
    assert m["t_err"] is None and m["r_err"] is None
    assert all(r["t_err"] is None for r in m["per_length"])
    for w in note_words:
        assert w in m["note"]
    assert math.isfinite(m["ate_rmse"]) and (step == 1.0 or m["ate_rmse"] > 0)
    if step != 1.0:
        m2 = evaluate(pred, None, gt, align=align, lengths=[5, 10, 15, 20, 25, 30, 35, 40])
        assert m2["num_segments"] == 5 + 4 + 4 + 3 + 3 + 2 + 2 + 1  # first frames 0, 10, .., end a + L + 1 <= 50
        for row in m2["per_length"]:
            assert row["t_err"] == pytest.approx(2.0 * (row["length"] + 1) / row["length"], rel=1e-9)


def test_suggest_lengths():
    assert suggest_lengths(110) == [10, 20, 30, 40, 50, 60, 70, 80]
    assert suggest_lengths(60) == [5, 10, 15, 20, 25, 30, 35, 40]
    assert suggest_lengths(0) == []


def test_too_few_common_frames_and_degenerate_alignment_raise():
    gt = winding(30, seed=6)
    with pytest.raises(InputError, match="only 2 frame.*at least 3"):
        evaluate(gt[:2], np.array([3, 4]), gt)
    with pytest.raises(InputError, match="only 0 frame.*at least 3"):
        evaluate(gt[:5], np.arange(100, 105), gt)
    with pytest.raises(InputError, match="at least 3"):
        evaluate(straight(10)[:2], [0, 1], straight(10), None)
    still = np.tile(pose(t=(1.0, 2.0, 3.0)), (30, 1, 1))
    for mode in ("7dof", "6dof", "scale"):
        with pytest.raises(InputError, match="all predicted"):
            evaluate(still, None, gt, align=mode)
        with pytest.raises(InputError, match="cannot estimate"):
            evaluate(gt, None, still, align=mode)
    with pytest.raises(InputError, match="cannot estimate"):
        evaluate(np.tile(np.eye(4), (10, 1, 1)), None, straight(10), None)
    # without alignment there is nothing to estimate: a standing camera is evaluated
    m = evaluate(still, None, gt, align="none", lengths=(5,))
    assert m["ate_rmse"] > 1.0


def test_evaluate_associated_rejects_bad_lengths_and_mode():
    gt = winding(20)
    with pytest.raises(InputError, match="lengths"):
        evaluate_associated(gt, gt, "7dof", lengths=[10, -5])
    for bad in ("sim3", "8dof"):
        with pytest.raises(InputError, match="unknown alignment"):
            evaluate_associated(gt, gt, bad)


# --------------------------------------------------------------------------- vs evo


def _noisy(gt: np.ndarray, seed: int, trans: float = 0.03, rot_sd: float = 0.003) -> np.ndarray:
    """gt's relative motions with small random pose noise, chained again from identity."""
    rng = np.random.default_rng(seed)
    steps = []
    for i in range(len(gt) - 1):
        rel = np.linalg.inv(gt[i]) @ gt[i + 1]
        steps.append(rel @ pose(Rotation.from_rotvec(rng.normal(0, rot_sd, 3)).as_matrix(), rng.normal(0, trans, 3)))
    return chain(steps)


@pytest.mark.parametrize("rebase_for_evo", [False, True])
def test_alignment_ate_rpe_agree_with_evo(rebase_for_evo):
    """A noisy, scaled, rigidly moved prediction. evo's own ``PosePath3D.align`` (Sim(3))
    on the raw or re-based trajectories gives the same residuals as our re-base + align
    (and, on the re-based ones, the same aligned poses); evo's APE is our ATE; evo's RPE
    over 1 frame (not our implementation) gives our RPE on orthonormal rotations."""
    from evo.core import lie_algebra, metrics, trajectory

    if rebase_for_evo:
        gt = wiggly(250, seed=4)
        pred = apply_alignment(_noisy(gt, 5), 0.6, rot([1, 0, 1], 0.4), np.array([2.0, 0.0, 1.0]))
    else:
        gt = winding(200, seed=11)
        pred = RIGID @ scaled(_noisy(gt, 2), 0.6)
    result = evaluate_associated(pred, gt, align="7dof", lengths=(20, 50))
    m = result.metrics

    if rebase_for_evo:
        ref = trajectory.PosePath3D(poses_se3=list(result.gt_rebased))
        est = trajectory.PosePath3D(poses_se3=list(np.linalg.inv(pred[0]) @ pred))
    else:
        ref = trajectory.PosePath3D(poses_se3=list(gt))
        est = trajectory.PosePath3D(poses_se3=[lie_algebra.se3(T[:3, :3], T[:3, 3]) for T in pred])
    est.align(ref, correct_scale=True)
    if rebase_for_evo:
        np.testing.assert_allclose(np.array(est.poses_se3), result.pred_aligned, atol=1e-8)

    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    assert m["ate_rmse"] == pytest.approx(ape.get_statistic(metrics.StatisticsType.rmse), rel=1e-9)
    assert m["ate_mean"] == pytest.approx(ape.get_statistic(metrics.StatisticsType.mean), rel=1e-9)
    assert m["ate_rmse"] > 0.1

    for relation, key, key_mean in [
        (metrics.PoseRelation.translation_part, "rpe_trans", "rpe_trans_mean"),
        (metrics.PoseRelation.rotation_angle_deg, "rpe_rot", "rpe_rot_mean"),
    ]:
        rpe = metrics.RPE(relation, delta=1, delta_unit=metrics.Unit.frames, all_pairs=False)
        rpe.process_data((ref, est))
        assert m[key] == pytest.approx(rpe.get_statistic(metrics.StatisticsType.rmse), rel=1e-7), key
        assert m[key_mean] == pytest.approx(rpe.get_statistic(metrics.StatisticsType.mean), rel=1e-7), key
        assert m[key] > 0
    assert m["t_err"] > 0.1  # the noise is visible in the segment metric


def test_rpe_accepts_rotations_from_files_which_evo_refuses():
    """Rotations read from files are orthonormal to ~1e-7 only (KITTI, 7-Scenes): evo's RPE
    (``so3_log``) refuses anything more than 1e-6 off SO(3); ours keeps the devkit's exact
    inverse and acos angle -- the reason RPE is not evo's. Here every ground-truth rotation
    is scaled by 1 + 1e-4: with exact inverses that cancels in the relative rotations."""
    from evo.core import lie_algebra, metrics, trajectory

    gt = straight(30)
    pred = chain([pose(rot([0, 1, 0], 2e-3), (0.0, 0.0, 1.0))] * 29)
    gt_off = gt.copy()
    gt_off[:, :3, :3] *= 1.0 + 1e-4  # not orthonormal any more, still accepted by our reader (1e-2)
    t_ref, r_ref = rpe_errors(gt, pred)
    t_off, r_off = rpe_errors(gt_off, pred)
    assert np.all(np.isfinite(r_off)) and np.abs(r_off - r_ref).max() < 1e-9
    assert r_ref == pytest.approx(np.full(29, 2e-3), rel=1e-6)
    rpe = metrics.RPE(metrics.PoseRelation.rotation_angle_deg, delta=1, delta_unit=metrics.Unit.frames)
    with pytest.raises(lie_algebra.LieAlgebraException):
        rpe.process_data((trajectory.PosePath3D(poses_se3=list(gt_off)), trajectory.PosePath3D(poses_se3=list(pred))))
