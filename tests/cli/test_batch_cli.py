"""``trianflow-vo batch`` without a cluster: the missing-Ray message, bad options and configuration keys
(exit 2, nothing run), and the exit status / summary for every outcome (the runner replaced by a stub
returning known rows). The real Ray runs are in tests/batch/test_batch_ray.py.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from trianflow_vo.cli.main import main


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def one_line_error(r) -> str:
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert "Traceback" not in r.output, r.output
    assert isinstance(r.exception, SystemExit) or r.exception is None, repr(r.exception)
    return lines[-1]


@pytest.fixture
def no_runner(monkeypatch):
    """Fail the test if the batch gets as far as running anything."""
    import trianflow_vo.batch.runner as runner

    def refuse(*a, **k):
        raise AssertionError("run_batch must not be called")

    monkeypatch.setattr(runner, "run_batch", refuse)
    monkeypatch.setenv("RAY_USAGE_STATS_ENABLED", "0")


def test_without_ray_one_line_install_hint(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    r = invoke("batch", tmp_path / "seq", "--out", tmp_path / "out")
    assert r.exit_code == 1
    line = one_line_error(r)
    assert line == "Error: ray is not installed; install the batch extra: pip install 'trianflow-vo[batch]'"
    assert not (tmp_path / "out").exists()


def test_help_does_not_import_ray():
    code = ("import sys; from trianflow_vo.cli.main import main\n"
            "try:\n    main(['batch', '--help'])\nexcept SystemExit:\n    pass\n"
            "print('RAY' if 'ray' in sys.modules else 'NORAY')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "--manifest" in out.stdout and out.stdout.strip().endswith("NORAY")


def test_no_sequence_is_a_usage_error(no_runner, tmp_path):
    r = invoke("batch", "--out", tmp_path / "o")
    assert r.exit_code == 2 and "give sequences (SEQ...) or --manifest FILE" in r.output


@pytest.mark.parametrize("extra, needle", [
    (["--set", "sampling.nope=1"], "unknown key 'sampling.nope'"),
    (["--set", "input.stride=0"], "input.stride"),
    (["--sweep", "sampling.seed"], "not section.key=v1,v2"),
    (["--sweep", "sampling.seeds=1,2"], "unknown key 'sampling.seeds'"),
    (["--lengths", "10,-1"], "lengths must be positive"),
])
def test_bad_keys_exit_2_before_anything_runs(no_runner, tmp_path, extra, needle):
    r = invoke("batch", tmp_path / "seq", "--out", tmp_path / "o", *extra)
    assert r.exit_code == 2, r.output
    assert needle in r.output and "Traceback" not in r.output
    assert not (tmp_path / "o").exists()


def test_bad_manifest_exit_2_naming_file(no_runner, tmp_path):
    m = tmp_path / "m.yaml"
    m.write_text("- path: a\n  strid: 2\n")
    r = invoke("batch", "--manifest", m, "--out", tmp_path / "o")
    assert r.exit_code == 2
    line = one_line_error(r)
    assert str(m) in line and "unknown field 'strid'" in line


def test_bad_per_sequence_key_names_the_sequence(no_runner, tmp_path):
    m = tmp_path / "m.csv"
    m.write_text("path,set\na,sampling.nope=3\n")
    r = invoke("batch", "--manifest", m, "--out", tmp_path / "o")
    assert r.exit_code == 2
    line = one_line_error(r)
    assert f"{m}:2" in line and "sampling.nope" in line


def test_duplicate_names_exit_2(no_runner, tmp_path):
    r = invoke("batch", tmp_path / "x" / "seq", tmp_path / "y" / "seq", "--out", tmp_path / "o")
    assert r.exit_code == 2 and "give each sequence its own 'name'" in r.output


# -- exit status and summary, with the runner replaced by known rows ------------------------------------------
def _fake_runner(monkeypatch, outcome):
    """run_batch stub: each job gets the status `outcome(job)` returns (or raises it)."""
    import trianflow_vo.batch.runner as runner
    from trianflow_vo.batch.jobs import new_result

    calls = []

    def fake(jobs, out_root, configs, **kw):
        calls.append((jobs, kw))
        rows = []
        for job in jobs:
            status = outcome(job)
            row = new_result(job, Path(out_root) / job.out, status, None if status == "completed" else "boom")
            row.update(frames=10, task_s=1.0)
            kw["on_result"](row)
            rows.append(row)
        return rows

    monkeypatch.setattr(runner, "run_batch", fake)
    monkeypatch.setenv("RAY_USAGE_STATS_ENABLED", "0")
    return calls


def test_exit_0_when_all_completed_and_options_reach_the_runner(monkeypatch, tmp_path):
    calls = _fake_runner(monkeypatch, lambda job: "completed")
    r = invoke("batch", tmp_path / "a", tmp_path / "b", "--out", tmp_path / "o", "--workers", 3, "--timeout", 60,
               "--force", "--sweep", "sampling.seed=1,2", "-q")
    assert r.exit_code == 0, r.output
    assert "4/4 completed" in r.output
    jobs, kw = calls[0]
    assert [j.out for j in jobs] == ["a/sampling.seed=1", "a/sampling.seed=2", "b/sampling.seed=1",
                                     "b/sampling.seed=2"]
    assert kw["workers"] == 3 and kw["timeout"] == 60.0 and kw["force"] is True and kw["address"] is None
    md = (tmp_path / "o" / "summary.md").read_text()
    assert "--sweep sampling.seed=1,2" in md and md.count("| a |") == 2


def test_exit_1_when_one_failed_summary_written(monkeypatch, tmp_path):
    _fake_runner(monkeypatch, lambda job: "failed" if job.name == "b" else "completed")
    r = invoke("batch", tmp_path / "a", tmp_path / "b", "--out", tmp_path / "o")
    assert r.exit_code == 1
    assert "failed: b: boom" in r.output and "1/2 completed" in r.output
    assert "b,,failed,boom" in (tmp_path / "o" / "summary.csv").read_text()


def test_progress_line_counts_and_rate(monkeypatch, tmp_path):
    """The live view (not a terminal here: one line whenever the counts change)."""
    import trianflow_vo.batch.runner as runner
    from trianflow_vo.batch.jobs import new_result

    def fake(jobs, out_root, configs, **kw):
        P = runner.BatchProgress
        kw["on_progress"](P(total=2, completed=0, failed=0, running=2, pending=0, frames=0, elapsed_s=0.5, workers=2))
        kw["on_progress"](P(total=2, completed=0, failed=0, running=2, pending=0, frames=9, elapsed_s=1.5, workers=2))
        row = new_result(jobs[1], Path(out_root) / jobs[1].out, "failed", "InputError: b: no images")
        kw["on_result"](row)
        kw["on_progress"](P(total=2, completed=0, failed=1, running=1, pending=0, frames=20, elapsed_s=4.0, workers=2))
        done = new_result(jobs[0], Path(out_root) / jobs[0].out, "completed")
        kw["on_result"](done)
        kw["on_progress"](P(total=2, completed=1, failed=1, running=0, pending=0, frames=30, elapsed_s=6.0, workers=2))
        return [done, row]

    monkeypatch.setattr(runner, "run_batch", fake)
    monkeypatch.setenv("RAY_USAGE_STATS_ENABLED", "0")
    r = invoke("batch", tmp_path / "a", tmp_path / "b", "--out", tmp_path / "o")
    assert r.exit_code == 1
    lines = r.output.splitlines()
    assert lines[:4] == [
        "0/2 done (0 failed), 2 running, 0 pending  0 frames  -- frames/s  0:00",  # the same counts: not repeated
        "failed: b: InputError: b: no images",
        "1/2 done (1 failed), 1 running, 0 pending  20 frames  5.0 frames/s  0:04",
        "2/2 done (1 failed), 0 running, 0 pending  30 frames  5.0 frames/s  0:06",
    ]
    assert "workers: 2" in (tmp_path / "o" / "summary.md").read_text()
    r = invoke("batch", tmp_path / "a", tmp_path / "b", "--out", tmp_path / "o", "-q")
    assert "frames/s" not in r.output and "failed: b: InputError: b: no images" in r.output


def test_runner_that_cannot_start_still_writes_summary(monkeypatch, tmp_path):
    import trianflow_vo.batch.runner as runner

    def fail(*a, **k):
        raise ConnectionError("could not connect to ray://nowhere:10001")

    monkeypatch.setattr(runner, "run_batch", fail)
    monkeypatch.setenv("RAY_USAGE_STATS_ENABLED", "0")
    r = invoke("batch", tmp_path / "a", "--out", tmp_path / "o", "--address", "ray://nowhere:10001")
    assert r.exit_code == 1
    assert one_line_error(r) == ("Error: the batch could not run: ConnectionError: could not connect to "
                                 "ray://nowhere:10001")
    text = (tmp_path / "o" / "summary.csv").read_text()
    assert "a,,pending,not run: ConnectionError" in text


def test_unreachable_cluster_one_line_at_once(monkeypatch, tmp_path):
    pytest.importorskip("ray", reason="ray is not installed (pip install 'trianflow-vo[batch]')")
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again: nothing listens there
    monkeypatch.setenv("RAY_USAGE_STATS_ENABLED", "0")
    r = invoke("batch", tmp_path / "a", "--out", tmp_path / "o", "--address", f"ray://127.0.0.1:{port}")
    assert r.exit_code == 1
    assert one_line_error(r) == ("Error: the batch could not run: cannot reach the Ray cluster at "
                                 f"ray://127.0.0.1:{port} (Connection refused); is `ray start --head` running there, "
                                 "and is the port open to this machine?")
    assert 'a,,pending,"not run: cannot reach the Ray cluster' in (tmp_path / "o" / "summary.csv").read_text()


def test_interrupted_batch_exit_130_with_summary(monkeypatch, tmp_path):
    import trianflow_vo.batch.runner as runner
    from trianflow_vo.batch.jobs import new_result

    def interrupted(jobs, out_root, configs, **kw):
        rows = [new_result(jobs[0], Path(out_root) / jobs[0].out, "interrupted", "batch interrupted"),
                new_result(jobs[1], Path(out_root) / jobs[1].out, "pending", "not started (batch interrupted)")]
        raise runner.BatchInterrupted(rows)

    monkeypatch.setattr(runner, "run_batch", interrupted)
    monkeypatch.setenv("RAY_USAGE_STATS_ENABLED", "0")
    r = invoke("batch", tmp_path / "a", tmp_path / "b", "--out", tmp_path / "o")
    assert r.exit_code == 130
    text = (tmp_path / "o" / "summary.csv").read_text()
    assert "a,,interrupted,batch interrupted" in text and "b,,pending,not started" in text
