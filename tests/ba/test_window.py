"""One window bundle adjustment on GTSAM: known scenes, noise, outliers, failure."""

import numpy as np
import pytest

pytest.importorskip("gtsam", reason="the window back-end needs gtsam (a dependency of the project)")

from trianflow_vo.ba.window import reprojection_errors, select_observations, solve_window  # noqa: E402

K = np.array([[480.0, 0.0, 416.0], [0.0, 480.0, 128.0], [0.0, 0.0, 1.0]])
SIZE = (256, 832)


def _scene(n_poses=8, n_points=500, noise=0.3, seed=0):
    """A drive forward (0.9 m a step, drifting sideways) past points 5-60 m ahead."""
    rng = np.random.default_rng(seed)
    P = np.c_[rng.uniform(-15, 15, n_points), rng.uniform(-3, 1.6, n_points), rng.uniform(5, 60, n_points)]
    poses = {}
    for i in range(n_poses):
        T = np.eye(4)
        T[:3, 3] = (0.02 * i * i, 0.0, 0.9 * i)
        poses[i] = T
    obs = {}
    for i, T in poses.items():
        Xc = (P - T[:3, 3]) @ T[:3, :3]
        uv = (Xc @ K.T)[:, :2] / Xc[:, 2:3]
        ok = (Xc[:, 2] > 0.5) & (uv[:, 0] > 0) & (uv[:, 0] < SIZE[1]) & (uv[:, 1] > 0) & (uv[:, 1] < SIZE[0])
        obs[i] = (np.flatnonzero(ok).astype(np.int64), uv[ok] + rng.normal(0, noise, (int(ok.sum()), 2)))
    return P, poses, obs, rng


def _drifted(poses, rate=1.03):
    """Each step after the second ``rate`` times longer than the one before (a scale drift)."""
    init = {}
    for i, T in poses.items():
        T = T.copy()
        if i >= 2:
            T[2, 3] = 0.9 + sum(0.9 * rate ** k for k in range(1, i))
        init[i] = T
    return init


def test_window_removes_a_scale_drift_and_holds_the_fixed_keyframes():
    P, poses, obs, rng = _scene()
    init = _drifted(poses)
    lm = {j: P[j] * (1 + rng.normal(0, 0.05)) for j in range(len(P))}
    sol, ok = solve_window(K, init, {0, 1}, obs, lm, huber_px=1.0, max_iterations=20)
    assert ok and sol.error_after < 0.1 * sol.error_before
    for i in (0, 1):
        np.testing.assert_allclose(sol.poses[i], poses[i], atol=1e-5)  # held
    err_init = abs(init[7][2, 3] - poses[7][2, 3])
    err = np.linalg.norm(sol.poses[7][:3, 3] - poses[7][:3, 3])
    assert err_init > 0.5 and err < 0.03, (err_init, err)
    assert np.median(list(sol.residual_px.values())) < 1.0
    assert sol.n_points > 300 and sol.n_factors > 5 * sol.n_points - 1


def test_gross_outliers_do_not_move_the_solution_and_are_reported():
    P, poses, obs, rng = _scene(seed=1)
    ids, uv = obs[7]
    bad = ids[:20]
    uv = uv.copy()
    uv[:20] += rng.uniform(15, 30, (20, 2))  # 20 observations 15-30 px off
    obs[7] = (ids, uv)
    lm = {j: P[j] for j in range(len(P))}
    init = _drifted(poses, 1.01)
    sol, ok = solve_window(K, init, {0, 1}, obs, lm, huber_px=1.0, max_iterations=20)
    assert ok
    assert np.linalg.norm(sol.poses[7][:3, 3] - poses[7][:3, 3]) < 0.03
    worst = np.array([sol.residual_px[t] for t in bad.tolist()])
    assert np.all(worst > 5.0)  # the outliers stand out for the caller to end them


def test_too_few_points_or_no_free_pose_is_invalid():
    P, poses, obs, _ = _scene(n_points=10)
    lm = {j: P[j] for j in range(len(P))}
    assert solve_window(K, poses, {0, 1}, obs, lm, min_points=20) == (None, False)
    P, poses, obs, _ = _scene(n_poses=2)
    lm = {j: P[j] for j in range(len(P))}
    assert solve_window(K, poses, {0, 1}, obs, lm) == (None, False)
    with pytest.raises(ValueError):
        solve_window(K, poses, {5}, obs, lm)
    with pytest.raises(ValueError):
        solve_window(K, poses, set(), obs, lm)


def test_observations_behind_a_camera_or_without_landmark_are_left_out():
    P, poses, obs, _ = _scene(n_poses=3, n_points=50)
    lm = {j: P[j] for j in range(len(P))}
    lm[0] = np.array([0.0, 0.0, -5.0])  # behind every camera
    del lm[1]
    kf, tid, uv = select_observations(poses, obs, lm, fixed={0, 1})
    assert 0 not in tid and 1 not in tid
    counts = np.bincount(tid)
    assert np.all(counts[counts > 0] >= 2)
    # a track seen only by fixed keyframes constrains nothing
    kf, tid, uv = select_observations({0: poses[0], 1: poses[1]}, obs, lm, fixed={0, 1})
    assert tid.size == 0
    err = reprojection_errors(K, poses, {j: P[j] for j in range(len(P))}, *select_observations(
        poses, obs, {j: P[j] for j in range(len(P))}, fixed={0}))
    assert np.median(err) < 1.0


def test_step_factors_pull_towards_the_measured_steps():
    P, poses, obs, rng = _scene(seed=2, noise=2.0)
    lm = {j: P[j] for j in range(len(P))}
    init = _drifted(poses, 1.02)
    steps = {i: (i - 1, np.linalg.inv(poses[i - 1]) @ poses[i]) for i in range(1, 8)}  # exact steps
    free, _ = solve_window(K, init, {0, 1}, obs, lm)
    tied, _ = solve_window(K, init, {0, 1}, obs, lm, steps=steps, step_rot_sigma=1e-4, step_trans_sigma=1e-3)
    e_free = np.linalg.norm(free.poses[7][:3, 3] - poses[7][:3, 3])
    e_tied = np.linalg.norm(tied.poses[7][:3, 3] - poses[7][:3, 3])
    assert e_tied < e_free


def test_a_step_s_own_translation_sigma_is_honoured():
    """A third element in a step is its translation sigma (trajectory units): a wrong step given a
    tight sigma drags the keyframe, the same step given a loose one is left to the reprojections."""
    P, poses, obs, rng = _scene(seed=3, noise=0.3)
    lm = {j: P[j] for j in range(len(P))}
    steps = {i: (i - 1, np.linalg.inv(poses[i - 1]) @ poses[i]) for i in range(1, 8)}
    wrong = steps[7][1].copy()
    wrong[:3, 3] = (0.5, 0.0, 0.5)  # 45 degrees off and 0.2 m short of the true 0.9 m step ahead
    tight = {**steps, 7: (6, wrong, 1e-4)}
    loose = {**steps, 7: (6, wrong, 10.0)}
    kw = dict(step_rot_sigma=1e-3, step_trans_sigma=1e-2, max_iterations=20)
    sol_t, ok_t = solve_window(K, poses, {0, 1}, obs, lm, steps=tight, **kw)
    sol_l, ok_l = solve_window(K, poses, {0, 1}, obs, lm, steps=loose, **kw)
    assert ok_t and ok_l
    e_tight = np.linalg.norm(sol_t.poses[7][:3, 3] - poses[7][:3, 3])
    e_loose = np.linalg.norm(sol_l.poses[7][:3, 3] - poses[7][:3, 3])
    assert e_tight > 0.1 and e_loose < 0.02, (e_tight, e_loose)
