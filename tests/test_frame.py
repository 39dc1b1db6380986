"""The per-frame contract: Branch, FrameStats, FrameView, FrameResult are typed and immutable."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from trianflow_vo.frame import Branch, FrameResult, FrameStats, FrameView


def _result(**kw) -> FrameResult:
    args = dict(line=3, frame_index=9, timestamp=0.9, T_world_cam=np.eye(4), branch=Branch.TWO_VIEW, reason="",
                ref_index=6, T_ref_cam=np.eye(4), is_keyframe=True, K=np.eye(3),
                stats=FrameStats(inliers=120, scale=0.5, ms={"flow": 3.0}))
    args.update(kw)
    return FrameResult(**args)


def test_branch_values_are_the_words_written_to_the_outputs():
    assert [b.value for b in Branch] == ["init", "two-view", "pnp", "rotation", "identity", "failed"]
    assert str(Branch.TWO_VIEW) == "two-view" and Branch("pnp") is Branch.PNP
    assert not Branch.ROTATION.is_routine and not Branch.FAILED.is_routine and Branch.PNP.is_routine


def test_result_is_frozen_and_its_arrays_read_only():
    T = np.eye(4)
    r = _result(T_world_cam=T)
    with pytest.raises(dataclasses.FrozenInstanceError):
        r.branch = Branch.FAILED  # type: ignore[misc]
    with pytest.raises(ValueError):
        r.T_world_cam[0, 3] = 1.0
    T[0, 3] = 5.0  # the caller's array is copied, not shared
    assert r.T_world_cam[0, 3] == 0.0
    with pytest.raises(TypeError):
        r.stats.ms["flow"] = 1.0  # type: ignore[index]


def test_result_checks_shapes_and_accepts_branch_words():
    with pytest.raises(ValueError, match=r"T_world_cam must be \(4, 4\)"):
        _result(T_world_cam=np.eye(3))
    assert _result(branch="identity").branch is Branch.IDENTITY
    with pytest.raises(ValueError):
        _result(branch="teleport")


def test_stats_scalars_leave_out_what_was_not_measured():
    s = FrameStats(inliers=7, parallax_px=1.5, ms={"flow": 2.0}, frame_ms=4.0)
    assert s.scalars() == {"inliers": 7, "parallax_px": 1.5, "degraded": False, "ms": {"flow": 2.0}, "frame_ms": 4.0}


def test_view_arrays_are_read_only_views():
    img = np.zeros((4, 5, 3), np.uint8)
    v = FrameView.of(image=img, flow=None)
    assert v.flow is None and v.image.shape == (4, 5, 3)
    with pytest.raises(ValueError):
        v.image[0, 0, 0] = 1
    assert _result(view=v).view is v
    assert _result(stats=FrameStats(degraded=True)).is_degraded and _result(branch="rotation").is_degraded
    assert not _result().is_degraded
