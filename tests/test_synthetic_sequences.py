"""The synthetic sequence renderer (``tests/synthetic_sequences.py``) gives the known answers.

Known answers first: a 3-D point of a rectangle is drawn at the pixel it projects to with
the texture's value at that point; a near rectangle hides a far one; the dense flow DIS
measures between two rendered frames is the flow the known poses and depths predict;
the files written are read back by the tool's own readers as written; a camera that does
not move gives identical frames and the tool calls them ``identity``. Small images (at
most 128x384) and few frames keep the whole file to a few seconds.
"""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from synthetic_sequences import (
    Scene,
    SCENARIOS,
    handheld_indoor,
    intrinsics,
    make_rect,
    make_sequence,
    pose,
    predicted_flow,
    render,
    rot_x,
    rot_y,
    static,
    urban_turn,
    write_kitti_sequence,
)
from trianflow_vo.cli.main import main
from trianflow_vo.config import Config, merge_dict
from trianflow_vo.eval import load_ground_truth
from trianflow_vo.flow.dis import DisFlow
from trianflow_vo.frame import Branch
from trianflow_vo.io.sequence import open_sequence
from trianflow_vo.io.trajectory import read_trajectory

SIZE = (96, 320)
K = intrinsics(300.0, 300.0, 159.5, 47.5)
BRANCHES = {b.value for b in Branch}


def _texture_rect(rng, texel=0.05, shape=(40, 60), R=np.eye(3)):
    """A rectangle with a white-noise texture (every texel independent: a wrong texel or a
    half-texel shift shows), axes ``R``'s first two columns."""
    tex = rng.uniform(0.05, 0.95, shape).astype(np.float32)
    rect = make_rect(np.zeros(3), R[:, 0], R[:, 1], ((shape[1] - 1) * texel, (shape[0] - 1) * texel), texel,
                     texture=tex)
    return rect, tex


def _bilinear(tex, x, y):
    i, j = int(math.floor(x)), int(math.floor(y))
    fx, fy = x - i, y - j
    return ((1 - fx) * (1 - fy) * tex[j, i] + fx * (1 - fy) * tex[j, i + 1]
            + (1 - fx) * fy * tex[j + 1, i] + fx * fy * tex[j + 1, i + 1])


def test_a_point_of_a_rectangle_is_drawn_where_it_projects_with_its_texture_value():
    """Camera placed so that the known point X = rect(a, b) lies on the ray of an integer
    pixel: that pixel shows the texture at (a, b): texel centres exactly, between texels
    the bilinear value. Incidence under 33 degrees and footprint under a texel: level 0,
    one tap (see ``_shade``), so no filtering is involved."""
    rng = np.random.default_rng(0)
    R_rect = rot_y(0.4) @ rot_x(-0.3)  # an oblique rectangle
    rect, tex = _texture_rect(rng, R=R_rect)
    scene = Scene([rect], background=0.0)
    R_cam = rot_y(0.2) @ rot_x(-0.1)
    errs, neighbour_gaps = [], []
    for k in range(24):
        if k % 2 == 0:  # a texel centre
            i, j = int(rng.integers(2, tex.shape[1] - 2)), int(rng.integers(2, tex.shape[0] - 2))
            a, b = i * rect.texel, j * rect.texel
            expected = tex[j, i]
            neighbour_gaps.append(min(abs(tex[j, i] - tex[j, i + 1]), abs(tex[j, i] - tex[j + 1, i])))
        else:  # between texels
            x, y = rng.uniform(2, tex.shape[1] - 3), rng.uniform(2, tex.shape[0] - 3)
            a, b = x * rect.texel, y * rect.texel
            expected = _bilinear(tex, x, y)
        X = rect.point(a, b)
        while True:  # a pixel whose ray meets the rectangle within 33 degrees of its normal
            px = np.array([rng.integers(10, SIZE[1] - 10), rng.integers(10, SIZE[0] - 10), 1.0])
            ray = R_cam @ np.linalg.solve(K, px)
            if abs(ray @ rect.normal) / np.linalg.norm(ray) > math.cos(math.radians(33)):
                break
        z = rng.uniform(2.0, 4.0)
        c = X - z * ray  # the pixel's ray meets X at depth z
        img, aux = render(scene, pose(R_cam, c), K, SIZE, as_float=True, aux=True)
        u, v = int(px[0]), int(px[1])
        assert aux.rect_id[v, u] == 0
        assert aux.depth[v, u] == pytest.approx(z, rel=1e-5)
        assert aux.level[v, u] == 0.0
        errs.append(abs(float(img[v, u]) - float(expected)))
    # uint16 texture storage: 1/65535 per value; float32 ray arithmetic: ~1e-6 m
    assert max(errs) < 3e-5, errs
    # the check can fail: a neighbouring texel (a one-texel or half-texel slip) differs by far more
    assert np.median(neighbour_gaps) > 0.05


def test_a_near_rectangle_hides_a_far_one_whatever_their_order():
    ex, ey = np.eye(3)[0], np.eye(3)[1]
    far = make_rect((-20.0, -20.0, 20.0), ex, ey, (40.0, 40.0), 1.0, texture=np.full((41, 41), 0.2))
    near = make_rect((-0.5, -0.2, 5.0), ex, ey, (1.0, 0.4), 0.1, texture=np.full((5, 11), 0.9))
    behind = make_rect((-50.0, -50.0, -3.0), ex, ey, (100.0, 100.0), 1.0, texture=np.full((101, 101), 0.5))
    T = np.eye(4)
    img, aux = render(Scene([far, near, behind]), T, K, SIZE, as_float=True, aux=True)
    img2 = render(Scene([behind, near, far]), T, K, SIZE, as_float=True)
    np.testing.assert_array_equal(img, img2)
    # the near rectangle's image: x in [cx - f 0.5/5, cx + f 0.5/5], y in [cy - f 0.2/5, cy + f 0.2/5]
    gx, gy = np.meshgrid(np.arange(SIZE[1]), np.arange(SIZE[0]))
    inside = (np.abs(gx - K[0, 2]) < 300 * 0.5 / 5 - 0.5) & (np.abs(gy - K[1, 2]) < 300 * 0.2 / 5 - 0.5)
    outside = (np.abs(gx - K[0, 2]) > 300 * 0.5 / 5 + 0.5) | (np.abs(gy - K[1, 2]) > 300 * 0.2 / 5 + 0.5)
    assert inside.sum() > 200
    np.testing.assert_allclose(img[inside], 0.9, atol=1e-4)
    np.testing.assert_allclose(aux.depth[inside], 5.0, rtol=1e-5)
    np.testing.assert_allclose(img[outside], 0.2, atol=1e-4)
    np.testing.assert_allclose(aux.depth[outside], 20.0, rtol=1e-5)
    assert not (aux.rect_id == 2).any()  # behind the camera: never drawn
    # seen from behind the far wall looking back (+z -> -z), the near one is now behind the far one
    back = pose(rot_y(math.pi), np.array([0.0, 0.0, 30.0]))
    img3, aux3 = render(Scene([near, far]), back, K, SIZE, as_float=True, aux=True)
    np.testing.assert_allclose(img3, 0.2, atol=1e-4)
    np.testing.assert_allclose(aux3.depth, 10.0, rtol=1e-4)


def _flow_errors(seq, i, j, margin=8):
    """DIS (the tool's default flow) from frame i to j vs the flow of the known geometry,
    on pixels that stay visible (same rectangle at the predicted depth in frame j), away
    from object boundaries and the image border. Returns (EPE per pixel, fraction used)."""
    a, A = render(seq.scene, seq.poses[i], seq.K, seq.size, aux=True)
    b, B = render(seq.scene, seq.poses[j], seq.K, seq.size, aux=True)
    dis = DisFlow("medium")
    fw, _ = dis.flow_pair(dis.prepare(a), dis.prepare(b))
    pf, zb = predicted_flow(A.depth, seq.K, seq.poses[i], seq.poses[j])
    return _masked_epe(fw, pf, zb, A, B, margin)


def _masked_epe(fw, pf, zb, A, B, margin):
    h, w = A.depth.shape
    gx, gy = np.meshgrid(np.arange(w), np.arange(h))
    u, v = gx + pf[..., 0], gy + pf[..., 1]
    finite = np.isfinite(u) & np.isfinite(v)
    u, v = np.where(finite, u, -1e3), np.where(finite, v, -1e3)
    inside = (u >= margin) & (u <= w - 1 - margin) & (v >= margin) & (v <= h - 1 - margin) & (A.rect_id >= 0)
    ui, vi = np.clip(np.rint(u), 0, w - 1).astype(int), np.clip(np.rint(v), 0, h - 1).astype(int)
    with np.errstate(invalid="ignore"):
        visible = inside & (np.abs(B.depth[vi, ui] - zb) < 0.02 * zb) & (B.rect_id[vi, ui] == A.rect_id)
    ids = A.rect_id.astype(np.float32)
    boundary = cv2.dilate(ids, np.ones((9, 9))) != cv2.erode(ids, np.ones((9, 9)))
    m = visible & ~boundary
    return np.linalg.norm(fw - np.nan_to_num(pf), axis=-1)[m], float(m.mean())


@pytest.mark.parametrize("make, i, j, med_px, p90_px", [
    # street, 1 m forward and a little yaw: flow 0-25 px at 128x384
    (lambda: urban_turn(n_frames=4, size=(128, 384)), 0, 1, 0.2, 0.75),
    # room, 3 frames of hand-held motion (~2 cm): flow ~3 px at 120x160
    (lambda: handheld_indoor(n_frames=4, size=(120, 160)), 0, 3, 0.2, 0.5),
])
def test_dense_flow_of_two_rendered_frames_is_the_flow_of_the_known_geometry(make, i, j, med_px, p90_px):
    """Measured here: urban median 0.09 px, 90th percentile 0.42 px; room 0.06 / 0.13 px
    (at 240x320). Bounds about twice that. A wrong pose (frame j + 1 as the target)
    breaks them: the test can fail."""
    seq = make()
    epe, frac = _flow_errors(seq, i, j)
    assert frac > 0.4
    assert np.median(epe) < med_px, np.median(epe)
    assert np.percentile(epe, 90) < p90_px, np.percentile(epe, 90)
    # negative control: the same flow against the geometry of another frame
    a, A = render(seq.scene, seq.poses[i], seq.K, seq.size, aux=True)
    b, B = render(seq.scene, seq.poses[j], seq.K, seq.size, aux=True)
    dis = DisFlow("medium")
    fw, _ = dis.flow_pair(dis.prepare(a), dis.prepare(b))
    wrong = seq.poses[j] @ pose(rot_y(math.radians(0.5)), np.array([0.05, 0.0, 0.05]))
    pf, zb = predicted_flow(A.depth, seq.K, seq.poses[i], wrong)
    epe_wrong, _ = _masked_epe(fw, pf, zb, A, B, 8)
    assert np.median(epe_wrong) > 2 * med_px


def test_kitti_folder_is_read_back_by_the_tool_as_written(tmp_path):
    seq = make_sequence("urban_turn", tmp_path / "seq", n_frames=5, size=SIZE, seed=3)
    folder = tmp_path / "seq"
    gt = load_ground_truth(folder / "poses.txt")
    assert gt.kind == "kitti"
    np.testing.assert_allclose(gt.poses, seq.poses, atol=1e-10)
    np.testing.assert_allclose(gt.poses[0], np.eye(4), atol=1e-12)
    np.testing.assert_array_equal(gt.frames, np.arange(5))
    s = open_sequence(folder)
    assert len(s) == 5 and s.kind == "kitti" and tuple(s.image_size) == SIZE
    np.testing.assert_allclose(s.K, seq.K, atol=1e-9)
    assert s.timestamp(3) == pytest.approx(3 / seq.fps)
    for i in (0, 4):
        np.testing.assert_array_equal(cv2.imread(str(folder / "image_0" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED),
                                      seq.render(i))
    meta = json.loads((folder / "scenario.json").read_text())
    assert meta["n_frames"] == 5 and meta["allowed_branches"] == ["two-view", "pnp"]
    # a first pose that is not the identity, BGR images: written and read back as they are
    T = pose(rot_y(0.3) @ rot_x(0.1), np.array([10.0, -2.0, 5.0]))
    poses = np.einsum("ij,njk->nik", T, seq.poses)
    bgr = [cv2.cvtColor(seq.render(i), cv2.COLOR_GRAY2BGR) for i in range(5)]
    write_kitti_sequence(tmp_path / "moved", bgr, poses, seq.K, times=[0.5 * i for i in range(5)])
    np.testing.assert_allclose(read_trajectory(tmp_path / "moved" / "poses.txt").poses, poses, atol=1e-9)
    assert open_sequence(tmp_path / "moved").timestamp(2) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="4 images for 5 poses"):
        write_kitti_sequence(tmp_path / "short", bgr[:4], poses, seq.K)


def test_scenarios_are_deterministic_and_seeded():
    a = urban_turn(n_frames=3, size=SIZE, seed=1)
    b = urban_turn(n_frames=3, size=SIZE, seed=1)
    c = urban_turn(n_frames=3, size=SIZE, seed=2)
    np.testing.assert_array_equal(a.render(2), b.render(2))
    assert np.abs(a.render(2).astype(int) - c.render(2).astype(int)).mean() > 5
    for name, make in SCENARIOS.items():
        assert set(make.__code__.co_varnames) >= {"n_frames", "seed", "size"}, name


def test_a_static_camera_renders_identical_frames_and_noise_is_per_frame():
    seq = static(n_frames=3, size=SIZE)
    np.testing.assert_array_equal(seq.poses[1], seq.poses[0])
    f0, f1 = seq.render(0), seq.render(2)
    np.testing.assert_array_equal(f0, f1)
    assert f0.std() > 20  # textured, not blank
    noisy = static(n_frames=3, size=SIZE, noise_std=2.0)
    n0, n1 = noisy.render(0), noisy.render(1)
    d = n0.astype(float) - n1.astype(float)
    assert 2.0 < d.std() < 3.6  # two independent draws of sigma 2 (rounded): std ~2.8
    np.testing.assert_array_equal(noisy.render(1), n1)  # and reproducible


def test_trianflow_vo_run_on_a_static_clip_reports_identity(tmp_path):
    make_sequence("static", tmp_path / "seq", n_frames=5, size=(128, 384))
    out = tmp_path / "run"
    res = CliRunner().invoke(main, ["run", str(tmp_path / "seq"), "--out", str(out), "--quiet", "--no-plot",
                                    "--threads", "1"])
    assert res.exit_code == 0, res.output
    rows = [ln.split("\t") for ln in (out / "frames.tsv").read_text().splitlines()]
    col = rows[0].index("branch")
    assert [r[col] for r in rows[1:]] == ["init"] + ["identity"] * 4
    summary = json.loads((out / "run.json").read_text())
    assert summary["branch_counts"]["identity"] == 4
    np.testing.assert_allclose(read_trajectory(out / "poses.txt").poses, np.tile(np.eye(4), (5, 1, 1)), atol=1e-12)


def test_a_short_highway_clip_runs_through_the_pipeline(tmp_path):
    from trianflow_vo.pipeline import run

    seq = make_sequence("highway", tmp_path / "seq", n_frames=6, size=(128, 384))
    cfg = merge_dict(Config(), {"runtime": {"threads": 1}, "output": {"plot": False}}, "test")
    summary = run(tmp_path / "seq", tmp_path / "run", cfg)
    assert summary["status"] == "completed"
    assert summary["frames_processed"] == len(seq) == 6
    assert set(summary["branch_counts"]) <= BRANCHES
    assert sum(summary["branch_counts"].values()) == 6
    poses = read_trajectory(tmp_path / "run" / "poses.txt").poses
    assert poses.shape == (6, 4, 4) and np.isfinite(poses).all()
