"""The runner's lock on an experiment's folder: one runner at a time trains into a ``--out``.

:func:`runner_lock` holds ``<out>/.runner.lock`` while a runner decides which runs are due and
trains them. The lock is the operating system's (``flock``): it is released when its holder
ends, however it ends (``kill -9`` included), so a lock left behind is never in the way. The file
names its holder (pid, host, start time, command line) for the error another runner on the same
folder gets, :class:`FolderLocked`. A holder that ended without removing the file left a stale
record there, which the next runner reports on stderr and replaces.

The runner's worker processes hold ``<out>/.runner.workers.lock`` shared
(:func:`hold_worker_lock`) for as long as they live; a runner that takes the folder over waits
until the workers of one that ended are gone (they exit about a second after it), so no two
runners' processes ever write one folder at once.

Without ``fcntl`` (Windows) the lock file is created exclusively instead and a holder that ended
without removing it leaves it behind: the error then says to delete it once no runner is running.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import os
import pathlib
import socket
import sys
import time
from typing import Any, Dict, Iterator, List, Optional, Union

try:
    import fcntl
except ImportError:  # Windows
    fcntl = None  # type: ignore[assignment]

LOCK_NAME = ".runner.lock"
WORKERS_LOCK_NAME = ".runner.workers.lock"

_worker_lock_fds: List[int] = []  # this worker process's descriptors, open until it ends


class FolderLocked(RuntimeError):
    """Another runner holds the lock on an experiment's folder."""

    def __init__(self, folder: pathlib.Path, holder: Optional[Dict[str, Any]], message: str = "") -> None:
        self.folder = folder
        self.holder = holder or {}
        who = describe_holder(self.holder) if holder else "one that has not written its name yet"
        super().__init__(
            message or f"{folder} is in use by another runner ({who}): wait for it to end or use another --out"
        )


def describe_holder(holder: Dict[str, Any]) -> str:
    """One line for a lock file's record: pid, host, since when, command line."""
    parts = [f"pid {holder.get('pid', '?')} on {holder.get('host', '?')}"]
    if holder.get("started"):
        parts.append(f"since {holder['started']}")
    if holder.get("command"):
        parts.append(f"command: {holder['command']}")
    return ", ".join(parts)


def read_holder(path: Union[str, pathlib.Path]) -> Optional[Dict[str, Any]]:
    """The record a lock file holds, or ``None`` if it is missing, empty or unreadable."""
    try:
        record = json.loads(pathlib.Path(path).read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) else None


@contextlib.contextmanager
def runner_lock(out: Union[str, pathlib.Path], worker_wait_s: float = 30.0) -> Iterator[Dict[str, Any]]:
    """Hold the lock on the experiment folder ``out`` (created if missing) for the block; yield the
    record written into the lock file. Raise :class:`FolderLocked` at once if another runner (or
    another block of this process) holds it.

    ``worker_wait_s``: how long to wait for the worker processes of a runner that ended (see the
    module's description) before raising :class:`FolderLocked` naming them.
    """
    folder = pathlib.Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / LOCK_NAME
    record = {
        "pid": os.getpid(),
        "host": socket.gethostname(),
        "started": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
        "command": " ".join([os.path.basename(sys.executable), *sys.argv]),
    }
    fd = _acquire(folder, path)
    try:
        stale = read_holder(path)
        if stale is not None:
            print(
                f"{folder}: taking over the lock of a runner that ended without releasing it "
                f"({describe_holder(stale)})",
                file=sys.stderr,
                flush=True,
            )
        _wait_for_workers(folder, worker_wait_s)
        os.ftruncate(fd, 0)
        os.lseek(fd, 0, os.SEEK_SET)
        os.write(fd, json.dumps(record).encode())
        os.fsync(fd)
        try:
            yield record
        finally:
            _remove_workers_file(folder)
    finally:
        # Removed while still locked, so that the next runner never locks a file no longer there.
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)
        os.close(fd)


def hold_worker_lock(out: Union[str, pathlib.Path]) -> None:
    """In a runner's worker process: hold ``out``'s workers lock shared until this process ends."""
    if fcntl is None:
        return
    fd = _open_locked(pathlib.Path(out) / WORKERS_LOCK_NAME, fcntl.LOCK_SH, block=True)
    _worker_lock_fds.append(fd)


@contextlib.contextmanager
def worker_lock(out: Union[str, pathlib.Path]) -> Iterator[None]:
    """Hold ``out``'s workers lock shared for the block (a worker process that outlives its runs,
    as a Ray worker does, releases it after each run); nothing without ``flock``."""
    if fcntl is None:
        yield
        return
    fd = _open_locked(pathlib.Path(out) / WORKERS_LOCK_NAME, fcntl.LOCK_SH, block=True)
    try:
        yield
    finally:
        os.close(fd)


def _acquire(folder: pathlib.Path, path: pathlib.Path) -> int:
    if fcntl is None:
        try:
            return os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            holder = read_holder(path)
            raise FolderLocked(
                folder,
                holder,
                f"{folder} is in use by another runner ({describe_holder(holder or {})}): wait for it to end "
                f"or use another --out; if no runner is running there, delete {path}",
            ) from None
    try:
        fd = _open_locked(path, fcntl.LOCK_EX, block=False)
    except OSError as error:
        raise OSError(f"cannot lock {path} ({error}): the runner needs a filesystem with flock") from error
    if fd is None:
        raise FolderLocked(folder, read_holder(path))
    return fd


def _open_locked(path: pathlib.Path, operation: int, block: bool) -> Optional[int]:
    """A descriptor of ``path`` (created if missing) locked with ``flock(operation)``; ``None`` if
    ``block`` is false and another process holds a conflicting lock."""
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, operation if block else operation | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            return None
        # Its holder may have removed the file between our open and our lock: lock the one there now.
        try:
            current = os.stat(path)
        except FileNotFoundError:
            current = None
        if current is not None and os.path.samestat(os.fstat(fd), current):
            return fd
        os.close(fd)


def _wait_for_workers(folder: pathlib.Path, wait_s: float) -> None:
    """Wait until no worker process of an earlier runner holds ``folder``'s workers lock."""
    if fcntl is None:
        return
    path = folder / WORKERS_LOCK_NAME
    deadline = time.monotonic() + wait_s
    while True:
        fd = _open_locked(path, fcntl.LOCK_EX, block=False)
        if fd is not None:
            os.close(fd)
            return
        if time.monotonic() > deadline:
            raise FolderLocked(
                folder,
                None,
                f"worker processes of a runner that ended still write into {folder} ({wait_s:.0f} s after "
                f"it ended, they hold {path}): end them first",
            )
        time.sleep(0.1)


def _remove_workers_file(folder: pathlib.Path) -> None:
    """Remove the workers lock file, unless a worker still holds it."""
    if fcntl is None:
        return
    path = folder / WORKERS_LOCK_NAME
    if not path.exists():
        return
    fd = _open_locked(path, fcntl.LOCK_EX, block=False)
    if fd is not None:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)
        os.close(fd)
