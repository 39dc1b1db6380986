"""write_atomic: whole files only, also with several processes writing the same file."""

import multiprocessing as mp

import pytest

from trianflow_vo.io.atomic import write_atomic


def _writer(path, payload, n):
    for _ in range(n):
        write_atomic(path, payload)


def test_replaces_the_file_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "a.json"
    target.write_bytes(b"old")
    assert write_atomic(target, b"new") == target
    assert target.read_bytes() == b"new"
    assert [p.name for p in tmp_path.iterdir()] == ["a.json"]


def test_failure_keeps_the_old_file(tmp_path):
    target = tmp_path / "a.json"
    target.write_bytes(b"old")
    with pytest.raises(TypeError):
        write_atomic(target, object())  # not bytes: fails while writing the temporary
    assert target.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["a.json"]


def test_two_processes_writing_one_file_at_once(tmp_path):
    """The ranks of a distributed run fill one cache file at the same time: no process fails
    and the file is always one writer's whole payload."""
    target = tmp_path / "cache.json"
    payloads = [b"a" * 50_000, b"b" * 50_000]
    ctx = mp.get_context("fork")
    procs = [ctx.Process(target=_writer, args=(target, p, 200)) for p in payloads]
    for p in procs:
        p.start()
    for p in procs:
        p.join(60)
    assert [p.exitcode for p in procs] == [0, 0]
    assert target.read_bytes() in payloads
    assert [p.name for p in tmp_path.iterdir()] == ["cache.json"]
