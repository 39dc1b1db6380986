"""Fixtures of the back-end tests: a rendered drive and a run of the pipeline on it."""

from __future__ import annotations

import json

import numpy as np
import pytest
from synthetic_sequences import make_sequence


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """A rendered urban turn (14 frames, known poses)."""
    seq = tmp_path_factory.mktemp("seq") / "urban"
    make_sequence("urban_turn", seq, n_frames=14, seed=3, size=(128, 384))
    return seq


@pytest.fixture
def run_seq():
    """``run_seq(seq, out, *overrides) -> (run.json, poses (N, 3, 4))`` with plots off."""
    from trianflow_vo.config import Config, apply_overrides
    from trianflow_vo.pipeline import run

    def _run(seq, out, *overrides):
        run(seq, out, apply_overrides(Config(), ["output.plot=false", *overrides]))
        return json.loads((out / "run.json").read_text()), np.loadtxt(out / "poses.txt").reshape(-1, 3, 4)

    return _run
