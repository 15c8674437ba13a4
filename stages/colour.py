"""Stage colour: a colour correction from a ColorChecker 24 chart in a calibration shot.

Each shot in ``calibration/`` is searched for the chart
(pipeline.imaging.colour_chart); the one whose fitted 3x3 matrix matches the chart's
references best gives the correction that undistort applies to every photo and
plate. Without a chart, or with a chart that no matrix fits, photos are left as
they are and colour.json says why.

==============  ================================================================
output          content
==============  ================================================================
colour.json     the matrix, the shot, its exposure (to scale photos shot at
                another), CIEDE2000 of the patches before and after, the reason
==============  ================================================================

Limitations: the correction holds for the light the chart was shot under; shoot it
in the specimen's place, under the same lights, with the same camera settings.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

from pipeline import logger
from pipeline.core import progress
from pipeline.core.config import Range
from pipeline.core.stage import Stage, StageInputs, StageResult
from pipeline.formats.colour import ColourRecord, write_colour
from pipeline.imaging.colour_chart import ColourCorrection, exposure, find_chart, fit_correction, patch_means
from pipeline.imaging.photo_io import photo_files, read_metadata, read_photo

DETECTION_SIZE = 1600
"""Longer side (pixels) a shot is reduced to before the chart is looked for."""


@dataclass(frozen=True)
class Config:
    """Colour correction from a chart shot."""

    chart: Literal["auto", "none"] = "auto"
    """auto: look for a ColorChecker 24 in the calibration/ shots and correct every photo
    with it; none: leave the photos' colours as the camera recorded them."""
    max_delta_e: Annotated[float, Range(0.5, 50.0)] = 8.0
    """A chart whose patches stay further than this (mean CIEDE2000) from their
    references after the fit is not used: a false detection, or a chart in mixed light."""


def _search(shots: list[Path]) -> tuple[Path, ColourCorrection] | None:
    """The shot whose chart the matrix fits best, with that correction."""
    best = None
    for shot in progress.track(shots, "looking for a colour chart"):
        _, (width, height) = read_metadata(shot)
        linear = read_photo(shot, reduce=max(1, max(width, height) // DETECTION_SIZE)).pixels
        corners = find_chart(linear)
        if corners is None:
            continue
        correction = fit_correction(patch_means(linear, corners))
        logger.info("%s: colour chart, CIEDE2000 %.1f after the matrix", shot.name, correction.delta_e_after)
        if best is None or correction.delta_e_after < best[1].delta_e_after:
            best = (shot, correction)
    return best


def main(conf: Config, inputs: StageInputs, out_dir: Path) -> StageResult:
    shots = photo_files(list(inputs.files))
    found = _search(shots) if conf.chart == "auto" else None
    if conf.chart == "none":
        record = ColourRecord(None, None, None, "colour.chart = none")
    elif found is None:
        record = ColourRecord(None, None, None, f"no ColorChecker 24 in the {len(shots)} calibration/ shot(s)")
    elif found[1].delta_e_after > conf.max_delta_e:
        shot, correction = found
        record = ColourRecord(
            None,
            None,
            None,
            f"no ColorChecker 24 in the {len(shots)} calibration/ shot(s) that a matrix fits: the best find, in "
            f"{shot.name}, stays {correction.delta_e_after:.1f} from the references (colour.max_delta_e = "
            f"{conf.max_delta_e})",
        )
        # Far off is a board's squares taken for a chart; near is a chart in mixed light.
        near = correction.delta_e_after < 2 * conf.max_delta_e
        logger.log(logging.WARNING if near else logging.INFO, "%s", record.reason)
    else:
        shot, correction = found
        record = ColourRecord(
            correction,
            shot.name,
            exposure(read_metadata(shot)[0]),
            f"{shot.name}: CIEDE2000 {correction.delta_e_before:.1f} -> {correction.delta_e_after:.1f}",
        )
        logger.info("colour correction from %s", record.reason)
    colour = write_colour(out_dir / "colour.json", record)
    metrics = {"chart": record.correction is not None}
    if record.correction is not None:
        metrics |= {
            "delta_e_before": record.correction.delta_e_before,
            "delta_e_after": record.correction.delta_e_after,
        }
    return StageResult({"colour": colour}, metrics)


STAGE = Stage(
    name="colour",
    version=1,
    config=Config,
    main=main,
    outputs=("colour",),
    reads=("calibration/*",),
    exports=("colour",),
)
