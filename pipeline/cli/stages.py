"""Commands over a capture's stage DAG: ``run``, ``status``, ``clean``, ``config``."""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import dataclass, field
from typing import Annotated

from rich.table import Table

from pipeline import logger, output_guide
from pipeline import report as html_report
from pipeline.cli import registry
from pipeline.cli.options import Arg
from pipeline.cli.registry import ConfigLayers, capture_dir, command
from pipeline.core import jsonio, progress
from pipeline.core.cache import StageCache
from pipeline.core.config import describe_schema, load_config
from pipeline.core.errors import ConfigError, PipelineError
from pipeline.core.hashing import tree_size
from pipeline.core.lock import CaptureLock
from pipeline.core.publish import STAGES, current_manifest
from pipeline.core.runner import PlannedStage, Runner, Selection, summary
from pipeline.core.sections import schema
from pipeline.render import mitsuba_variant

Capture = Annotated[str, Arg(positional=True)]


@dataclass(frozen=True)
class RunOptions:
    """Run the stage DAG on a capture, reusing cached results."""

    capture: Capture
    """Capture folder (images/, capture.toml, ...)."""
    config: ConfigLayers = field(default_factory=ConfigLayers)
    """Preset and overrides."""
    start: Annotated[str | None, Arg(flag="--from", metavar="STAGE")] = None
    """Rerun STAGE and everything downstream; upstream must be cached."""
    until: Annotated[str | None, Arg(metavar="STAGE")] = None
    """Stop after STAGE."""
    only: Annotated[str | None, Arg(metavar="STAGE")] = None
    """Rerun just STAGE; upstream must be cached."""
    force: Annotated[tuple[str, ...], Arg(repeat=True, metavar="STAGE|all")] = ()
    """Recompute STAGE (and what is downstream) even if cached."""
    dry_run: bool = False
    """List each stage as cached or to run, with the reason."""
    no_wait: bool = False
    """Fail at once when another run holds the capture, instead of waiting for it."""
    json: bool = False
    """Print a machine-readable summary."""


@dataclass(frozen=True)
class ReportOptions:
    """Rewrite CAPTURE/output/report.html from what is cached for the current settings."""

    capture: Capture
    """Capture folder."""
    config: ConfigLayers = field(default_factory=ConfigLayers)
    """Preset and overrides (the report shows the results of these settings)."""


@dataclass(frozen=True)
class StatusOptions:
    """Stages, cache keys, timings and cache size."""

    capture: Capture
    """Capture folder."""
    config: ConfigLayers = field(default_factory=ConfigLayers)
    """Preset and overrides."""
    json: bool = False
    """Print a machine-readable summary."""


@dataclass(frozen=True)
class CleanOptions:
    """Delete cached results (never output/)."""

    capture: Capture
    """Capture folder."""
    keep_latest: bool = False
    """Keep the newest result of each stage."""
    no_wait: bool = False
    """Fail at once when a run holds the capture, instead of waiting for it."""


@dataclass(frozen=True)
class ConfigOptions:
    """Show every setting with its value and documentation."""

    capture: Annotated[str | None, Arg(positional=True)] = None
    """Include this capture's capture.toml."""
    config: ConfigLayers = field(default_factory=ConfigLayers)
    """Preset and overrides."""


def make_runner(capture: str, layers: ConfigLayers, wait: bool = True) -> Runner:
    folder = capture_dir(capture)
    stages = registry.registered_stages()
    return Runner(folder, stages, load_config(schema(stages), folder, layers.preset, layers.set), wait=wait)


def _settings(runner: Runner, layers: ConfigLayers) -> html_report.RunSettings:
    files = tuple(str(source) for source in runner.config.sources if not str(source).startswith("-s "))
    return html_report.RunSettings(layers.preset, tuple(layers.set), files)


def _describe(item: PlannedStage) -> str:
    took = f"{item.seconds:7.1f} s" if item.seconds is not None else " " * 9
    return f"  {item.action:8s} {item.stage.name:14s} {took}  {item.key[:10]}  {item.reason}"


def _check_variant(runner: Runner, selection: Selection) -> None:
    """A Mitsuba variant the settings name (not auto) that cannot render here is
    refused before any stage runs, rather than by the first stage that renders."""
    variant = runner.config["mitsuba"].variant
    if variant == "auto":
        return
    rendering = [p for p in runner.plan(selection) if p.action == "run" and "mitsuba" in p.stage.shared]
    if not rendering:
        return
    try:
        mitsuba_variant.choose(variant)
    except PipelineError as error:
        why = " ".join(str(error).split())  # one line: the candidates' reasons after the variant's name
        raise ConfigError(
            f"{why}; stage {rendering[0].stage.name} renders with it: set mitsuba.variant = 'auto'"
        ) from None


@command("run", RunOptions, "run the stage DAG on a capture, reusing cached results")
def run(options: RunOptions) -> int:
    runner = make_runner(options.capture, options.config, wait=not options.no_wait)
    selection = Selection(start=options.start, until=options.until, only=options.only, force=options.force)
    if options.dry_run:
        plan = runner.plan(selection)
        if options.json:  # JSON alone, so that it parses
            print(json.dumps({"dry_run": True, "stages": [summary(p) for p in plan]}, indent=2))
            return 0
        for item in plan:
            print(_describe(item))
        return 0
    started = time.time()

    def report(item: PlannedStage) -> None:
        if progress.is_enabled():
            progress.console.print(_describe(item), highlight=False)

    def write_report(plan: list[PlannedStage]) -> None:
        ran = {p.stage.name for p in plan if p.action == "run"}
        output_guide.write(runner.capture_dir)  # first: the report links to it
        html_report.write(
            runner.capture_dir, html_report.records(runner.plan(), ran), _settings(runner, options.config)
        )

    _check_variant(runner, selection)
    plan = runner.run(selection, on_stage_done=report, on_published=write_report)
    logger.info(
        "%d stage(s) ran, %d cached, in %.1f s; results in %s",
        sum(p.action == "run" for p in plan),
        sum(p.action == "cached" for p in plan),
        time.time() - started,
        runner.capture_dir / "output",
    )
    if options.json:
        output = runner.capture_dir / "output"
        published = current_manifest(runner.capture_dir) or {}
        result = {
            "seconds": time.time() - started,
            "outputs": {name: str(output / name) for name in sorted(published) if "/" not in name},
            "stage_outputs": {
                stage: str(output / STAGES / stage)
                for stage in sorted({name.split("/")[1] for name in published if name.startswith(STAGES + "/")})
            },
            "report": str(output / html_report.REPORT_HTML),
            "figures": {p.stage.name: p.metrics for p in plan if p.metrics},
            "stages": [summary(p) for p in plan],
        }
        print(jsonio.dumps(result, indent=2))
    return 0


@command("report", ReportOptions, "write output/report.html from what is cached")
def report(options: ReportOptions) -> int:
    runner = make_runner(options.capture, options.config)
    with CaptureLock(runner.capture_dir, "pipeline report"):
        output_guide.write(runner.capture_dir)  # first: the report links to it
        path = html_report.write(
            runner.capture_dir, html_report.records(runner.plan()), _settings(runner, options.config)
        )
    print(path)
    return 0


def status_summary(runner: Runner) -> dict:
    """`pipeline status --json`'s summary (and `pipeline studio`'s stage table): each
    stage's state under the runner's settings, why it would run, its cache key, its
    last result's time and seconds, its cache entries and their size."""
    plan = {p.stage.name: p for p in runner.plan()}
    cache = runner.cache
    rows = []
    for stage in runner.stages:
        entries = cache.entries(stage.name)
        item = plan[stage.name]
        shown = item.entry or (entries[-1] if entries else None)
        rows.append(
            {
                "stage": stage.name,
                "state": {"cached": "cached", "run": "to run", "disabled": "disabled"}[item.action],
                "reason": item.reason,
                "key": item.key,
                "finished": time.strftime("%Y-%m-%d %H:%M", time.localtime(shown.finished)) if shown else "-",
                "seconds": shown.status["seconds"] if shown else None,
                "entries": len(entries),
                "bytes": sum(tree_size(e.path) for e in entries),
            }
        )
    total = tree_size(cache.state_dir) if cache.state_dir.is_dir() else 0
    return {"stages": rows, "cache_bytes": total}


@command("status", StatusOptions, "stages, cache keys, timings and cache size")
def status(options: StatusOptions) -> int:
    runner = make_runner(options.capture, options.config)
    summary = status_summary(runner)
    if options.json:
        print(json.dumps(summary, indent=2))
        return 0
    table = Table("stage", "current config", "key", "finished", "seconds", "entries", "size")
    for row in summary["stages"]:
        seconds = "-" if row["seconds"] is None else f"{row['seconds']:.1f}"
        size = f"{row['bytes'] / 1e6:.1f} MB"
        table.add_row(row["stage"], row["state"], row["key"][:10], row["finished"], seconds, str(row["entries"]), size)
    progress.console.print(table)
    progress.console.print(f"cache: {summary['cache_bytes'] / 1e6:.1f} MB in {runner.cache.state_dir}")
    return 0


@command("clean", CleanOptions, "delete cached results (never output/)")
def clean(options: CleanOptions) -> int:
    folder = capture_dir(options.capture)
    cache = StageCache(folder)
    before = tree_size(cache.state_dir) if cache.state_dir.is_dir() else 0
    with CaptureLock(folder, "pipeline clean", wait=not options.no_wait):
        for leftover in cache.leftovers():
            shutil.rmtree(leftover)
        if options.keep_latest:
            for stage in cache.stages():
                for entry in cache.entries(stage)[:-1]:
                    cache.remove(entry)
        elif cache.root.is_dir():
            shutil.rmtree(cache.root)
    after = tree_size(cache.state_dir) if cache.state_dir.is_dir() else 0
    logger.info("freed %.1f MB in %s", (before - after) / 1e6, cache.state_dir)
    return 0


@command("config", ConfigOptions, "show every setting with its value and documentation")
def config(options: ConfigOptions) -> int:
    stages = registry.registered_stages()
    capture = capture_dir(options.capture) if options.capture else None
    loaded = load_config(schema(stages), capture, options.config.preset, options.config.set)
    print(f"# preset {loaded.preset}; layers: {', '.join(loaded.sources)}\n")
    print(describe_schema(schema(stages), loaded))
    return 0
