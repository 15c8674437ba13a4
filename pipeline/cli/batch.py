"""``pipeline batch``: many captures on a Dask cluster.

Each capture is one task, ``run_capture``, which runs the stage DAG exactly as
``pipeline run`` does (same cache, same lock, same output/). A local cluster of
worker processes is started unless ``--scheduler`` names a running one; then
every worker must see the captures at the same paths (a shared folder) and have
this package installed (README: "Many specimens"). A capture that fails is
reported and the others go on; the exit code is 0 only when all succeeded.
"""

from __future__ import annotations

import importlib.util
import json
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

from rich.table import Table

from pipeline import logger
from pipeline.cli.options import Arg
from pipeline.cli.registry import ConfigLayers, capture_dir, command
from pipeline.core import progress
from pipeline.core.config import Range
from pipeline.core.errors import PipelineError
from pipeline.core.fsutil import atomic_write_text
from pipeline.core.runner import Selection, summary


@dataclass(frozen=True)
class BatchOptions:
    """Run the stage DAG on many captures on a Dask cluster."""

    captures: Annotated[tuple[str, ...], Arg(positional=True, metavar="CAPTURE")]
    """Capture folders."""
    config: ConfigLayers = field(default_factory=ConfigLayers)
    """Preset and overrides, the same for every capture (each capture.toml still applies)."""
    until: Annotated[str | None, Arg(metavar="STAGE")] = None
    """Stop each capture after STAGE."""
    scheduler: Annotated[str | None, Arg(metavar="ADDRESS")] = None
    """Address of a running Dask scheduler (tcp://host:8786); default: a local cluster."""
    workers: Annotated[int, Range(1, None)] = 2
    """Worker processes of the local cluster; each runs one capture at a time."""
    no_wait: bool = False
    """Fail a capture at once when another run holds it, instead of waiting."""
    report: str = "batch.json"
    """Where the batch's JSON summary is written."""
    json: bool = False
    """Also print the summary as JSON."""


STAGE_TOPIC = "pipeline-stage"
"""The Dask event topic a worker reports each finished stage on (the client logs it)."""


def run_capture(capture: str, preset: str, overrides: tuple[str, ...], until: str | None, wait: bool) -> dict:
    """One capture's run, on a worker: a summary record; a user-caused failure is a
    record too (a bug raises, and the batch reports its traceback). Each stage that
    finishes is reported to the client as it happens."""
    from pipeline.cli.stages import make_runner

    started = time.time()
    record: dict[str, Any] = {"capture": capture}
    try:
        runner = make_runner(capture, ConfigLayers(preset, overrides), wait)
        plan = runner.run(Selection(until=until), on_stage_done=lambda item: _report_stage(capture, item))
    except PipelineError as error:
        return record | {"status": "failed", "exit_code": error.exit_code, "error": str(error), "seconds": 0.0}
    record["seconds"] = time.time() - started
    record["stages"] = [summary(item) for item in plan]
    record["figures"] = heldout_figures(plan)
    return record | {"status": "ok", "exit_code": 0}


def heldout_figures(plan) -> dict[str, Any]:
    """The capture's held-out error: that of the last fit stage that measured one (its
    photos never fitted to), with the stage's name; {} when no fit stage ran."""
    measured = [item for item in plan if isinstance(item.metrics.get("validation_mse"), (int, float))]
    if not measured:
        return {}
    last = measured[-1]
    return {"heldout_mse": last.metrics["validation_mse"], "heldout_stage": last.stage.name}


def _report_stage(capture: str, item) -> None:
    """On a worker: one finished stage, as an event the client logs (nothing outside Dask)."""
    from distributed import get_worker

    message = {"capture": capture, "stage": item.stage.name, "action": item.action, "seconds": item.seconds}
    get_worker().log_event(STAGE_TOPIC, message)


def _figures(record: dict) -> str:
    if record["status"] != "ok":
        return record["error"].splitlines()[0][:100]
    figures = record["figures"]
    if not figures:
        return "no fit stage ran: no held-out error"
    return f"{figures['heldout_mse']:.3g} ({figures['heldout_stage']})"


def _client(options: BatchOptions):
    from dask.distributed import Client, LocalCluster

    if options.scheduler:
        return Client(options.scheduler)
    cluster = LocalCluster(n_workers=options.workers, threads_per_worker=1, processes=True, dashboard_address=":0")
    return Client(cluster)


def _log_stage(message: dict) -> None:
    took = f" in {message['seconds']:.1f} s" if message.get("seconds") is not None else ""
    logger.info("%s: %s %s%s", Path(message["capture"]).name, message["stage"], message["action"], took)


@command("batch", BatchOptions, "run many captures on a Dask cluster (local by default)")
def batch(options: BatchOptions) -> int:
    from dask.distributed import as_completed

    captures = [str(capture_dir(c).resolve()) for c in options.captures]
    started = time.time()
    records = []
    with _client(options) as client:
        futures = {
            client.submit(
                run_capture,
                capture,
                options.config.preset,
                options.config.set,
                options.until,
                not options.no_wait,
                key=f"capture-{index}-{Path(capture).name}",
                pure=False,
            ): capture
            for index, capture in enumerate(captures)
        }
        logger.info("%d capture(s) on %s", len(captures), client.scheduler.address)
        if importlib.util.find_spec("bokeh") is None:
            logger.info("no dashboard: Dask's needs bokeh (pip install 'bokeh>=3.1'); each stage is logged here")
        else:
            logger.info("dashboard at %s", client.dashboard_link)
        client.subscribe_topic(STAGE_TOPIC, lambda event: _log_stage(event[1]))
        for future in as_completed(futures):
            if future.status == "error":
                error = future.exception()
                text = "".join(traceback.format_exception(type(error), error, future.traceback()))
                record = {"capture": futures[future], "status": "error", "exit_code": 1, "error": text, "seconds": 0.0}
            else:
                record = future.result()
            records.append(record)
            log = logger.info if record["status"] == "ok" else logger.error
            log("[%d/%d] %s: %s %s", len(records), len(captures), record["capture"], record["status"], _figures(record))
    records.sort(key=lambda r: captures.index(r["capture"]))
    table = Table("capture", "status", "seconds", "held-out error (MSE)")
    for record in records:
        table.add_row(Path(record["capture"]).name, record["status"], f"{record['seconds']:.1f}", _figures(record))
    progress.console.print(table)
    succeeded = sum(r["status"] == "ok" for r in records)
    result = {"captures": records, "succeeded": succeeded, "failed": len(records) - succeeded}
    result["seconds"] = time.time() - started
    atomic_write_text(Path(options.report), json.dumps(result, indent=2))
    logger.info(
        "%d of %d capture(s) succeeded in %.1f s; summary in %s",
        succeeded,
        len(records),
        result["seconds"],
        options.report,
    )
    if options.json:
        print(json.dumps(result, indent=2))
    return 0 if succeeded == len(records) else 1
