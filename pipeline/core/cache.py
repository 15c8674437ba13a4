"""The on-disk cache of stage results.

Layout under ``CAPTURE/.pipeline/``::

    cache/<stage>/<key>/          a committed result: outputs, status.json, log.txt
    cache/<stage>/.tmp-<key>-<pid>/   a run in progress (or one that was killed)
    failed/<stage>/<timestamp>/   the folder of a run that raised, kept for its log
    checkpoints/<stage>-<key>/    resumable state of an unfinished run (long fits)
    file_hashes.json              content hashes memo (see pipeline.core.hashing)
    runs/<timestamp>.json         effective config and summary of each `pipeline run`

A result is visible only once its folder has been renamed to ``<key>``, which
happens after the stage returned and its status.json was written; the rename is
atomic, so a crash or SIGKILL at any moment leaves either no entry or a whole one.
status.json lists every file of the entry with its size and SHA-256, and a
result is reused only when its files still match: an entry damaged later (a file
deleted or edited, status.json truncated) is recomputed with a warning.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline import logger
from pipeline.core.fsutil import atomic_write_text, sha256_of

STATUS_FILE = "status.json"
LOG_FILE = "log.txt"
REQUIRED_KEYS = {"outputs", "contents", "finished", "seconds", "components"}


def contents(folder: Path) -> dict[str, list]:
    """Every file under ``folder`` but status.json: relative path -> [size, sha256]."""
    return {
        p.relative_to(folder).as_posix(): [p.stat().st_size, sha256_of(p)]
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != STATUS_FILE
    }


def damage(entry: "Entry") -> str | None:
    """What is wrong with a committed entry's files, or None when they are intact: one
    missing, changed or added since the entry was committed."""
    recorded = entry.status["contents"]
    for rel, (size, digest) in recorded.items():
        path = entry.path / rel
        if not path.is_file():
            return f"{rel} is missing"
        if path.stat().st_size != size or sha256_of(path) != digest:
            return f"{rel} has changed"
    for path in entry.path.rglob("*"):
        rel = path.relative_to(entry.path).as_posix()
        if not path.is_dir() and path.name != STATUS_FILE and rel not in recorded:
            return f"{rel} was added"
    return None


def status_problem(status: Any) -> str | None:
    """What makes a status.json unlike the ones commit() writes (None: nothing), so that
    a damaged one is recomputed rather than read."""
    if not isinstance(status, dict) or not REQUIRED_KEYS <= status.keys():
        return "incomplete"
    if not isinstance(status["finished"], (int, float)) or not isinstance(status["seconds"], (int, float)):
        return "its times are not numbers"
    if not isinstance(status["components"], dict) or not isinstance(status.get("metrics", {}), dict):
        return "its components or metrics are not tables"
    for table in ("outputs", "contents"):
        if not isinstance(status[table], dict):
            return f"its {table} is not a table"
        for rel in [*status[table], *(status[table].values() if table == "outputs" else ())]:
            parts = Path(rel).parts if isinstance(rel, str) else ()
            if not parts or Path(rel).is_absolute() or ".." in parts:
                return f"its {table} name a path outside the entry"
    for entry in status["contents"].values():
        if not (
            isinstance(entry, list) and len(entry) == 2 and isinstance(entry[0], int) and isinstance(entry[1], str)
        ):
            return "its contents are not [size, sha256]"
    return None


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
        try:
            status = json.loads(status_file.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError):
            logger.warning("cache entry %s has a damaged %s; it will be recomputed", path, STATUS_FILE)
            return None
        problem = status_problem(status)
        if problem is not None:
            logger.warning("cache entry %s has a damaged %s (%s); it will be recomputed", path, STATUS_FILE, problem)
            return None
        return Entry(stage=stage, key=path.name, path=path, status=status)

    def lookup(self, stage: str, key: str) -> Entry | None:
        """The entry of ``stage`` for ``key`` when it exists and its files are intact."""
        entry = self._read(stage, self.root / stage / key)
        if entry is None:
            return None
        problem = damage(entry)
        if problem:
            logger.warning("cache entry %s is damaged (%s); it will be recomputed", entry.path, problem)
            return None
        return entry

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
        status = {**status, "contents": contents(tmp)}
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

    def keep_failed(self, tmp: Path, stage: str, log_only: bool = False) -> Path:
        """Move a failed run's folder out of the cache, keeping its log for the user;
        with ``log_only``, only its log (the partial results are deleted)."""
        dest = self._new_failed_folder(stage)
        if log_only:
            if (tmp / LOG_FILE).is_file():
                os.rename(tmp / LOG_FILE, dest / LOG_FILE)
            shutil.rmtree(tmp)
        else:
            os.rename(tmp, dest)  # onto the empty folder just made
        return dest

    def _new_failed_folder(self, stage: str) -> Path:
        """An empty folder under failed/ named by the time and this process; numbered on,
        because a process that runs the stages twice (a script or notebook calling the
        runner, the tests) can fail a stage twice within a second."""
        parent = self.state_dir / "failed" / stage
        parent.mkdir(parents=True, exist_ok=True)
        name = f"{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}"
        dest, number = parent / name, 1
        while True:
            try:
                dest.mkdir()
                return dest
            except FileExistsError:
                number += 1
                dest = parent / f"{name}-{number}"

    def remove(self, entry: Entry) -> None:
        shutil.rmtree(entry.path)

    def checkpoint_dir(self, stage: str, key: str) -> Path:
        return self.state_dir / "checkpoints" / f"{stage}-{key}"

    def remove_unfinished(self) -> int:
        """Delete the folders of runs that never committed (killed); the caller holds
        the capture's lock, so none of them belongs to a live run. Returns how many."""
        unfinished = [p for stage_dir in self.root.glob("*") for p in stage_dir.glob(".*") if p.is_dir()]
        for path in unfinished:
            shutil.rmtree(path)
        return len(unfinished)

    def leftovers(self) -> list[Path]:
        """Folders of runs that never committed (killed runs) and of failed runs."""
        found = [p for stage_dir in self.root.glob("*") for p in stage_dir.glob(".*") if p.is_dir()]
        for folder in ("failed", "checkpoints"):
            if (self.state_dir / folder).is_dir():
                found.append(self.state_dir / folder)
        return found
