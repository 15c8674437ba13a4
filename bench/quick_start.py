"""The README's two Quick start commands in a fresh clone, as a new user and CI run them.

    .venv/bin/python -m bench.quick_start [--parts pipeline,tests] [--keep DIR] [--write]

Each command runs alone, in a clone of its own of the repository's HEAD (DIR/fresh-pipeline,
DIR/fresh-tests) with a Dr.Jit kernel cache of its own, in a folder whose parent holds
no ``shared`` folder (so the optional real-capture tests skip, as in CI), so that each
pays its own bootstrap as on a new machine: ``bin/pipeline run sample_captures/bird``
(the default preset), then ``pipeline score`` on the bird, and ``CI=true .ci/run`` (=
``bin/test``). Reports each command's exit code and wall time, pytest's summary, the
stages' times, and the score's figures after each fit stage. ``--write`` puts the
table into docs/benchmarks.md. About 30 minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import tempfile
import time
from pathlib import Path

from bench.common import ROOT, machine, write_section

FIT_STAGES = ("fit_material", "fit_texture", "fit_geometry")


def fresh_clone(parent: Path, name: str) -> Path:
    parent.mkdir(parents=True, exist_ok=True)
    clone = parent / name
    subprocess.run(["git", "clone", "--quiet", "--no-hardlinks", str(ROOT), str(clone)], check=True)
    if (parent / "shared").exists():
        raise SystemExit(f"{parent / 'shared'} exists: the clone would see the real captures, which CI does not")
    return clone


def timed(command: list[str], cwd: Path, env: dict[str, str], log: Path) -> tuple[int, float, str]:
    """Run ``command``: its exit code, wall time and standard output (its log: ``log``)."""
    started = time.perf_counter()
    with log.open("w") as handle:
        done = subprocess.run(command, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=handle, text=True)
    seconds = time.perf_counter() - started
    with log.open("a") as handle:
        handle.write(done.stdout + f"\nwall seconds: {seconds:.0f}\n")
    return done.returncode, seconds, done.stdout


def _kept_wall_seconds(log: Path) -> float | None:
    """The wall time ``timed`` wrote at the end of a kept log."""
    found = re.findall(r"^wall seconds: (\d+)$", log.read_text(), re.MULTILINE)
    return float(found[-1]) if found else None


def test_row(clone: Path, environment: dict[str, str], run: bool = True) -> list[str]:
    """The test command's row (``run``: False reads the kept log of an earlier run)."""
    log = clone.parent / "tests.log"
    if run:
        code, seconds, _ = timed([".ci/run"], clone, environment | {"CI": "true"}, log)
    else:
        code, seconds = 0, _kept_wall_seconds(log)
    wall = "-" if seconds is None else f"{seconds:.0f} s"
    summary = re.findall(r"=+ (.*(?:passed|failed|error).*) in ([\d.]+)s", log.read_text())
    result, pytest_seconds = summary[-1] if summary else ("no pytest summary (see the log)", "-")
    return [f"| `CI=true .ci/run` | {code} | {wall} | {result}, pytest {pytest_seconds} s |"]


def pipeline_row(clone: Path, environment: dict[str, str], run: bool = True) -> list[str]:
    """The Quick start's run (``run``: False reads the kept log of an earlier one), and
    `pipeline score` on its results."""
    log = clone.parent / "pipeline.log"
    capture = clone / "sample_captures" / "bird"
    command = "`bin/pipeline run sample_captures/bird`"
    if run:
        code, seconds, printed = timed(
            ["bin/pipeline", "run", "sample_captures/bird", "--json"], clone, environment, log
        )
        wall = f"{seconds:.0f} s"
    else:
        code, printed = 0, log.read_text()
        wall = "-" if (kept := _kept_wall_seconds(log)) is None else f"{kept:.0f} s"
    start = re.search(r"^\{$", printed, re.MULTILINE)  # run --json's object, after the log's lines
    if start is None:
        return [f"| {command} | {code or 'no summary'} | {wall} | see {log} |"]
    summary, _ = json.JSONDecoder().raw_decode(printed[start.start() :])  # a kept log ends with its wall time
    times = {s["stage"]: s["seconds"] or 0.0 for s in summary["stages"]}
    fits = ", ".join(f"{name} {times[name]:.0f} s" for name in FIT_STAGES if name in times)
    rows = [
        f"| {command} | {code} | {wall} | the run {summary['seconds']:.0f} s: stages {sum(times.values()):.0f} s ({fits}) |"
    ]
    score = subprocess.run(
        [str(clone / ".venv" / "bin" / "pipeline"), "score", str(capture), "--json"],
        cwd=clone,
        env=environment,
        capture_output=True,
        text=True,
    )
    if score.returncode == 0:
        figures = json.loads(score.stdout)
        rows.append(f"| `pipeline score sample_captures/bird` | 0 | - | {score_cells(figures)} |")
    return rows


def score_cells(figures: dict) -> str:
    """Held-out PSNR after each fit stage, and the material's errors at the end."""
    psnr = [figures.get(part, {}).get("psnr_db_mean") for part in ("heldout", "heldout_textured", "heldout_geometry")]
    shown = " / ".join("-" if value is None else f"{value:.1f}" for value in psnr)
    errors = figures.get("material_fit_geometry") or {}
    cells = ", ".join(
        f"{name.removesuffix('_abs_error').removesuffix('_rel_error')} {value:.3f}"
        for name, value in errors.items()
        if name.endswith("_error")
    )
    return f"held-out PSNR {shown} dB after {' / '.join(FIT_STAGES)}; errors after fit_geometry: {cells}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", default="pipeline,tests")
    parser.add_argument(
        "--keep", type=Path, help="clone into DIR/fresh-PART and keep the clones (default: a new temporary folder)"
    )
    parser.add_argument("--report-only", action="store_true", help="report the run kept in --keep DIR, run nothing")
    parser.add_argument("--write", action="store_true", help="rewrite docs/benchmarks.md's section")
    args = parser.parse_args()
    if args.report_only and args.keep is None:
        raise SystemExit("--report-only reads the run kept in --keep DIR: name it")
    parent = args.keep or Path(tempfile.mkdtemp(prefix="quick_start_"))
    lines = ["| command | exit | wall time (bootstrap included) | result |", "|---|---|---|---|"]
    parts = args.parts.split(",")
    commits = set()
    for part, row in (("pipeline", pipeline_row), ("tests", test_row)):
        if part not in parts:
            continue
        clone = parent / f"fresh-{part}" if args.report_only else fresh_clone(parent, f"fresh-{part}")
        done = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=clone, capture_output=True, text=True)
        commits.add(done.stdout.strip())
        # no Dr.Jit kernels compiled before, no pip cache: as on a new machine
        kernels = parent / f"drjit-kernels-{part}"
        kernels.mkdir(exist_ok=True)
        environment = os.environ | {"DRJIT_CACHE_DIR": str(kernels), "PIP_NO_CACHE_DIR": "1"}
        environment.pop("VIRTUAL_ENV", None)
        environment.pop("DRJIT_LIBLLVM_PATH", None)
        added = row(clone, environment, run=not args.report_only)
        lines += added
        print("\n".join(added), flush=True)
    if args.write:
        intro = [
            "## Quick start and test suite",
            "",
            f"{machine()} Command: `.venv/bin/python -m bench.quick_start --parts {args.parts} --write`:",
            f"each command alone on the machine in a fresh clone of its own of {', '.join(sorted(commits))}",
            "beside no real captures (as CI), with an empty Dr.Jit kernel cache and no pip cache,",
            "so that each pays its own bootstrap (a virtual environment, this package).",
            "",
        ]
        write_section("quick-start", intro + lines)


if __name__ == "__main__":
    main()
