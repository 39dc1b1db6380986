"""The window adjustment in a worker process (``backend.concurrent``): same poses, clean ends."""

from __future__ import annotations

import json
import multiprocessing
import os
import signal
import sys

import numpy as np
import pytest

pytest.importorskip("gtsam", reason="the window back-end needs gtsam (a dependency of the project)")

from trianflow_vo.ba.backend import WindowBackend  # noqa: E402
from trianflow_vo.ba.worker import init_worker  # noqa: E402


def test_the_worker_process_gives_the_poses_of_a_blocking_adjustment(long_drive, tmp_path, run_seq):
    doc_c, p_c = run_seq(long_drive, tmp_path / "c", "backend.window=5", "backend.concurrent=true")
    doc_b, p_b = run_seq(long_drive, tmp_path / "b", "backend.window=5", "backend.concurrent=false")
    _, p_0 = run_seq(long_drive, tmp_path / "w0", "backend.window=0")
    be_c, be_b = doc_c["backend"], doc_b["backend"]
    assert be_c["concurrent"] is True and be_b["concurrent"] is False
    assert be_c["solves"] == be_b["solves"] >= 4 and be_c["revisions"] == be_b["revisions"] == be_c["solves"]
    # the adjustments did move the poses, and both ways the same (poses.txt prints 9 digits)
    assert np.abs(p_b - p_0).max() > 1e-4
    np.testing.assert_allclose(p_c, p_b, rtol=0, atol=1e-8)
    assert be_c["worker_peak_rss_mb"] > 10 and be_b["worker_peak_rss_mb"] is None
    assert multiprocessing.active_children() == []  # the worker was stopped with the run


def test_a_worker_process_that_dies_is_reported_and_the_run_adjusts_in_process(long_drive, tmp_path, monkeypatch,
                                                                                run_seq):
    real = WindowBackend._worker

    def dying(self):
        pool = real(self)
        pool.submit(os._exit, 3).exception()  # the worker process exits: the pool is broken
        return pool

    monkeypatch.setattr(WindowBackend, "_worker", dying)
    doc, poses = run_seq(long_drive, tmp_path / "died", "backend.window=5", "backend.concurrent=true")
    _, p_b = run_seq(long_drive, tmp_path / "b", "backend.window=5", "backend.concurrent=false")
    assert doc["status"] == "completed"
    warning = doc["warnings"]["backend-worker"]
    assert warning["count"] == 1 and "adjusting in this process" in warning["items"][0]["message"]
    assert doc["backend"]["failures"] == 0 and doc["backend"]["revisions"] == doc["backend"]["solves"] >= 4
    np.testing.assert_allclose(poses, p_b, rtol=0, atol=1e-8)  # the lost window was solved again here
    assert multiprocessing.active_children() == []


def test_a_run_that_fails_mid_way_stops_the_worker(drive, tmp_path, monkeypatch, run_seq):
    import trianflow_vo.pipeline as pipeline

    real = pipeline._step
    calls = {"n": 0}

    def failing(*a, **k):
        calls["n"] += 1
        if calls["n"] == 9:  # after a few adjustments were started
            raise RuntimeError("boom")
        return real(*a, **k)

    monkeypatch.setattr(pipeline, "_step", failing)
    with pytest.raises(RuntimeError, match="boom"):
        run_seq(drive, tmp_path / "fail", "backend.window=5", "backend.concurrent=true")
    doc = json.loads((tmp_path / "fail" / "run.json").read_text())
    assert doc["status"] == "failed" and doc["backend"]["solves"] >= 1
    assert multiprocessing.active_children() == []


@pytest.mark.parametrize("mode", ["affine", "scale"])
def test_depth_correction_keeps_the_worker_and_its_poses_equal_to_blocking(long_drive, tmp_path, run_seq, mode):
    """The correction of the next keyframe's depth comes from the same adjusted points in both orders
    (``min_points`` 10: on this short drive 36-56 adjusted points reach each keyframe, fewer of them on
    pixels with front-end depth; every correction applied, however small)."""
    args = ("backend.window=5", f"backend.depth_correction={mode}", "backend.min_points=10",
            "backend.depth_correction_min=0")
    doc_c, p_c = run_seq(long_drive, tmp_path / "c", *args)
    doc_b, p_b = run_seq(long_drive, tmp_path / "b", *args, "backend.concurrent=false")
    _, p_n = run_seq(long_drive, tmp_path / "n", "backend.window=5", "backend.min_points=10",
                     "backend.depth_correction=none")
    assert doc_c["backend"]["concurrent"] is True and doc_b["backend"]["concurrent"] is False
    assert doc_c["backend"]["depth_corrections"] > 0
    assert doc_c["backend"]["depth_corrections"] == doc_b["backend"]["depth_corrections"]
    assert doc_c["backend"]["depth_correction"] == mode
    if mode == "scale":
        assert doc_c["backend"]["depth_spread_max"] == 1.0
    else:
        assert doc_c["backend"]["depth_spread_max"] > 1.0  # some offsets were corrected
    np.testing.assert_allclose(p_c, p_b, rtol=0, atol=1e-8)
    assert np.abs(p_c - p_n).max() > 1e-6  # the corrections did change the run


def test_depth_corrections_below_the_minimum_change_are_counted_and_not_applied(long_drive, tmp_path, run_seq):
    """``depth_correction_min``: a correction changing no depth of the keyframe by more than this
    fraction is left out; with a minimum no correction reaches, the run is the one without corrections."""
    base = ("backend.window=5", "backend.min_points=10")
    doc_m, p_m = run_seq(long_drive, tmp_path / "m", *base, "backend.depth_correction=affine",
                         "backend.depth_correction_min=10", "backend.concurrent=false")
    _, p_n = run_seq(long_drive, tmp_path / "n", *base, "backend.depth_correction=none", "backend.concurrent=false")
    be = doc_m["backend"]
    assert be["depth_corrections"] == 0 and be["depth_corrections_small"] > 0
    np.testing.assert_allclose(p_m, p_n, rtol=0, atol=1e-12)


def test_depth_corrections_with_an_insignificant_offset_are_counted_and_not_applied(long_drive, tmp_path, run_seq):
    """``depth_correction_t``: ``shape`` makes no correction whose offset of inverse depth lies fewer
    standard errors from zero than this; with a bar no fit reaches, the run is the one without
    corrections, and with none every fit that passes the minimum is applied."""
    base = ("backend.window=5", "backend.min_points=10", "backend.depth_correction=shape",
            "backend.depth_correction_min=0", "backend.depth_correction_max=3", "backend.concurrent=false")
    doc_t, p_t = run_seq(long_drive, tmp_path / "t", *base, "backend.depth_correction_t=1e9")
    doc_0, p_0 = run_seq(long_drive, tmp_path / "0", *base, "backend.depth_correction_t=0")
    _, p_n = run_seq(long_drive, tmp_path / "n", "backend.window=5", "backend.min_points=10",
                     "backend.depth_correction=none", "backend.concurrent=false")
    assert doc_t["backend"]["depth_corrections"] == 0 and doc_t["backend"]["depth_corrections_insignificant"] > 0
    np.testing.assert_allclose(p_t, p_n, rtol=0, atol=1e-12)
    assert doc_0["backend"]["depth_corrections_insignificant"] == 0 and doc_0["backend"]["depth_corrections"] > 0
    assert np.abs(p_0 - p_n).max() > 1e-6


def test_the_worker_leaves_ctrl_c_to_the_run():
    before = signal.getsignal(signal.SIGINT)
    try:
        init_worker()
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, before)


PARENT = """
import os, sys
from concurrent.futures import ProcessPoolExecutor
import multiprocessing
from trianflow_vo.ba.worker import init_worker
if __name__ == "__main__":
    pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"), initializer=init_worker,
                               initargs=(os.getpid(), 0.1))
    print(pool.submit(os.getpid).result(), flush=True)
    os._exit(9)  # as if killed: nothing closes the pool
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc to tell a zombie from a live process")
def test_the_worker_ends_when_its_run_is_killed(tmp_path):
    import subprocess
    import time

    script = tmp_path / "parent.py"
    script.write_text(PARENT)
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 9, out.stderr
    child = int(out.stdout.split()[0])
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            os.kill(child, 0)
        except ProcessLookupError:
            return  # gone
        with open(f"/proc/{child}/stat") as f:  # a zombie (exited, not yet reaped by init) counts as gone
            if f.read().split(")")[-1].split()[0] == "Z":
                return
        time.sleep(0.1)
    os.kill(child, signal.SIGKILL)
    pytest.fail(f"the worker process {child} outlived its killed parent")
