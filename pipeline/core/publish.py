"""Publishing results to ``CAPTURE/output/`` as a whole, atomically.

``output`` is a symbolic link to one complete version under
``CAPTURE/.pipeline/published/<version>/``. A new version is assembled beside the
current one (one file per name: when several stages export a file of the same
name, as mesh, cleanup and uv do with mesh.ply, the last stage in DAG order
wins), gets its manifest.json, and replaces the link with one ``rename``. A
reader, or a run killed at any moment, therefore sees either the old output or
the new one, never a mixture; the versions a killed publish leaves are removed
by the next one. A real ``output/`` folder from an older version of the pipeline
is moved into ``published/legacy-*`` the first time and kept (users may have put
files there).
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path
from typing import Any

from pipeline import logger
from pipeline.core.errors import ConfigError
from pipeline.core.fsutil import atomic_write_text

OUTPUT = "output"
PUBLISHED = "published"
MANIFEST = "manifest.json"
LEGACY = "legacy-"
"""Prefix of a real output/ folder moved aside the first time; never deleted."""


def check_output_path(capture_dir: Path) -> None:
    """Refuse before anything runs when ``output`` is in the way of publishing."""
    output = capture_dir / OUTPUT
    # A link (even to a removed version) is ours and gets replaced; a folder is one
    # an older pipeline wrote, moved aside when publishing.
    if output.is_symlink() or output.is_dir() or not output.exists():
        return
    raise ConfigError(
        f"{output} is a file, but the pipeline publishes its results in a folder of that name: move or delete the file"
    )


def current_manifest(capture_dir: Path) -> dict[str, Any] | None:
    """The manifest of the published output, or None when there is none or it is unreadable."""
    path = capture_dir / OUTPUT / MANIFEST
    try:
        manifest = json.loads(path.read_text())
    except (FileNotFoundError, NotADirectoryError, json.JSONDecodeError, UnicodeDecodeError):
        return None
    return manifest if isinstance(manifest, dict) else None


def _intact(capture_dir: Path, manifest: dict[str, Any]) -> bool:
    return all((capture_dir / OUTPUT / name).exists() for name in manifest)


def publish(capture_dir: Path, files: dict[str, tuple[Path, dict[str, Any]]]) -> bool:
    """Make ``output/`` hold exactly ``files`` (name -> (source, manifest record)).

    Returns False when the published output already is that (nothing written).
    """
    manifest = {name: record for name, (_, record) in files.items()}
    if current_manifest(capture_dir) == manifest and _intact(capture_dir, manifest):
        return False
    published = capture_dir / ".pipeline" / PUBLISHED
    published.mkdir(parents=True, exist_ok=True)
    version = time.strftime("%Y%m%d-%H%M%S") + f"-{time.time_ns() % 1_000_000_000:09d}"
    staging = published / f".tmp-{version}"
    staging.mkdir()
    for name, (source, _) in files.items():
        if source.is_dir():
            shutil.copytree(source, staging / name)
        else:
            shutil.copy2(source, staging / name)
    atomic_write_text(staging / MANIFEST, json.dumps(manifest, indent=2, sort_keys=True))
    os.rename(staging, published / version)

    output = capture_dir / OUTPUT
    if output.is_dir() and not output.is_symlink():
        legacy = published / f"{LEGACY}{version}"
        os.rename(output, legacy)
        logger.warning("the output/ folder an older pipeline wrote was moved to %s (kept; delete it when done)", legacy)
    for stale in capture_dir.glob(f".{OUTPUT}.tmp-*"):
        stale.unlink()  # links a killed publish left; the caller holds the capture's lock
    link = capture_dir / f".{OUTPUT}.tmp-{os.getpid()}"
    os.symlink(Path(".pipeline") / PUBLISHED / version, link)
    os.replace(link, output)
    for old in published.iterdir():
        if old.name != version and not old.name.startswith(LEGACY):
            shutil.rmtree(old)
    return True


__all__ = ["MANIFEST", "OUTPUT", "check_output_path", "current_manifest", "publish"]
