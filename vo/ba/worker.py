"""The worker process window adjustments run in (``backend.concurrent``).

GTSAM holds Python's global interpreter lock while it optimises, so a thread
cannot overlap an adjustment with the front-end; a process can. This module is
what that process imports: nothing but NumPy and
:mod:`~trianflow_vo.ba.window` (GTSAM when the first window is solved).
"""

from __future__ import annotations

import os
import signal
import threading
import time

from trianflow_vo.ba.window import solve_window
from trianflow_vo.resources import peak_rss_mb


def init_worker(parent_pid: int | None = None, poll_s: float = 1.0, blas_threads: int | None = None) -> None:
    """Ctrl-C is the parent's: it stops the run and closes the worker itself. With ``parent_pid``,
    the worker also ends within ``poll_s`` seconds of its parent's death (a run killed with
    SIGKILL cannot close it, and the worker would otherwise wait forever for the next window).
    With ``blas_threads``, NumPy's BLAS uses that many threads in this process (for its life)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if blas_threads is not None:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=int(blas_threads), user_api="blas")
    if parent_pid is not None:
        threading.Thread(target=_exit_with_parent, args=(int(parent_pid), float(poll_s)), name="parent-watch",
                         daemon=True).start()


def _exit_with_parent(parent_pid: int, poll_s: float) -> None:
    while os.getppid() == parent_pid:
        time.sleep(poll_s)
    os._exit(0)


def warm_up() -> bool:
    """Import GTSAM ahead of the first window."""
    import gtsam  # noqa: F401

    return True


def solve_timed(args: tuple, kwargs: dict) -> tuple:
    """``(solve_window(*args, **kwargs), milliseconds it took, this process's peak RSS in MiB)``."""
    t0 = time.perf_counter()
    out = solve_window(*args, **kwargs)
    return out, (time.perf_counter() - t0) * 1000.0, peak_rss_mb()
