"""What a stage is: the contract between a module in ``stages/`` and the runner.

A stage module defines one ``Config`` dataclass (its config section, named after
the stage), a ``main(conf, inputs, out_dir) -> StageResult`` function that reads
paths and writes only inside ``out_dir``, and a module-level ``STAGE`` that ties
them together. The runner owns everything else: where ``out_dir`` lives, when a
result may be reused, and which upstream outputs the stage sees.

Stages talk only through declared outputs: a stage lists the names it returns
(``outputs``) and the upstream outputs it reads (``needs``, as ``stage.output``);
the runner checks before anything runs that every need is an output some stage
declares, hands a stage exactly the outputs it needs, and fails a stage that
returns other names than it declared. The files behind the names are
pipeline.formats' business.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping


@dataclass(frozen=True)
class StageInputs:
    """Everything a stage may read, resolved by the runner."""

    capture_dir: Path
    """The capture folder (read-only for stages)."""
    files: tuple[Path, ...]
    """Capture files matched by the stage's ``reads`` patterns, sorted."""
    upstream: Mapping[str, Mapping[str, Path]]
    """The outputs the stage needs: stage name -> output name -> path."""
    shared: Mapping[str, Any]
    """What the stage declared in ``shared``: a section by its name (``board``), a single
    setting by its dotted name (``capture.rig``: the value)."""
    checkpoint_dir: Path | None = None
    """A folder for state that lets a killed run of this stage resume (long fits,
    pipeline.fit.checkpoint): kept across killed runs with the same cache key,
    deleted once the result is committed."""


@dataclass
class StageResult:
    """What a stage returns: named output paths inside its ``out_dir``, and metrics."""

    outputs: dict[str, Path]
    metrics: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Stage:
    """A node of the DAG."""

    name: str
    """Unique name; also the name of the stage's config section."""
    version: int
    """Bump when the code changes its results: old cache entries stop matching."""
    config: type
    """Dataclass of the stage's own config section."""
    main: Callable[[Any, StageInputs, Path], StageResult]
    """``main(conf, inputs, out_dir)``: does the work, writes only into ``out_dir``."""
    needs: tuple[str, ...] = ()
    """Upstream outputs this stage reads, as ``"stage.output"``."""
    outputs: tuple[str, ...] = ()
    """Names of the outputs ``main`` returns, every one of them, every time."""
    reads: tuple[str, ...] = ()
    """Glob patterns, relative to the capture folder, of the capture files it reads."""
    shared: tuple[str, ...] = ()
    """Shared config sections (``"board"``) or single settings of one (``"capture.rig"``)
    whose values change its results: only these enter its cache key and ``inputs.shared``."""
    exports: tuple[str, ...] = ()
    """Outputs (a subset of ``outputs``) copied to ``CAPTURE/output/stages/<name>/`` after a
    successful run (a folder's contents, or the file)."""
    result: tuple[str, str] | None = None
    """``(role, export)``: the export that is the capture's result of that role (``"scene"``,
    ``"model"``) unless a later stage in DAG order with a valid result declares the same
    role; it is also published at the top of ``output/`` (a folder's contents, or the
    file), so that the final scene, its params.json and the model are found first."""
    enabled: Callable[[Any], bool] | None = None
    """Optional predicate on the stage's config; a disabled stage is skipped."""

    @property
    def upstream(self) -> tuple[str, ...]:
        """Names of the stages whose outputs this stage needs, in the order first named."""
        return tuple(dict.fromkeys(need.split(".", 1)[0] for need in self.needs))
