"""Cell medians of the ray angle and the floor on them (``geometry/parallax.py``), and the
epipolar correction of matches before triangulation."""

from __future__ import annotations

import numpy as np
import pytest

from synthetic import K_TEST, two_view_scene
from trianflow_vo.geometry.epipolar import epipolar_distance, project_to_epipolar_line
from trianflow_vo.geometry.fundamental import fundamental_from_pose
from trianflow_vo.geometry.parallax import cell_median, local_angle_floor
from trianflow_vo.geometry.triangulation import triangulate_midpoint


def test_cell_median_known_cells():
    # two cells of side 10: the left one holds 1, 2, 9; the right one 5, 7
    pts = np.array([[1.0, 1.0], [2.0, 3.0], [9.0, 9.0], [15.0, 1.0], [19.0, 2.0]])
    values = np.array([1.0, 2.0, 9.0, 5.0, 7.0])
    assert np.allclose(cell_median(values, pts, 10.0), [2.0, 2.0, 2.0, 6.0, 6.0])


def test_cell_median_matches_a_loop_on_random_points():
    rng = np.random.default_rng(3)
    pts = rng.uniform(0, 200, (500, 2))
    values = rng.normal(size=500)
    got = cell_median(values, pts, 32.0)
    cell = [tuple(c) for c in np.floor(pts / 32.0).astype(int)]
    for i in range(0, 500, 37):
        members = [j for j in range(500) if cell[j] == cell[i]]
        assert got[i] == pytest.approx(np.median(values[members]))


def test_cell_median_checks_its_inputs():
    with pytest.raises(ValueError, match="pts"):
        cell_median(np.zeros(3), np.zeros((2, 2)), 8.0)
    with pytest.raises(ValueError, match="cell_px"):
        cell_median(np.zeros(2), np.zeros((2, 2)), 0.0)
    assert cell_median(np.zeros(0), np.zeros((0, 2)), 8.0).shape == (0,)


def test_floor_drops_whole_cells_not_points_picked_by_their_own_angle():
    # left half of the image sees the scene at 0.02 rad, the right half at 0.002 rad; the
    # angles are noisy, so a floor on each point's own angle would keep the right half's
    # points whose noise lifted them over it
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(0, 640, 4000), rng.uniform(0, 320, 4000)])
    near = pts[:, 0] < 320
    angle = np.where(near, 0.02, 0.002) * np.exp(rng.normal(0, 0.8, 4000))
    valid = np.ones(4000, bool)
    kept, used = local_angle_floor(angle, pts, valid, floor=0.008, keep=0.0, cell_px=32.0)
    assert used == 0.008
    assert kept[near].mean() > 0.99 and kept[~near].mean() < 0.01
    own = angle > 0.008
    assert own[~near].sum() > 40  # what a per-point floor would have kept


def test_floor_is_lowered_to_keep_the_asked_share():
    rng = np.random.default_rng(1)
    pts = rng.uniform(0, 640, (3000, 2))
    angle = np.full(3000, 0.001) * (1 + pts[:, 0] / 640)  # every cell under the floor
    kept, used = local_angle_floor(angle, pts, np.ones(3000, bool), floor=0.008, keep=0.75, cell_px=32.0)
    assert used < 0.008
    assert kept.mean() >= 0.75
    # the dropped points are those of the smallest-angle cells
    assert angle[~kept].max() <= angle[kept].min() + 1e-4


def test_floor_off_and_invalid_points():
    angle = np.array([0.001, 0.02, 0.03])
    pts = np.array([[0.0, 0.0], [100.0, 0.0], [200.0, 0.0]])
    valid = np.array([True, True, False])
    kept, used = local_angle_floor(angle, pts, valid, floor=0.0, keep=0.75, cell_px=32.0)
    assert used == 0.0 and np.array_equal(kept, valid)
    kept, _ = local_angle_floor(angle, pts, valid, floor=0.008, keep=0.0, cell_px=32.0)
    assert kept.tolist() == [False, True, False]  # an invalid point never comes back
    with pytest.raises(ValueError, match="keep"):
        local_angle_floor(angle, pts, valid, floor=0.008, keep=1.5, cell_px=32.0)


def test_projection_onto_the_epipolar_line():
    pts1, pts2, _, R, t = two_view_scene(n=200, seed=2)
    F = fundamental_from_pose(R, t, K_TEST)
    rng = np.random.default_rng(2)
    noisy = pts2 + rng.normal(0, 1.0, pts2.shape)
    on = project_to_epipolar_line(F, pts1, noisy)
    assert np.allclose(epipolar_distance(F, pts1, on), 0.0, atol=1e-6)
    # the move is perpendicular to the line: its length is the distance to the line
    assert np.allclose(np.linalg.norm(on - noisy, axis=1), epipolar_distance(F, pts1, noisy), atol=1e-6)
    # exact matches do not move
    assert np.allclose(project_to_epipolar_line(F, pts1, pts2), pts2, atol=1e-6)


def test_epipolar_correction_removes_the_depth_bias_of_small_parallax():
    # a small sideways baseline: 1-4 px of parallax, 0.5 px of flow noise on the second point;
    # the mid-point reads the noise across the line as ray angle and shortens the depths
    R = np.eye(3)
    t = np.array([-0.05, 0.0, 0.0])
    pts1, pts2, X1, _, _ = two_view_scene(n=4000, R=R, t=t, seed=4, depth=(8.0, 20.0))
    rng = np.random.default_rng(4)
    noisy = pts2 + rng.normal(0, 0.5, pts2.shape)
    F = fundamental_from_pose(R, t, K_TEST)
    X_raw, ok_raw, _ = triangulate_midpoint(pts1, noisy, K_TEST, R, t, min_angle=0.0)
    X_cor, ok_cor, _ = triangulate_midpoint(pts1, project_to_epipolar_line(F, pts1, noisy), K_TEST, R, t,
                                            min_angle=0.0)
    bias_raw = np.median(np.log(X_raw[ok_raw, 2] / X1[ok_raw, 2]))
    bias_cor = np.median(np.log(X_cor[ok_cor, 2] / X1[ok_cor, 2]))
    assert bias_raw < -0.05  # the uncorrected median depth is more than 5 % short
    assert abs(bias_cor) < 0.03
