"""Work done as another user in a forked child: root ignores permission bits, so a test
of what a user meets with a read-only or unreadable folder runs it as ``nobody``."""

import os
import pwd
import shutil
import tempfile
import traceback
from pathlib import Path

import pytest


def nobody():
    """The unprivileged user; the test is skipped where it cannot become one (not root)."""
    if os.geteuid() != 0:
        pytest.skip("needs root to run the work as another user")
    return pwd.getpwnam("nobody")


def reachable_folder(request, prefix: str) -> Path:
    """A fresh folder any user can reach (pytest's are root's alone, 0700), removed after
    the test."""
    folder = Path(tempfile.mkdtemp(prefix=prefix))
    request.addfinalizer(lambda: shutil.rmtree(folder, ignore_errors=True))
    os.chmod(folder, 0o755)
    return folder


def give(folder: Path, user) -> None:
    """``folder`` and everything in it owned by ``user``."""
    for path in [folder, *folder.rglob("*")]:
        os.lchown(path, user.pw_uid, user.pw_gid)


def as_user(user, work) -> int:
    """``work()`` in a forked child that has become ``user`` (this interpreter cannot be
    started as another user: its files are root's); the child's exit code, 1 on any
    exception, whose traceback it prints."""
    pid = os.fork()
    if pid == 0:  # the child: never returns into pytest
        code = 1
        try:
            os.setgid(user.pw_gid)
            os.setuid(user.pw_uid)
            work()
            code = 0
        except BaseException:
            traceback.print_exc()  # the child ends below without unwinding into pytest
            raise
        finally:
            os._exit(code)
    return os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])
