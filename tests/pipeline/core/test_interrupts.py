"""What counts as an interruption, however deep a library wrapped it."""

import signal

from pipeline.core.interrupts import Interrupted, exit_code, interruption


def _wrapped(error: BaseException) -> RuntimeError:
    """As Dr.Jit wraps an exception raised inside a frozen function: RuntimeErrors, each
    caused by the one before."""
    try:
        try:
            raise error
        except BaseException as inner:
            raise RuntimeError("FlatVariables::traverse(): error encountered") from inner
    except RuntimeError as outer:
        try:
            raise RuntimeError("FlatVariables::assign(): error encountered") from outer
        except RuntimeError as outermost:
            return outermost


def test_an_interruption_is_found_behind_a_library_s_wrapping_and_gives_its_exit_code():
    term = _wrapped(Interrupted(signal.SIGTERM))
    assert isinstance(interruption(term), Interrupted) and exit_code(interruption(term)) == 143
    assert exit_code(interruption(_wrapped(KeyboardInterrupt()))) == 130
    assert exit_code(Interrupted(signal.SIGHUP)) == 129
    assert interruption(_wrapped(ValueError("a bug"))) is None


SIGTERM_AFTER_PYCOLMAP = """
import os, signal, sys, time
from pipeline.core import interrupts
interrupts.install()
import pipeline.colmap  # pycolmap loads glog, whose handler printed a stack dump for SIGTERM
try:
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(10)
except interrupts.Interrupted as stopped:
    sys.exit(stopped.exit_code)
"""


def test_sigterm_after_pycolmap_loads_reaches_python_without_a_stack_dump():
    from tests.support.toy_stages import run_python

    done = run_python(SIGTERM_AFTER_PYCOLMAP)
    assert done.returncode == 143 and "stack trace" not in done.stderr and "Aborted" not in done.stderr


OTHER_SIGNALS_THEN_SIGTERM = """
import os, signal, sys, time
from pipeline.core import interrupts
interrupts.install()
signal.signal(signal.SIGALRM, lambda *args: None)  # a watchdog's, or any other handled signal
for _ in range(3):
    os.kill(os.getpid(), signal.SIGALRM)
time.sleep(0.5)  # the watcher thread has read them
try:
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(10)
except interrupts.Interrupted as stopped:
    sys.exit(stopped.exit_code)
"""


def test_only_interruptions_count_towards_the_second_signal_that_ends_at_once():
    from tests.support.toy_stages import run_python

    done = run_python(OTHER_SIGNALS_THEN_SIGTERM)
    assert done.returncode == 143 and "interrupted twice" not in done.stderr
