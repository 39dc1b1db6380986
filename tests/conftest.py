"""Shared fixtures: where the shipped sample and the optional ../shared data are."""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample" / "kitti00"


def shared_data_dir() -> Path:
    """``$TRIANFLOW_SHARED_DATA`` or ``../shared/data`` beside the repository."""
    env = os.environ.get("TRIANFLOW_SHARED_DATA")
    return Path(env) if env else REPO.parent / "shared" / "data"


@pytest.fixture
def shared_data() -> Path:
    d = shared_data_dir()
    if not d.is_dir():
        pytest.skip(f"shared data not found at {d} (set TRIANFLOW_SHARED_DATA or put ../shared beside the repo)")
    return d


@pytest.fixture(scope="module")
def benchmark_module():
    """``load(name)``: ``benchmarks/NAME.py`` as a module (the benchmark scripts are not a
    package), registered in ``sys.modules`` (a dataclass looks its module up there) until the
    test module ends."""
    loaded = []

    def load(name: str):
        spec = importlib.util.spec_from_file_location(name, REPO / "benchmarks" / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod
        loaded.append(name)
        spec.loader.exec_module(mod)
        return mod

    yield load
    for name in loaded:
        sys.modules.pop(name, None)


@pytest.fixture
def sample_seq() -> Path:
    if not SAMPLE.is_dir():
        pytest.skip(f"shipped sample missing at {SAMPLE}")
    return SAMPLE


@pytest.fixture(autouse=True, scope="session")
def _home_out_of_the_way(tmp_path_factory):
    """Tests never write into the real HOME (evo writes ~/.evo when its plotting is first imported)."""
    mp = pytest.MonkeyPatch()
    mp.setenv("HOME", str(tmp_path_factory.mktemp("home")))
    yield
    mp.undo()


# -- the back-end tests (tests/ba): a rendered drive and a run of the pipeline on it ------------------
def _urban_turn(tmp_path_factory, n_frames: int):
    from synthetic_sequences import make_sequence

    seq = tmp_path_factory.mktemp("seq") / f"urban{n_frames}"
    make_sequence("urban_turn", seq, n_frames=n_frames, seed=3, size=(128, 384))
    return seq


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """A rendered urban turn (14 frames, known poses)."""
    return _urban_turn(tmp_path_factory, 14)


@pytest.fixture(scope="session")
def long_drive(tmp_path_factory):
    """The urban turn over 26 frames: enough keyframes for several window adjustments.

    The 14-frame ``drive`` gives 5 or more adjustments on one CPU and 3 on another (the
    keyframe choice moves with the floating-point paths); this one gives 12 on the latter.
    """
    return _urban_turn(tmp_path_factory, 26)


@pytest.fixture
def run_seq():
    """``run_seq(seq, out, *overrides) -> (run.json, poses (N, 3, 4))`` with plots off."""
    import json

    import numpy as np

    from trianflow_vo.config import Config, apply_overrides
    from trianflow_vo.pipeline import run

    def _run(seq, out, *overrides):
        run(seq, out, apply_overrides(Config(), ["output.plot=false", *overrides]))
        return json.loads((out / "run.json").read_text()), np.loadtxt(out / "poses.txt").reshape(-1, 3, 4)

    return _run
