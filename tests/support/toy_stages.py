"""A tiny stage DAG defined only for the tests (never registered as real stages).

    ingest (reads images/*.txt) ──> double ──> report (exported)
                                └─> meta

``RUNS`` records which stages actually executed, so tests can assert what a
run recomputed. ``ingest`` can be told to fail or to SIGKILL its own process.
"""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import textwrap
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

from pipeline import logger
from pipeline.core.config import InputFile, Range, input_file_path, load_config
from pipeline.core.errors import PipelineError
from pipeline.core.runner import PlannedStage, Runner, Selection
from pipeline.core.sections import schema
from pipeline.core.stage import Stage, StageInputs, StageResult

REPOSITORY = Path(__file__).resolve().parents[2]

RUNS: list[str] = []


@dataclass(frozen=True)
class IngestConfig:
    """Sum the numbers in the capture's text files."""

    scale: Annotated[float, Range(0.0, 10.0)] = 1.0
    """Factor applied to the sum."""
    fail: Literal["no", "raise", "user", "sigkill", "diskfull", "sleep", "stubborn"] = "no"
    """Make the stage fail (a bug, a user error, a kill, a full disk), or wait to be
    interrupted (stubborn: it ignores the first interruption), to test crash safety."""
    extra: Annotated[str, InputFile()] = ""
    """A file with one more number to add (an input named by a setting)."""


@dataclass(frozen=True)
class DoubleConfig:
    """Multiply the total."""

    factor: Annotated[int, Range(1, 100)] = 2
    """Integer factor."""


@dataclass(frozen=True)
class EmptyConfig:
    """No settings."""


def ingest(conf: IngestConfig, inputs: StageInputs, out_dir: Path) -> StageResult:
    RUNS.append("ingest")
    files = [*inputs.files, *([input_file_path(inputs.capture_dir, conf.extra)] if conf.extra else [])]
    total = sum(float(p.read_text()) for p in files) * conf.scale
    (out_dir / "partial.txt").write_text("half-written")
    if conf.fail == "raise":
        raise RuntimeError("ingest failed on purpose")
    if conf.fail == "user":
        raise PipelineError(f"{inputs.files[0].name}: not a number; fix the file")
    if conf.fail == "sigkill":
        os.kill(os.getpid(), signal.SIGKILL)
    if conf.fail == "diskfull":
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(out_dir / "total.txt"))
    if conf.fail in ("sleep", "stubborn"):
        (out_dir / "waiting").write_text("")
        try:
            time.sleep(60)
        except KeyboardInterrupt:
            if conf.fail == "sleep":
                raise
            time.sleep(60)
    (out_dir / "total.txt").write_text(str(total))
    return StageResult({"total": out_dir / "total.txt"}, {"files": len(inputs.files)})


def double(conf: DoubleConfig, inputs: StageInputs, out_dir: Path) -> StageResult:
    RUNS.append("double")
    total = float(inputs.upstream["ingest"]["total"].read_text())
    (out_dir / "doubled.txt").write_text(str(total * conf.factor))
    return StageResult({"doubled": out_dir / "doubled.txt"})


def meta(conf: EmptyConfig, inputs: StageInputs, out_dir: Path) -> StageResult:
    RUNS.append("meta")
    (out_dir / "meta.txt").write_text(f"{len(inputs.upstream['ingest'])} outputs")
    logger.warning("meta wrote %s", out_dir / "meta.txt")  # a warning naming a result's file
    return StageResult({"meta": out_dir / "meta.txt"})


def report(conf: EmptyConfig, inputs: StageInputs, out_dir: Path) -> StageResult:
    RUNS.append("report")
    doubled = inputs.upstream["double"]["doubled"].read_text()
    (out_dir / "report.txt").write_text(f"result {doubled}\n")
    return StageResult({"report": out_dir / "report.txt"})


def make_stages(ingest_version: int = 1) -> tuple[Stage, ...]:
    return (
        Stage("ingest", ingest_version, IngestConfig, ingest, outputs=("total",), reads=("images/*.txt",)),
        Stage("double", 1, DoubleConfig, double, needs=("ingest.total",), outputs=("doubled",)),
        Stage("meta", 1, EmptyConfig, meta, needs=("ingest.total",), outputs=("meta",)),
        Stage(
            "report",
            1,
            EmptyConfig,
            report,
            needs=("double.doubled",),
            outputs=("report",),
            exports=("report",),
            result=("report", "report"),
        ),
    )


def make_capture(root: Path, numbers=(1.0, 2.0, 3.0)) -> Path:
    capture = root / "capture"
    (capture / "images").mkdir(parents=True)
    for i, n in enumerate(numbers):
        (capture / "images" / f"{i:03d}.txt").write_text(str(n))
    return capture


def toy_runner(
    capture: Path, presets_dir: Path, *overrides: str, version: int = 1, wait: bool = True, preset: str = "standard"
) -> Runner:
    stages = make_stages(ingest_version=version)
    config = load_config(schema(stages), capture, preset, list(overrides), presets_dir)
    return Runner(capture, stages, config, wait=wait)


def run_toy(
    capture: Path, presets_dir: Path, *overrides: str, selection: Selection = Selection(), version: int = 1
) -> dict[str, PlannedStage]:
    """Run the toy DAG in this process; the plan by stage name. ``RUNS`` then lists what ran."""
    RUNS.clear()
    plan = toy_runner(capture, presets_dir, *overrides, version=version).run(selection)
    return {p.stage.name: p for p in plan}


def run_python(script: str, timeout: float = 60) -> subprocess.CompletedProcess:
    """Run ``script`` in a fresh interpreter from the repository root (where ``tests``
    imports), for runs that must be killed or hold a lock in another process."""
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(script)], capture_output=True, text=True, cwd=REPOSITORY, timeout=timeout
    )


HOLD_LOCK = """
import sys, time
from pathlib import Path
from pipeline.core.lock import CaptureLock
with CaptureLock(Path(sys.argv[1]), "test holder"):
    print("held", flush=True)
    time.sleep(float(sys.argv[2]))
"""


def hold_lock(capture, seconds):
    """A process holding the capture's lock for ``seconds``; returns once it holds it."""
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD_LOCK, str(capture), str(seconds)], stdout=subprocess.PIPE, text=True, cwd=REPOSITORY
    )
    assert holder.stdout.readline().strip() == "held"
    return holder


TOY_CLI = """
import sys
from pathlib import Path
from pipeline import cli
from pipeline.cli import registry
from pipeline.core import config
from tests.support.toy_stages import make_stages
registry.registered_stages = make_stages
config.PRESETS_DIR = Path(sys.argv[1])
sys.exit(cli.main(sys.argv[2:]))
"""


def start_toy_cli(presets_dir: Path, *argv: str) -> subprocess.Popen:
    """The real CLI over the toy stages in a process of its own (to be signalled)."""
    return subprocess.Popen(
        [sys.executable, "-c", TOY_CLI, str(presets_dir), *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPOSITORY,
    )
