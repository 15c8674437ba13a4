"""Where fit_geometry's time goes: Dr.Jit's kernel history over one run of the stage.

Runs the stage DAG on a capture up to fit_geometry (standard preset), fit_geometry
forced, with ``dr.JitFlag.KernelHistory`` on. The history is drained at every step of
every fitting loop (it keeps each kernel's IR, too much to hold for a whole stage) and
summed by where the work ran: the geometry passes' loops ("shape fit"), the material
passes' ("fit"), and the rest of the stage (loading views, scoring, writing); within
each, Dr.Jit's JIT kernels by where their machine code came from (its in-memory cache,
its disk cache, or compiled) and by whether they ran inside a frozen function's
recording or replay, and every other operation (memory copies, reductions, ...) on one
row. For each row: launches, and the seconds Dr.Jit reports for generating the IR
(codegen), compiling it (backend) and running it (execution). What the history does
not cover (Python, Mitsuba's tracing of each step, the host waiting for results it
reads) is the stage's wall time less their sum.

Usage: ``.venv/bin/python -m bench.studies.geometry_kernels [--capture DIR] [--write]``
(after bin/bootstrap). Without ``--capture`` the bundled bird is copied into a new
folder and every stage before fit_geometry runs first (minutes); a capture already
cached through fit_texture runs fit_geometry alone. ``--write`` puts the table into
docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from collections import defaultdict
from pathlib import Path

from bench.common import ROOT, code_version, machine, run_stages, write_section
from pipeline.render import mitsuba_variant

DRAINED = ("execution_time", "codegen_time", "backend_time")
"""The history's times (milliseconds) summed per row."""
OUTSIDE = "rest of the stage"
"""Where the work outside every fitting loop counts."""


def row_of(entry: dict) -> str:
    """The kind of operation a history entry counts as."""
    if str(entry["type"]).rpartition(".")[2] != "JIT":
        return "other operations"
    source = "memory cache" if entry.get("cache_hit") else "disk cache" if entry.get("cache_disk") else "compiled"
    mode = str(entry.get("recording_mode", "")).rpartition(".")[2]
    return f"JIT kernels, {source}" + (f", {mode.lower()}" if mode not in ("", "Inactive") else "")


class History:
    """Kernel history summed by (where, kind), drained into ``where`` by ``drain``."""

    def __init__(self, dr):
        self.dr = dr
        self.rows: dict[tuple[str, str], dict[str, float]] = defaultdict(
            lambda: dict.fromkeys(("launches", *DRAINED), 0.0)
        )

    def drain(self, where: str) -> None:
        for entry in self.dr.kernel_history():
            row = self.rows[(where, row_of(entry))]
            row["launches"] += 1
            for key in DRAINED:
                row[key] += float(entry.get(key, 0.0) or 0.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--capture", type=Path, help="a capture (default: a copy of sample_captures/bird)")
    parser.add_argument("--write", action="store_true", help="rewrite docs/benchmarks.md's section")
    args = parser.parse_args()
    capture = args.capture
    if capture is None:
        capture = Path(tempfile.mkdtemp(prefix="geometry_kernels_")) / "bird"
        shutil.copytree(
            ROOT / "sample_captures" / "bird", capture, ignore=shutil.ignore_patterns(".pipeline", "output")
        )
    variant = mitsuba_variant.activate("auto")
    import drjit as dr

    from pipeline.fit import loop

    run_stages(capture, "fit_texture")
    history = History(dr)
    train, run = loop._Loop.train, loop.run

    def drained_train(self, *arguments, **keywords):
        history.drain(self.label)
        return train(self, *arguments, **keywords)

    def drained_run(*arguments, label: str = "fit", **keywords):
        dr.sync_thread()
        history.drain(OUTSIDE)
        try:
            return run(*arguments, label=label, **keywords)
        finally:
            dr.sync_thread()
            history.drain(label)

    loop._Loop.train, loop.run = drained_train, drained_run
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    started = time.perf_counter()
    try:
        run_stages(capture, "fit_geometry", force=("fit_geometry",))
        dr.sync_thread()
        history.drain(OUTSIDE)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        loop._Loop.train, loop.run = train, run
    wall = time.perf_counter() - started

    lines = [
        "| where | operation | launches | codegen s | backend (compile) s | execution s |",
        "|---|---|---|---|---|---|",
    ]
    totals = dict.fromkeys(("launches", *DRAINED), 0.0)
    for (where, name), row in sorted(history.rows.items(), key=lambda item: (item[0][0], -item[1]["execution_time"])):
        lines.append(
            f"| {where} | {name} | {int(row['launches'])} | {row['codegen_time'] / 1e3:.1f} | "
            f"{row['backend_time'] / 1e3:.1f} | {row['execution_time'] / 1e3:.1f} |"
        )
        for key in totals:
            totals[key] += row[key]
    covered = sum(totals[key] for key in DRAINED) / 1e3
    lines += [
        f"| all | all | {int(totals['launches'])} | {totals['codegen_time'] / 1e3:.1f} | "
        f"{totals['backend_time'] / 1e3:.1f} | {totals['execution_time'] / 1e3:.1f} |",
        "",
        f"fit_geometry's wall time {wall:.0f} s: {covered:.0f} s in the kernel history's operations, "
        f"{wall - covered:.0f} s outside it (Python, Mitsuba's tracing of each step, the host waiting on results).",
    ]
    print("\n".join(lines))
    if args.write:
        intro = [
            "## Where fit_geometry's time goes",
            "",
            f"{machine()} Mitsuba variant {variant}; code: {code_version('pipeline', 'stages')}. Command:",
            "`.venv/bin/python -m bench.studies.geometry_kernels --write` (the bird on the standard preset,",
            "fit_geometry alone; Dr.Jit's kernel cache as the machine had it). Rows: bench/studies/geometry_kernels.py's",
            "docstring.",
            "",
        ]
        write_section("geometry-kernels", intro + lines)


if __name__ == "__main__":
    main()
