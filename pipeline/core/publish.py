"""Publishing results to ``CAPTURE/output/`` as a whole, atomically.

``output/`` is a real folder of copies: deleting ``.pipeline/`` (the cache) or copying
``output/`` elsewhere keeps every result. Each stage's exports sit in
``output/stages/<stage>/``; the final result of each role (the scene, the model) is
also at the top. A new version is assembled beside it in ``.output.tmp-<version>/``,
gets its manifest.json, and trades places with ``output/`` in one
``renameat2(RENAME_EXCHANGE)``. A reader, or a run killed at any moment, therefore sees
either the old output or the new one, never a mixture; the folders a killed publish
leaves are removed by the next one.

The manifest holds every published file's size and SHA-256. A published file that was
edited or removed since is restored from the cache, and an edited one is kept beside it
as ``<name>.edited<suffix>``. Files the pipeline did not publish (notes a user put
there, the report, score.json) are carried into every new version, as
``<name>.yours<suffix>`` when a result takes their name.
"""

from __future__ import annotations

import ctypes
import errno
import json
import os
import shutil
import time
from pathlib import Path
from typing import Any

from pipeline import logger
from pipeline.core.errors import ConfigError, DiskFull
from pipeline.core.fsutil import atomic_write_text, disk_full_error, sha256_of

OUTPUT = "output"
MANIFEST = "manifest.json"
STAGES = "stages"
"""The folder of output/ that holds each stage's exports, by stage name."""
STAGING = f".{OUTPUT}.tmp-"
"""Prefix of a version being assembled (or one a killed publish left)."""
OLD_LAYOUT = Path(".pipeline") / "published"
"""Where an older pipeline kept its versions, ``output`` being a link into it."""
_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def check_output_path(capture_dir: Path) -> None:
    """Refuse before anything runs when ``output`` is in the way of publishing."""
    output = capture_dir / OUTPUT
    if output.is_symlink() or output.is_dir() or not output.exists():
        return
    raise ConfigError(
        f"{output} is a file, but the pipeline publishes its results in a folder of that name: move or delete the file"
    )


def current_manifest(capture_dir: Path) -> dict[str, Any] | None:
    """The manifest of the published output, or None when there is none, it is unreadable
    or it is not of the shape publish() writes (a path in it that leaves output/, a
    record that is not a table of sizes and digests): a damaged manifest is never
    trusted to say which files to restore, hash or keep aside."""
    path = capture_dir / OUTPUT / MANIFEST
    try:
        manifest = json.loads(path.read_text())
    except (FileNotFoundError, NotADirectoryError, IsADirectoryError, json.JSONDecodeError, UnicodeDecodeError):
        return None
    except PermissionError:
        logger.warning("%s cannot be read: the published output is treated as unknown", path)
        return None
    problem = manifest_problem(manifest)
    if problem is not None:
        logger.warning("%s is damaged (%s): ignored; the next run publishes a new one", path, problem)
        return None
    return manifest


def manifest_problem(manifest: Any) -> str | None:
    """What makes ``manifest`` unlike the ones publish() writes, or None."""
    if not isinstance(manifest, dict):
        return "not a JSON object"
    for name, record in manifest.items():
        if not _inside(name) or not isinstance(record, dict) or not isinstance(record.get("stage", ""), str):
            return f"entry {name!r}"
        contents = record.get("contents", {})
        if not isinstance(contents, dict):
            return f"entry {name!r}: contents"
        for rel, entry in contents.items():
            if not _inside(rel):
                return f"path {rel!r} leaves output/"
            if (
                not isinstance(entry, list)
                or len(entry) != 2
                or not isinstance(entry[0], int)
                or not isinstance(entry[1], str)
            ):
                return f"entry {rel!r}: not [size, sha256]"
    return None


def _inside(relative: str) -> bool:
    """Whether a manifest's path names something inside output/ (relative, no '..')."""
    parts = Path(relative).parts
    return bool(parts) and not Path(relative).is_absolute() and ".." not in parts and "\\" not in relative


def _changed(output: Path, manifest: dict[str, Any]) -> dict[str, str]:
    """Published files that are no longer what the manifest says: path -> 'removed' or 'edited'."""
    changed = {}
    for record in manifest.values():
        for rel, (size, digest) in record.get("contents", {}).items():
            path = output / rel
            if not path.is_file() or path.is_symlink():
                changed[rel] = "removed"
            elif path.stat().st_size != size or sha256_of(path) != digest:
                changed[rel] = "edited"
    return changed


def _link_or_copy(source: str, destination: str) -> None:
    try:
        os.link(source, destination)
    except OSError:
        shutil.copy2(source, destination)


def _exchange(a: Path, b: Path) -> None:
    """Swap two paths in one step (Linux renameat2); OSError where unsupported."""
    renameat2 = getattr(ctypes.CDLL(None, use_errno=True), "renameat2", None)
    if renameat2 is None:
        raise OSError(errno.ENOSYS, "renameat2 is not available", str(a))
    if renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) != 0:
        code = ctypes.get_errno()
        raise OSError(code, os.strerror(code), str(a))


def _swap_in(staging: Path, output: Path) -> None:
    """Make ``staging`` the folder ``output``; the old output (if any) ends at ``staging``."""
    if not output.exists() and not output.is_symlink():
        os.rename(staging, output)
        return
    try:
        _exchange(staging, output)
    except OSError as error:
        if error.errno not in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP):
            raise
        # A file system without exchange: two renames, with a moment without output/.
        old = staging.with_name(staging.name + "-old")
        os.rename(output, old)
        os.rename(staging, output)
        os.rename(old, staging)


def _assemble(
    staging: Path,
    output: Path,
    files: dict[str, tuple[Path, dict[str, Any]]],
    old: dict[str, Any] | None,
    changed: dict[str, str],
) -> None:
    for name, (source, _) in files.items():
        (staging / name).parent.mkdir(parents=True, exist_ok=True)
        if source.is_dir():
            shutil.copytree(source, staging / name)
        else:
            shutil.copy2(source, staging / name)
    if not output.is_dir():
        return
    ours = {_top(name) for name in old or {}} | {MANIFEST}
    taken = {_top(name) for name in files}
    for path in sorted(output.iterdir()):
        if path.name in ours:
            continue
        # Not published by the pipeline's stages: the report, score.json, a user's notes;
        # one that a stage's result now takes the name of is kept under another.
        target = staging / path.name
        if path.name in taken:
            target = staging / f"{Path(path.name).stem}.yours{Path(path.name).suffix}"
            logger.warning("output/%s was not the pipeline's: kept as %s beside its result", path.name, target.name)
        if path.is_dir() and not path.is_symlink():
            shutil.copytree(path, target, copy_function=_link_or_copy, symlinks=True)
        elif path.is_symlink():
            os.symlink(os.readlink(path), target)
        else:
            _link_or_copy(str(path), str(target))
    for rel, how in changed.items():
        if how == "edited" and (staging / rel).parent.is_dir():
            kept = staging / rel
            kept = kept.with_name(f"{kept.stem}.edited{kept.suffix}")
            _link_or_copy(str(output / rel), str(kept))
            logger.warning(
                "output/%s was edited after it was published: restored, your copy kept as %s", rel, kept.name
            )
        elif how == "removed":
            logger.warning("output/%s was removed after it was published: restored from the cache", rel)


def _top(name: str) -> str:
    """The entry of output/ that a published path is in."""
    return name.split("/", 1)[0]


def remove_tree(path: Path) -> bool:
    """Delete ``path`` (a folder or a file), making read-only folders in it writable
    first (a user's chmod of output/ must not stop the next publish); False with a
    warning naming it where that is not allowed either."""

    def writable_and_again(function, failed: str, error) -> None:
        parent = Path(failed).parent
        os.chmod(parent, os.stat(parent).st_mode | 0o700)
        if Path(failed).is_dir() and not Path(failed).is_symlink():
            os.chmod(failed, os.stat(failed).st_mode | 0o700)
        function(failed)

    try:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, onerror=lambda function, failed, info: writable_and_again(function, failed, info))
        else:
            path.unlink(missing_ok=True)
    except PermissionError as error:
        logger.warning("%s cannot be removed (%s): delete it by hand", error.filename or path, error.strerror)
        return False
    return True


def remove_leftovers(capture_dir: Path) -> None:
    """Delete what a killed publish left and an older pipeline's version folders; the
    caller holds the capture's lock."""
    for stale in capture_dir.glob(f"{STAGING}*"):
        remove_tree(stale)
    old_layout = capture_dir / OLD_LAYOUT
    if old_layout.is_dir() and not (capture_dir / OUTPUT).is_symlink():
        for version in old_layout.iterdir():
            if not version.name.startswith("legacy-"):  # a user's output/ folder an older pipeline moved aside
                remove_tree(version)


def publish(capture_dir: Path, files: dict[str, tuple[Path, dict[str, Any]]]) -> bool:
    """Make ``output/`` hold exactly ``files`` (path in output/ -> (source, manifest record
    with "contents": {path in output/: [size, sha256]})), besides files it did not publish.
    The caller holds the capture's lock and has called ``remove_leftovers``.

    Returns False when the published output already is that (nothing written).
    """
    output = capture_dir / OUTPUT
    manifest = {name: record for name, (_, record) in files.items()}
    old = current_manifest(capture_dir)
    changed = _changed(output, old or {})  # hashed once: the check and the restore both use it
    if old == manifest and not output.is_symlink() and not changed:
        return False
    version = time.strftime("%Y%m%d-%H%M%S") + f"-{time.time_ns() % 1_000_000_000:09d}"
    staging = capture_dir / f"{STAGING}{version}"
    staging.mkdir()
    try:
        _assemble(staging, output, files, old, changed)
        atomic_write_text(staging / MANIFEST, json.dumps(manifest, indent=2, sort_keys=True))
    except OSError as error:
        shutil.rmtree(staging)
        if disk_full_error(error):
            size = sum(entry[0] for record in manifest.values() for entry in record.get("contents", {}).values())
            raise DiskFull(
                capture_dir,
                f"publishing {len(files)} file(s) to {output}",
                "the previous output/ and every cached result were kept",
                needed_bytes=size,
            ) from error
        raise
    was_link = output.is_symlink()
    _swap_in(staging, output)
    remove_tree(staging)  # the old output
    if was_link:
        remove_leftovers(capture_dir)
    return True


__all__ = ["MANIFEST", "OUTPUT", "STAGES", "check_output_path", "current_manifest", "publish", "remove_leftovers"]
