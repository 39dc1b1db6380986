"""The runner's decisions before and around Ray, checked without starting Ray (a stand-in ``ray`` module):
a local batch starts its own Ray even when a cluster runs on the machine, an unreachable cluster address is
refused at once, SIGTERM keeps the caller's handler (and its signal number), a MemoryError is reported as
out of memory.
"""

from __future__ import annotations

import os
import signal
import socket
import time

import pytest

import trianflow_vo.batch.runner as runner
from trianflow_vo.batch.jobs import run_job
from trianflow_vo.batch.manifest import expand_jobs, sequences_from_args
from trianflow_vo.errors import InputError


class _Stop(Exception):
    pass


class FakeRay:
    """Records ``ray.init``'s arguments, then stops the batch (nothing runs)."""

    def __init__(self):
        self.init_calls: list[dict] = []

    def is_initialized(self) -> bool:
        return False

    def init(self, **kwargs):
        self.init_calls.append(kwargs)
        raise _Stop("stop here")


@pytest.fixture
def fake_ray(monkeypatch):
    fake = FakeRay()
    monkeypatch.setattr(runner, "import_ray", lambda: fake)
    return fake


def _jobs(tmp_path, *overrides):
    return expand_jobs(sequences_from_args([tmp_path / "seq"]), overrides=list(overrides))


def test_local_batch_starts_its_own_ray_even_with_a_cluster_on_the_machine(fake_ray, tmp_path):
    # plain ray.init() joins a cluster started here with `ray start --head` (and then refuses num_cpus)
    with pytest.raises(_Stop):
        runner.run_batch(_jobs(tmp_path, "runtime.threads=2"), tmp_path / "out", workers=3)
    (kw,) = fake_ray.init_calls
    assert kw["address"] == "local" and kw["num_cpus"] == 6  # 3 workers x 2 threads


def test_cluster_address_goes_to_ray(fake_ray, tmp_path):
    with pytest.raises(_Stop):
        runner.run_batch(_jobs(tmp_path), tmp_path / "out", address="auto")
    (kw,) = fake_ray.init_calls
    assert kw["address"] == "auto" and "num_cpus" not in kw


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]  # nothing listens there once closed


@pytest.mark.parametrize("form", ["{port}", "ray://{port}"])
def test_unreachable_address_refused_at_once(fake_ray, tmp_path, form):
    address = form.format(port=f"127.0.0.1:{_closed_port()}")
    t0 = time.perf_counter()
    with pytest.raises(InputError, match=rf"cannot reach the Ray cluster at {address} \(Connection refused\)"):
        runner.run_batch(_jobs(tmp_path), tmp_path / "out", address=address)
    assert time.perf_counter() - t0 < 5.0
    assert fake_ray.init_calls == []  # Ray was not asked (it would retry for 30 s to minutes)


def test_reachable_address_and_auto_pass_the_check():
    with socket.socket() as srv:
        srv.bind(("127.0.0.1", 0))
        srv.listen(1)
        port = srv.getsockname()[1]
        runner.check_reachable(f"127.0.0.1:{port}")
        runner.check_reachable(f"ray://127.0.0.1:{port}")
    runner.check_reachable("auto")  # left to Ray
    runner.check_reachable("ray://headnode")  # no port: Ray's default


def test_signal_watch_keeps_the_callers_handler_and_notes_the_signal():
    seen = []

    def callers_handler(signum, frame):
        seen.append(signum)

    before = signal.getsignal(signal.SIGTERM)
    sigint = signal.getsignal(signal.SIGINT)
    signal.signal(signal.SIGTERM, lambda s, f: None)  # what ray.init leaves (its own handler)
    try:
        watch = runner._SignalWatch({signal.SIGTERM: callers_handler, signal.SIGINT: signal.SIG_DFL})
        assert signal.getsignal(signal.SIGINT) is sigint  # a default handler is not taken over
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.05)  # the handler runs in the main thread at the next bytecode
        assert seen == [signal.SIGTERM] and watch.signum == signal.SIGTERM
        watch.close()
        assert signal.getsignal(signal.SIGTERM) is not callers_handler
    finally:
        signal.signal(signal.SIGTERM, before)


def test_memory_error_is_reported_as_out_of_memory(monkeypatch, tmp_path):
    import trianflow_vo.pipeline as pipeline

    def no_memory(*a, **k):
        raise MemoryError("Unable to allocate 3.00 GiB for an array with shape (1024, 1024, 384)")

    monkeypatch.setattr(pipeline, "run", no_memory)
    (job,) = _jobs(tmp_path)
    row = run_job(job, tmp_path / "out")
    assert row["status"] == "failed"
    assert row["reason"] == ("out of memory: Unable to allocate 3.00 GiB for an array with shape (1024, 1024, 384); "
                             "use a smaller working size (input.size), fewer threads or fewer --workers")


def test_cluster_that_refuses_the_driver_hints_at_the_token(monkeypatch, tmp_path):
    class Refusing(FakeRay):
        def init(self, **kwargs):
            self.init_calls.append(kwargs)
            raise ConnectionError(f"Failed to connect to Ray cluster at {kwargs['address']}")

    fake = Refusing()
    monkeypatch.setattr(runner, "import_ray", lambda: fake)
    with socket.socket() as srv:  # reachable: the check passes, ray.init is asked and refuses
        srv.bind(("127.0.0.1", 0))
        srv.listen(1)
        address = f"127.0.0.1:{srv.getsockname()[1]}"
        with pytest.raises(InputError) as err:
            runner.run_batch(_jobs(tmp_path), tmp_path / "out", address=address)
    assert str(err.value) == (f"Failed to connect to Ray cluster at {address}; if the cluster uses token "
                              "authentication, set RAY_AUTH_MODE=token and its RAY_AUTH_TOKEN here as on the cluster")
