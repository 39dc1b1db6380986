"""Shared fixtures: where the shipped sample and the optional ../shared data are."""

from __future__ import annotations

import os
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
