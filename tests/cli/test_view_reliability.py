"""``trianflow-vo view``: a recording left by a killed writer is reported as incomplete (and
still opens with --allow-incomplete); ``--web`` twice in a row works (a busy port is
replaced by a free one, or named when it was asked for)."""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

import trianflow_vo.cli.view_cmd as view_cmd
from trianflow_vo.cli.main import main

WRITER = textwrap.dedent("""
    import os, sys
    import numpy as np
    import rerun as rr
    rec = rr.RecordingStream("trianflow-vo-test", make_default=False)
    rec.save(sys.argv[1])
    for i in range(30):
        rec.set_time("frame", sequence=i)
        rec.log("points", rr.Points3D(np.random.default_rng(i).random((200, 3))))
        rec.flush()
    if sys.argv[2] == "kill":
        os.kill(os.getpid(), 9)  # as a run killed with SIGKILL (or by the OOM killer)
    rec.flush()
    del rec
""")


def write_recording(path: Path, mode: str) -> Path:
    """A real recording written by rerun-sdk in a child process: ``"finish"`` closes it,
    ``"kill"`` kills the writer before it can."""
    pytest.importorskip("rerun")
    res = subprocess.run([sys.executable, "-c", WRITER, str(path), mode], capture_output=True, timeout=120)
    if mode == "kill":
        assert res.returncode == -9, res.stderr
    else:
        assert res.returncode == 0, res.stderr
    assert path.stat().st_size > 1000
    return path


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    d = tmp_path_factory.mktemp("rrd")
    return write_recording(d / "finished.rrd", "finish"), write_recording(d / "killed.rrd", "kill")


@pytest.fixture
def with_display(monkeypatch):
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.setenv("DISPLAY", ":0")


def fake_viewer(monkeypatch, tmp_path):
    argv_file = tmp_path / "argv.json"
    code = f"import json, sys; json.dump(sys.argv[1:], open({str(argv_file)!r}, 'w'))"
    monkeypatch.setattr(view_cmd, "_viewer_command", lambda: [sys.executable, "-c", code])
    return argv_file


def invoke(*args):
    return CliRunner().invoke(main, ["view", *map(str, args)])


def one_error_line(res, *fragments) -> str:
    assert res.exit_code != 0
    assert isinstance(res.exception, SystemExit), res.exception
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error: "), res.stderr
    for f in fragments:
        assert f in lines[0], (f, lines[0])
    return lines[0]


# --------------------------------------------------------------------------- item 19: incomplete recordings


def test_killed_writer_is_reported_as_incomplete(recordings, with_display, monkeypatch, tmp_path):
    _, killed = recordings
    argv_file = fake_viewer(monkeypatch, tmp_path)
    one_error_line(invoke(killed), str(killed), "incomplete", "killed", "--allow-incomplete")
    assert not argv_file.exists()  # the viewer was not started on it


def test_incomplete_recording_opens_with_the_flag(recordings, with_display, monkeypatch, tmp_path):
    _, killed = recordings
    argv_file = fake_viewer(monkeypatch, tmp_path)
    res = invoke(killed, "--allow-incomplete")
    assert res.exit_code == 0, res.output
    warn = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(warn) == 1 and warn[0].startswith(f"warning: {killed}: incomplete"), res.stderr
    assert json.loads(argv_file.read_text()) == [str(killed)]


def test_finished_recording_opens_without_warning(recordings, with_display, monkeypatch, tmp_path):
    finished, _ = recordings
    argv_file = fake_viewer(monkeypatch, tmp_path)
    res = invoke(finished)
    assert res.exit_code == 0, res.output
    assert res.stderr == ""
    assert json.loads(argv_file.read_text()) == [str(finished)]


@pytest.mark.parametrize("cut_at", ["half", "in-footer", "header-only"])
def test_truncated_copies_are_incomplete(recordings, tmp_path, cut_at):
    """Cut anywhere (inside a message, inside the end of stream, after the header): incomplete."""
    finished, _ = recordings
    data = finished.read_bytes()
    n = {"half": len(data) // 2, "in-footer": len(data) - 64, "header-only": 12}[cut_at]
    cut = tmp_path / "cut.rrd"
    cut.write_bytes(data[:n])
    assert view_cmd.recording_end(cut) is not None
    assert view_cmd.recording_end(finished) is None


def test_rerun_agrees(recordings):
    """`rerun rrd verify` (which decodes everything) agrees with the quick check."""
    finished, killed = recordings
    for path, ok in ((finished, True), (killed, False)):
        res = subprocess.run([sys.executable, "-m", "rerun", "rrd", "verify", str(path)], capture_output=True,
                             timeout=120)
        assert (res.returncode == 0) == ok, res.stderr
        assert (view_cmd.recording_end(path) is None) == ok


# --------------------------------------------------------------------------- item 20: busy ports


@pytest.fixture
def busy_port():
    """A port something listens on (as a first viewer would)."""
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    s.bind(("0.0.0.0", 0))
    s.listen(1)
    yield s.getsockname()[1]
    s.close()


@pytest.fixture
def rrd(tmp_path):
    p = tmp_path / "out.rrd"
    p.write_bytes(b"RRF2" + bytes(60))  # header + end of stream (the viewer is replaced here)
    return p


def test_busy_default_web_port_is_replaced_by_a_free_one(rrd, busy_port, monkeypatch, tmp_path):
    monkeypatch.setattr(view_cmd, "DEFAULT_WEB_PORT", busy_port)
    argv_file = fake_viewer(monkeypatch, tmp_path)
    res = invoke(rrd, "--web")
    assert res.exit_code == 0, res.output
    argv = json.loads(argv_file.read_text())
    port = int(argv[argv.index("--web-viewer-port") + 1])
    assert port != busy_port and view_cmd.port_is_free(port)
    assert f"warning: port {busy_port} is busy" in res.stderr and f"port {port}" in res.stderr


def test_busy_port_asked_for_is_named_in_one_line(rrd, busy_port, monkeypatch, tmp_path):
    argv_file = fake_viewer(monkeypatch, tmp_path)
    one_error_line(invoke(rrd, "--web", "--web-port", busy_port), f"port {busy_port} is busy", "--web-port")
    assert not argv_file.exists()


def test_busy_data_port_is_replaced_too(rrd, busy_port, monkeypatch, tmp_path):
    """The viewer also listens for gRPC (9876): a second viewer fails on it as well."""
    monkeypatch.setattr(view_cmd, "DEFAULT_GRPC_PORT", busy_port)
    argv_file = fake_viewer(monkeypatch, tmp_path)
    res = invoke(rrd, "--web", "--web-port", "0")
    assert res.exit_code == 0, res.output
    argv = json.loads(argv_file.read_text())
    assert argv[:4] == [str(rrd), "--web-viewer", "--web-viewer-port", "0"]
    grpc = int(argv[argv.index("--port") + 1])
    assert grpc != busy_port and f"port {busy_port} is busy" in res.stderr


class _Viewer:
    """``trianflow-vo view REC --web`` in its own process group, its stderr collected."""

    HOSTING = re.compile(r"Hosting a web-viewer at http://[^:\s]+:(\d+)")

    def __init__(self, rec: Path):
        env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
        self.proc = subprocess.Popen([sys.executable, "-m", "trianflow_vo.cli", "view", str(rec), "--web"],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env,
                                     start_new_session=True)
        self.lines: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self):
        for ln in self.proc.stderr:
            self.lines.append(ln)

    def web_port(self, timeout: float = 60.0) -> int | None:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for ln in list(self.lines):
                m = self.HOSTING.search(ln)
                if m:
                    return int(m.group(1))
            if self.proc.poll() is not None:
                time.sleep(0.2)  # let the reader drain
                return None
            time.sleep(0.1)
        return None

    def stop(self):
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)  # our own group: the CLI and its viewer
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(timeout=10)


def test_view_web_twice_in_a_row(recordings):
    """The real viewer, twice: the second picks free ports instead of failing."""
    finished, _ = recordings
    first = _Viewer(finished)
    second = None
    try:
        p1 = first.web_port()
        assert p1 is not None, "".join(first.lines)
        second = _Viewer(finished)
        p2 = second.web_port()
        assert p2 is not None, "".join(second.lines)
        assert p2 != p1
        time.sleep(1.0)
        assert first.proc.poll() is None and second.proc.poll() is None, "".join(second.lines)
        if p1 == view_cmd.DEFAULT_WEB_PORT:
            assert any(f"port {p1} is busy" in ln for ln in second.lines), "".join(second.lines)
    finally:
        for v in (second, first):
            if v is not None:
                v.stop()
