"""Camera RAW files for the tests: a minimal DNG (one Bayer CFA image, RGGB) whose
development is known exactly: the scene's linear sRGB values times the camera's
white-balance response, between a black and a white level."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import tifffile

XYZ_TO_LINEAR_SRGB = np.array(
    [[3.2404542, -1.5371385, -0.4985314], [-0.9692660, 1.8760108, 0.0415560], [0.0556434, -0.2040259, 1.0572252]]
)
BAYER_RGGB = ((0, 0, 0), (0, 1, 1), (1, 0, 1), (1, 1, 2))
"""(row offset, column offset, channel) of each site of the 2x2 pattern."""


def _rationals(values) -> list[int]:
    return [part for value in np.ravel(values) for part in (int(round(value * 10000)), 10000)]


def write_dng(
    path: Path,
    linear_srgb: np.ndarray,
    neutral=(0.5, 1.0, 0.7),
    black: int = 256,
    white: int = 16383,
    make: str = "TestMake",
    model: str = "TestModel",
) -> Path:
    """A DNG of ``linear_srgb`` (height, width, 3; even sizes) as a camera with sensor
    primaries equal to sRGB's and the white-balance response ``neutral`` records it."""
    camera = np.clip(linear_srgb * np.asarray(neutral), 0.0, 1.0)
    mosaic = np.empty(linear_srgb.shape[:2])
    for row, column, channel in BAYER_RGGB:
        mosaic[row::2, column::2] = camera[row::2, column::2, channel]
    raw = np.round(black + mosaic * (white - black)).astype(np.uint16)
    tags = [
        (33421, "H", 2, (2, 2), True),  # CFARepeatPatternDim
        (33422, "B", 4, (0, 1, 1, 2), True),  # CFAPattern: RGGB
        (50706, "B", 4, (1, 4, 0, 0), True),  # DNGVersion
        (50708, "s", 0, f"{make} {model}", True),  # UniqueCameraModel
        (50721, "2i", 9, _rationals(np.diag(neutral) @ XYZ_TO_LINEAR_SRGB), True),  # ColorMatrix1: XYZ -> camera
        (50778, "H", 1, (21,), True),  # CalibrationIlluminant1: D65
        (50728, "2I", 3, _rationals(neutral), True),  # AsShotNeutral
        (50714, "H", 1, (black,), True),  # BlackLevel
        (50717, "H", 1, (white,), True),  # WhiteLevel
        (271, "s", 0, make, True),
        (272, "s", 0, model, True),
    ]
    tifffile.imwrite(path, raw, photometric=32803, extratags=tags, metadata=None)
    return path
