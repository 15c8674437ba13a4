"""One writer per capture: an advisory lock on ``CAPTURE/.pipeline/lock``.

``pipeline run``, ``clean`` and ``batch`` hold it while they change the cache or
output/. The lock is an ``flock`` on the file, so the kernel releases it when its
holder dies: a lock left by a killed run is never stale, the next run simply
gets it (and says whose it was, from the holder record written into the file).
Commands that only read (``status``, ``run --dry-run``) take no lock.
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import time
from pathlib import Path
from types import TracebackType

from pipeline import logger
from pipeline.core.errors import PipelineError

LOCK_FILE = "lock"


class CaptureBusy(PipelineError):
    """Another run holds the capture's lock and the caller chose not to wait."""


def _holder_text(record: dict) -> str:
    started = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(record.get("started", 0)))
    return f"pid {record.get('pid')} on {record.get('host')} ({record.get('command')}, since {started})"


class CaptureLock:
    """Context manager holding a capture's lock; waits for it unless ``wait`` is False.

    ``lock_file`` locks another folder the same way (`pipeline fit`'s --out, whose lock
    is ``OUT/.fit.lock``), and ``busy_hint`` is what a caller that does not wait is told
    to do."""

    def __init__(
        self,
        capture_dir: Path,
        command: str,
        wait: bool = True,
        lock_file: Path | None = None,
        busy_hint: str = "wait for it to finish, or run again without --no-wait to queue behind it",
    ):
        self.folder = capture_dir
        self.path = lock_file or capture_dir / ".pipeline" / LOCK_FILE
        self.command = command
        self.wait = wait
        self.busy_hint = busy_hint
        self._fd: int | None = None

    def _read_holder(self) -> dict:
        try:
            return json.loads(self.path.read_text() or "{}")
        except json.JSONDecodeError:
            return {}  # written by a holder killed mid-write: nothing to report

    def __enter__(self) -> "CaptureLock":
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except PermissionError as error:
            raise PipelineError(
                f"cannot write to {self.path.parent}: {self.folder} must be writable for {self.command} "
                "(copy it somewhere writable, or fix its permissions)"
            ) from error
        except IsADirectoryError as error:
            raise PipelineError(f"{self.path} is a folder, not the pipeline's lock file: remove it") from error
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder_text(self._read_holder())
            if not self.wait:
                os.close(fd)
                raise CaptureBusy(f"{self.folder} is in use by {holder}: {self.busy_hint}") from None
            logger.warning("%s is in use by %s; waiting for it to finish", self.folder, holder)
            fcntl.flock(fd, fcntl.LOCK_EX)
        previous = self._read_holder()
        if previous:
            # The file keeps its last holder's record; a record left behind means
            # that holder died without releasing (killed), and we took over.
            logger.warning("took over the lock of %s, which ended without releasing it", _holder_text(previous))
        record = {"pid": os.getpid(), "host": socket.gethostname(), "command": self.command, "started": time.time()}
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, json.dumps(record).encode(), 0)
        except OSError as error:  # a full disk: the lock holds without its record, which only names us
            logger.debug("could not write the lock's holder record: %s", error)
        self._fd = fd
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        assert self._fd is not None
        os.ftruncate(self._fd, 0)  # an empty record: released in good order
        fcntl.flock(self._fd, fcntl.LOCK_UN)
        os.close(self._fd)
        self._fd = None


def holder(capture_dir: Path) -> str | None:
    """Who holds the capture's lock now (None: nobody), without waiting or taking it
    for longer than the test."""
    path = capture_dir / ".pipeline" / LOCK_FILE
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        try:
            return _holder_text(json.loads(path.read_text() or "{}"))
        except json.JSONDecodeError:
            return "another process"
    finally:
        os.close(fd)  # closing releases a lock the test took
    return None


__all__ = ["CaptureBusy", "CaptureLock", "holder"]
