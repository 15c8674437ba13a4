"""Colour correction from a ColorChecker 24: error before and after, and false finds.

    .venv/bin/python -m bench.colour_chart [--captures ../shared/captures] [--write]

Part 1 renders the chart (tests/support/colour_chart_scene.py) under lights of
several colours and sensors with several channel mixings, with sensor noise, and
reports the patches' mean and worst CIEDE2000 from their references before the
correction (after the best exposure gain alone) and after it. Part 2 runs the chart
search on every photo of the real captures and the bundled samples, none of which
shows a chart: each find there is false, and its error after the fit must stay far
above ``colour.max_delta_e`` for the threshold to reject it.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from bench.common import ROOT, write_section
from pipeline.imaging.colour_chart import delta_e, find_chart, fit_correction, patch_means, reference_linear
from pipeline.imaging.photo_io import photo_files, read_metadata, read_photo
from stages.colour import DETECTION_SIZE, Config
from tests.support import colour_chart_scene

LIGHTS = {"white": (1.0, 1.0, 1.0), "tungsten": (1.0, 0.78, 0.5), "shade": (0.7, 0.85, 1.0)}
MIXES = {
    "sRGB sensor": np.eye(3),
    "mild mixing": colour_chart_scene.SENSOR_MIX,
    "strong mixing": np.array([[0.65, 0.3, 0.05], [0.2, 0.6, 0.2], [0.05, 0.35, 0.6]]),
}


def rendered_rows(noise: float) -> list[str]:
    rows = []
    rng = np.random.default_rng(0)
    for light_name, light in LIGHTS.items():
        for mix_name, mix in MIXES.items():
            colour_chart_scene.LIGHT, colour_chart_scene.SENSOR_MIX = light, mix
            photo = colour_chart_scene.render_chart()
            photo += rng.normal(0.0, noise, photo.shape).astype(np.float32)
            corners = find_chart(photo)
            if corners is None:
                rows.append(f"| {light_name} | {mix_name} | not found | | |")
                continue
            correction = fit_correction(patch_means(photo, corners))
            after = delta_e(patch_means(correction.apply(photo), corners), reference_linear())
            rows.append(
                f"| {light_name} | {mix_name} | {correction.delta_e_before:.2f} | {after.mean():.2f} | {after.max():.2f} |"
            )
    return rows


def false_finds(folders: list[Path]) -> tuple[int, list[tuple[str, float]]]:
    photos, found = 0, []
    for folder in folders:
        for path in photo_files(list(folder.iterdir())):
            _, (width, height) = read_metadata(path)
            linear = read_photo(path, reduce=max(1, max(width, height) // DETECTION_SIZE)).pixels
            photos += 1
            corners = find_chart(linear)
            if corners is not None:
                found.append(
                    (f"{folder.parent.name}/{path.name}", fit_correction(patch_means(linear, corners)).delta_e_after)
                )
    return photos, sorted(found, key=lambda item: item[1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--captures", type=Path, default=ROOT.parent / "shared" / "captures")
    parser.add_argument("--noise", type=float, default=0.002, help="sensor noise, standard deviation (linear)")
    parser.add_argument("--write", action="store_true")
    args = parser.parse_args()
    folders = sorted(args.captures.glob("*/images")) + [
        folder
        for name in ("bird", "bird_volumetric")
        for folder in sorted((ROOT / "sample_captures" / name).glob("*/"))
        if folder.name in ("images", "calibration")
    ]
    photos, found = false_finds(folders)
    lines = [
        "## Colour correction from a chart (issue 54)",
        "",
        "Machine: the 2-core development VM. Command: `.venv/bin/python -m bench.colour_chart --write`.",
        "",
        f"A rendered ColorChecker 24 (320x240, sensor noise {args.noise} linear): CIEDE2000 of its 24 patches from",
        "their references, before (the best exposure gain alone) and after the fitted 3x3 matrix.",
        "",
        "| light | sensor | before, mean | after, mean | after, worst |",
        "|---|---|---|---|---|",
        *rendered_rows(args.noise),
        "",
        f"False finds: the chart search on {photos} photos without a chart (the real captures' images, the samples'",
        f"images and board shots) found {len(found)} chart-like patterns; after the fit they stay",
        f"{found[0][1]:.1f} or more from the references (the closest: "
        + ", ".join(f"{name} {error:.1f}" for name, error in found[:3])
        + f"), against `colour.max_delta_e` = {Config.max_delta_e}: none is used."
        if found
        else f"False finds: none in {photos} photos without a chart.",
        "",
    ]
    print("\n".join(lines))
    if args.write:
        write_section("colour-chart", lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
