"""Run batch jobs on Ray: a fresh worker process per job, at most ``workers`` at once, resume,
timeouts, failures isolated, progress reported through callbacks.

Ray is imported inside the functions (``pip install 'trianflow-vo[batch]'``). Ray is started
locally (``address=None``: always a new instance, even when a cluster runs on this machine) or
joined (``"auto"``, ``"host:port"``, ``"ray://host:port"``; an address where nothing accepts a
connection is refused at once), and shut down at the end only if this call started or joined it;
an already initialised Ray (e.g. a test's) is used as is and left running. The caller's own
SIGINT/SIGTERM handlers stay in force while the batch runs (``ray.init`` replaces SIGTERM's).

Each job is one Ray task with ``max_calls=1`` (its worker process exits after it, so memory and
``peak_rss_mb`` are the run's own; the worker start, ~0.5-1 s, is part of every task) and
``max_retries=0`` (a crash is reported, not retried). It asks for ``runtime.threads`` CPUs. The
driver keeps at most ``workers`` tasks in flight, so a timeout counts from the submission of the
task (including its worker's start), not from when the batch started.

A task that exceeds ``timeout`` is cancelled (Ctrl-C in the worker: the pipeline closes the
folder, run.json ``interrupted``) and, if still running ``grace_s`` later, its worker is killed.
Either way the job is ``failed`` with reason ``timeout: ...`` and its ``run.json`` is changed to
``failed`` when the driver can see it, which also removes the lock a killed run left. A crashed or
out-of-memory worker is ``failed`` with a one-line reason; the other jobs go on.
"""

from __future__ import annotations

import logging
import os
import signal
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from trianflow_vo.batch.jobs import (
    earlier_state,
    fill_from_run,
    job_config,
    mark_stopped,
    new_result,
    read_run_json,
    run_job,
)
from trianflow_vo.batch.manifest import Job
from trianflow_vo.errors import DependencyError, InputError

INSTALL_HINT = "ray is not installed; install the batch extra: pip install 'trianflow-vo[batch]'"
LIVE_EVERY_S = 1.0  # how often the frames of running jobs are read from their run.json
REACH_TIMEOUT_S = 5.0  # a cluster address that accepts no connection within this is refused


def import_ray():
    """The ``ray`` module, or :class:`DependencyError` with the one-line install hint."""
    try:
        import ray
    except ImportError:
        raise DependencyError(INSTALL_HINT) from None
    return ray


def available_cores() -> int:
    """CPU cores this process may use (its affinity mask where known)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def default_workers(cpus: float, threads: int) -> int:
    """Runs at once by default: ``cpus // threads`` (at least 1)."""
    return max(1, int(cpus // max(1, threads)))


def check_reachable(address: str, timeout_s: float = REACH_TIMEOUT_S) -> None:
    """Refuse at once a cluster address (``host:port`` or ``ray://host:port``) where nothing accepts a
    connection: ``ray.init`` would retry for 30 s (Ray Client) to over 10 minutes (GCS address), printing
    dozens of lines. ``auto`` and addresses without a port are left to Ray.

    Raises:
        InputError: naming the address and the socket's reason.
    """
    import socket

    target = address[len("ray://"):] if address.startswith("ray://") else address
    host, sep, port = target.rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port.isdigit():
        return
    try:
        with socket.create_connection((host, int(port)), timeout=timeout_s):
            pass
    except OSError as e:
        why = e.strerror or str(e) or type(e).__name__
        raise InputError(f"cannot reach the Ray cluster at {address} ({why}); is `ray start --head` running there, "
                         f"and is the port open to this machine?") from None


@dataclass(frozen=True)
class BatchProgress:
    """A snapshot of a batch for a progress display.

    Attributes:
        total: jobs in the batch.
        completed, failed: jobs finished so far, by outcome (resumed ones count as completed).
        running: tasks in flight; ``pending``: not started yet.
        frames: frames processed by this batch: finished jobs (not resumed ones) plus what running ones
            reported in their run.json so far.
        elapsed_s: since the batch started.
        workers: runs at once.
    """

    total: int
    completed: int
    failed: int
    running: int
    pending: int
    frames: int
    elapsed_s: float
    workers: int

    @property
    def fps(self) -> float | None:
        """Frames per second of the whole batch (wall time), or None before the first second."""
        return self.frames / self.elapsed_s if self.elapsed_s >= 1.0 else None


class BatchInterrupted(KeyboardInterrupt):
    """Ctrl-C / SIGTERM in the driver: the running jobs were stopped; ``results`` holds every job's row
    (``interrupted`` for those that were running, ``pending`` for those never started)."""

    def __init__(self, results: list[dict], signum: int = signal.SIGINT):
        super().__init__("batch interrupted")
        self.results = results
        self.signum = int(signum)


def ray_failure(exc: BaseException) -> str:
    """One line for a Ray error: the job's own exception (``RayTaskError``), a crashed or killed
    worker, out of memory, a cancelled task."""
    import ray.exceptions as rex

    from trianflow_vo.pipeline import failure_reason

    if isinstance(exc, rex.TaskCancelledError):
        return "cancelled"
    if isinstance(exc, rex.OutOfMemoryError):
        return ("out of memory: Ray's memory monitor killed the worker (use a smaller working size, fewer "
                "--workers or fewer threads)")
    if isinstance(exc, rex.WorkerCrashedError):
        return "worker crashed (killed, out of memory, or a fault in native code); see the Ray worker logs"
    if isinstance(exc, rex.RayTaskError):
        cause = getattr(exc, "cause", None)
        if isinstance(cause, BaseException) and not isinstance(cause, rex.RayTaskError):
            return failure_reason(cause)
    first = " ".join(str(exc).split("\n", 1)[0].split())
    return f"{type(exc).__name__}: {first}" if first else type(exc).__name__


def _task(job: Job, out_root: str, config: dict, force: bool, cwd: str | None, setup, job_fn) -> dict:
    """The body of one Ray task, in its own worker process."""
    if cwd and os.path.isdir(cwd):
        os.chdir(cwd)  # relative paths in the configuration mean what they mean to the driver
    if setup is not None:
        setup()
    return (job_fn or run_job)(job, out_root, config, force=force)


def _failed_row(job: Job, out_root: Path, reason: str, status: str = "failed") -> dict:
    """The row of a job that did not return a result (timeout, crash, interrupted, never started), with
    what its run.json says when the driver can see it."""
    out_dir = out_root / job.out
    row = new_result(job, out_dir, status, reason)
    row.update({"host": None, "pid": None})
    if status != "pending":
        fill_from_run(row, read_run_json(out_dir))
    return row


def run_batch(
    jobs: Sequence[Job],
    out_root: str | Path,
    configs: Sequence | None = None,
    *,
    workers: int | None = None,
    address: str | None = None,
    timeout: float | None = None,
    force: bool = False,
    on_progress: Callable[[BatchProgress], None] | None = None,
    on_result: Callable[[dict], None] | None = None,
    worker_setup: Callable[[], object] | None = None,
    job_fn: Callable[..., dict] | None = None,
    poll_s: float = 0.25,
    grace_s: float = 5.0,
) -> list[dict]:
    """Run every job on Ray and return their result rows, in job order.

    Args:
        jobs: from :func:`trianflow_vo.batch.manifest.expand_jobs`.
        out_root: the batch folder ``DIR`` (made absolute; it must be visible to the workers).
        configs: each job's configuration (a ``Config``), or None to build them with
            :func:`~trianflow_vo.batch.jobs.job_config` here first (a bad key fails the whole batch
            before anything runs).
        workers: runs at once; default ``cores // runtime.threads`` locally, ``cluster CPUs // threads``
            on a cluster.
        address: None = start Ray locally; ``"auto"``, ``"host:port"`` (GCS) or ``"ray://host:port"`` (Ray Client) =
            join a cluster.
        timeout: seconds per job (None = no limit).
        force: run again jobs whose folder holds a completed run.
        on_progress: called with a :class:`BatchProgress` while the batch runs (about every ``poll_s``).
        on_result: called with each job's row as soon as it is known.
        worker_setup: called first in every worker process (e.g. the ``run`` command's allocator setting).
        job_fn: replaces :func:`~trianflow_vo.batch.jobs.run_job` in the workers (same arguments).
        poll_s: how long the driver waits for a result between checks.
        grace_s: time a cancelled (timed-out) task has to close its folder before its worker is killed.

    Returns:
        One row per job (see :func:`~trianflow_vo.batch.jobs.run_job`) plus ``task_s``: the time from
        submitting the task to its result (worker start included; None for jobs resumed here).

    Raises:
        DependencyError: Ray is not installed.
        ConfigError: a job's configuration is bad (``configs`` None only).
        InputError: bad ``workers`` / ``timeout``; a job needs more threads than Ray has CPUs; the cluster
            address accepts no connection, or the cluster refuses this driver (e.g. its token).
        BatchInterrupted: Ctrl-C or SIGTERM; the rows are in its ``results``.
    """
    ray = import_ray()
    if workers is not None and workers < 1:
        raise InputError(f"workers must be at least 1, got {workers}")
    if timeout is not None and not timeout > 0:
        raise InputError(f"timeout must be a positive number of seconds, got {timeout}")
    out_root = Path(out_root).absolute()
    jobs = list(jobs)
    configs = [job_config(j) for j in jobs] if configs is None else list(configs)
    if len(configs) != len(jobs):
        raise ValueError(f"{len(configs)} configurations for {len(jobs)} jobs")
    results: list[dict | None] = [None] * len(jobs)
    t_start = time.perf_counter()

    def finish(i: int, row: dict) -> None:
        results[i] = row
        if on_result is not None:
            on_result(row)

    # resume what the driver can see is complete, without a worker
    todo = []
    for i, (job, cfg) in enumerate(zip(jobs, configs)):
        if not force and earlier_state(out_root / job.out, job.seq, cfg)[0] == "completed":
            row = run_job(job, out_root, cfg, force=False)
            row["task_s"] = None
            finish(i, row)
        else:
            todo.append(i)
    if not todo:
        return results  # type: ignore[return-value]

    threads = max(c.runtime.threads for c in (configs[i] for i in todo))
    started = False
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}  # ray.init replaces them
    if not ray.is_initialized():
        init = {"include_dashboard": False, "log_to_driver": False, "logging_level": logging.ERROR}
        if address is None:
            n = workers or default_workers(available_cores(), threads)
            ray.init(address="local", num_cpus=n * threads, **init)  # a new local instance, even if one runs here
        else:
            check_reachable(address)
            try:
                ray.init(address=address, **init)
            except ConnectionError as e:  # reachable, but refused: most often a missing or wrong token
                what = " ".join(str(e).split()) or f"could not join the Ray cluster at {address}"
                raise InputError(f"{what}; if the cluster uses token authentication, set RAY_AUTH_MODE=token and "
                                 "its RAY_AUTH_TOKEN here as on the cluster") from None
        started = True
    watch = _SignalWatch(handlers)  # the caller's own handlers, back in place after ray.init, noting the signal
    try:
        cpus = ray.cluster_resources().get("CPU", 0)
        if threads > cpus:  # such a task would wait for ever
            raise InputError(f"runtime.threads={threads}, but Ray has only {cpus:g} CPUs; set fewer threads")
        if workers is None:
            workers = default_workers(cpus, threads)
        remote = ray.remote(max_calls=1, max_retries=0)(_task)
        cwd = os.getcwd()
        queue = list(todo)
        inflight: dict = {}  # ref -> [job index, t_submit, t_cancelled | None, killed]
        live: dict[int, int] = {}  # job index -> frames its run.json reports
        t_live = 0.0

        def progress() -> None:
            if on_progress is None:
                return
            done = [r for r in results if r is not None]
            frames = (sum(r["frames"] or 0 for r in done if not r.get("resumed"))
                      + sum(live.get(v[0], 0) for v in inflight.values()))
            on_progress(BatchProgress(
                total=len(jobs), completed=sum(r["status"] == "completed" for r in done),
                failed=sum(r["status"] != "completed" for r in done), running=len(inflight),
                pending=len(queue), frames=frames, elapsed_s=time.perf_counter() - t_start,
                workers=workers))

        try:
            while queue or inflight:
                while queue and len(inflight) < workers:
                    i = queue.pop(0)
                    opts = {"num_cpus": configs[i].runtime.threads}
                    ref = remote.options(**opts).remote(jobs[i], str(out_root), configs[i].to_dict(), force, cwd,
                                                        worker_setup, job_fn)
                    inflight[ref] = [i, time.perf_counter(), None, False]
                ready, _ = ray.wait(list(inflight), num_returns=1, timeout=poll_s)
                now = time.perf_counter()
                for ref in ready:
                    i, t_sub, t_cancel, _killed = inflight.pop(ref)
                    live.pop(i, None)
                    row = _collect(ray, ref, jobs[i], out_root, t_cancel is not None, timeout, grace_s)
                    row["task_s"] = now - t_sub
                    finish(i, row)
                if timeout is not None:
                    for ref, st in inflight.items():
                        i, t_sub, t_cancel, killed = st
                        if t_cancel is None and now - t_sub > timeout:
                            ray.cancel(ref, force=False)  # Ctrl-C in the worker: the folder is closed
                            st[2] = now
                        elif t_cancel is not None and not killed and now - t_cancel > grace_s:
                            ray.cancel(ref, force=True)  # still running: kill the worker
                            st[3] = True
                if on_progress is not None and now - t_live >= LIVE_EVERY_S:
                    t_live = now
                    for st in inflight.values():
                        doc = read_run_json(out_root / jobs[st[0]].out)
                        if doc is not None and doc.get("status") == "running":
                            live[st[0]] = int(doc.get("frames_processed") or 0)
                progress()
        except KeyboardInterrupt as exc:
            _stop_all(ray, inflight, grace_s)
            for st in inflight.values():
                # a run that had not closed its folder within the grace time was killed with its worker
                # (on a loaded machine 5 s can be too short): its folder is closed here
                _close_stopped(out_root / jobs[st[0]].out, grace_s,
                               "batch interrupted: the run was killed before it closed its folder", "interrupted")
                results[st[0]] = _failed_row(jobs[st[0]], out_root, "batch interrupted", "interrupted")
            for i in queue:
                results[i] = _failed_row(jobs[i], out_root, "not started (batch interrupted)", "pending")
            for r in results:
                if r is not None:
                    r.setdefault("task_s", None)
            signum = getattr(exc, "signum", None) or watch.signum or signal.SIGINT
            raise BatchInterrupted(results, signum) from None  # type: ignore[arg-type]
    finally:
        watch.close()
        if started:
            ray.shutdown()
            for s, h in handlers.items():  # the caller's process gets its own handlers back
                if h is not None:
                    signal.signal(s, h)
    return results  # type: ignore[return-value]


class _SignalWatch:
    """While a batch runs (main thread only): the caller's own SIGINT/SIGTERM handlers (``handlers``, as they
    were before ``ray.init``) are installed again, wrapped so that the signal number is noted in ``signum``.

    ``ray.init`` replaces the SIGTERM handler with its own (``sys.exit``, plus a native one printing a stack
    trace): a SIGTERM then ended the driver without stopping the jobs or writing their rows. And Ray turns an
    exception raised by a handler inside ``ray.wait`` into a plain ``KeyboardInterrupt``, which loses which
    signal it was (130 instead of 143). Default handlers (``SIG_DFL``, ``SIG_IGN``) are left to Ray.
    """

    def __init__(self, handlers: dict):
        import threading

        self.signum: int | None = None
        self._installed: dict = {}
        if threading.current_thread() is not threading.main_thread():
            return
        for s, h in handlers.items():
            if callable(h):
                self._installed[s] = signal.getsignal(s)
                signal.signal(s, self._wrap(h))

    def _wrap(self, handler):
        def noted(signum, frame):
            if self.signum is None:
                self.signum = signum
            return handler(signum, frame)

        return noted

    def close(self) -> None:
        """Put back the handlers found when the watch started."""
        for s, h in self._installed.items():
            signal.signal(s, h)
        self._installed.clear()


def _collect(ray, ref, job: Job, out_root: Path, timed_out: bool, timeout: float | None, grace_s: float) -> dict:
    """The row of a finished task: its result, or a failed row for a timeout, a crash, an error."""
    import ray.exceptions as rex

    try:
        row = ray.get(ref)
    except rex.RayError as exc:
        reason = f"timeout: stopped after {timeout:g} s" if timed_out else ray_failure(exc)
        _close_stopped(out_root / job.out, grace_s, reason)
        return _failed_row(job, out_root, reason)
    if timed_out and row.get("status") != "completed":  # the job saw the cancel and returned
        reason = f"timeout: stopped after {timeout:g} s"
        mark_stopped(out_root / job.out, reason)
        row.update({"status": "failed", "reason": reason})
    return row


def _close_stopped(out_dir: Path, wait_s: float, reason: str, status: str = "failed") -> None:
    """Close the folder of a run stopped from outside: wait (at most ``wait_s``) while the run may
    still be closing it, remove the lock a killed run could not, and set its ``run.json`` (when still
    ``running`` / ``interrupted``) to ``status`` with ``reason`` (:func:`mark_stopped`)."""
    from trianflow_vo.io.run_dir import clear_stale_lock

    _wait_unlocked(out_dir, wait_s)
    clear_stale_lock(out_dir)
    mark_stopped(out_dir, reason, status)


def _wait_unlocked(out_dir: Path, wait_s: float) -> None:
    """Wait (at most ``wait_s``) until no live run holds the folder: a cancelled run has closed its files."""
    from trianflow_vo.io.run_dir import lock_held_here

    deadline = time.perf_counter() + wait_s
    while lock_held_here(out_dir) and time.perf_counter() < deadline:
        time.sleep(0.05)


def _stop_all(ray, inflight: dict, grace_s: float) -> None:
    """Cancel every task in flight (Ctrl-C in each worker), wait up to ``grace_s``, then kill the rest."""
    refs = list(inflight)
    for ref in refs:
        try:
            ray.cancel(ref, force=False)
        except Exception:  # noqa: BLE001 - best effort while stopping
            pass
    deadline = time.perf_counter() + grace_s
    left = refs
    while left and time.perf_counter() < deadline:
        try:
            _, left = ray.wait(left, num_returns=len(left), timeout=0.2)
        except KeyboardInterrupt:
            break
    for ref in left:
        try:
            ray.cancel(ref, force=True)
        except Exception:  # noqa: BLE001
            pass
