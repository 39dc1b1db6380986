"""Flow computed one frame ahead (``flow.ahead``): the same flow, hits and misses counted."""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest
from synthetic_sequences import make_sequence

from trianflow_vo.config import Config, apply_overrides
from trianflow_vo.flow.dis import DisFlow
from trianflow_vo.flow.speculative import SpeculativeFlow
from trianflow_vo.pipeline import _with_next, make_flow_source, run


class CountingFlow:
    """A fake source: flow filled with a per-call number, and the thread that computed it."""

    name = "counting"

    def __init__(self, fail_on=None):
        self.calls, self.threads, self.fail_on = [], [], fail_on

    def prepare(self, image):
        return np.asarray(image)

    def flow_pair(self, a, b):
        self.calls.append((a, b))
        self.threads.append(threading.current_thread().name)
        if self.fail_on is not None and len(self.calls) == self.fail_on:
            raise RuntimeError("flow failed")
        f = np.full((2, 3, 2), float(len(self.calls)), np.float32)
        return f, -f

    def describe(self):
        return {"name": self.name}


def test_a_guess_that_comes_true_is_computed_in_the_background_once():
    main, spare = CountingFlow(), CountingFlow()
    flow = SpeculativeFlow(main, spare)
    a, b, c = np.zeros(1), np.ones(1), np.ones(1)
    flow.speculate(a, b)
    fw, bw = flow.flow_pair(a, b)
    assert fw[0, 0, 0] == 1 and not main.calls and spare.threads == ["flow-ahead"]
    flow.speculate(a, b)
    flow.flow_pair(a, c)  # an equal array is not the same input: a miss, computed here
    assert len(main.calls) == 1 and main.calls[0][1] is c and main.threads == [threading.current_thread().name]
    assert flow.describe()["computed_ahead"] == {"hits": 1, "misses": 1}
    flow.speculate(a, b)
    flow.close()  # waits for the guess; nothing left running
    assert flow.describe()["computed_ahead"] == {"hits": 1, "misses": 2}
    assert not [t for t in threading.enumerate() if t.name == "flow-ahead"]


def test_an_error_in_the_background_is_met_again_in_the_main_thread():
    flow = SpeculativeFlow(CountingFlow(fail_on=1), CountingFlow(fail_on=1))
    a, b = np.zeros(1), np.ones(1)
    flow.speculate(a, b)
    with pytest.raises(RuntimeError, match="flow failed"):
        flow.flow_pair(a, b)


def test_dis_ahead_gives_the_same_flow_as_dis():
    rng = np.random.default_rng(0)
    img = (rng.random((96, 160)) * 255).astype(np.uint8)
    import cv2

    img = cv2.GaussianBlur(img, (5, 5), 1.5)
    moved = np.ascontiguousarray(np.roll(img, (2, 3), axis=(0, 1)))
    plain = DisFlow("medium").flow_pair(img, moved)
    dis = DisFlow("medium")
    ahead = SpeculativeFlow(dis, dis.clone())
    ahead.speculate(img, moved)
    got = ahead.flow_pair(img, moved)
    assert ahead.hits == 1
    for x, y in zip(got, plain):
        np.testing.assert_array_equal(x, y)
    assert np.median(plain[0][..., 0]) == pytest.approx(3, abs=0.2)


def test_make_flow_source_follows_flow_ahead():
    assert isinstance(make_flow_source(Config()), SpeculativeFlow)
    assert isinstance(make_flow_source(apply_overrides(Config(), ["flow.ahead=false"])), DisFlow)


def test_with_next_pairs_items_and_hands_out_the_last_before_an_error():
    assert list(_with_next([])) == []
    assert list(_with_next([1, 2, 3])) == [(1, 2), (2, 3), (3, None)]

    def failing():
        yield 1
        yield 2
        raise OSError("disk gone")

    got = []
    with pytest.raises(OSError, match="disk gone"):
        for pair in _with_next(failing()):
            got.append(pair)
    assert got == [(1, 2), (2, None)]  # frame 2 was handed out before the error


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    seq = tmp_path_factory.mktemp("seq") / "room"
    make_sequence("handheld_indoor", seq, n_frames=40, seed=2, size=(120, 160))
    return seq


def test_the_pipeline_gives_the_same_poses_with_and_without_flow_ahead(room, tmp_path):
    out = {}
    for ahead in ("true", "false"):
        run(room, tmp_path / ahead, apply_overrides(Config(), ["output.plot=false", f"flow.ahead={ahead}"]))
        out[ahead] = (json.loads((tmp_path / ahead / "run.json").read_text()),
                      (tmp_path / ahead / "poses.txt").read_text())
    doc, poses = out["true"]
    assert poses == out["false"][1]
    counts = doc["flow_source"]["computed_ahead"]
    branches = doc["branch_counts"]
    # keyframes both made and kept in this clip: the guesses both come true and miss
    assert branches["two-view"] > 0 and branches["pnp"] > 0
    assert counts["hits"] > 0 and counts["misses"] > 0
    assert counts["hits"] + counts["misses"] == doc["frames_processed"] - 1
    assert "computed_ahead" not in out["false"][0]["flow_source"]
