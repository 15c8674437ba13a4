"""Work done as another user in a forked child: root ignores permission bits, so a test
of what a user meets with a read-only or unreadable folder runs it as ``nobody``."""

import os
import traceback


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
