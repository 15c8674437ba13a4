"""Memory and time to decode a huge photo whole and reduced while decoding.

    .venv/bin/python -m bench.huge_photos [--width 12000 --height 9000] [--write]

Writes a JPEG of the given size (a smooth gradient plus noise), then decodes it in
fresh processes with pipeline.imaging.photo_io.read_photo at reduce = 1 (whole),
2, 4 and 8, reporting the process's peak RSS after its imports and after decoding,
and the decoding time. ``--write`` puts the table into docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import machine, write_section

MEASURE = """
import resource, sys, time
from pathlib import Path
from pipeline.imaging.photo_io import read_photo
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
started = time.perf_counter()
photo = read_photo(Path(sys.argv[1]), reduce=int(sys.argv[2]))
seconds = time.perf_counter() - started
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(photo.size[0], photo.size[1], before / 1024, peak / 1024, seconds)
"""


def main() -> None:
    from pipeline.imaging.photo_io import write_image

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=12000)
    parser.add_argument("--height", type=int, default=9000)
    parser.add_argument("--write", action="store_true", help="rewrite docs/benchmarks.md's section")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "huge.jpg"
        rng = np.random.default_rng(0)
        rows = np.linspace(0, 200, args.height, dtype=np.float32)[:, None, None]
        pixels = (rows + rng.integers(0, 40, (args.height, args.width, 1), dtype=np.uint8)).astype(np.uint8)
        started = time.perf_counter()
        write_image(path, np.repeat(pixels, 3, axis=2))
        del pixels
        lines = [
            f"A {args.width}x{args.height} JPEG ({path.stat().st_size / 1e6:.0f} MB), each decode in a fresh process:",
            "",
            "| reduce | decoded size | peak RSS after imports | peak RSS after decoding | seconds |",
            "|---|---|---|---|---|",
        ]
        print(f"written in {time.perf_counter() - started:.1f} s")
        for reduce in (1, 2, 4, 8):
            out = subprocess.run(
                [sys.executable, "-c", MEASURE, str(path), str(reduce)], capture_output=True, text=True, check=True
            ).stdout.split()
            lines.append(
                f"| {reduce} | {out[0]}x{out[1]} | {float(out[2]):.0f} MB | {float(out[3]):.0f} MB | {float(out[4]):.1f} |"
            )
            print(lines[-1])
    if args.write:
        command = ".venv/bin/python -m bench.huge_photos" + (
            "" if (args.width, args.height) == (12000, 9000) else f" --width {args.width} --height {args.height}"
        )
        write_section("huge-photos", ["## Huge photos", "", f"{machine()} Command: `{command} --write`.", "", *lines])


if __name__ == "__main__":
    main()
