"""Every setting at the ends of what `pipeline config` accepts, run by the real CLI:
each value must run, or be refused before anything runs with its reason (issue 101,
point 9), never crash, hang or print a traceback.

    .venv/bin/python -m bench.setting_extremes [--work /tmp/extremes] [--only SECTION ...] [--write]

A tiny synthetic capture (6 views of 96x72 px) with its cameras and mesh given as
another tool's (tests/support/byo_capture.py: no SfM on 96 px) is run once to the end on
the draft preset (the sfm and mesh sections on 12 views of 320x240 px, whose cameras and
mesh the pipeline makes); each probe copies it with its cache, sets one setting with ``-s`` and
runs ``--until`` the last stage that reads it, so only that stage and what it feeds
run (fit_geometry, which the draft preset leaves off, is turned on for its own
probes). The values: a number at each end of its range (an open end at a hundred times
the default, at least 100), every choice of a choice, a switch flipped, a triple at
each end of its elements' range (unbounded: all zero and all 1e30), a list of names
given a name that is none, and a file setting given a folder and a file of another
kind (the capture's images/ and capture.toml). A
probe passes when it ends 0, or ends 2 (refused before anything ran) with one message
and no traceback, within the watchdog; a stage failing with exit 1 is shown for
review with its message.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import subprocess
import sys
import time
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

from bench.common import CLI, finish, synthetic_capture, write_section
from bench.common import ROOT as REPOSITORY
from pipeline.core.config import InputFile, Range

WATCHDOG_S = 240
SECTION = "## Settings at the ends of their ranges (issue 101)"
GIVEN = ["-s", "cameras.source='external'", "-s", "mesh.source='ground_truth/mesh.ply'", "--preset", "draft"]
"""The capture's cameras and mesh from "another tool", on the fast end of the trade."""
SOLVED = ("sfm", "mesh")
"""Sections probed on a capture whose cameras and mesh the pipeline makes itself: 12
views of 320x240 px, large enough for SfM, run on the draft preset."""
REVIEWED = {
    "uv.texture_size=16384": "runs alone in about 5 minutes: xatlas packs 16384 texels in 233 s on this mesh of "
    "20,000 faces, the checker takes 38 s (a run of `pipeline run` with this one setting, no watchdog)",
}
"""What a probe over the watchdog did when run alone to its end."""
ENABLED = {"fit_geometry": ["-s", "fit_geometry.enabled=true"]}
"""What a section's stage needs to run at all on the draft preset, which leaves it off."""


@dataclass
class Probe:
    section: str
    key: str
    value: Any
    until: str
    result: dict = field(default_factory=dict)

    @property
    def override(self) -> str:
        return f"{self.section}.{self.key}={_toml(self.value)}"


def _toml(value: Any) -> str:
    """``value`` as the right side of ``-s SECTION.KEY=VALUE`` (TOML)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)  # a TOML basic string: JSON's escapes
    if isinstance(value, tuple):
        return "[" + ", ".join(_toml(item) for item in value) + "]"
    return repr(value)


def probes(only: list[str]) -> list[Probe]:
    """Each setting at its ends (``_values``), run until the last stage reading it."""
    from pipeline.cli.registry import registered_stages
    from pipeline.core.sections import schema

    stages = registered_stages()
    order = [stage.name for stage in stages]
    found = []
    for section, cls in schema(stages).items():
        if only and section not in only:
            continue
        readers = [s.name for s in stages if s.name == section or any(n.split(".")[0] == section for n in s.shared)]
        if not readers:
            continue
        until = max(readers, key=order.index)
        hints = typing.get_type_hints(cls, include_extras=True)
        for item in dataclasses.fields(cls):
            default = item.default if item.default is not dataclasses.MISSING else item.default_factory()
            for value in _values(hints[item.name], default):
                if value != default:
                    found.append(Probe(section, item.name, value, until))
    return found


def _values(hint: Any, default: Any) -> list[Any]:
    """The values of a setting of type ``hint`` that probe it (the module's docstring)."""
    base, extras = (
        (typing.get_args(hint)[0], typing.get_args(hint)[1:]) if typing.get_origin(hint) is Annotated else (hint, ())
    )
    bounds = next((e for e in extras if isinstance(e, Range)), None)
    if base in (int, float):
        return _ends(bounds, base, default) if bounds else []
    if base is bool:
        return [not default]
    if typing.get_origin(base) is Literal:
        return list(typing.get_args(base))
    if base is str:
        return ["images", "capture.toml"] if any(isinstance(e, InputFile) for e in extras) else []
    if typing.get_origin(base) is tuple:
        items = typing.get_args(base)
        if items[-1] is Ellipsis:
            return [("none_such",)] if items[0] is str else []
        element = items[0]
        if typing.get_origin(element) is Annotated:
            ranged = next((e for e in typing.get_args(element)[1:] if isinstance(e, Range)), None)
            if ranged is not None:
                kind = typing.get_args(element)[0]
                return [tuple([end] * len(items)) for end in _ends(ranged, kind, max(default))]
        return [tuple([0.0] * len(items)), tuple([1e30] * len(items))]
    return []


def _ends(bounds: Range, kind: type, default: float) -> list[float | int]:
    lo = bounds.lo
    if lo is not None and bounds.exclusive_lo:
        lo = lo + 1 if kind is int else lo + 1e-6
    hi = bounds.hi if bounds.hi is not None else max(abs(default) * 100, 100)
    return [kind(v) for v in (lo, hi) if v is not None]


def arguments(section: str) -> list[str]:
    """The run's options for probes of ``section``, besides the probe's own."""
    return ["--preset", "draft"] if section in SOLVED else [*GIVEN, *ENABLED.get(section, [])]


def solved_capture(work: Path) -> Path:
    """The capture for SOLVED sections, run to the mesh."""
    return synthetic_capture(work / "solved", 12, (320, 240), 8, 0, "--preset", "draft", "--until", "mesh")


def base_capture(work: Path) -> Path:
    """The capture for every other section: its cameras and mesh given, run to the end."""
    base = work / "base"
    if (base / "output" / "manifest.json").is_file():
        return base
    sys.path.insert(0, str(REPOSITORY))
    from tests.support.byo_capture import byo_capture

    photos = synthetic_capture(work / "photos", 6, (96, 72), 4, 3)
    shutil.rmtree(base, ignore_errors=True)
    byo_capture(photos, base)
    subprocess.run([sys.executable, "-c", CLI, "-q", "run", str(base), *GIVEN], check=True, cwd=REPOSITORY)
    return base


def run_probe(probe: Probe, base: Path, work: Path) -> dict:
    capture = work / "probe"
    shutil.rmtree(capture, ignore_errors=True)
    shutil.copytree(base, capture, symlinks=True)
    argv = ["run", str(capture), *arguments(probe.section), "--until", probe.until, "-s", probe.override]
    started = time.time()
    process = subprocess.Popen(
        [sys.executable, "-c", CLI, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPOSITORY
    )
    out, err, hung = finish(process, WATCHDOG_S)
    code = process.returncode
    lines = [line for line in (out + err).splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("E ")]
    dumped = any(word in out + err for word in ("Traceback", "stack trace", "Aborted", "Segmentation"))
    message = (errors[-1] if errors else lines[-1] if lines else "").replace(str(capture), "CAPTURE")
    verdict = (
        "over the watchdog"
        if hung
        else "crash"
        if code is None or code < 0 or code >= 128 or dumped
        else "runs"
        if code == 0
        else "refused"
        if code == 2 and errors
        else "stage failed"
        if code == 1 and errors
        else "crash"
    )
    return {"code": code, "seconds": round(time.time() - started, 1), "verdict": verdict, "message": message[:200]}


def write_table(rows: list[Probe], command: str) -> None:
    lines = [
        SECTION,
        "",
        f"Machine: the 2-core development VM (no GPU). Command: `.venv/bin/python {command}`. Each number",
        "at each end of its range (an open end at 100 times its default), each choice, each switch flipped,",
        "each triple at its ends (unbounded: 0 and 1e30), a name that is none in a list of names, a folder",
        "and a file of another kind in a file setting, `-s` on a copy of a 6-view",
        "96x72 px synthetic capture with given cameras and mesh (the sfm and mesh sections: 12 views of 320x240",
        "px whose cameras and mesh the pipeline makes), draft preset, run `--until` the last stage",
        f"reading it under a {WATCHDOG_S} s watchdog. runs: exit 0; refused: exit 2 before anything ran;",
        "stage failed: exit 1 with one message; crash: a signal, a traceback or another exit; over the",
        "watchdog: still running when it fired (a long fit at a large count, or a hang: listed for review).",
        "",
    ]
    counts: dict[str, int] = {}
    for probe in rows:
        counts[probe.result["verdict"]] = counts.get(probe.result["verdict"], 0) + 1
    lines.append(", ".join(f"{n} {verdict}" for verdict, n in sorted(counts.items())) + f" of {len(rows)} probes.")
    lines += ["", "| setting | value | until | exit | s | verdict | message |", "|---|---|---|---|---|---|---|"]
    for probe in rows:
        r = probe.result
        if r["verdict"] == "runs":
            continue
        message = r["message"].replace("|", "\\|")
        lines.append(
            f"| {probe.section}.{probe.key} | {_toml(probe.value)} | {probe.until} | {r['code']} | {r['seconds']} | "
            f"{r['verdict']} | {message} |"
        )
    lines += ["", "Probes that ran (exit 0) are counted above and not listed."]
    reviewed = [
        f"- `{override}` {note}." for override, note in REVIEWED.items() if override in {p.override for p in rows}
    ]
    lines += ["", "Run alone to their end:", "", *reviewed, ""] if reviewed else [""]
    write_section("setting-extremes", lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", default="/tmp/extremes")
    parser.add_argument("--only", nargs="*", default=[], help="sections to probe (default: all)")
    parser.add_argument("--settings", nargs="*", default=[], help="of those, only these SECTION.KEY")
    parser.add_argument(
        "--results", default="/tmp/extremes-results.jsonl", help="where each probe's result is appended"
    )
    parser.add_argument("--again", action="store_true", help="probe again what --results already holds")
    parser.add_argument("--write", action="store_true", help="rewrite docs/benchmarks.md's section")
    parser.add_argument("--write-only", action="store_true", help="write the section from --results, probing nothing")
    args = parser.parse_args()
    results = Path(args.results)
    chosen = [p for p in probes(args.only) if not args.settings or f"{p.section}.{p.key}" in args.settings]
    done = {json.loads(line)["override"] for line in results.read_text().splitlines()} if results.is_file() else set()
    if not args.again:
        chosen = [probe for probe in chosen if probe.override not in done]
    if not args.write_only:
        work = Path(args.work)
        work.mkdir(parents=True, exist_ok=True)
        given = base_capture(work)
        solved = solved_capture(work) if any(probe.section in SOLVED for probe in chosen) else None
        for probe in chosen:
            probe.result = run_probe(probe, solved if probe.section in SOLVED else given, work)
            print(probe.override, probe.until, json.dumps(probe.result), flush=True)
            with results.open("a") as log:  # one line a probe: batches run apart add to one table
                log.write(json.dumps({"override": probe.override, "result": probe.result}) + "\n")
    if args.write or args.write_only:
        stored = {}
        for line in results.read_text().splitlines():
            record = json.loads(line)
            stored[record["override"]] = record["result"]
        every = [probe for probe in probes([]) if probe.override in stored]
        for probe in every:
            probe.result = stored[probe.override]
        write_table(every, "-m bench.setting_extremes [--only SECTION ...] (then --write-only)")
    return 0 if all(p.result["verdict"] in ("runs", "refused") for p in chosen if p.result) else 1


if __name__ == "__main__":
    sys.exit(main())
