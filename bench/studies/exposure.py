"""How well a held-out photo's exposure is read off the table it shares with the training
photos (pipeline.fit.exposure), for several numbers of nearest cameras: each training
photo's gain predicted from the others (leave one out) against the gain fit_material
fitted to it, and the held-out photos' predicted gains.

Usage: ``.venv/bin/python -m bench.studies.exposure CAPTURE [-s KEY=VALUE ...]`` with the
overrides its runs used (bench/light.py's REAL), after bin/bootstrap and a
``pipeline run CAPTURE --until fit_material`` with them, on a capture whose photos'
gains are fitted (``fit_material.exposure`` or ``white_balance``). Prints a Markdown
table; rewrites the section ``exposure-NAME`` of docs/benchmarks.md with ``--write``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from bench.common import write_section
from bench.studies.ceiling import cached_outputs
from pipeline.fit.exposure import NEAREST, table_gains
from pipeline.fit.views import read_capture_photos
from pipeline.formats.fit_results import MaterialFit
from pipeline.formats.scene_description import SceneDescription

COUNTS = (2, 3, 4, 6, 10)
"""Numbers of nearest cameras compared."""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("capture", type=Path)
    parser.add_argument("-s", "--set", dest="overrides", action="append", default=[])
    parser.add_argument("--write", action="store_true", help="rewrite docs/benchmarks.md's section")
    args = parser.parse_args()
    outputs = cached_outputs(args.capture, "fit_material", args.overrides)
    params = MaterialFit.read(outputs["fit_material"]["params"])
    if not params.photo_gains:
        raise SystemExit(f"{args.capture}: fit_material fitted no photo gains (fit_material.exposure, white_balance)")
    photos = read_capture_photos(
        outputs["sfm"]["cameras"], outputs["undistort"]["pinhole"], outputs["masks"]["masks_json"]
    )
    description = SceneDescription.read(outputs["scene"]["description"])
    held = params.held_out
    lines = [
        f"| nearest cameras ({args.capture.name}) | median | 90th percentile | largest | " + " | ".join(held) + " |",
        "|---|---|---|---|" + "---|" * len(held),
    ]
    for count in COUNTS:
        found = table_gains(description, photos, params.photo_gains, held, 3, count)
        if not found:
            raise SystemExit(f"{args.capture}: its scene has no table, or no two photos share enough of it")
        error = found["training_error"]
        gains = [found["gains"].get(name) for name in held]
        cells = [f"{min(g):.2f}-{max(g):.2f}" if g else "none" for g in gains]
        kept = " (kept)" if count == NEAREST else ""
        lines.append(
            f"| {count}{kept} | {100 * error['median']:.1f} % | {100 * error['p90']:.1f} % | "
            f"{100 * error['max']:.1f} % | " + " | ".join(cells) + " |"
        )
    print("\n".join(lines))
    if args.write:
        write_section(f"exposure-{args.capture.name}", lines)


if __name__ == "__main__":
    main()
