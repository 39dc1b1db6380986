"""``trianflow-vo run``: nothing lost, nothing silent.

Concurrent runs, locked and earlier-run folders, signals, a full disk, bad Rerun
paths, huge working sizes, absurd intrinsics, and the progress line (skipped
frames, one frame rate, ETA). Runs are a few frames of the shipped sample; the
cases that need a real process (two runs at once, signals, a file-size limit)
run the command in a subprocess.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from datetime import datetime, timedelta
from pathlib import Path

import pytest
from click.testing import CliRunner

from synthetic_sequences import make_sequence
from trianflow_vo.cli.main import main

FAST = ("--end", "9", "--stride", "2", "--no-plot")  # 5 frames at the default size
SMALL = ("--size", "128x384")


def invoke(*args) -> object:
    return CliRunner().invoke(main, [str(a) for a in args])


def one_line_error(r, *needles: str, code: int) -> str:
    assert r.exit_code == code, r.output
    assert isinstance(r.exception, SystemExit), repr(r.exception)
    assert "Traceback" not in r.output
    errs = [ln for ln in r.output.splitlines() if ln.startswith("Error")]
    assert len(errs) == 1, r.output
    for n in needles:
        assert n in errs[0], (n, errs[0])
    return errs[0]


def cli(*args, cwd: Path, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "trianflow_vo.cli", *map(str, args)], cwd=cwd,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


def lines(path: Path) -> list[str]:
    text = path.read_text()
    assert text == "" or text.endswith("\n"), f"{path}: last line cut"
    return text.splitlines()


def status(out: Path) -> dict:
    return json.loads((out / "run.json").read_text())


# --------------------------------------------------------------------------- 1. folder and lock


def test_two_runs_at_once_with_the_default_folder_get_two_valid_folders(sample_seq, tmp_path):
    ref = tmp_path / "ref"
    assert invoke("run", sample_seq, *FAST, "-q", "--out", ref).exit_code == 0
    # the next seconds' default names are taken, so both runs race for the same "-2" name
    now = datetime.now()
    for s in range(40):
        (tmp_path / "runs" / f"kitti00-{(now + timedelta(seconds=s)).strftime('%Y%m%d-%H%M%S')}").mkdir(
            parents=True, exist_ok=True)
    procs = [cli("run", sample_seq, *FAST, "-q", cwd=tmp_path) for _ in range(2)]
    outs = [p.communicate(timeout=120) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    written = sorted(d for d in (tmp_path / "runs").iterdir() if (d / "poses.txt").exists())
    assert len(written) == 2, written
    assert {o.strip() for o, _ in outs} == {f"wrote {Path('runs') / d.name}" for d in written}
    for d in written:
        assert (d / "poses.txt").read_bytes() == (ref / "poses.txt").read_bytes()
        assert status(d)["status"] == "completed" and not (d / ".lock").exists()


def test_folder_locked_by_a_live_run_is_refused_with_one_line(sample_seq, tmp_path):
    import socket

    out = tmp_path / "out"
    out.mkdir()
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (out / ".lock").write_text(f"{live.pid}\n{socket.gethostname()}\n")
        r = invoke("run", sample_seq, *FAST, "--out", out)
        one_line_error(r, str(out), f"pid {live.pid}", "in use", code=1)
        assert sorted(p.name for p in out.iterdir()) == [".lock"]
    finally:
        live.kill()
        live.wait()


def test_stale_lock_is_taken_over_with_a_notice(sample_seq, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    (out / ".lock").write_text(f"{p.pid}\n")
    r = invoke("run", sample_seq, *FAST, "--out", out)
    assert r.exit_code == 0, r.output
    notices = [ln for ln in r.output.splitlines() if "stale lock" in ln]
    assert len(notices) == 1 and notices[0].startswith("warning:") and str(p.pid) in notices[0], r.output
    assert status(out)["status"] == "completed" and not (out / ".lock").exists()


# --------------------------------------------------------------------------- 4. earlier run in --out


def test_out_with_an_earlier_run_is_refused_unless_overwrite(sample_seq, tmp_path):
    out = tmp_path / "out"
    assert invoke("run", sample_seq, "--end", "5", "-q", "--out", out).exit_code == 0
    assert (out / "trajectory.png").exists()
    (out / "notes.md").write_text("keep me")
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    r = invoke("run", sample_seq, *FAST, "--out", out)
    one_line_error(r, str(out), "earlier run", "--overwrite", code=1)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    r = invoke("run", sample_seq, *FAST, "-q", "--out", out, "--overwrite")
    assert r.exit_code == 0, r.output
    assert not (out / "trajectory.png").exists()  # --no-plot: the earlier plot is gone, not stale
    assert (out / "notes.md").read_text() == "keep me"
    assert len(lines(out / "poses.txt")) == 5 and status(out)["frames_processed"] == 5


# --------------------------------------------------------------------------- 2. final status on every exit


def _default_signals() -> None:
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, signal.SIG_DFL)


@pytest.mark.parametrize("sig, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_signals_close_the_run_as_interrupted(sample_seq, tmp_path, sig, code):
    out = tmp_path / "out"
    # the run starts with the signals' default actions: a test process launched in the background by a
    # non-interactive shell ignores SIGINT, the child would inherit that, and the run rightly keeps a
    # caller's SIG_IGN (it then finished all 48 frames: exit 0, not 130)
    p = cli("run", sample_seq, *SMALL, "--no-plot", "--out", out, cwd=tmp_path, preexec_fn=_default_signals)
    deadline = time.monotonic() + 60
    # two frames complete: frames.tsv is the last of the four files a frame writes (header + 2 rows). Waiting
    # on frames.txt raced: a signal between its line and frames.tsv's takes the frame back (n = 1), as it should
    while not ((out / "frames.tsv").exists() and (out / "frames.tsv").read_text().count("\n") >= 3):
        assert p.poll() is None and time.monotonic() < deadline, p.communicate()
        time.sleep(0.02)
    assert p.poll() is None, p.communicate()  # the premise: the run is still going
    p.send_signal(sig)
    _, err = p.communicate(timeout=60)
    assert p.returncode == code, err
    name = signal.Signals(sig).name
    assert ("interrupted: " if sig == signal.SIGINT else "interrupted (SIGTERM): ") + \
        f"the trajectory so far is in {out}" in err
    assert "Traceback" not in err
    doc = status(out)
    assert doc["status"] == "interrupted" and doc["signal"] == name and doc["error"] is None
    n = doc["frames_processed"]
    assert 2 <= n < 48 and len(lines(out / "poses.txt")) == n == len(lines(out / "frames.txt"))
    assert not (out / ".lock").exists()


def test_rerun_observer_failing_after_the_folder_exists_says_failed(sample_seq, tmp_path, monkeypatch):
    import trianflow_vo.viz.rerun_logger as rl
    from trianflow_vo.errors import VOError

    def cannot_start(*a, **k):
        raise VOError("cannot start the Rerun viewer: spawn failed")

    monkeypatch.setattr(rl, "RerunObserver", cannot_start)
    out = tmp_path / "out"
    r = invoke("run", sample_seq, *FAST, "--out", out, "--rerun", out / "rec.rrd")
    one_line_error(r, "spawn failed", code=1)
    doc = status(out)
    assert doc["status"] == "failed" and doc["error"] == "VOError: cannot start the Rerun viewer: spawn failed"


# --------------------------------------------------------------------------- 5. Rerun paths, before the folder


def _no_display(monkeypatch):
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)


@pytest.mark.parametrize("case", ["missing-parent", "folder", "spawn-no-display", "no-rerun-sdk"])
def test_rerun_problems_are_one_line_before_the_run_folder(sample_seq, tmp_path, monkeypatch, case):
    out = tmp_path / "out"
    if case == "missing-parent":
        args, needles, code = ("--rerun", tmp_path / "nonexistent" / "x.rrd"), ("does not exist",), 2
    elif case == "folder":
        args, needles, code = ("--rerun", tmp_path), ("is a folder",), 2
    elif case == "spawn-no-display":
        _no_display(monkeypatch)
        args, needles, code = ("--rerun-spawn",), ("no display", "--rerun"), 1
    else:
        monkeypatch.setitem(sys.modules, "rerun", None)
        args, needles, code = ("--rerun", tmp_path / "x.rrd"), ("rerun-sdk", ">=0.41"), 1
    r = invoke("run", sample_seq, *FAST, "--out", out, *args)
    one_line_error(r, *needles, code=code)
    assert not out.exists() and not (tmp_path / "nonexistent").exists() and not (tmp_path / "x.rrd").exists()


def test_rerun_problems_leave_no_default_folder(sample_seq, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    r = invoke("run", sample_seq, *FAST, "--rerun", "/nonexistent-dir-for-test/x.rrd")
    one_line_error(r, "does not exist", code=2)
    assert not Path("/nonexistent-dir-for-test").exists()
    assert not (tmp_path / "runs").exists()  # neither the run folder nor runs/ itself


# --------------------------------------------------------------------------- 3. disk full


def test_file_size_limit_keeps_whole_lines_and_names_the_file(tmp_path):
    """A real short write: RLIMIT_FSIZE lets poses.txt grow to 16000 bytes (a whole number of lines and a part);
    the other files (config.yaml with its comments, about 12.7 kB, and run.json, about 5.5 kB) stay under it. The
    shipped sample is too short for that (48 frames, about 9.5 kB of poses), so the run is a rendered 140-frame clip."""
    resource = pytest.importorskip("resource")
    seq = tmp_path / "seq"
    make_sequence("urban_turn", seq, n_frames=140, seed=2, size=(128, 384))  # a small run.json
    out = tmp_path / "out"
    limit = 16000

    def limit_files():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG instead of being killed
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    p = subprocess.run([sys.executable, "-B", "-m", "trianflow_vo.cli", "run", str(seq),
                        "--no-plot", "-q", "--out", str(out)],
                       cwd=tmp_path, capture_output=True, text=True, timeout=120, preexec_fn=limit_files)
    assert p.returncode == 1, p.stderr
    err = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert err == [f"Error: {out / 'poses.txt'}: File too large"], p.stderr
    poses = lines(out / "poses.txt")
    raw = (out / "poses.txt").read_bytes()
    assert len(raw) <= limit and raw.endswith(b"\n") and 30 < len(poses) < 140  # whole lines up to the limit
    assert all(len(x.split()) == 12 for x in poses)
    assert len(lines(out / "frames.txt")) == len(poses) == len(lines(out / "frames.tsv")) - 1
    doc = status(out)
    assert doc["status"] == "failed" and doc["error"] == f"OSError: {out / 'poses.txt'}: File too large"


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="needs /proc/self/fd")
def test_disk_full_is_one_line_naming_the_file(sample_seq, tmp_path, monkeypatch):
    import errno

    real = os.write
    count = {"n": 0}

    def enospc_on_frames(fd, data):
        if os.path.basename(os.readlink(f"/proc/self/fd/{fd}")) == "frames.txt":
            count["n"] += 1
            if count["n"] > 3:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(fd, data)

    monkeypatch.setattr(os, "write", enospc_on_frames)
    out = tmp_path / "out"
    r = invoke("run", sample_seq, *FAST, "--out", out)
    monkeypatch.undo()
    one_line_error(r, f"{out / 'frames.txt'}: No space left on device", code=1)
    assert len(lines(out / "poses.txt")) == len(lines(out / "frames.txt")) == 3  # the 4th frame taken back
    assert status(out)["status"] == "failed"


# --------------------------------------------------------------------------- 6. huge working size


@pytest.mark.parametrize("args", [("--size", "64000x64000"), ("--set", "input.size=8192x64"),
                                  ("--set", "input.size=[64, 64000]")])
def test_huge_size_is_one_line_exit_2(sample_seq, tmp_path, args):
    r = invoke("run", sample_seq, *FAST, "--out", tmp_path / "out", *args)
    one_line_error(r, "input.size", "at most 4096 per side", code=2)
    assert not (tmp_path / "out").exists()


def test_size_that_does_not_fit_in_memory_is_one_line_exit_2(sample_seq, tmp_path, monkeypatch):
    import trianflow_vo.pipeline as pl

    monkeypatch.setattr(pl, "available_memory", lambda: 200 * 1024 ** 2)
    r = invoke("run", sample_seq, *FAST, "--out", tmp_path / "out", "--size", "4096x4096")
    one_line_error(r, "4096x4096", "GiB", "available", "--size", code=2)
    assert not (tmp_path / "out").exists()


def test_help_states_the_size_limit():
    r = invoke("run", "--help")
    assert "4096 per side" in " ".join(r.output.split())


# --------------------------------------------------------------------------- 7. absurd intrinsics


@pytest.mark.parametrize("how", ["intrinsics-cx", "intrinsics-zero", "calib-tiny-focal", "calib-cy", "sequence-calib"])
def test_absurd_intrinsics_are_one_line(sample_seq, tmp_path, how):
    seq = sample_seq
    calib = tmp_path / "K.txt"
    if how == "intrinsics-cx":
        args, needles, code = ("--intrinsics", "718.9,718.9,60000,185"), ("principal point", "--intrinsics"), 1
    elif how == "intrinsics-zero":
        args, needles, code = ("--intrinsics", "0,718.9,607,185"), ("focal",), 2
    elif how == "calib-tiny-focal":
        calib.write_text("1e-9 0 607\n0 1e-9 185\n0 0 1\n")
        args, needles, code = ("--calib", calib), ("focal", str(calib)), 1
    elif how == "calib-cy":
        calib.write_text("718.9 718.9 607 -5000\n")
        args, needles, code = ("--calib", calib), ("principal point", str(calib)), 1
    else:
        seq = tmp_path / "seq"
        (seq / "image_0").mkdir(parents=True)
        for i in range(3):
            (seq / "image_0" / f"{i:06d}.jpg").write_bytes((sample_seq / "image_0" / f"{i:06d}.jpg").read_bytes())
        (seq / "calib.txt").write_text("P0: 718.856 0 -9000 0 0 718.856 185.2 0 0 0 1 0\n")
        args, needles, code = (), ("principal point", "calib.txt:P0"), 1
    r = invoke("run", seq, "--no-plot", "--out", tmp_path / "out", *args)
    one_line_error(r, *needles, code=code)
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- 16-18. progress


def _seq_with_last_frame_broken(sample_seq: Path, folder: Path, n: int) -> None:
    folder.mkdir()
    for i in range(n):
        (folder / f"{i:06d}.jpg").write_bytes((sample_seq / "image_0" / f"{2 * i:06d}.jpg").read_bytes())
    last = folder / f"{n - 1:06d}.jpg"
    last.write_bytes(last.read_bytes()[:200])


def test_progress_counts_skipped_frames(sample_seq, tmp_path):
    seq = tmp_path / "seq"
    _seq_with_last_frame_broken(sample_seq, seq, 5)
    r = invoke("run", seq, "--intrinsics", "718.856,718.856,607.1928,185.2157", *SMALL, "--no-plot",
               "--out", tmp_path / "out")
    assert r.exit_code == 0, r.output
    progress = [ln for ln in r.output.splitlines() if re.match(r"\d+/\d+ frames", ln)]
    assert progress and progress[-1].startswith("5/5 frames (1 skipped)"), r.output
    assert "4 frames (1 skipped)" in r.output


def test_one_frame_rate_for_progress_run_json_and_summary(sample_seq, tmp_path, monkeypatch):
    """Time spent after the last frame (a slow observer closing) is in none of the three."""
    import trianflow_vo.pipeline as pl
    from trianflow_vo.observer import Observer

    class SlowClose(Observer):
        def close(self, interrupted=False):
            time.sleep(0.8)

    real_run = pl.run
    monkeypatch.setattr(pl, "run", lambda seq, out, config, observers=(), **kw:
                        real_run(seq, out, config, observers=[*observers, SlowClose()], **kw))
    out = tmp_path / "out"
    r = invoke("run", sample_seq, *FAST, "--out", out)
    assert r.exit_code == 0, r.output
    doc = status(out)
    fps = f"{doc['fps']:.1f}"
    assert doc["fps"] == pytest.approx(doc["frames_processed"] / doc["elapsed_s"])
    bar = [ln for ln in r.output.splitlines() if re.match(r"\d+/\d+ frames", ln)][-1]
    assert re.search(r"\s([\d.]+) fps", bar).group(1) == fps, bar
    summary = next(ln for ln in r.output.splitlines() if "frames/s" in ln)
    assert f"in {doc['elapsed_s']:.1f} s, {fps} frames/s" in summary, summary


def test_progress_bar_shows_an_eta(monkeypatch):
    from trianflow_vo.cli.run_cmd import Progress
    from trianflow_vo.frame import Branch
    from trianflow_vo.io.run_writer import RunClock

    class Rec:
        branch = Branch.TWO_VIEW

    t = [0.0]
    clock = RunClock(clock=lambda: t[0])
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True, raising=False)
    progress = Progress(enabled=True, clock=clock)
    progress.on_start(1000)
    clock.start(1000)
    for _ in range(100):
        t[0] += 2.0
        clock.frame_done()
    progress.counts = {}
    line = progress.line()
    assert line.startswith("100/1000 frames") and "0.5 fps" in line and "ETA 30:00" in line, line
    for _ in range(890):
        t[0] += 2.0
        clock.frame_done()
    assert "990/1000 frames" in progress.line() and "ETA 0:20" in progress.line(), progress.line()
    for _ in range(10):
        t[0] += 2.0
        clock.frame_done()
    assert "ETA" not in progress.line()  # done
