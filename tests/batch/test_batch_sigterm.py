"""SIGTERM to a real ``trianflow-vo batch`` process (its own local Ray): the running job is stopped and
closed, the summary is written, exit 143. ``ray.init`` installs its own SIGTERM handlers (``sys.exit``
plus a native one printing a stack trace); with them the command ended with exit 1, no summary, and the
run folder left ``running``.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time

import pytest

pytest.importorskip("ray", reason="ray is not installed (pip install 'trianflow-vo[batch]')")


def test_sigterm_stops_jobs_writes_summary_exit_143(shared_data, tmp_path):
    long_seq, short_seq = shared_data / "kitti00-f0000-0150", shared_data / "kitti06-f0000-0050"
    out = tmp_path / "b"
    # 150 frames at the default 256x832 on one thread: far longer than the test waits
    cmd = [sys.executable, "-m", "trianflow_vo.cli", "batch", str(long_seq), str(short_seq), "--out", str(out),
           "--workers", "1", "--set", "runtime.threads=1", "--no-plot", "-q"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env={**os.environ, "RAY_USAGE_STATS_ENABLED": "0"})
    run_json, log = out / long_seq.name / "run.json", out / long_seq.name / "frames.tsv"
    try:
        deadline = time.monotonic() + 120
        # until the run has written a whole frame: frames.tsv (header + one row) is the last file a frame
        # writes; a signal while a frame is being written takes that frame back
        while time.monotonic() < deadline and p.poll() is None:
            if log.is_file() and log.read_text().count("\n") >= 2:
                break
            time.sleep(0.1)
        assert p.poll() is None, p.communicate()
        p.send_signal(signal.SIGTERM)
        _, err = p.communicate(timeout=90)
    finally:
        if p.poll() is None:
            p.kill()
            p.communicate()
    assert p.returncode == 143, err
    assert "SIGTERM received" not in err  # Ray's native handler did not take the signal
    assert "batch interrupted: running jobs were stopped" in err
    with open(out / "summary.csv", newline="") as f:
        rows = {r["name"]: r for r in csv.DictReader(f)}
    assert rows[long_seq.name]["status"] == "interrupted"
    assert rows[short_seq.name]["status"] == "pending"
    assert rows["ALL"]["status"] == "0/2 completed"
    doc = json.loads(run_json.read_text())
    assert doc["status"] == "interrupted" and doc["frames_processed"] > 0
    assert not (out / long_seq.name / ".lock").exists()
