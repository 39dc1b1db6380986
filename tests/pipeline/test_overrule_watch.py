"""The warning for a keyframe whose carried depth keeps overruling the two-view steps."""

from types import SimpleNamespace

import pytest

from trianflow_vo.frame import Branch
from trianflow_vo.runlog import PER_FRAME_KINDS, OverruleWatch


def _frame(i, ref, branch, pnp_ratio=None):
    return SimpleNamespace(frame_index=i, ref_index=ref, branch=branch, stats=SimpleNamespace(pnp_ratio=pnp_ratio))


def _feed(watch, frames):
    return [(f.frame_index, w) for f in frames if (w := watch.update(f))]


def test_a_long_streak_against_one_keyframe_warns_once_naming_the_frames_and_ratios():
    frames = [_frame(i, 10, Branch.PNP, 0.1 + 0.01 * i) for i in range(11, 31)]
    out = _feed(OverruleWatch(min_streak=10), frames)
    assert len(out) == 1
    frame, msg = out[0]
    assert frame == 20
    assert "frames 11-20" in msg and "keyframe 10" in msg and "10 two-view steps" in msg
    assert "0.21-0.30x" in msg
    assert "depth-contradicted" in PER_FRAME_KINDS


def test_short_streaks_plain_pnp_frames_and_new_keyframes_do_not_warn():
    watch = OverruleWatch(min_streak=10)
    frames = []
    # 9 overruled, then a two-view step (new keyframe 20): the streak starts again
    frames += [_frame(i, 10, Branch.PNP, 0.5) for i in range(11, 20)]
    frames += [_frame(20, 10, Branch.TWO_VIEW)]
    frames += [_frame(i, 20, Branch.PNP, 0.5) for i in range(21, 30)]
    # PnP frames without a ratio (small parallax: no two-view step tried) are not overrules
    frames += [_frame(i, 30, Branch.PNP) for i in range(31, 60)]
    # a keyframe handed on (the reference changes) ends the streak too
    frames += [_frame(i, 60, Branch.PNP, 2.0) for i in range(61, 66)]
    frames += [_frame(i, 66, Branch.PNP, 2.0) for i in range(67, 72)]
    assert _feed(watch, frames) == []


def test_plain_pnp_frames_between_overrules_do_not_break_the_streak_and_each_keyframe_warns_once():
    watch = OverruleWatch(min_streak=3)
    frames = [_frame(1, 0, Branch.PNP, 3.0), _frame(2, 0, Branch.PNP), _frame(3, 0, Branch.PNP, 3.0),
              _frame(4, 0, Branch.PNP, 3.0), _frame(5, 0, Branch.PNP, 3.0), _frame(6, 0, Branch.PNP, 3.0)]
    out = _feed(watch, frames)
    assert [f for f, _ in out] == [4]
    with pytest.raises(ValueError):
        OverruleWatch(min_streak=0)
