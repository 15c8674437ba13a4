"""Content hashes of capture files, remembered by (size, mtime).

An unchanged folder of 1,000 photos is hashed once; later runs only stat it.
Touching a file changes its mtime, so it is re-read, but its hash, and with it
every cache key, stays the same.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from pipeline import logger
from pipeline.core.fsutil import atomic_write_text


class FileHasher:
    """SHA-256 of files, with a JSON memo keyed by path, size and mtime."""

    def __init__(self, memo_path: Path):
        self.memo_path = memo_path
        self._memo: dict[str, dict] = {}
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
        known = self._memo.get(key)
        if known and known["size"] == stat.st_size and known["mtime_ns"] == stat.st_mtime_ns:
            return known["sha256"]
        with path.open("rb") as f:
            digest = hashlib.file_digest(f, "sha256").hexdigest()
        self.files_read += 1
        self._memo[key] = {"size": stat.st_size, "mtime_ns": stat.st_mtime_ns, "sha256": digest}
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
        if self._dirty:
            self.memo_path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_text(self.memo_path, json.dumps(self._memo, indent=0, sort_keys=True))
            self._dirty = False


def glob_capture_files(capture_dir: Path, patterns: tuple[str, ...]) -> list[Path]:
    """Files under ``capture_dir`` matching any pattern, sorted, without duplicates."""
    found = {
        p
        for pattern in patterns
        for p in capture_dir.glob(pattern)
        if p.is_file() and not any(part.startswith(".") for part in p.relative_to(capture_dir).parts)
    }
    return sorted(found)


def tree_size(path: Path) -> int:
    return sum(os.path.getsize(os.path.join(root, f)) for root, _, files in os.walk(path) for f in files)
