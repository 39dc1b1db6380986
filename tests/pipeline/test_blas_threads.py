"""``runtime.blas_threads``: NumPy's BLAS threads during a run, in the main process and the back-end worker.

OpenBLAS threads spin-wait between the run's small products on the cores the flow thread
and the back-end process need (benchmarks/README.md: 1.5x the frames/s on 2 cores with 1
thread, same poses). A run holds BLAS to the configured count and gives the caller's
setting back when it ends.
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor

import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from trianflow_vo.config import Config, merge_dict
from trianflow_vo.frame import FrameResult
from trianflow_vo.observer import Observer


def _blas_threads(info: list[dict]) -> list[int]:
    return [int(lib["num_threads"]) for lib in info if lib["user_api"] == "blas"]


@pytest.fixture
def blas_library():
    if not _blas_threads(threadpool_info()):
        pytest.skip("threadpoolctl finds no BLAS library under NumPy here (nothing to hold)")


class BlasSeen(Observer):
    """Records the BLAS thread counts at every frame of a run."""

    def __init__(self):
        self.seen: list[list[int]] = []

    def on_frame(self, rec: FrameResult) -> None:
        self.seen.append(_blas_threads(threadpool_info()))


@pytest.mark.parametrize("n", [1, 3])
def test_a_run_holds_blas_to_the_configured_threads_and_restores_the_callers(sample_seq, tmp_path, blas_library, n):
    from trianflow_vo.pipeline import run

    cfg = merge_dict(Config(), {"input": {"stride": 3, "end": 15}, "output": {"plot": False},
                                "backend": {"window": 0}, "runtime": {"blas_threads": n}}, "test")
    seen = BlasSeen()
    with threadpool_limits(limits=2, user_api="blas"):  # the caller's own setting, different from both
        run(sample_seq, tmp_path / "out", cfg, observers=[seen])
        after = _blas_threads(threadpool_info())
    assert len(seen.seen) == 5
    assert all(threads and set(threads) == {n} for threads in seen.seen), seen.seen
    assert set(after) == {2}


def test_the_default_is_one_blas_thread():
    assert Config().runtime.blas_threads == 1


@pytest.mark.parametrize("n", [1, 2])
def test_the_backend_worker_process_starts_with_the_configured_blas_threads(blas_library, n):
    pytest.importorskip("gtsam", reason="the worker module imports the window adjustment (gtsam)")
    from trianflow_vo.ba.worker import init_worker

    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"), initializer=init_worker,
                             initargs=(None, 1.0, n)) as pool:
        info = pool.submit(threadpool_info).result(timeout=120)
    assert set(_blas_threads(info)) == {n}, info


def test_run_json_names_the_blas_and_its_threads(sample_seq, tmp_path, blas_library):
    import json

    from trianflow_vo.pipeline import run

    cfg = merge_dict(Config(), {"input": {"stride": 3, "end": 9}, "output": {"plot": False},
                                "backend": {"window": 0}, "runtime": {"blas_threads": 1}}, "test")
    with threadpool_limits(limits=2, user_api="blas"):
        run(sample_seq, tmp_path / "out", cfg)
    blas = json.loads((tmp_path / "out" / "run.json").read_text())["versions"]["blas"]
    names = {lib["internal_api"] for lib in threadpool_info() if lib["user_api"] == "blas"}
    # every BLAS loaded (NumPy's, and e.g. SciPy's own once imported), each held to the run's one thread
    assert blas and all(b.endswith(", 1 thread(s)") for b in blas), blas
    assert {b.split()[0] for b in blas} <= names
