"""Plans and runs the stage DAG over one capture.

Cache key of a stage = SHA-256 of (stage name, version, its config section, the
shared sections or single shared settings it declared, the keys of its upstream stages, the content hashes
of the capture files it reads): a Merkle chain, so a change anywhere reruns
exactly the stages downstream of it, and reverting the change finds the old
entries again.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import platform
import shutil
import time
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any, Literal, Sequence

from pipeline import logger
from pipeline.core import progress
from pipeline.core.cache import LOG_FILE, Entry, StageCache
from pipeline.core.config import Config, input_file_path, input_file_settings, section_dict
from pipeline.core.errors import ConfigError, DiskFull, PipelineError
from pipeline.core.fsutil import atomic_write_text, disk_full_error
from pipeline.core.hashing import FileHasher, glob_capture_files, tree_size
from pipeline.core.interrupts import interruption
from pipeline.core.lock import CaptureLock
from pipeline.core.publish import STAGES, check_output_path, publish, remove_leftovers
from pipeline.core.stage import Stage, StageInputs

Action = Literal["run", "cached", "disabled"]

LIBRARIES = (
    "mitsuba",
    "drjit",
    "pycolmap",
    "opencv-contrib-python-headless",
    "pymeshlab",
    "xatlas",
    "trimesh",
    "OpenImageIO",
    "numpy",
)


@dataclass(frozen=True)
class Selection:
    """Which stages a run covers, from the CLI's --from/--until/--only/--force."""

    start: str | None = None
    until: str | None = None
    only: str | None = None
    force: tuple[str, ...] = ()
    """Stage names, or ``("all",)``."""


@dataclass
class PlannedStage:
    stage: Stage
    key: str
    components: dict[str, Any]
    action: Action
    reason: str
    entry: Entry | None = None
    seconds: float | None = None
    metrics: dict[str, Any] = field(default_factory=dict)


def check_contract(stages: Sequence[Stage]) -> None:
    """Every need names an output its stage declares, and every export is an output."""
    by_name = {s.name: s for s in stages}
    if len(by_name) != len(stages):
        raise ValueError("two stages share a name")
    for s in stages:
        for need in s.needs:
            up, _, output = need.partition(".")
            if up not in by_name:
                raise ValueError(f"stage {s.name} needs {need}: there is no stage {up}")
            if output not in by_name[up].outputs:
                raise ValueError(
                    f"stage {s.name} needs {need}, which stage {up} does not declare "
                    f"(its outputs: {', '.join(by_name[up].outputs) or 'none'})"
                )
        undeclared = set(s.exports) - set(s.outputs)
        if undeclared:
            raise ValueError(f"stage {s.name} exports {', '.join(sorted(undeclared))}, which it does not declare")
        if s.result is not None and s.result[1] not in s.exports:
            raise ValueError(f"stage {s.name}'s result {s.result[1]} is not one of its exports")


def shared_inputs(config: Config, stage: Stage) -> dict[str, Any]:
    """What ``stage`` declared in ``shared``: a section (``"board"``) or one setting of it
    (``"capture.rig"``), by that name."""
    values = {}
    for name in stage.shared:
        section, _, setting = name.partition(".")
        values[name] = getattr(config[section], setting) if setting else config[section]
    return values


def _plain(value: Any) -> Any:
    """A shared section or setting as JSON-ready values, for the cache key."""
    if dataclasses.is_dataclass(value):
        return section_dict(value)
    return list(value) if isinstance(value, tuple) else value


def topological_order(stages: Sequence[Stage]) -> list[Stage]:
    """Stages ordered so that each comes after its upstream; rejects bad graphs."""
    check_contract(stages)
    by_name = {s.name: s for s in stages}
    ordered: list[Stage] = []
    visiting: set[str] = set()

    def visit(s: Stage) -> None:
        if s in ordered:
            return
        if s.name in visiting:
            raise ValueError(f"stage graph has a cycle through {s.name}")
        visiting.add(s.name)
        for up in s.upstream:
            visit(by_name[up])
        visiting.discard(s.name)
        ordered.append(s)

    for s in stages:
        visit(s)
    return ordered


def descendants(stages: Sequence[Stage], name: str) -> set[str]:
    found = {name}
    for s in topological_order(stages):
        if found.intersection(s.upstream):
            found.add(s.name)
    return found


def ancestors(stages: Sequence[Stage], name: str) -> set[str]:
    by_name = {s.name: s for s in stages}
    found: set[str] = set()
    todo = list(by_name[name].upstream)
    while todo:
        up = todo.pop()
        if up not in found:
            found.add(up)
            todo.extend(by_name[up].upstream)
    return found


def _flatten(prefix: str, value: Any) -> dict[str, Any]:
    if isinstance(value, dict):
        out: dict[str, Any] = {}
        for k, v in value.items():
            out.update(_flatten(f"{prefix}.{k}" if prefix else k, v))
        return out
    return {prefix: value}


def explain_change(old: dict[str, Any], new: dict[str, Any]) -> str:
    """Why a key differs from the one of the previous entry, for --dry-run."""
    reasons: list[str] = []
    if old["version"] != new["version"]:
        reasons.append(f"stage version {old['version']} -> {new['version']}")
    for part in ("config", "shared"):
        flat_old = _flatten(new["stage"] if part == "config" else "", old[part])
        flat_new = _flatten(new["stage"] if part == "config" else "", new[part])
        for key in sorted(set(flat_old) | set(flat_new)):
            if flat_old.get(key) != flat_new.get(key):
                reasons.append(f"setting {key}: {flat_old.get(key)!r} -> {flat_new.get(key)!r}")
    files_old, files_new = old["files"], new["files"]
    changed = [f for f in files_new if f in files_old and files_old[f] != files_new[f]]
    added = [f for f in files_new if f not in files_old]
    removed = [f for f in files_old if f not in files_new]
    for verb, names in (("changed", changed), ("added", added), ("removed", removed)):
        if names:
            more = f" (+{len(names) - 3} more)" if len(names) > 3 else ""
            reasons.append(f"input {verb}: {', '.join(names[:3])}{more}")
    for setting, digest in new["setting_files"].items():
        if old.get("setting_files", {}).get(setting) != digest:
            reasons.append(f"the file {setting} names changed")
    for up, key in new["upstream"].items():
        if old["upstream"].get(up) != key:
            reasons.append(f"upstream {up} changed")
    return "; ".join(reasons) or "cache entry missing"


def library_versions() -> dict[str, str]:
    versions = {"python": platform.python_version()}
    for name in LIBRARIES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue  # not every environment installs every optional library
    return versions


class _FinalPaths(logging.Filter):
    """Rewrites a running stage's temporary folder to the folder its result will have,
    so that a warning's path still exists when the user reads it."""

    def __init__(self, tmp: Path, final: Path):
        super().__init__()
        self.tmp, self.final = str(tmp), str(final)

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        if self.tmp in message:
            record.msg, record.args = message.replace(self.tmp, self.final), None
        return True


class _StageLog(logging.FileHandler):
    """A stage's log.txt. A record it cannot write (a full disk) is dropped without the
    traceback logging prints by default: the stage's own error says what happened."""

    def handleError(self, record: logging.LogRecord) -> None:
        pass

    def close(self) -> None:
        try:
            super().close()
        except OSError:
            pass  # the last lines could not be flushed: the same full disk


class Runner:
    """Plans and executes ``stages`` on one capture with one validated config."""

    def __init__(self, capture_dir: Path, stages: Sequence[Stage], config: Config, wait: bool = True):
        if not capture_dir.is_dir():
            raise ConfigError(f"capture folder {capture_dir} does not exist")
        check_output_path(capture_dir)
        state_dir = capture_dir / ".pipeline"
        if state_dir.exists() and not state_dir.is_dir():
            raise ConfigError(
                f"{state_dir} is a file, but the pipeline keeps its cache in a folder of that name: "
                "move or delete the file"
            )
        self.capture_dir = capture_dir
        self.stages = topological_order(stages)
        self.by_name = {s.name: s for s in self.stages}
        self.config = config
        self.wait = wait
        """Whether run() waits for another run on the capture to finish, or fails."""
        self.cache = StageCache(capture_dir)
        self.hasher = FileHasher(self.cache.state_dir / "file_hashes.json")
        self.keys: dict[str, str] = {}
        """Every stage's cache key under the current config, filled by plan()."""

    # -- planning -----------------------------------------------------------

    def _check_name(self, name: str, option: str) -> None:
        if option == "--force" and name == "all":
            return
        if name not in self.by_name:
            raise ConfigError(f"{option} {name}: no such stage; stages are " + ", ".join(self.by_name))

    def _components(self, stage: Stage, upstream_keys: dict[str, str]) -> dict[str, Any]:
        files = glob_capture_files(self.capture_dir, stage.reads)
        setting_files = {
            f"{section}.{key}": self.hasher.hash_input(input_file_path(self.capture_dir, value))
            for section, _, setting in (name.partition(".") for name in (stage.name, *stage.shared))
            for key, value in input_file_settings(self.config[section]).items()
            if setting in ("", key)
        }
        return {
            "stage": stage.name,
            "version": stage.version,
            "config": section_dict(self.config[stage.name]),
            "shared": {name: _plain(value) for name, value in shared_inputs(self.config, stage).items()},
            "upstream": {up: upstream_keys[up] for up in stage.upstream},
            "files": {f.relative_to(self.capture_dir).as_posix(): self.hasher.hash(f) for f in files},
            "setting_files": setting_files,
        }

    def plan(self, selection: Selection = Selection()) -> list[PlannedStage]:
        """Decide, for every stage the selection covers, whether it runs and why."""
        for name, option in (
            (selection.start, "--from"),
            (selection.until, "--until"),
            (selection.only, "--only"),
            *((f, "--force") for f in selection.force),
        ):
            if name is not None:
                self._check_name(name, option)

        targets = set(self.by_name)
        if selection.until:
            targets = ancestors(self.stages, selection.until) | {selection.until}
        forced: dict[str, str] = {}
        must_be_cached: set[str] = set()
        if selection.only:
            targets = {selection.only}
            forced[selection.only] = f"--only {selection.only}"
            must_be_cached = ancestors(self.stages, selection.only)
        if selection.start and selection.start not in targets:
            raise ConfigError(
                f"--from {selection.start} is not upstream of --until {selection.until or selection.only}: "
                "nothing lies between them to run; pick a --from before --until"
            )
        if selection.start:
            for name in descendants(self.stages, selection.start) & targets:
                forced[name] = f"--from {selection.start}"
            must_be_cached = ancestors(self.stages, selection.start)
        for name in selection.force:
            chosen = self.by_name if name == "all" else descendants(self.stages, name)
            for forced_name in set(chosen) & targets:
                forced.setdefault(forced_name, f"--force {name}")

        keys = self.keys
        planned: list[PlannedStage] = []
        for stage in self.stages:
            components = self._components(stage, keys)
            key = hashlib.sha256(json.dumps(components, sort_keys=True).encode()).hexdigest()[:16]
            keys[stage.name] = key
            entry = self.cache.lookup(stage.name, key)
            if stage.enabled is not None and not stage.enabled(self.config[stage.name]):
                action, reason = "disabled", f"{stage.name}.enabled is off"
            elif stage.name in forced:
                action, reason = "run", f"forced ({forced[stage.name]})"
            elif entry is not None:
                action, reason = "cached", "inputs, settings and upstream unchanged"
            elif stage.name in must_be_cached:
                raise ConfigError(
                    f"stage {stage.name} has no cached result for the current config, and "
                    f"--from/--only do not compute upstream stages: run "
                    f"`pipeline run {self.capture_dir} --until {stage.name}` first"
                )
            else:
                previous = self.cache.entries(stage.name)
                action = "run"
                reason = explain_change(previous[-1].status["components"], components) if previous else "never run"
            if stage.name in targets or stage.name in must_be_cached:
                planned.append(PlannedStage(stage, key, components, action, reason, entry))
        if os.access(self.capture_dir, os.W_OK):
            self.hasher.save()  # a memo only: status and --dry-run work on a read-only capture
        return planned

    # -- execution ----------------------------------------------------------

    def run(self, selection: Selection = Selection(), on_stage_done=None, on_published=None) -> list[PlannedStage]:
        """Run what the selection needs while holding the capture's lock, then publish;
        ``on_published(plan)`` runs after publishing, still under the lock (the report)."""
        with CaptureLock(self.capture_dir, "pipeline run", wait=self.wait):
            removed = self.cache.remove_unfinished()
            if removed:
                logger.info("removed %d unfinished result folder(s) of killed runs", removed)
            remove_leftovers(self.capture_dir)
            plan = self._run_locked(selection, on_stage_done)
            if on_published is not None:
                on_published(plan)
            return plan

    def _run_locked(self, selection: Selection, on_stage_done) -> list[PlannedStage]:
        plan = self.plan(selection)
        results: dict[str, Entry] = {}
        for item in plan:
            if item.action == "disabled":
                continue
            if item.action == "cached":
                assert item.entry is not None
                results[item.stage.name] = item.entry
                item.seconds = item.entry.status["seconds"]
                item.metrics = item.entry.status.get("metrics", {})
            else:
                item.entry = self._execute(item, results)
                results[item.stage.name] = item.entry
            if on_stage_done is not None:
                on_stage_done(item)
        self._publish(results)
        self._record_run(plan)
        return plan

    def _execute(self, item: PlannedStage, results: dict[str, Entry]) -> Entry:
        stage = item.stage
        conf = self.config[stage.name]
        inputs = StageInputs(
            capture_dir=self.capture_dir,
            files=tuple(self.capture_dir / f for f in item.components["files"]),
            upstream=self._needed_outputs(stage, results),
            shared=shared_inputs(self.config, stage),
            checkpoint_dir=self.cache.checkpoint_dir(stage.name, item.key),
        )
        tmp = self.cache.begin(stage.name, item.key)
        handler = _StageLog(tmp / LOG_FILE)
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
        handler.setLevel(logging.DEBUG)
        logger.addHandler(handler)
        final_paths = _FinalPaths(tmp, self.cache.root / stage.name / item.key)
        logger.addFilter(final_paths)
        started = time.time()
        committed = False
        try:
            logger.info("stage %s (key %s): %s", stage.name, item.key, item.reason)
            with progress.in_stage(stage.name):
                result = stage.main(conf, inputs, tmp)
            item.seconds = time.time() - started
            item.metrics = result.metrics
            if set(result.outputs) != set(stage.outputs):
                raise RuntimeError(
                    f"stage {stage.name} returned outputs {sorted(result.outputs)} but declares {sorted(stage.outputs)}"
                )
            outputs = {}
            for name, path in result.outputs.items():
                resolved = Path(path).resolve()
                if not resolved.exists() or not resolved.is_relative_to(tmp.resolve()):
                    raise RuntimeError(
                        f"stage {stage.name} returned output {name}={path}, "
                        f"which is not an existing path inside its output folder"
                    )
                outputs[name] = resolved.relative_to(tmp.resolve()).as_posix()
            logger.info("stage %s done in %.1f s", stage.name, item.seconds)
            handler.close()
            status = {
                "stage": stage.name,
                "key": item.key,
                "version": stage.version,
                "components": item.components,
                "effective_config": self.config.as_dict(),
                "config_sources": list(self.config.sources),
                "libraries": library_versions(),
                "started": started,
                "finished": time.time(),
                "seconds": item.seconds,
                "outputs": outputs,
                "metrics": result.metrics,
            }
            entry = self.cache.commit(tmp, stage.name, item.key, status)
            committed = True
            if inputs.checkpoint_dir.exists():
                shutil.rmtree(inputs.checkpoint_dir)
            return entry
        except BaseException as error:
            logger.removeHandler(handler)  # its file moves with the failed folder
            handler.close()
            if not committed:
                self._keep_failed(stage.name, tmp, error)
            raise
        finally:
            logger.removeFilter(final_paths)
            logger.removeHandler(handler)
            handler.close()

    def _keep_failed(self, stage: str, tmp: Path, error: BaseException) -> None:
        """Keep a failed run's log in failed/; the partial results too, unless the disk
        is full or the user stopped the run (then they are in the way)."""
        full = disk_full_error(error)
        stopped = interruption(error) is not None
        written = tree_size(tmp)
        kept = self.cache.keep_failed(tmp, stage, log_only=full or stopped)
        if full:
            raise DiskFull(
                tmp.parent,
                f"stage {stage} wrote its results",
                f"its partial files ({written / 1e6:.1f} MB) were removed and every earlier result kept "
                f"(its log: {kept / LOG_FILE})",
                needed_bytes=written,
            ) from error
        if not stopped:
            logger.error("stage %s failed; its log is in %s", stage, kept / LOG_FILE)

    @staticmethod
    def _needed_outputs(stage: Stage, results: dict[str, Entry]) -> dict[str, dict[str, Path]]:
        """Exactly the upstream outputs ``stage`` declares it needs, by stage and name."""
        needed: dict[str, dict[str, Path]] = {}
        for need in stage.needs:
            up, _, output = need.partition(".")
            if up in results:
                needed.setdefault(up, {})[output] = results[up].outputs[output]
        return needed

    def _publish(self, results: dict[str, Entry]) -> None:
        """Publish to CAPTURE/output/ the exports of every stage whose result is valid
        for the current config: this run's, or cached ones outside its selection (so
        ``--until cleanup`` after a full run keeps uv's mesh). Each stage's go to
        output/stages/<stage>/; the last result of each role also goes on top."""
        files: dict[str, tuple[Path, dict[str, Any]]] = {}
        on_top: dict[str, tuple[Stage, Entry, str]] = {}
        for stage in self.stages:
            if not stage.exports or stage.enabled is not None and not stage.enabled(self.config[stage.name]):
                continue
            entry = results.get(stage.name) or self.cache.lookup(stage.name, self.keys[stage.name])
            if entry is None:
                continue
            files.update(_published(stage, entry, stage.exports, f"{STAGES}/{stage.name}/"))
            if stage.result is not None:
                on_top[stage.result[0]] = (stage, entry, stage.result[1])
        for stage, entry, name in on_top.values():
            files.update(_published(stage, entry, (name,), ""))
        if publish(self.capture_dir, files):
            logger.info("published %d file(s) to %s", len(files), self.capture_dir / "output")

    def _record_run(self, plan: list[PlannedStage]) -> None:
        runs = self.cache.state_dir / "runs"
        runs.mkdir(parents=True, exist_ok=True)
        record = {
            "effective_config": self.config.as_dict(),
            "config_sources": list(self.config.sources),
            "stages": [summary(p) for p in plan],
        }
        name = time.strftime("%Y%m%d-%H%M%S") + f"-{time.time_ns() % 1_000_000:06d}.json"
        atomic_write_text(runs / name, json.dumps(record, indent=2))


def _published(stage: Stage, entry: Entry, names: Sequence[str], prefix: str) -> dict[str, tuple[Path, dict[str, Any]]]:
    """The files to publish for exports ``names`` of ``stage``'s cached ``entry``, by
    their path in output/ under ``prefix``: a folder's children, or the file. An export
    inside another one (fit_material's params.json in its folder) comes with that one."""
    paths = {name: entry.outputs[name] for name in names}
    files = {}
    for name, source in paths.items():
        if any(other != source and other in source.parents for other in paths.values()):
            continue
        for piece in sorted(source.iterdir()) if source.is_dir() else [source]:
            rel = piece.relative_to(entry.path).as_posix()
            contents = {
                prefix + piece.name + path[len(rel) :]: size_and_hash
                for path, size_and_hash in entry.status["contents"].items()
                if path == rel or path.startswith(rel + "/")
            }
            record = {
                "stage": stage.name,
                "output": name,
                "key": entry.key,
                "finished": entry.finished,
                "contents": contents,
            }
            files[prefix + piece.name] = (piece, record)
    return files


def summary(item: PlannedStage) -> dict[str, Any]:
    return {
        "stage": item.stage.name,
        "key": item.key,
        "action": item.action,
        "reason": item.reason,
        "seconds": item.seconds,
        "metrics": item.metrics,
    }


__all__ = ["PipelineError", "PlannedStage", "Runner", "Selection", "summary"]
