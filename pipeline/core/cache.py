"""The on-disk cache of stage results.

Layout under ``CAPTURE/.pipeline/``::

    cache/<stage>/<key>/          a committed result: outputs, status.json, log.txt
    cache/<stage>/.tmp-<key>-<pid>/   a run in progress (or one that was killed)
    failed/<stage>/<timestamp>/   the folder of a run that raised, kept for its log
    file_hashes.json              content hashes memo (see pipeline.core.hashing)
    runs/<timestamp>.json         effective config and summary of each `pipeline run`

A result is visible only once its folder has been renamed to ``<key>``, which
happens after the stage returned and its status.json was written; the rename is
atomic, so a crash or SIGKILL at any moment leaves either no entry or a whole one.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.core.fsutil import atomic_write_text

STATUS_FILE = "status.json"
LOG_FILE = "log.txt"


@dataclass(frozen=True)
class Entry:
    """A committed cache entry."""

    stage: str
    key: str
    path: Path
    status: dict[str, Any]

    @property
    def outputs(self) -> dict[str, Path]:
        return {name: self.path / rel for name, rel in self.status["outputs"].items()}

    @property
    def finished(self) -> float:
        return self.status["finished"]


class StageCache:
    def __init__(self, capture_dir: Path):
        self.state_dir = capture_dir / ".pipeline"
        self.root = self.state_dir / "cache"

    def _read(self, stage: str, path: Path) -> Entry | None:
        status_file = path / STATUS_FILE
        if not status_file.is_file():
            return None
        status = json.loads(status_file.read_text())
        return Entry(stage=stage, key=path.name, path=path, status=status)

    def lookup(self, stage: str, key: str) -> Entry | None:
        return self._read(stage, self.root / stage / key)

    def entries(self, stage: str) -> list[Entry]:
        """Committed entries of a stage, oldest first."""
        stage_dir = self.root / stage
        if not stage_dir.is_dir():
            return []
        found = [
            e for p in stage_dir.iterdir() if not p.name.startswith(".") and (e := self._read(stage, p)) is not None
        ]
        return sorted(found, key=lambda e: e.finished)

    def stages(self) -> list[str]:
        return sorted(p.name for p in self.root.iterdir()) if self.root.is_dir() else []

    def begin(self, stage: str, key: str) -> Path:
        """A fresh folder for a run of ``stage``; nothing reads it until commit."""
        tmp = self.root / stage / f".tmp-{key}-{os.getpid()}"
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir(parents=True)
        return tmp

    def commit(self, tmp: Path, stage: str, key: str, status: dict[str, Any]) -> Entry:
        """Write status.json, then atomically publish ``tmp`` as the entry for ``key``."""
        atomic_write_text(tmp / STATUS_FILE, json.dumps(status, indent=2, sort_keys=True))
        final = self.root / stage / key
        if final.exists():
            # A forced rerun replaces the entry: move the old one aside first,
            # because rename() cannot replace a non-empty directory.
            old = final.with_name(f".old-{key}-{os.getpid()}")
            os.rename(final, old)
            os.rename(tmp, final)
            shutil.rmtree(old)
        else:
            os.rename(tmp, final)
        return Entry(stage=stage, key=key, path=final, status=status)

    def keep_failed(self, tmp: Path, stage: str) -> Path:
        """Move a failed run's folder out of the cache, keeping its log for the user."""
        stamp = time.strftime("%Y%m%d-%H%M%S")
        dest = self.state_dir / "failed" / stage / f"{stamp}-{os.getpid()}"
        dest.parent.mkdir(parents=True, exist_ok=True)
        os.rename(tmp, dest)
        return dest

    def remove(self, entry: Entry) -> None:
        shutil.rmtree(entry.path)

    def leftovers(self) -> list[Path]:
        """Folders of runs that never committed (killed runs) and of failed runs."""
        found = [p for stage_dir in self.root.glob("*") for p in stage_dir.glob(".*") if p.is_dir()]
        failed = self.state_dir / "failed"
        if failed.is_dir():
            found.append(failed)
        return found
