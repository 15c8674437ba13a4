"""Do two runs of the pipeline give the same outputs? Stage by stage, every file of
each capture's newest cache entry compared: byte for byte, else (EXR, whose headers
carry a time stamp) pixel for pixel, else (JSON) value for value without the keys
that hold wall times, else how far apart the numbers are.

For refactors that must not change results: run the old code on one copy of a
capture and the new code on another (with bench/tools/one_thread.py, so that the fits
can agree to the bit), then

    .venv/bin/python -m bench.tools.same_outputs OLD_CAPTURE NEW_CAPTURE [--section NAME]

prints one row per stage; with ``--section`` the table is written into
docs/benchmarks.md under that name.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from bench.common import write_section


def is_timing(key: str) -> bool:
    """Keys holding wall times (``seconds``, ``hull_seconds``, ``started``, ...), which
    differ between any two runs."""
    return key in ("seconds", "started", "finished") or key.endswith("_seconds")


def newest_entry(capture: Path, stage: str) -> Path | None:
    entries = [p for p in (capture / ".pipeline" / "cache" / stage).glob("[!.]*") if (p / "status.json").is_file()]
    return max(entries, key=lambda p: json.loads((p / "status.json").read_text())["finished"], default=None)


def _without_timing(value):
    if isinstance(value, dict):
        return {k: _without_timing(v) for k, v in value.items() if not is_timing(k)}
    if isinstance(value, list):
        return [_without_timing(v) for v in value]
    return value


def _largest_difference(a, b) -> float:
    """The largest absolute difference between numbers at the same place (inf: other shape)."""
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            return math.inf
        return max((_largest_difference(a[k], b[k]) for k in a), default=0.0)
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return math.inf
        return max((_largest_difference(x, y) for x, y in zip(a, b)), default=0.0)
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        return abs(float(a) - float(b))
    return 0.0 if a == b else math.inf


def compare_file(old: Path, new: Path) -> str:
    """ "bytes", "pixels", "values" when the same; else what differs."""
    if old.read_bytes() == new.read_bytes():
        return "bytes"
    if old.suffix == ".exr":
        import numpy as np
        import OpenImageIO as oiio

        a, b = oiio.ImageBuf(str(old)).get_pixels(), oiio.ImageBuf(str(new)).get_pixels()
        if a.shape == b.shape and np.array_equal(a, b):
            return "pixels"
        return "pixels differ" if a.shape != b.shape else f"pixels differ by up to {np.abs(a - b).max():.3g}"
    if old.suffix in (".json", ".jsonl"):

        def load(path: Path):
            lines = path.read_text().splitlines() if path.suffix == ".jsonl" else [path.read_text()]
            return [_without_timing(json.loads(line)) for line in lines if line.strip()]

        a, b = load(old), load(new)
        if a == b:
            return "values"
        return f"values differ by up to {_largest_difference(a, b):.3g}"
    return "bytes differ"


def compare_stage(old_capture: Path, new_capture: Path, stage: str) -> tuple[int, dict[str, list[str]]]:
    """(files compared, {verdict: files}) over the stage's newest entries."""
    old, new = newest_entry(old_capture, stage), newest_entry(new_capture, stage)
    if old is None or new is None:
        return 0, {"missing in " + ("old" if old is None else "new"): [stage]}
    skip = {"status.json", "log.txt"}  # run records: times, paths, library versions
    files = sorted(
        {p.relative_to(old) for p in old.rglob("*") if p.is_file()}
        | {p.relative_to(new) for p in new.rglob("*") if p.is_file()}
    )
    verdicts: dict[str, list[str]] = {}
    for rel in files:
        if rel.name in skip:
            continue
        if not (old / rel).is_file() or not (new / rel).is_file():
            verdict = "only in " + ("new" if not (old / rel).is_file() else "old")
        else:
            verdict = compare_file(old / rel, new / rel)
        verdicts.setdefault(verdict, []).append(str(rel))
    return sum(len(v) for v in verdicts.values()), verdicts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("old", type=Path, help="capture run by the old code")
    parser.add_argument("new", type=Path, help="capture run by the new code")
    parser.add_argument("--section", help="also write the table into docs/benchmarks.md under this name")
    args = parser.parse_args()
    from stages import STAGES

    rows = ["| stage | files | identical (bytes / pixels / values) | different |", "|---|---|---|---|"]
    for stage in STAGES:
        count, verdicts = compare_stage(args.old, args.new, stage.name)
        same = [len(verdicts.get(k, [])) for k in ("bytes", "pixels", "values")]
        different = {k: v for k, v in verdicts.items() if k not in ("bytes", "pixels", "values")}
        listing = "; ".join(f"{k}: {', '.join(v[:3])}{' ...' if len(v) > 3 else ''}" for k, v in different.items())
        rows.append(f"| {stage.name} | {count} | {same[0]} / {same[1]} / {same[2]} | {listing or '-'} |")
    print("\n".join(rows))
    if args.section:
        write_section(args.section, rows)


if __name__ == "__main__":
    main()
