"""Small file-system helpers whose point is atomicity."""

from __future__ import annotations

import errno
import hashlib
import os
import stat
import tempfile
from pathlib import Path

KERNEL_FILE_SYSTEMS = frozenset(
    "proc sysfs devtmpfs devpts debugfs tracefs securityfs configfs cgroup cgroup2 pstore bpf efivarfs "
    "fusectl mqueue hugetlbfs binfmt_misc autofs".split()
)
"""File systems whose files the kernel makes up as they are read: a regular file there
(/proc/kmsg, /sys/kernel/...) can block for ever or never end."""


def _process_umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


UMASK = _process_umask()
"""The umask the process started with (read once: os.umask can only be read by setting it)."""


def shared_mode(fd: int) -> None:
    """Give a file made by ``tempfile.mkstemp`` (always 0600) the mode that ``open``
    would have given it under the process's umask, so that a renamed temporary file
    reads like any other output."""
    os.fchmod(fd, 0o666 & ~UMASK)


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` so that readers see either the old file or the whole new one."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        shared_mode(fd)
        with os.fdopen(fd, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as error:
        os.unlink(tmp)  # a full disk leaves no partial file, and the error names the file
        if error.filename is None:
            raise OSError(error.errno, error.strerror, str(path)) from error
        raise
    except BaseException:
        os.unlink(tmp)  # nor does an interruption
        raise


def disk_full_error(error: BaseException) -> bool:
    """Whether ``error`` (or what caused it) says the file system or quota is full."""
    while error is not None:
        if isinstance(error, OSError) and error.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        error = error.__cause__ or error.__context__
    return False


def special_kind(path: Path) -> str | None:
    """ "a FIFO", "a socket", "a device" or a kernel file when ``path`` is one (reading it
    could block for ever or never end), else None."""
    mode = path.stat().st_mode
    for test, kind in ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket"), (stat.S_ISCHR, "a device")):
        if test(mode):
            return kind
    if stat.S_ISBLK(mode):
        return "a device"
    file_system = file_system_type(path)
    return f"a file the kernel makes up ({file_system})" if file_system in KERNEL_FILE_SYSTEMS else None


def file_system_type(path: Path) -> str | None:
    """The type of the file system ``path`` lies on (Linux's /proc/self/mountinfo: the
    longest mount point above it); None where that cannot be read."""
    try:
        lines = Path("/proc/self/mountinfo").read_text().splitlines()
    except OSError:
        return None
    resolved = str(path.resolve())
    best, kind = "", None
    for line in lines:
        fields = line.split()
        if " - " not in line or len(fields) < 5:
            continue
        mount_point = fields[4].replace("\\040", " ")
        below = resolved == mount_point or resolved.startswith(mount_point.rstrip("/") + "/")
        if below and len(mount_point) >= len(best):
            best, kind = mount_point, line.split(" - ", 1)[1].split()[0]
    return kind


def sha256_of(path: Path) -> str:
    """The SHA-256 of a file's bytes, as hex."""
    with path.open("rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()
