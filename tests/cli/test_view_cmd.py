"""``trianflow-vo view``: clear one-line errors, and the viewer command it runs."""

from __future__ import annotations

import json
import sys

import pytest
from click.testing import CliRunner

import trianflow_vo.cli.view_cmd
from trianflow_vo.cli.main import main


@pytest.fixture
def rrd(tmp_path):
    """A file that starts like a recording (the viewer itself is replaced in these tests)."""
    p = tmp_path / "out.rrd"
    p.write_bytes(b"RRF2" + bytes(60))
    return p


@pytest.fixture
def with_display(monkeypatch):
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.setenv("DISPLAY", ":0")


@pytest.fixture
def without_display(monkeypatch):
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)


def fake_viewer(monkeypatch, tmp_path, exit_code=0):
    """Replace the Rerun CLI with a script recording its arguments and exiting with ``exit_code``."""
    argv_file = tmp_path / "argv.json"
    code = f"import json, sys; json.dump(sys.argv[1:], open({str(argv_file)!r}, 'w')); sys.exit({exit_code})"
    monkeypatch.setattr(trianflow_vo.cli.view_cmd, "_viewer_command", lambda: [sys.executable, "-c", code])
    return argv_file


def invoke(*args):
    return CliRunner().invoke(main, ["view", *map(str, args)])


def assert_one_line_error(res, *fragments):
    assert res.exit_code != 0
    assert isinstance(res.exception, SystemExit), res.exception  # no traceback
    err = res.output.strip()
    assert err.startswith("Error: ") and "\n" not in err, err
    for f in fragments:
        assert f in err, err


def test_missing_file(tmp_path, with_display):
    assert_one_line_error(invoke(tmp_path / "nope.rrd"), "nope.rrd", "no such file")


def test_directory(tmp_path, with_display):
    assert_one_line_error(invoke(tmp_path), str(tmp_path), "not a file")


def test_not_a_recording(tmp_path, with_display):
    p = tmp_path / "poses.txt"
    p.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    assert_one_line_error(invoke(p), "poses.txt", "not a Rerun recording")
    e = tmp_path / "empty.rrd"
    e.write_bytes(b"")
    assert_one_line_error(invoke(e), "empty.rrd", "empty file")


def test_no_display_says_so_and_suggests_web(rrd, without_display, monkeypatch, tmp_path):
    argv_file = fake_viewer(monkeypatch, tmp_path)
    assert_one_line_error(invoke(rrd), "no display", "DISPLAY", "--web")
    assert not argv_file.exists()  # the viewer was not started


def test_viewer_failure_is_one_line(rrd, with_display, monkeypatch, tmp_path):
    fake_viewer(monkeypatch, tmp_path, exit_code=3)
    assert_one_line_error(invoke(rrd), "exited with status 3", "out.rrd", "--web")


def test_viewer_cannot_start(rrd, with_display, monkeypatch):
    monkeypatch.setattr(trianflow_vo.cli.view_cmd, "_viewer_command", lambda: ["/nonexistent/rerun-viewer"])
    assert_one_line_error(invoke(rrd), "cannot start the Rerun viewer")


def test_opens_the_recording(rrd, with_display, monkeypatch, tmp_path):
    argv_file = fake_viewer(monkeypatch, tmp_path)
    res = invoke(rrd)
    assert res.exit_code == 0, res.output
    assert json.loads(argv_file.read_text()) == [str(rrd)]


def test_web_needs_no_display(rrd, without_display, monkeypatch, tmp_path):
    argv_file = fake_viewer(monkeypatch, tmp_path)
    res = invoke(rrd, "--web", "--web-port", "9123")
    assert res.exit_code == 0, res.output
    assert json.loads(argv_file.read_text()) == [str(rrd), "--web-viewer", "--web-viewer-port", "9123"]


def test_missing_rerun_sdk(rrd, with_display, monkeypatch):
    real = trianflow_vo.cli.view_cmd.importlib.util.find_spec
    monkeypatch.setattr(trianflow_vo.cli.view_cmd.importlib.util, "find_spec",
                        lambda name, *a: None if name == "rerun" else real(name, *a))
    assert_one_line_error(invoke(rrd), "rerun-sdk", "pip install")


def test_viewer_command_is_this_python():
    pytest.importorskip("rerun")
    assert trianflow_vo.cli.view_cmd._viewer_command() == [sys.executable, "-m", "rerun"]


def test_web_option_is_supported_by_the_installed_rerun():
    """The flags ``--web`` passes exist in the installed Rerun CLI."""
    pytest.importorskip("rerun")
    import subprocess

    res = subprocess.run([sys.executable, "-m", "rerun", "--help"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0
    assert "--web-viewer-port" in res.stdout and "--web-viewer" in res.stdout
