"""colour.json (stage colour): the colour correction every photo gets, or why none."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.imaging.colour_chart import ColourCorrection


@dataclass(frozen=True)
class ColourRecord:
    correction: ColourCorrection | None
    """None when no chart was used."""
    shot: str | None
    """The calibration shot the chart was found in."""
    exposure: float | None
    """That shot's relative exposure (pipeline.imaging.colour_chart.exposure), if its EXIF says."""
    reason: str
    """Why this correction (or none)."""


def write_colour(path: Path, record: ColourRecord) -> Path:
    body = {"shot": record.shot, "exposure": record.exposure, "reason": record.reason}
    body["correction"] = record.correction.to_json() if record.correction is not None else None
    path.write_text(json.dumps(body, indent=1))
    return path


def read_colour(path: Path) -> ColourRecord:
    body = json.loads(path.read_text())
    found = body["correction"]
    correction = (
        ColourCorrection(
            np.asarray(found["matrix"], dtype=float),
            found["patches_used"],
            found["delta_e_before"],
            found["delta_e_after"],
            found["delta_e_after_max"],
        )
        if found is not None
        else None
    )
    return ColourRecord(correction, body["shot"], body["exposure"], body["reason"])
