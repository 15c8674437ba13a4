"""Content hashes of capture files, remembered by what the file system says of them.

An unchanged folder of 1,000 photos is hashed once; later runs only stat it.
A memo entry is trusted only while the file's size, mtime, inode and ctime all
match. ctime is the one a user cannot set: ``cp -p`` or ``touch -d`` over a file
keeps its size and mtime but not its ctime. As in git's "racy" rule, a file whose
ctime lies within RACY_NS of the moment it was hashed may have changed again in the
same clock tick, so it is hashed again next time.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from pathlib import Path

from pipeline import logger
from pipeline.core.errors import PipelineError
from pipeline.core.fsutil import atomic_write_text, sha256_of

RACY_NS = 2_000_000_000
"""The coarsest timestamp resolution of the file systems captures live on (FAT: 2 s)."""
STAT_FIELDS = ("st_size", "st_mtime_ns", "st_ctime_ns", "st_ino")


class FileHasher:
    """SHA-256 of files, with a JSON memo keyed by path (see the module's docstring)."""

    def __init__(self, memo_path: Path):
        self.memo_path = memo_path
        self._memo: dict[str, dict] = {}
        self._usable = memo_path.is_file() or not memo_path.exists()
        if not self._usable:
            logger.warning("%s is not a file; hashing the capture files without a memo (remove it)", memo_path)
        if memo_path.is_file():
            try:
                self._memo = json.loads(memo_path.read_text())
            except (json.JSONDecodeError, UnicodeDecodeError):
                logger.warning("%s is damaged; hashing the capture files again", memo_path)
        self._dirty = False
        self.files_read = 0

    def hash(self, path: Path) -> str:
        stat = path.stat()
        key = str(path.resolve())
        seen = [getattr(stat, name) for name in STAT_FIELDS]
        known = self._memo.get(key)
        if known and known.get("stat") == seen and stat.st_ctime_ns < known["hashed_ns"] - RACY_NS:
            return known["sha256"]
        hashed_ns = time.time_ns()
        digest = sha256_of(path)
        self.files_read += 1
        self._memo[key] = {"stat": seen, "hashed_ns": hashed_ns, "sha256": digest}
        self._dirty = True
        return digest

    def hash_input(self, path: Path) -> str:
        """A file's hash, or for a folder one hash over its files' names and hashes."""
        if not path.is_dir():
            return self.hash(path)
        files = sorted(p for p in path.rglob("*") if p.is_file())
        listing = "\n".join(f"{p.relative_to(path).as_posix()} {self.hash(p)}" for p in files)
        return hashlib.sha256(listing.encode()).hexdigest()

    def save(self) -> None:
        if self._dirty and self._usable:
            try:
                self.memo_path.parent.mkdir(parents=True, exist_ok=True)
                atomic_write_text(self.memo_path, json.dumps(self._memo, indent=0, sort_keys=True))
            except OSError as error:  # a memo only: the hashes are taken again next time
                logger.warning(
                    "could not save %s (%s); the capture's files will be hashed again", self.memo_path, error
                )
            self._dirty = False


def glob_capture_files(capture_dir: Path, patterns: tuple[str, ...]) -> list[Path]:
    """Files under ``capture_dir`` matching any pattern, sorted, without duplicates. A
    folder a pattern reaches into that cannot be listed is a user error naming it (a
    glob would silently find nothing there)."""
    for pattern in patterns:
        folder = capture_dir / Path(pattern).parent
        try:
            if folder.is_dir():
                os.listdir(folder)
        except PermissionError as error:
            raise PipelineError(
                f"{folder} cannot be read ({error.strerror}): give yourself permission to list it (chmod u+rx)"
            ) from None
    found = {
        p
        for pattern in patterns
        for p in capture_dir.glob(pattern)
        if p.is_file() and not any(part.startswith(".") for part in p.relative_to(capture_dir).parts)
    }
    return sorted(found)


def tree_size(path: Path) -> int:
    return sum(os.path.getsize(os.path.join(root, f)) for root, _, files in os.walk(path) for f in files)
