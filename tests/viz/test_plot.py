"""trajectory.png: alignment to ground truth (eval's, through evo), drawing through evo's
plotting (headless, quiet) or matplotlib when evo's plotting is unavailable, input checks."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from trianflow_vo.eval.align import align_rebased
from trianflow_vo.viz.plot import align_estimate_to_gt, common_indices, plot_trajectory

REPO = Path(__file__).resolve().parents[2]

BLUE_BGR = (180, 119, 31)  # matplotlib tab:blue, the estimate
ORANGE_BGR = (14, 127, 255)  # matplotlib tab:orange, the ground truth


def rot_y(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def pose(R, t):
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def curve(n, start_yaw=0.3, start=(4.0, 0.0, -2.0)):
    """A camera driving forward along a curve, first pose not the identity."""
    T0 = pose(rot_y(start_yaw), start)
    rel = [pose(rot_y(0.04 * i), [0.1 * i * i, 0.02 * i, 1.0 * i]) for i in range(n)]
    return np.stack([T0 @ T for T in rel])


def similar(T, s, R, t):
    """The same path in another world: rotated by ``R``, scaled by ``s``, moved by ``t``."""
    return np.stack([pose(R @ P[:3, :3], s * R @ P[:3, 3] + t) for P in T])


def count_colour(img, bgr, tol=12):
    return int((np.abs(img.astype(int) - np.array(bgr)).max(axis=2) <= tol).sum())


def test_common_indices():
    i_est, i_gt = common_indices(np.array([5, 6, 7, 9]), np.array([0, 1, 5, 7, 8, 9]))
    assert i_est.tolist() == [0, 2, 3]
    assert i_gt.tolist() == [2, 3, 5]


def test_alignment_recovers_a_known_similarity():
    est = curve(15)
    R = rot_y(1.1) @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])
    gt = similar(curve(17, start_yaw=-0.5, start=(1, 2, 3)), 3.0, R, np.array([10.0, -4.0, 2.0]))
    est_frames = np.arange(2, 17)  # the estimate covers gt frames 2..16 of 0..16
    gt_frames = np.arange(0, 17)
    # make the estimate the ground truth's frames 2..16 seen in its own world at 1/3 scale
    est = similar(gt[2:], 1 / 3.0, rot_y(-0.4), np.array([1.0, 1.0, 1.0]))
    (S, B, n), valid = align_estimate_to_gt(est, gt, est_frames, gt_frames)
    assert valid and n == 15
    mapped = est[:, :3, 3] @ S[:3, :3].T + S[:3, 3]
    gt_ref = gt[:, :3, 3] @ B[:3, :3].T + B[:3, 3]
    np.testing.assert_allclose(mapped, gt_ref[2:], atol=1e-9)
    np.testing.assert_allclose(gt_ref[2], 0, atol=1e-9)  # re-based to the first common frame
    assert np.linalg.det(S[:3, :3]) == pytest.approx(27.0)  # scale 3 in each direction


def test_alignment_is_evals():
    """One implementation: the similarity maps the estimate exactly where eval's 7dof
    alignment puts it, and the ground truth where eval re-bases it."""
    gt = curve(40, start_yaw=-0.2, start=(3, 1, 2))
    rng = np.random.default_rng(0)
    est = similar(gt, 0.4, rot_y(0.7), np.array([2.0, 0.0, -1.0]))
    est[:, :3, 3] += rng.normal(0, 0.05, (40, 3))
    frames, gt_frames = np.arange(5, 40), np.arange(40)
    (S, B, n), valid = align_estimate_to_gt(est[5:], gt, frames, gt_frames)
    assert valid and n == 35
    pred_aligned, gt_rebased, _, ok = align_rebased(est[5:], gt[5:], "7dof")
    assert ok
    np.testing.assert_allclose(est[5:, :3, 3] @ S[:3, :3].T + S[:3, 3], pred_aligned[:, :3, 3], atol=1e-9)
    np.testing.assert_allclose(gt[5:, :3, 3] @ B[:3, :3].T + B[:3, 3], gt_rebased[:, :3, 3], atol=1e-9)


def test_alignment_of_a_straight_drive():
    """Positions on a line: evo's Umeyama refuses them, eval's alignment solves them."""
    gt = np.tile(np.eye(4), (10, 1, 1))
    gt[:, 2, 3] = np.arange(10.0)
    est = gt.copy()
    est[:, 2, 3] *= 0.5
    (S, B, n), valid = align_estimate_to_gt(est, gt)
    assert valid and n == 10
    np.testing.assert_allclose(est[:, :3, 3] @ S[:3, :3].T + S[:3, 3], gt[:, :3, 3], atol=1e-12)


def test_alignment_invalid_cases():
    est = curve(5)
    (_, _, n), valid = align_estimate_to_gt(est, curve(5), np.arange(5), np.arange(10, 15))
    assert n == 0 and not valid
    (_, _, n), valid = align_estimate_to_gt(est, curve(5), np.arange(5), np.array([0, 1, 20, 21, 22]))
    assert n == 2 and not valid
    static = np.stack([np.eye(4)] * 5)
    assert not align_estimate_to_gt(est, static)[1]
    assert not align_estimate_to_gt(static, est)[1]


def test_plot_without_ground_truth(tmp_path):
    out = plot_trajectory(curve(30), tmp_path / "trajectory.png")
    assert out == tmp_path / "trajectory.png"
    img = cv2.imread(str(out))
    assert img is not None and img.shape == (700, 700, 3)
    assert count_colour(img, BLUE_BGR) > 300  # the path is drawn
    assert count_colour(img, ORANGE_BGR) < 50  # no ground truth


def test_plot_with_ground_truth_draws_both(tmp_path):
    gt = curve(30, start_yaw=0.0, start=(0, 0, 0))
    est = similar(gt, 0.2, rot_y(0.9), np.array([3.0, 0, 3.0]))
    est[:, 0, 3] += 0.05 * np.arange(30) ** 1.5  # drift, so the two paths differ
    out = plot_trajectory(est, tmp_path / "t.png", gt_T_world_cam=gt, title="kitti00")
    img = cv2.imread(str(out))
    assert count_colour(img, BLUE_BGR) > 300
    assert count_colour(img, ORANGE_BGR) > 100


def test_plot_with_unalignable_ground_truth_still_writes(tmp_path):
    gt = np.stack([np.eye(4)] * 4)
    out = plot_trajectory(curve(4), tmp_path / "t.png", gt_T_world_cam=gt)
    assert cv2.imread(str(out)) is not None


def test_plot_input_checks(tmp_path):
    with pytest.raises(ValueError, match=r"\(N, 4, 4\)"):
        plot_trajectory(np.zeros((3, 3, 4)), tmp_path / "a.png")
    with pytest.raises(ValueError, match="empty"):
        plot_trajectory(np.zeros((0, 4, 4)), tmp_path / "a.png")
    with pytest.raises(ValueError, match="frames"):
        plot_trajectory(curve(3), tmp_path / "a.png", frames=[0, 1])
    with pytest.raises(ValueError, match="gt_frames"):
        plot_trajectory(curve(3), tmp_path / "a.png", gt_T_world_cam=curve(3), gt_frames=[1])
    assert not (tmp_path / "a.png").exists()


def test_plot_is_headless_quiet_and_leaves_no_pyplot_state(tmp_path):
    """In a fresh process without a display and a fresh HOME: the figure is drawn through
    evo's plotting (which imports pyplot and, on first use, writes ~/.evo and prints so),
    yet nothing reaches stdout, the backend is Agg, no pyplot figure is left open and
    matplotlib's global style is untouched."""
    code = (
        "import sys, numpy as np, matplotlib\n"
        "style = matplotlib.rcParams.copy()  # copy() does not resolve the backend\n"
        "from trianflow_vo.viz.plot import plot_trajectory\n"
        "assert 'matplotlib.pyplot' not in sys.modules\n"
        "T = np.stack([np.eye(4)] * 3); T[:, 2, 3] = [0, 1, 2]\n"
        f"plot_trajectory(T, {str(tmp_path / 'h.png')!r})\n"
        "import matplotlib.pyplot as plt\n"
        "assert 'evo.tools.plot' in sys.modules\n"
        "assert plt.get_fignums() == [], plt.get_fignums()\n"
        "assert matplotlib.get_backend().lower() == 'agg', matplotlib.get_backend()\n"
        "changed = [k for k in style if k != 'backend' and matplotlib.rcParams[k] != style[k]]\n"
        "assert not changed, changed\n"
        "print('ok')\n"
    )
    home = tmp_path / "home"
    home.mkdir()
    env = {k: v for k, v in __import__("os").environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "MPLBACKEND")}
    env["HOME"] = str(home)
    res = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0 and res.stdout == "ok\n", res.stdout + res.stderr
    assert res.stderr == ""
    assert (home / ".evo" / "settings.json").is_file()
    assert (tmp_path / "h.png").stat().st_size > 1000


def test_fallback_without_evo_plotting_draws_the_same_and_warns(tmp_path, monkeypatch):
    """When evo's plotting cannot be imported, one PlotFallbackWarning and the same figure
    drawn with matplotlib directly (same colours, same size)."""
    import evo.tools

    import trianflow_vo.eval.plot as eval_plot

    monkeypatch.setattr(eval_plot, "_EVO_PLOT", None)
    monkeypatch.setitem(sys.modules, "evo.tools.plot", None)  # import fails
    monkeypatch.delattr(evo.tools, "plot", raising=False)
    gt = curve(30, start_yaw=0.0, start=(0, 0, 0))
    est = similar(gt, 0.2, rot_y(0.9), np.array([3.0, 0, 3.0]))
    est[:, 0, 3] += 0.05 * np.arange(30) ** 1.5
    with pytest.warns(eval_plot.PlotFallbackWarning, match="evo's plotting is unavailable"):
        out = plot_trajectory(est, tmp_path / "t.png", gt_T_world_cam=gt)
    assert eval_plot._EVO_PLOT is False
    img = cv2.imread(str(out))
    assert img.shape == (700, 700, 3)
    assert count_colour(img, BLUE_BGR) > 300 and count_colour(img, ORANGE_BGR) > 100
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # warned once, not on every figure
        plot_trajectory(est, tmp_path / "t2.png")
