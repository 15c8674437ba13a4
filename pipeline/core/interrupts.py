"""Ctrl-C, SIGTERM and SIGHUP end a command in good order: the running stage's partial
folder is removed, the lock released, and the CLI prints one line and exits 128 + the
signal.

Python raises KeyboardInterrupt for SIGINT; SIGTERM and SIGHUP are turned into
``Interrupted`` the same way. They only reach Python code once a native call (a render,
a COLMAP step) returns, so a second signal while the first is pending ends the process
at once; the next run removes the unfinished folder it leaves.

Native libraries install their own handlers when they load: glog's (through pycolmap)
prints a stack dump for SIGTERM and for every crash signal. ``after_native_import``
puts ours back and gives crashes the default action.
"""

from __future__ import annotations

import os
import signal
import sys
import threading

STOP_SIGNALS = (signal.SIGTERM, signal.SIGHUP)
"""Ask the process to end: handled as Ctrl-C is (SIGHUP: the terminal was closed)."""
CRASH_SIGNALS = (signal.SIGSEGV, signal.SIGILL, signal.SIGFPE, signal.SIGABRT, signal.SIGBUS)
_installed = False
_received: list[int] = []
"""Signals the handlers raised for: a library may swallow the exception (an import cut
short by Ctrl-C fails later with another error), so the CLI asks here too."""


class Interrupted(BaseException):
    """A signal asking the process to stop (SIGTERM, SIGHUP; SIGINT where its
    KeyboardInterrupt was swallowed); a BaseException so that no ``except Exception`` keeps running."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


def interruption(error: BaseException | None) -> BaseException | None:
    """The KeyboardInterrupt or Interrupted behind ``error`` (Dr.Jit wraps an exception
    raised inside a frozen function in RuntimeErrors, each caused by the last), or the
    signal received since install() when something swallowed it; None when neither."""
    while error is not None:
        if isinstance(error, (KeyboardInterrupt, Interrupted)):
            return error
        error = error.__cause__ or error.__context__
    return Interrupted(_received[0]) if _received else None


def signal_name(error: BaseException) -> str:
    """SIGINT, SIGTERM or SIGHUP: the signal behind an interruption."""
    return signal.Signals(exit_code(error) - 128).name


def exit_code(error: BaseException) -> int:
    """128 + the signal of an interruption (KeyboardInterrupt: SIGINT)."""
    return error.exit_code if isinstance(error, Interrupted) else 128 + signal.SIGINT


def _raise_interrupted(signum, frame) -> None:
    first = not _received
    _received.append(signum)
    if first:  # a second signal is the watcher's: it ends the process at once
        raise Interrupted(signum)


def _raise_keyboard_interrupt(signum, frame) -> None:
    first = not _received
    _received.append(signum)
    if first:
        raise KeyboardInterrupt


def _watch(read_fd: int) -> None:
    """Count signals as the C handler records them; a second one ends the process."""
    pending = 0
    watched = {int(signal.SIGINT), *map(int, STOP_SIGNALS)}
    while True:
        received = os.read(read_fd, 16)
        # Every signal with a Python handler writes its number here (a test's SIGALRM
        # too): only interruptions count.
        pending += sum(1 for signum in received if signum in watched)
        if pending >= 2:
            sys.stderr.write("interrupted twice: stopping at once; the next run removes the unfinished work\n")
            sys.stderr.flush()
            os._exit(128 + received[-1])


def install() -> None:
    """Install the handlers for this process (from the main thread; once)."""
    global _installed
    if threading.current_thread() is not threading.main_thread() or _installed:
        return
    for stop in STOP_SIGNALS:
        signal.signal(stop, _raise_interrupted)
    signal.signal(signal.SIGINT, _raise_keyboard_interrupt)
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)
    signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
    threading.Thread(target=_watch, args=(read_fd,), name="signal-watch", daemon=True).start()
    _installed = True


def after_native_import() -> None:
    """Undo the handlers a native library installed on import (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        return
    for crash in CRASH_SIGNALS:
        signal.signal(crash, signal.SIG_DFL)
    for stop in STOP_SIGNALS:
        signal.signal(stop, _raise_interrupted if _installed else signal.SIG_DFL)
    signal.signal(signal.SIGINT, _raise_keyboard_interrupt)


__all__ = ["Interrupted", "after_native_import", "exit_code", "install", "interruption", "signal_name"]
