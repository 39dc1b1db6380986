"""The back-end seam: a back-end that revises keyframe poses, and what the pipeline does with it.

A fake back-end moves the first two keyframes by a known translation when the third
arrives. The pipeline must re-anchor every frame solved from a revised keyframe
(``T = T_key_new @ T_ref_cam``), tell every observer once, rewrite ``poses.txt`` with
the final poses and count the revision in ``run.json``; ``NoBackend`` must change
nothing at all. :class:`Trajectory` is also tested alone on hand-made results.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from trianflow_vo.backend import NoBackend, PoseRevision, RevisedPoses, Trajectory
from trianflow_vo.config import Config, merge_dict
from trianflow_vo.frame import Branch, FrameResult, FrameStats
from trianflow_vo.geometry.se3 import make_T, rodrigues
from trianflow_vo.observer import Observer
from trianflow_vo.pipeline import run

SHIFT = np.array([0.7, -0.2, 1.5])  # the known translation (trajectory units)


def translation(t) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = t
    return T


class ShiftFirstTwoKeyframes:
    """Back-end that, on the third keyframe, moves the first two by ``shift`` (world frame)."""

    name = "shift-test"

    def __init__(self, shift: np.ndarray = SHIFT):
        self.shift = translation(shift)
        self.seen: list[tuple[int, np.ndarray, FrameResult]] = []
        self.finished = False

    def add_keyframe(self, keyframe, result: FrameResult) -> PoseRevision | None:
        self.seen.append((keyframe.index, np.array(keyframe.T_world_cam), result))
        if len(self.seen) == 3:
            return PoseRevision({k: self.shift @ T for k, T, _ in self.seen[:2]}, reason="test: first two shifted")
        return None

    def finish(self) -> PoseRevision | None:
        self.finished = True
        return None

    def describe(self) -> dict:
        return {"name": self.name}


class Recorder(Observer):
    """Keeps every hook call, in order."""

    def __init__(self):
        self.results: list[FrameResult] = []
        self.revised: list[RevisedPoses] = []
        self.events: list[tuple[str, int]] = []
        self.closed = None

    def on_frame(self, result: FrameResult) -> None:
        self.results.append(result)
        self.events.append(("frame", result.frame_index))

    def on_poses_revised(self, revised: RevisedPoses) -> None:
        self.revised.append(revised)
        self.events.append(("revised", revised.revision))

    def close(self, interrupted: bool = False) -> None:
        self.closed = interrupted


def read_poses(run_dir: Path) -> np.ndarray:
    rows = [ln.split() for ln in (run_dir / "poses.txt").read_text().splitlines()]
    assert all(len(r) == 12 for r in rows)
    P = np.tile(np.eye(4), (len(rows), 1, 1))
    P[:, :3, :4] = np.asarray(rows, dtype=np.float64).reshape(-1, 3, 4)
    return P


def read_tsv(run_dir: Path) -> list[dict]:
    with open(run_dir / "frames.tsv") as fh:
        return list(csv.DictReader(fh, delimiter="\t"))


def stride3(**keyframes) -> Config:
    # the seam is tested with the pipeline's own back-end off (backend.window 0): the fake one is passed in
    data = {"input": {"stride": 3}, "output": {"plot": False}, "backend": {"window": 0}}
    if keyframes:
        data["keyframes"] = keyframes
    return merge_dict(Config(), data, "test")


# Default: every frame of the sample at stride 3 is a two-view keyframe. With the parallax
# rule at 10 px some frames are PnP / rotation-only against a keyframe instead
# (measured: keyframes 0, 6, 12, ...; frame 3 solved from 0, frame 9 from 6), so the
# re-anchoring of frames that are not keyframes is exercised too.
CONFIGS = {"default": stride3(), "with-pnp-frames": stride3(policy="parallax", min_parallax_px=10.0)}


@pytest.fixture(scope="module", params=sorted(CONFIGS))
def revised_run(request, tmp_path_factory):
    from conftest import SAMPLE

    if not SAMPLE.is_dir():
        pytest.skip(f"shipped sample missing at {SAMPLE}")
    config = CONFIGS[request.param]
    base = tmp_path_factory.mktemp(f"seam-{request.param}")
    backend = ShiftFirstTwoKeyframes()
    observers = [Recorder(), Recorder()]
    summary = run(SAMPLE, base / "revised", config, observers=observers, backend=backend)
    plain = Recorder()
    run(SAMPLE, base / "plain", config, observers=[plain], backend=NoBackend())
    return {"dir": base, "backend": backend, "observers": observers, "summary": summary, "plain": plain,
            "name": request.param}


def expected_revision(results: list[FrameResult]):
    """``(lines, third keyframe)`` of what the fake back-end's revision must move: the first
    two keyframes, and the frames (not keyframes) solved from them up to the third keyframe."""
    kfs = [r for r in results if r.is_keyframe]
    assert len(kfs) >= 3
    first_two, third = {kfs[0].frame_index, kfs[1].frame_index}, kfs[2]
    lines = [r.line for r in results[: third.line + 1]
             if (r.is_keyframe and r.frame_index in first_two) or (not r.is_keyframe and r.ref_index in first_two)]
    return lines, first_two, third


def test_backend_sees_every_keyframe(revised_run):
    backend, rec = revised_run["backend"], revised_run["observers"][0]
    kfs = [r for r in rec.results if r.is_keyframe]
    assert [k for k, _, _ in backend.seen] == [r.frame_index for r in kfs]
    for (k, T, result), r in zip(backend.seen, kfs):
        assert result is r  # the frame that became the keyframe
        np.testing.assert_array_equal(T, r.T_world_cam)  # the keyframe's pose as first estimated
    assert backend.finished


def test_every_observer_is_told_the_revised_frames(revised_run):
    recs = revised_run["observers"]
    results = recs[0].results
    lines, first_two, third = expected_revision(results)
    if revised_run["name"] == "with-pnp-frames":  # the case this config is for
        assert any(not results[i].is_keyframe for i in lines), [(r.frame_index, r.branch) for r in results]
    shift = translation(SHIFT)
    new_key = {k: shift @ T for k, T, _ in revised_run["backend"].seen[:2]}
    for rec in recs:
        assert rec.closed is False
        assert len(rec.results) == len(results) and all(a is b for a, b in zip(rec.results, results))
        assert len(rec.revised) == 1
        rev = rec.revised[0]
        assert rev.revision == 1 and rev.reason == "test: first two shifted"
        assert rev.lines.tolist() == lines
        assert rev.frame_indices.tolist() == [results[i].frame_index for i in lines]
        assert rev.T_world_cam.shape == (len(lines), 4, 4)
        for line, T in zip(rev.lines, rev.T_world_cam):
            r = results[line]
            # each moved by the known translation, rotation untouched ...
            np.testing.assert_allclose(T, shift @ r.T_world_cam, atol=1e-9)
            np.testing.assert_array_equal(T[:3, :3], r.T_world_cam[:3, :3])
            # ... because a frame solved from a revised keyframe is re-anchored to it
            if not r.is_keyframe:
                np.testing.assert_allclose(T, new_key[r.ref_index] @ r.T_ref_cam, atol=1e-9)
        # told right after the third keyframe, the one whose arrival triggered the revision
        i = rec.events.index(("frame", third.frame_index))
        assert rec.events[i + 1] == ("revised", 1)
        assert rec.events.count(("revised", 1)) == 1
    # the third keyframe is not named by the revision: it keeps its own pose, even though it
    # was solved from a revised keyframe (a back-end owns the poses of keyframes)
    assert third.line not in lines and third.ref_index in first_two
    # frames after the third keyframe are solved from later keyframes only
    assert all(r.ref_index not in first_two for r in results[third.line + 1:])


def test_poses_txt_is_the_revised_trajectory(revised_run):
    out, plain_out = revised_run["dir"] / "revised", revised_run["dir"] / "plain"
    results = revised_run["observers"][0].results
    rev = revised_run["observers"][0].revised[0]
    expected = np.stack([r.T_world_cam for r in results])
    expected[rev.lines] = rev.T_world_cam
    poses = read_poses(out)
    assert poses.shape == expected.shape
    np.testing.assert_allclose(poses, expected, rtol=1e-8, atol=1e-8)
    # the first line is no longer the identity: it moved with keyframe 0
    np.testing.assert_allclose(poses[0][:3, 3], SHIFT, atol=1e-8)
    # lines not revised are those of a run without a back-end, to the byte; revised ones differ
    mine = (out / "poses.txt").read_text().splitlines()
    plain = (plain_out / "poses.txt").read_text().splitlines()
    assert len(mine) == len(plain) == len(results)
    moved = set(rev.lines.tolist())
    for i, (a, b) in enumerate(zip(mine, plain)):
        assert (a != b) if i in moved else (a == b), i
    # trajectory.tum is rewritten with the same final poses
    tum = np.loadtxt(out / "trajectory.tum", ndmin=2)
    np.testing.assert_allclose(tum[:, 1:4], poses[:, :3, 3], atol=1e-6)
    # frames.tsv stays the front-end's per-frame log: one row per frame, as first solved
    rows, plain_rows = read_tsv(out), read_tsv(plain_out)
    assert [int(r["frame"]) for r in rows] == [r.frame_index for r in results]
    assert (out / "frames.txt").read_text().split() == [str(r.frame_index) for r in results]
    drop = ("frame_ms",)  # timing differs between runs
    assert [{k: v for k, v in r.items() if k not in drop} for r in rows] == \
        [{k: v for k, v in r.items() if k not in drop} for r in plain_rows]


def test_run_json_counts_the_revision(revised_run):
    out = revised_run["dir"] / "revised"
    doc = json.loads((out / "run.json").read_text())
    n_lines = len(revised_run["observers"][0].revised[0].lines)
    assert doc["status"] == "completed"
    assert doc["revisions"] == {"count": 1, "frames_revised": n_lines}
    assert revised_run["summary"]["revisions"] == doc["revisions"]
    assert doc["backend"] == {"name": "shift-test"}
    plain = json.loads((revised_run["dir"] / "plain" / "run.json").read_text())
    assert plain["revisions"] == {"count": 0, "frames_revised": 0} and plain["backend"] == {"name": "none"}
    assert revised_run["plain"].revised == []


def test_no_backend_is_byte_identical_to_no_backend_argument(revised_run, tmp_path):
    from conftest import SAMPLE

    config = CONFIGS[revised_run["name"]]
    run(SAMPLE, tmp_path / "default", config)  # backend.window 0: NoBackend, chosen by the pipeline
    plain = revised_run["dir"] / "plain"
    for name in ("poses.txt", "trajectory.tum", "frames.txt"):
        assert (tmp_path / "default" / name).read_bytes() == (plain / name).read_bytes(), name


# --------------------------------------------------------------------------- Trajectory alone


def result(line, frame, branch, is_keyframe, ref, T_ref_cam, T_world_cam) -> FrameResult:
    return FrameResult(line, frame, None, T_world_cam, branch, "", ref, T_ref_cam, is_keyframe, np.eye(3),
                       FrameStats())


def pose(rvec, t) -> np.ndarray:
    return make_T(rodrigues(np.asarray(rvec, float)), np.asarray(t, float))


@pytest.fixture
def chain():
    """Keyframes 10, 12, 14; frame 11 solved from 10, 13 from 12, 15 from 14."""
    A, B, C, D = (pose([0.0, 0.02, 0.0], [0.1, 0.0, 0.5]), pose([0.01, 0.03, 0.0], [0.0, 0.1, 1.0]),
                  pose([0.0, -0.01, 0.02], [0.0, 0.0, 0.2]), pose([0.0, 0.02, 0.01], [0.2, 0.0, 1.1]))
    res = [result(0, 10, Branch.INIT, True, None, np.eye(4), np.eye(4)),
           result(1, 11, Branch.PNP, False, 10, A, A),
           result(2, 12, Branch.TWO_VIEW, True, 10, B, B),
           result(3, 13, Branch.ROTATION, False, 12, C, B @ C),
           result(4, 14, Branch.TWO_VIEW, True, 12, D, B @ D),
           result(5, 15, Branch.IDENTITY, False, 14, np.eye(4), B @ D)]
    traj = Trajectory()
    for r in res:
        traj.add(r)
    return traj, res


def test_trajectory_before_any_revision(chain):
    traj, res = chain
    np.testing.assert_array_equal(traj.poses(), np.stack([r.T_world_cam for r in res]))
    assert traj.frame_indices().tolist() == [10, 11, 12, 13, 14, 15]
    assert traj.revisions == 0
    assert Trajectory().poses().shape == (0, 4, 4)


def test_trajectory_revise_reanchors_frames_to_their_keyframe(chain):
    traj, res = chain
    N10, N12 = pose([0.0, 0.0, 0.1], [1.0, 2.0, 3.0]), pose([0.05, 0.0, 0.0], [-1.0, 0.5, 2.0])
    out = traj.revise(PoseRevision({10: N10, 12: N12}, reason="two moved"))
    assert isinstance(out, RevisedPoses)
    assert out.lines.tolist() == [0, 1, 2, 3] and out.frame_indices.tolist() == [10, 11, 12, 13]
    assert out.revision == 1 and out.reason == "two moved" and traj.revisions == 1
    expect = [N10, N10 @ res[1].T_ref_cam, N12, N12 @ res[3].T_ref_cam]
    np.testing.assert_allclose(out.T_world_cam, np.stack(expect), atol=1e-12)
    P = traj.poses()
    np.testing.assert_allclose(P[:4], np.stack(expect), atol=1e-12)
    # keyframe 14 is not named: it and the frame solved from it keep their poses
    np.testing.assert_array_equal(P[4], res[4].T_world_cam)
    np.testing.assert_array_equal(P[5], res[5].T_world_cam)
    # a second revision moves only what hangs on its keyframe, and counts on
    N14 = pose([0.0, 0.1, 0.0], [3.0, 0.0, 9.0])
    out2 = traj.revise(PoseRevision({14: N14}))
    assert out2.lines.tolist() == [4, 5] and out2.revision == 2
    np.testing.assert_allclose(traj.poses()[4:], np.stack([N14, N14]), atol=1e-12)
    np.testing.assert_allclose(traj.poses()[:4], np.stack(expect), atol=1e-12)  # earlier revision kept
    # revising a keyframe again re-anchors from T_ref_cam, not from the previous revision
    out3 = traj.revise(PoseRevision({10: np.eye(4)}))
    assert out3.lines.tolist() == [0, 1]
    np.testing.assert_allclose(traj.poses()[1], res[1].T_ref_cam, atol=1e-12)


@pytest.mark.parametrize("bad", [11, 13, 99], ids=["solved-from-10", "solved-from-12", "unknown"])
def test_trajectory_revise_rejects_frames_that_are_not_keyframes(chain, bad):
    traj, res = chain
    before = traj.poses().copy()
    with pytest.raises(ValueError, match=rf"not keyframes: \[{bad}\]"):
        traj.revise(PoseRevision({10: pose([0, 0, 0], [1, 1, 1]), bad: np.eye(4)}))
    # nothing applied, nothing counted
    np.testing.assert_array_equal(traj.poses(), before)
    assert traj.revisions == 0


def test_pose_revision_checks_and_freezes_its_poses():
    with pytest.raises(ValueError, match=r"keyframe 3 must be \(4, 4\)"):
        PoseRevision({3: np.eye(3)})
    T = np.eye(4)
    rev = PoseRevision({np.int64(5): T})
    assert list(rev.T_world_cam) == [5] and type(list(rev.T_world_cam)[0]) is int
    T[0, 3] = 9.0  # a copy was kept
    assert rev.T_world_cam[5][0, 3] == 0.0
    assert not rev.T_world_cam[5].flags.writeable
    with pytest.raises(TypeError):
        rev.T_world_cam[6] = np.eye(4)  # read-only mapping
