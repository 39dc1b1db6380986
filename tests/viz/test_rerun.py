"""Rerun recording: flow colours, depth quantisation, what a recording contains, its size,
and that runs without rerun flags never import rerun."""

from __future__ import annotations

import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np
import pytest

from trianflow_vo.backend import RevisedPoses
from trianflow_vo.errors import DependencyError, InputError, VOError
from trianflow_vo.frame import Branch, FrameResult, FrameStats, FrameView
from trianflow_vo.viz.flow_color import flow_to_rgb
from trianflow_vo.viz.rerun_logger import BRANCH_CODES, RerunObserver, quantize_depth

REPO = Path(__file__).resolve().parents[2]

rr = pytest.importorskip("rerun")


# -- helpers ------------------------------------------------------------------------


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def pose(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def synthetic_records(n=10, h=64, w=192, seed=0, n_matches=800, n_points=1500, skip_points_at=(), ref_step=1):
    """``n`` frames of a camera driving forward and turning slowly, with all fields set."""
    rng = np.random.default_rng(seed)
    K = np.array([[100.0, 0, w / 2], [0, 100.0, h / 2], [0, 0, 1]])
    out = []
    for i in range(n):
        T = pose(rot_y(0.05 * i), [0.05 * i * i, 0.01 * i, 1.0 * i])  # a curve, not a line
        img = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
        ref = (i // ref_step) * ref_step if i else 0
        depth = rng.uniform(2, 30, (h, w)).astype(np.float32)
        depth[:4] = 0  # unknown rows
        flow = rng.normal(0, 2, (h, w, 2)).astype(np.float32)
        pr = rng.uniform([0, 0], [w, h], (n_matches, 2))
        pc = pr + rng.normal(0, 2, pr.shape)
        pts = None if i in skip_points_at else rng.normal([0, 0, 10 + i], [3, 1, 3], (n_points, 3))
        cols = None if pts is None else rng.integers(0, 255, (n_points, 3), dtype=np.uint8)
        branch = Branch.INIT if i == 0 else (Branch.FAILED if i == 5 else Branch.TWO_VIEW)
        out.append(
            FrameResult(
                line=i, frame_index=10 + i, timestamp=0.1 * i, T_world_cam=T, branch=branch,
                reason="too few inliers" if i == 5 else "",
                ref_index=10 + ref, T_ref_cam=np.eye(4), is_keyframe=branch is Branch.TWO_VIEW, K=K,
                # pnp_ratio NaN (not finite) and scale_points None (not measured) must not be logged
                stats=FrameStats(inliers=100 + i, scale=1.5, mean_flow_px=2.0 + i, parallax_px=0.5,
                                 pnp_ratio=float("nan"), ms={"flow": 7.0, "pose": 2.0 + i}),
                view=FrameView.of(image=img, depth=depth, flow=flow, pts_ref=pr, pts_cur=pc,
                                  points_world=pts, point_colors=cols),
            )
        )
    return out


def minimal_result(i: int, T=None) -> FrameResult:
    """A result with nothing to draw: no view, no K, no statistics."""
    return FrameResult(line=i, frame_index=i, timestamp=None, T_world_cam=np.eye(4) if T is None else T,
                       branch=Branch.IDENTITY, reason="", ref_index=0, T_ref_cam=np.eye(4), is_keyframe=False,
                       K=None, stats=FrameStats())


def write(path, records, **kw) -> Path:
    obs = RerunObserver(path, **kw)
    for r in records:
        obs.on_frame(r)
    obs.close()
    return Path(path)


def read_recording(path) -> dict:
    """``{(entity, component): [(frame or None, value), ...]}`` of every non-null cell."""
    from rerun.chunk import RrdReader

    rows = defaultdict(list)
    for chunk in RrdReader(str(path)).store().stream().collect().stream():
        batch = chunk.to_record_batch()
        names = batch.schema.names
        frames = batch.column("frame").to_pylist() if "frame" in names else [None] * batch.num_rows
        for name in names:
            if ":" not in name:
                continue
            for f, v in zip(frames, batch.column(name).to_pylist()):
                if v is not None:
                    rows[(chunk.entity_path, name)].append((f, v))
    for k in rows:
        rows[k].sort(key=lambda fv: -1 if fv[0] is None else fv[0])
    return rows


def rerun_cli(*args, timeout=60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rerun", *args], capture_output=True, text=True, timeout=timeout)


# -- flow colours and depth quantisation ---------------------------------------------


def test_flow_colours_follow_direction_and_magnitude():
    f = np.zeros((2, 4, 2), np.float32)
    f[0, 0] = (2, 0)  # +x: red
    f[0, 1] = (-2, 0)  # -x: cyan
    f[0, 2] = (0, 2)  # +y (down): hue 90 deg
    f[0, 3] = (0, -2)  # -y (up): hue 270 deg
    f[1, 0] = (1, 0)  # half the largest magnitude: half saturated red
    f[1, 1] = (np.nan, 0)
    rgb, m = flow_to_rgb(f)
    assert m == 2.0
    assert rgb.dtype == np.uint8 and rgb.shape == (2, 4, 3)
    assert rgb[0, 0].tolist() == [255, 0, 0]
    assert rgb[0, 1].tolist() == [0, 255, 255]
    assert rgb[0, 2].tolist() == [128, 255, 0] or rgb[0, 2].tolist() == [127, 255, 0]
    assert rgb[0, 3].tolist() == [128, 0, 255] or rgb[0, 3].tolist() == [127, 0, 255]
    assert rgb[1, 0].tolist() == [255, 128, 128] or rgb[1, 0].tolist() == [255, 127, 127]
    assert rgb[1, 1].tolist() == [0, 0, 0]  # non-finite: black
    assert rgb[1, 2].tolist() == [255, 255, 255]  # zero flow: white
    # a fixed scale saturates everything above it
    rgb2, m2 = flow_to_rgb(f, max_magnitude=1.0)
    assert m2 == 1.0 and rgb2[1, 0].tolist() == [255, 0, 0]


def test_flow_colours_reject_bad_shape():
    with pytest.raises(ValueError, match=r"\(h, w, 2\)"):
        flow_to_rgb(np.zeros((4, 4, 3)))


def test_quantize_depth_round_trip():
    d = np.array([[0.0, 1.0, 2.5], [80.0, np.nan, -1.0]], np.float32)
    q, meter = quantize_depth(d)
    assert q.dtype == np.uint16
    assert q[1, 0] == 65535
    assert q[0, 0] == 0 and q[1, 1] == 0 and q[1, 2] == 0  # unknown stays unknown
    known = np.array([[False, True, True], [True, False, False]])
    np.testing.assert_allclose(q[known] / meter, d[known], atol=0.5 * 80 / 65535 + 1e-6)
    q0, m0 = quantize_depth(np.zeros((3, 3), np.float32))
    assert not q0.any() and m0 == 1.0


# -- constructor errors ---------------------------------------------------------------


def test_needs_a_sink():
    with pytest.raises(ValueError, match="path, spawn"):
        RerunObserver()


def test_spawn_without_display_is_a_clear_error(monkeypatch):
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(VOError, match="no display"):
        RerunObserver(spawn=True)


def test_missing_rerun_is_a_dependency_error(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "rerun", None)  # makes `import rerun` raise ImportError
    with pytest.raises(DependencyError, match=r"pip install"):
        RerunObserver(tmp_path / "out.rrd")


def test_unwritable_path_names_the_file(tmp_path):
    blocker = tmp_path / "afile"
    blocker.write_text("x")
    with pytest.raises(InputError, match="afile"):
        RerunObserver(blocker / "out.rrd")


def test_bad_ground_truth_shape(tmp_path):
    with pytest.raises(ValueError, match=r"\(N, 4, 4\)"):
        RerunObserver(tmp_path / "o.rrd", gt_T_world_cam=np.zeros((3, 3, 4)))
    with pytest.raises(ValueError, match="gt_frames"):
        RerunObserver(tmp_path / "o.rrd", gt_T_world_cam=np.stack([np.eye(4)] * 3), gt_frames=[0, 1])


# -- what a recording contains ---------------------------------------------------------


@pytest.fixture(scope="module")
def synthetic_recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("rrd") / "sub" / "out.rrd"  # folder created on demand
    records = synthetic_records(n=10, skip_points_at=(5,), ref_step=3)
    write(path, records, max_matches=500, max_points=1000)
    return path, records


def test_recording_verifies_with_rerun_cli(synthetic_recording):
    path, _ = synthetic_recording
    res = rerun_cli("rrd", "verify", str(path))
    assert res.returncode == 0, res.stderr[-2000:]
    assert "verified without error" in res.stdout + res.stderr


def test_recording_has_one_row_per_frame_per_entity(synthetic_recording):
    from rerun.chunk import RrdReader

    path, records = synthetic_recording
    reader = RrdReader(str(path))
    assert len(reader.recordings()) == 1 and len(reader.blueprints()) == 1  # the default layout
    rows = read_recording(path)
    n = len(records)
    frames = [r.frame_index for r in records]

    def frames_of(entity, component):
        return [f for f, _ in rows[(entity, component)]]

    assert frames_of("/world/camera", "Transform3D:translation") == frames
    assert frames_of("/world/camera/image", "EncodedImage:blob") == frames
    assert frames_of("/world/camera/image", "Pinhole:image_from_camera") == [frames[0]]  # K never changes
    assert frames_of("/reference/flow", "EncodedImage:blob") == frames
    assert frames_of("/world/trajectory", "LineStrips3D:strips") == frames
    assert frames_of("/log", "TextLog:text") == frames
    for name in ("inliers", "scale", "mean_flow_px", "parallax_px", "ms/flow", "ms/pose", "branch"):
        assert frames_of(f"/stats/{name}", "Scalars:scalars") == frames, name
    assert ("/stats/scale_points", "Scalars:scalars") not in rows  # not measured (None)
    assert ("/stats/pnp_ratio", "Scalars:scalars") not in rows  # not finite
    # depth only when the reference frame changes (references 10, 13, 16, 19; frame 1 keeps 10)
    assert frames_of("/reference/depth", "DepthImage:buffer") == [10, 13, 16, 19]
    # points of frame 5 are missing: cleared there, logged elsewhere
    assert frames_of("/world/points", "Points3D:positions") == [f for f in frames if f != 15]
    assert 15 in frames_of("/world/points", "Clear:is_recursive")
    # static declarations
    assert frames_of("/world/camera", "ViewCoordinates:xyz") == [None]
    assert frames_of("/world", "ViewCoordinates:xyz") == [None]
    assert len(rows[("/world/camera/image/matches", "LineStrips2D:strips")]) == n


def test_recording_values(synthetic_recording):
    path, records = synthetic_recording
    rows = read_recording(path)
    for (f, t), (_, m), r in zip(
        rows[("/world/camera", "Transform3D:translation")], rows[("/world/camera", "Transform3D:mat3x3")], records
    ):
        assert f == r.frame_index
        np.testing.assert_allclose(t[0], r.T_world_cam[:3, 3], atol=1e-5)
        # rerun stores mat3x3 column-major
        np.testing.assert_allclose(np.array(m[0]).reshape(3, 3).T, r.T_world_cam[:3, :3], atol=1e-6)
    assert rows[("/world/camera", "Transform3D:relation")][0][1] == [rr.TransformRelation.ParentFromChild.value]
    # trajectory so far: frame k has k + 1 positions, the last one the current pose
    for k, (f, strips) in enumerate(rows[("/world/trajectory", "LineStrips3D:strips")]):
        assert len(strips) == 1 and len(strips[0]) == k + 1
        np.testing.assert_allclose(strips[0][-1], records[k].T_world_cam[:3, 3], atol=1e-5)
    # subsampled to the bounds
    for _, strips in rows[("/world/camera/image/matches", "LineStrips2D:strips")]:
        assert len(strips) == 500 and all(len(s) == 2 for s in strips)
    for _, pts in rows[("/world/points", "Points3D:positions")]:
        assert len(pts) == 1000
    branch = [v[0] for _, v in rows[("/stats/branch", "Scalars:scalars")]]
    assert branch == [BRANCH_CODES[r.branch.value] for r in records]
    inliers = [v[0] for _, v in rows[("/stats/inliers", "Scalars:scalars")]]
    assert inliers == [r.stats.inliers for r in records]
    pose_ms = [v[0] for _, v in rows[("/stats/ms/pose", "Scalars:scalars")]]
    assert pose_ms == [r.stats.ms["pose"] for r in records]
    flow_px = [v[0] for _, v in rows[("/stats/mean_flow_px", "Scalars:scalars")]]
    assert flow_px == [r.stats.mean_flow_px for r in records]
    texts = dict(rows[("/log", "TextLog:text")])
    levels = dict(rows[("/log", "TextLog:level")])
    assert "failed" in texts[15][0] and "too few inliers" in texts[15][0] and levels[15] == ["WARN"]
    assert levels[11] == ["INFO"]
    # the image decodes to the logged size
    blob = bytes(rows[("/world/camera/image", "EncodedImage:blob")][0][1][0])
    assert cv2.imdecode(np.frombuffer(blob, np.uint8), cv2.IMREAD_COLOR).shape == records[0].view.image.shape
    # the depth is the reference depth subsampled by 4 and quantised
    buf = rows[("/reference/depth", "DepthImage:buffer")][0][1][0]
    fmt = rows[("/reference/depth", "DepthImage:format")][0][1][0]
    meter = rows[("/reference/depth", "DepthImage:meter")][0][1][0]
    d = np.frombuffer(bytes(buf), np.uint16).reshape(fmt["height"], fmt["width"]) / meter
    np.testing.assert_allclose(d, records[0].view.depth[::4, ::4], atol=1e-3)


def test_revised_poses_relog_the_trajectory(tmp_path):
    records = synthetic_records(n=6, n_matches=10, n_points=10)
    obs = RerunObserver(tmp_path / "rev.rrd")
    for r in records:
        obs.on_frame(r)
    shift = np.array([0.5, -1.0, 2.0])
    lines = np.array([1, 2])
    moved = np.stack([records[i].T_world_cam for i in lines])
    moved[:, :3, 3] += shift
    obs.on_poses_revised(RevisedPoses(lines, np.array([11, 12]), moved, revision=1, reason="test revision"))
    obs.close()
    rows = read_recording(tmp_path / "rev.rrd")
    strips = rows[("/world/trajectory", "LineStrips3D:strips")]
    assert len(strips) == len(records) + 1  # one per frame, and once more after the revision
    f, last = strips[-1]
    assert f == records[-1].frame_index  # logged at the current frame
    expect = np.stack([r.T_world_cam[:3, 3] for r in records])
    expect[lines] += shift
    np.testing.assert_allclose(np.array(last[0]), expect, atol=1e-5)
    texts = [v[0] for _, v in rows[("/log", "TextLog:text")]]
    assert any("poses revised (2 frames): test revision" in t for t in texts)
    assert rerun_cli("rrd", "verify", str(tmp_path / "rev.rrd")).returncode == 0


def test_ground_truth_is_aligned_into_the_estimate_frame(tmp_path):
    records = synthetic_records(n=12, n_matches=10, n_points=10)
    # ground truth = estimate seen through a known similarity, with one extra frame each side
    R_s, t_s, s = rot_y(0.7) @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]]), np.array([5.0, -2.0, 3.0]), 2.5
    est = np.stack([r.T_world_cam for r in records])
    extra_before = pose(rot_y(-0.1), [-1.0, 0, -1.0])
    extra_after = pose(np.eye(3), [9.0, 9.0, 99.0])
    gt_est_frame = np.concatenate([extra_before[None], est, extra_after[None]])
    # the same camera path in another world: rotated, moved and in other units
    gt = np.stack([pose(R_s @ T[:3, :3], s * R_s @ T[:3, 3] + t_s) for T in gt_est_frame])
    gt_frames = np.arange(9, 9 + len(gt))  # frame 9 .. 22 ; estimate frames 10 .. 21
    path = write(tmp_path / "gt.rrd", records, gt_T_world_cam=gt, gt_frames=gt_frames, gt_every=5)
    rows = read_recording(path)
    logged = rows[("/world/ground_truth", "LineStrips3D:strips")]
    # every 5 frames (frames 14, 19) and at close (frame 21)
    assert [f for f, _ in logged] == [14, 19, 21]
    f, strips = logged[-1]
    p = np.array(strips[0])
    # ground truth up to the last estimated frame (9 .. 21), mapped back onto the estimate
    assert p.shape == (13, 3)
    np.testing.assert_allclose(p[1:], est[:, :3, 3], atol=1e-4)
    np.testing.assert_allclose(p[0], extra_before[:3, 3], atol=1e-4)
    res = rerun_cli("rrd", "verify", str(path))
    assert res.returncode == 0, res.stderr[-2000:]


def test_interrupted_close_is_logged_and_idempotent(tmp_path):
    obs = RerunObserver(tmp_path / "i.rrd")
    for r in synthetic_records(n=2):
        obs.on_frame(r)
    obs.close(interrupted=True)
    obs.close()
    with pytest.raises(RuntimeError):
        obs.on_frame(synthetic_records(n=1)[0])
    texts = [v[0] for _, v in read_recording(tmp_path / "i.rrd")[("/log", "TextLog:text")]]
    assert texts[-1] == "run interrupted after 2 frames"


def test_minimal_records_without_optional_fields(tmp_path):
    obs = RerunObserver(tmp_path / "m.rrd")
    for i in range(3):
        obs.on_frame(minimal_result(i))
    obs.close()
    rows = read_recording(tmp_path / "m.rrd")
    assert len(rows[("/world/camera", "Transform3D:translation")]) == 3
    assert ("/world/camera/image", "EncodedImage:blob") not in rows
    assert rerun_cli("rrd", "verify", str(tmp_path / "m.rrd")).returncode == 0


# -- size -------------------------------------------------------------------------------


def realistic_records(sample_dir: Path, n: int, h=256, w=832):
    """Real KITTI frames at working size, with smooth depth, radial flow, 3000 matches and
    5000 points per frame, each frame its own reference (depth logged every frame)."""
    rng = np.random.default_rng(1)
    files = sorted((sample_dir / "image_0").iterdir())
    files = [files[i % len(files)] for i in range(n)]
    K = np.array([[482.0, 0, 407.0], [0, 489.0, 126.0], [0, 0, 1]])
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    ground = np.where(yy > 128, 1.65 * 489 / np.maximum(yy - 126, 1.0), 40.0).clip(0, 80)
    out = []
    for i, f in enumerate(files):
        img = cv2.resize(cv2.imread(str(f), cv2.IMREAD_COLOR), (w, h), interpolation=cv2.INTER_AREA)
        bumps = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), 8)
        depth = (ground * (1 + 0.05 * bumps / bumps.std())).astype(np.float32)
        flow = np.stack([(xx - 407) / depth, (yy - 126) / depth], -1).astype(np.float32)
        pr = rng.uniform([0, 0], [w, h], (3000, 2))
        out.append(
            FrameResult(
                line=i, frame_index=i, timestamp=0.1 * i, T_world_cam=pose(np.eye(3), [0, 0, i]),
                branch=Branch.TWO_VIEW, reason="", ref_index=i, T_ref_cam=np.eye(4), is_keyframe=True, K=K,
                stats=FrameStats(inliers=2000, scale=1.0, mean_flow_px=5.0, parallax_px=1.0, frame_ms=90.0),
                view=FrameView.of(image=img, depth=depth, flow=flow, pts_ref=pr, pts_cur=pr + 1.0,
                                  points_world=rng.normal([0, 0, 20 + i], [5, 1, 5], (5000, 3)),
                                  point_colors=rng.integers(0, 255, (5000, 3), dtype=np.uint8)),
            )
        )
    return out


BYTES_PER_FRAME_BOUND = 130_000  # measured ~97 KB per frame at 256x832 (depth on every frame)


def test_recording_size_per_frame_is_bounded(tmp_path, sample_seq):
    n = 20
    path = write(tmp_path / "big.rrd", realistic_records(sample_seq, n))
    per_frame = path.stat().st_size / n
    print(f"recording size: {per_frame:.0f} bytes per frame at 256x832")
    assert 20_000 < per_frame < BYTES_PER_FRAME_BOUND


# -- rerun stays off the default path -------------------------------------------------------


def test_default_path_never_imports_rerun():
    mods = ["trianflow_vo.cli.main", "trianflow_vo.cli.run_cmd", "trianflow_vo.cli.logs", "trianflow_vo.config",
            "trianflow_vo.frame", "trianflow_vo.keyframe", "trianflow_vo.observer", "trianflow_vo.backend",
            "trianflow_vo.runlog", "trianflow_vo.frontend", "trianflow_vo.odometry", "trianflow_vo.pipeline",
            "trianflow_vo.depth.triangulated", "trianflow_vo.depth.network", "trianflow_vo.io.run_writer",
            "trianflow_vo.baseline.sparse", "trianflow_vo.viz.rerun_logger", "trianflow_vo.viz.plot",
            "trianflow_vo.viz.flow_color"]
    code = (
        "import sys, importlib\n"
        f"for m in {mods!r}: importlib.import_module(m)\n"
        "from click.testing import CliRunner\n"
        "import trianflow_vo.cli.main\n"
        "res = CliRunner().invoke(trianflow_vo.cli.main.main, ['--help'])\n"
        "assert res.exit_code == 0, res.output\n"
        "res = CliRunner().invoke(trianflow_vo.cli.main.main, ['run', '--help'])\n"
        "assert res.exit_code == 0, res.output\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('rerun', 'rerun_bindings', 'matplotlib'))\n"
        "assert not bad, bad\n"
        "print('ok')\n"
    )
    res = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and "ok" in res.stdout, res.stdout + res.stderr


# -- end to end on the shipped sample ----------------------------------------------------------


def check_run_recording(rrd: Path, n_frames: int) -> dict:
    res = rerun_cli("rrd", "verify", str(rrd))
    assert res.returncode == 0, res.stderr[-2000:]
    rows = read_recording(rrd)
    frames = list(range(n_frames))
    for key in [("/world/camera", "Transform3D:translation"), ("/world/camera/image", "EncodedImage:blob"),
                ("/stats/branch", "Scalars:scalars")]:
        assert [f for f, _ in rows[key]] == frames, key
    # the trajectory and the log line on every frame, and again at a frame whose keyframes the back-end revised
    for key in [("/world/trajectory", "LineStrips3D:strips"), ("/log", "TextLog:text")]:
        logged = [f for f, _ in rows[key]]
        assert sorted(set(logged)) == frames and logged == sorted(logged), key
    # every frame after the first has a two-view/PnP result on the sample: flow, matches, inlier count
    for key in [("/reference/flow", "EncodedImage:blob"), ("/world/camera/image/matches", "LineStrips2D:strips"),
                ("/stats/inliers", "Scalars:scalars")]:
        assert [f for f, _ in rows[key]] == frames[1:], key
    assert rows[("/world/camera/image", "Pinhole:resolution")][0][1] == [[832.0, 256.0]]
    return rows


def test_pipeline_writes_a_recording_with_ground_truth(tmp_path, sample_seq):
    from trianflow_vo.config import Config, merge_dict
    from trianflow_vo.pipeline import run

    n = 6
    cfg = merge_dict(Config(), {"input": {"end": n},
                                "output": {"rerun": tmp_path / "out.rrd", "gt": sample_seq / "poses.txt"}}, "test")
    run(sample_seq, tmp_path / "run", cfg)
    rows = check_run_recording(tmp_path / "out.rrd", n)
    per_frame = (tmp_path / "out.rrd").stat().st_size / n
    print(f"pipeline recording: {per_frame:.0f} bytes per frame over {n} frames")
    assert per_frame < BYTES_PER_FRAME_BOUND
    # ground truth logged once, at close (fewer frames than gt_every), beside the estimate
    (f, strips), = rows[("/world/ground_truth", "LineStrips3D:strips")]
    assert f == n - 1 and len(strips[0]) == n
    traj = np.array(rows[("/world/trajectory", "LineStrips3D:strips")][-1][1][0])
    gt = np.array(strips[0])
    path_len = np.linalg.norm(np.diff(traj, axis=0), axis=1).sum()
    assert np.abs(gt - traj).max() < 0.2 * path_len  # the sample drives straight: they must agree
    assert (tmp_path / "run" / "trajectory.png").stat().st_size > 1000


@pytest.mark.parametrize("via", ["cli", "library"])
def test_run_without_rerun_flags_never_imports_rerun(tmp_path, sample_seq, via):
    if via == "cli":  # the real command line
        call = (
            "from click.testing import CliRunner\n"
            "from trianflow_vo.cli.main import main\n"
            f"res = CliRunner().invoke(main, ['run', {str(sample_seq)!r}, '--end', '3', '-q', "
            f"'--out', {str(tmp_path / 'run')!r}])\n"
            "assert res.exit_code == 0, res.output\n"
        )
    else:  # the library entry point, default configuration but for the frames
        call = (
            "from pathlib import Path\n"
            "from trianflow_vo.config import Config, merge_dict\n"
            "from trianflow_vo.pipeline import run\n"
            "cfg = merge_dict(Config(), {'input': {'end': 3}}, 'test')\n"
            f"s = run(Path({str(sample_seq)!r}), Path({str(tmp_path / 'run')!r}), cfg)\n"
            "assert s['status'] == 'completed', s\n"
        )
    code = (
        "import sys\n"
        + call
        + "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('rerun', 'rerun_bindings'))\n"
        "assert not bad, bad\n"
        "print('ok')\n"
    )
    res = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0 and "ok" in res.stdout, res.stdout + res.stderr[-3000:]
    assert (tmp_path / "run" / "poses.txt").exists()


def test_cli_run_with_rerun(tmp_path, sample_seq):
    from click.testing import CliRunner

    from trianflow_vo.cli.main import main

    n = 6
    res = CliRunner().invoke(main, ["run", str(sample_seq), "--end", str(n), "--rerun", str(tmp_path / "out.rrd"),
                                    "--out", str(tmp_path / "run")])
    assert res.exit_code == 0, res.output
    check_run_recording(tmp_path / "out.rrd", n)
    assert (tmp_path / "run" / "trajectory.png").stat().st_size > 1000


def test_cli_run_spawn_without_display_is_one_line(tmp_path, sample_seq, monkeypatch):
    from click.testing import CliRunner

    from trianflow_vo.cli.main import main

    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    res = CliRunner().invoke(main, ["run", str(sample_seq), "--end", "3", "--rerun-spawn", "-q",
                                    "--out", str(tmp_path / "run")])
    assert res.exit_code != 0 and isinstance(res.exception, SystemExit), res.output
    assert "no display" in res.output and "--rerun" in res.output
    assert "Traceback" not in res.output
