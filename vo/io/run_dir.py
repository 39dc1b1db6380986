"""The run folder: created atomically, held by one live run at a time, cleared only on request.

* :func:`make_unique_dir` creates ``PARENT/NAME`` (or ``NAME-2``, ``NAME-3`` ...) with
  ``os.mkdir``, which fails if the folder exists, so two runs started at once never
  pick the same folder.
* :class:`RunLock` is the file ``OUT/.lock`` (created with ``O_CREAT | O_EXCL``) holding
  the pid and host of the run that writes ``OUT``. A second run onto a folder whose
  lock names a live process refuses (:class:`RunDirBusy`); a lock left by a dead
  process is taken over with a warning. The check-and-take is serialised with
  ``flock`` on the folder itself where available (POSIX), so two runs cannot both
  take over one stale lock. The lock is removed at the end of the run; a batch that had
  to kill a run removes the lock it left (:func:`clear_stale_lock`).
* :func:`open_run_dir` = create the folder, take the lock, then refuse a folder that
  holds an earlier run (:data:`RUN_FILES`) unless ``overwrite`` is given, in which case
  only those files (and the earlier run's recording when it is inside the folder) are
  removed first; other files are never touched.
* :class:`InterruptSignals` turns SIGTERM into the same exception as Ctrl-C
  (:class:`Interrupted`, a ``KeyboardInterrupt`` carrying the signal number), so
  every stop is handled alike; :meth:`InterruptSignals.deferred` holds signals back
  while the final outputs are written.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import socket
import threading
from pathlib import Path

from trianflow_vo.errors import InputError

log = logging.getLogger("trianflow_vo")

LOCK_NAME = ".lock"
# every file a run writes into its folder (the writer's outputs, their temporaries, the plot)
RUN_FILES = ("poses.txt", "frames.txt", "trajectory.tum", "frames.tsv", "run.json", "config.yaml",
             "trajectory.png", "run.json.tmp", "poses.txt.tmp", "trajectory.tum.tmp")


class RunDirBusy(InputError):
    """The output folder is held by another live run."""


class EarlierRun(InputError):
    """The output folder holds an earlier run and ``overwrite`` was not given."""


def make_unique_dir(parent: Path, name: str) -> Path:
    """Create and return ``parent/name``, or ``name-2``, ``name-3`` ... if taken (atomic ``mkdir``)."""
    parent = Path(parent)
    parent.mkdir(parents=True, exist_ok=True)
    n = 1
    while True:
        path = parent / (name if n == 1 else f"{name}-{n}")
        try:
            os.mkdir(path)
            return path
        except FileExistsError:
            n += 1


def _pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    except OSError:
        return False
    return True


@contextlib.contextmanager
def _folder_mutex(folder: Path):
    """Exclusive ``flock`` on the folder (released when the process dies); a no-op without fcntl."""
    try:
        import fcntl
    except ImportError:  # Windows: the O_EXCL lock file alone
        yield
        return
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        yield
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the flock


class RunLock:
    """``OUT/.lock``: the pid (line 1) and host (line 2) of the run writing ``OUT``."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.path = self.folder / LOCK_NAME
        self.pid = os.getpid()
        self.host = socket.gethostname()
        self.held = False

    def _owner(self) -> tuple[int | None, str | None]:
        try:
            lines = self.path.read_text().splitlines()
        except (OSError, UnicodeDecodeError):
            return None, None
        try:
            pid = int(lines[0].strip())
        except (IndexError, ValueError):
            return None, None
        return pid, (lines[1].strip() if len(lines) > 1 else None)

    def owner_state(self) -> tuple[str, int | None, str | None]:
        """``(state, pid, host)`` of the lock file's owner. ``state``: ``"none"`` (no lock file, or
        no pid in it), ``"foreign"`` (another host: cannot be checked from here), ``"live"`` or
        ``"dead"`` (a process of this host; a lock without a host counts as this host's)."""
        pid, host = self._owner()
        if pid is None:
            return "none", None, host
        if host not in (None, self.host):
            return "foreign", pid, host
        return ("live" if _pid_alive(pid) else "dead"), pid, host

    def acquire(self) -> RunLock:
        """Take the lock; raises :class:`RunDirBusy` when a live run holds it."""
        with _folder_mutex(self.folder):
            for _ in range(5):
                try:
                    fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
                except FileExistsError:
                    state, pid, host = self.owner_state()
                    if state == "foreign":
                        raise RunDirBusy(f"in use by a run on host {host} (pid {pid}, lock {self.path}); "
                                         f"choose another --out, or delete {self.path} if no run uses it",
                                         self.folder) from None
                    if state == "live":
                        raise RunDirBusy(f"in use by another run (pid {pid}, lock {self.path}); "
                                         "choose another --out or wait for it to finish", self.folder) from None
                    what = f"of process {pid}, which is no longer running" if pid is not None else "without a pid"
                    log.warning(f"{self.folder}: taking over a stale lock {what} ({self.path})")
                    with contextlib.suppress(FileNotFoundError):
                        os.unlink(self.path)
                    continue
                try:
                    os.write(fd, f"{self.pid}\n{self.host}\n".encode())
                finally:
                    os.close(fd)
                self.held = True
                return self
        raise RunDirBusy(f"could not take the lock {self.path}", self.folder)

    def release(self) -> None:
        """Remove the lock if this process still holds it (idempotent)."""
        if not self.held:
            return
        self.held = False
        pid, _ = self._owner()
        if pid == self.pid:
            with contextlib.suppress(OSError):
                os.unlink(self.path)

    def __enter__(self) -> RunLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def lock_held_here(folder: Path) -> bool:
    """Whether ``folder/.lock`` names a live process of this host (a lock of another host
    cannot be checked from here and counts as not held)."""
    return RunLock(folder).owner_state()[0] == "live"


def clear_stale_lock(folder: Path) -> bool:
    """Remove ``folder/.lock`` when it names a process of this host that no longer runs
    (a run killed before it could remove it). Returns whether a lock was removed."""
    lock = RunLock(folder)
    if not lock.path.exists():
        return False
    with _folder_mutex(lock.folder):
        state, pid, _ = lock.owner_state()
        if state != "dead":
            return False
        try:
            os.unlink(lock.path)
        except OSError:
            return False
    log.info(f"{lock.folder}: removed the stale lock of process {pid}, which was stopped ({lock.path})")
    return True


def earlier_run_files(folder: Path) -> list[Path]:
    """Files of an earlier run in ``folder``: :data:`RUN_FILES` present, and the recording
    its ``run.json`` names when that file is inside the folder."""
    folder = Path(folder)
    found = [folder / n for n in RUN_FILES if (folder / n).is_file() or (folder / n).is_symlink()]
    try:
        doc = json.loads((folder / "run.json").read_text())
        rrd = (doc.get("config") or {}).get("output", {}).get("rerun")
    except (OSError, ValueError, AttributeError):
        rrd = None
    if rrd:
        p = Path(rrd)
        p = p if p.is_absolute() else Path.cwd() / p
        try:
            inside = p.resolve().parent == folder.resolve()
        except OSError:
            inside = False
        if inside and p.is_file() and p.suffix == ".rrd":
            found.append(p)
    return found


def open_run_dir(folder: Path, overwrite: bool = False) -> RunLock:
    """Create ``folder`` (parents too), take its lock, and clear or refuse an earlier run.

    Returns the held :class:`RunLock` (release it at the end). Raises :class:`RunDirBusy`
    (a live run holds the folder), :class:`EarlierRun` (an earlier run's files and no
    ``overwrite``) or :class:`InputError` (not a folder); on those the folder is left as it was.
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise InputError("exists and is not a folder; give a folder to --out", folder)
    folder.mkdir(parents=True, exist_ok=True)
    lock = RunLock(folder).acquire()
    try:
        earlier = earlier_run_files(folder)
        if earlier and not overwrite:
            names = ", ".join(p.name for p in earlier[:4]) + (", ..." if len(earlier) > 4 else "")
            raise EarlierRun(f"holds an earlier run ({names}); give --overwrite to replace it, "
                             "or choose another --out", folder)
        for p in earlier:
            p.unlink()
        if earlier:
            log.info(f"{folder}: removed the earlier run's files ({len(earlier)})")
    except BaseException:
        lock.release()
        raise
    return lock


# -- signals ---------------------------------------------------------------------------------------------------
class Interrupted(KeyboardInterrupt):
    """Ctrl-C (SIGINT) or SIGTERM: the run stops and closes its outputs as ``interrupted``."""

    def __init__(self, signum: int = signal.SIGINT):
        self.signum = int(signum)
        super().__init__(signal.Signals(self.signum).name)


def signal_name(exc: BaseException) -> str:
    """``"SIGTERM"`` for an :class:`Interrupted` from SIGTERM, else ``"SIGINT"`` (Ctrl-C)."""
    return signal.Signals(getattr(exc, "signum", signal.SIGINT)).name


def exit_code(exc: BaseException) -> int:
    """128 + signal number: 130 for Ctrl-C (SIGINT), 143 for SIGTERM."""
    return 128 + int(getattr(exc, "signum", signal.SIGINT))


def _raise_interrupted(signum, frame):
    raise Interrupted(signum)


class InterruptSignals:
    """Context manager: SIGINT and SIGTERM raise :class:`Interrupted` in the main thread.

    Installs the handler only in the main thread and only over the default handlers
    (a caller's own handler is kept); restores the previous handlers on exit. Nested
    use is a no-op.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self._saved: dict[int, object] = {}
        self.pending: int | None = None

    def __enter__(self) -> InterruptSignals:
        if threading.current_thread() is not threading.main_thread():
            return self
        for s in self.SIGNALS:
            cur = signal.getsignal(s)
            if cur in (signal.SIG_DFL, signal.default_int_handler):
                self._saved[s] = cur
                signal.signal(s, _raise_interrupted)
        return self

    def __exit__(self, *exc) -> None:
        for s, h in self._saved.items():
            signal.signal(s, h)
        self._saved.clear()

    @contextlib.contextmanager
    def deferred(self):
        """Hold SIGINT/SIGTERM back (record the first in ``pending``) while the outputs are closed."""
        if threading.current_thread() is not threading.main_thread():
            yield self
            return
        saved = {}

        def hold(signum, frame):
            if self.pending is None:
                self.pending = signum

        for s in self.SIGNALS:
            cur = signal.getsignal(s)
            if cur in (_raise_interrupted, signal.default_int_handler):
                saved[s] = cur
                signal.signal(s, hold)
        try:
            yield self
        finally:
            for s, h in saved.items():
                signal.signal(s, h)
