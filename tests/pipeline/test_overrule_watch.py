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


def test_overrules_inside_the_guards_limit_neither_count_nor_end_the_streak():
    """An overrule by the low-parallax limit only (PnP / two-view 0.8x, inside 1.5x) says nothing against the
    depth; the gross ones (0.5x, 2.5x) count, across the small ones, until the streak is reached."""
    small = [_frame(i, 10, Branch.PNP, 0.8) for i in range(11, 31)]
    assert _feed(OverruleWatch(min_streak=3, ratio=1.5), small) == []
    assert [f for f, _ in _feed(OverruleWatch(min_streak=3, ratio=0), small)] == [13]  # 0: every overrule counts
    mixed = [_frame(11, 10, Branch.PNP, 0.5), _frame(12, 10, Branch.PNP, 0.8), _frame(13, 10, Branch.PNP, 2.5),
             _frame(14, 10, Branch.PNP, 1.2), _frame(15, 10, Branch.PNP, 0.6)]
    out = _feed(OverruleWatch(min_streak=3, ratio=1.5), mixed)
    assert [f for f, _ in out] == [15]
    assert "frames 11-15" in out[0][1] and "3 two-view steps" in out[0][1] and "0.50-2.50x" in out[0][1]
    for bad in (1.0, 0.5, -1.0):
        with pytest.raises(ValueError):
            OverruleWatch(ratio=bad)


def test_the_run_watches_with_the_configured_guard(sample_seq, tmp_path, monkeypatch):
    """``pipeline.run`` builds its watch with ``scale.pnp_check_ratio`` and feeds it every frame."""
    from trianflow_vo import pipeline
    from trianflow_vo.config import Config, merge_dict

    made = []

    class Recording(OverruleWatch):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.fed = 0
            made.append((self, kwargs))

        def update(self, result):
            self.fed += 1
            return super().update(result)

    monkeypatch.setattr(pipeline, "OverruleWatch", Recording)
    config = merge_dict(Config(), {"input": {"stride": 3, "end": 12}, "output": {"plot": False},
                                   "scale": {"pnp_check_ratio": 1.3}}, "test")
    pipeline.run(sample_seq, tmp_path / "out", config)
    assert len(made) == 1
    watch, kwargs = made[0]
    assert kwargs == {"ratio": 1.3}
    assert watch.fed == 4  # frames 3, 6, 9, 12
