"""Commands for synthetic captures: ``synth`` renders one, ``score`` compares a
capture's outputs with its ground truth."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

from rich.table import Table

from pipeline.cli.options import Arg
from pipeline.cli.registry import capture_dir, command
from pipeline.core import progress
from pipeline.core.fsutil import atomic_write_text
from pipeline.core.lock import CaptureLock
from pipeline.synthetic.options import SynthOptions


@dataclass(frozen=True)
class SynthCommand:
    """Render a synthetic capture with ground truth."""

    out_dir: Annotated[str, Arg(positional=True)]
    """New folder for the capture."""
    options: SynthOptions = field(default_factory=SynthOptions)
    """What to render."""


@dataclass(frozen=True)
class ScoreOptions:
    """Compare a synthetic capture's outputs with its ground truth."""

    capture: Annotated[str, Arg(positional=True)]
    """Capture folder with ground_truth/ and output/."""
    json: bool = False
    """Print the full report."""


@command("synth", SynthCommand, "render a synthetic capture with ground truth")
def synth(command_options: SynthCommand) -> int:
    from pipeline.synthetic.synth import synthesize

    synthesize(Path(command_options.out_dir), command_options.options)
    return 0


@command("score", ScoreOptions, "compare a synthetic capture's outputs with its ground truth")
def score(options: ScoreOptions) -> int:
    from pipeline.synthetic.score import score_capture, summary_rows

    capture = capture_dir(options.capture)
    report = score_capture(capture)
    (capture / "output").mkdir(exist_ok=True)
    with CaptureLock(capture, "pipeline score"):
        atomic_write_text(capture / "output" / "score.json", json.dumps(report, indent=2))
    if options.json:
        print(json.dumps(report, indent=2))
        return 0
    table = Table("part", "metric", "value")
    for row in summary_rows(report):
        table.add_row(*row)
    progress.console.print(table)
    for missing in report["missing"]:
        progress.console.print(f"not scored: {missing}")
    return 0
