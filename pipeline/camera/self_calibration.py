"""Self-calibration without a board: which intrinsics the photos constrain, decided the
same way for COLMAP's incremental model (pipeline.colmap.mapping.self_calibrate) and for a
circular motion (pipeline.geometry.circular_motion).

A parameter is adjusted only when the observations cover enough of the frame and
its standard deviation from the bundle adjustment, as a displacement in pixels (the
principal point's own; radial distortion's at the frame's farthest corner), is
below a limit. What is held keeps the value it had (the image centre, no
distortion) and the report says why.

Self-calibrated distortion improves the poses and is reported, but the photos stay
as undistort made them (pinhole): ``outline_shift_px`` says how far it moves the
specimen's outline, for the warning when that matters.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import cv2
import numpy as np

from pipeline.core.config import Range

GRID = 6
"""Cells along each side of the frame for the coverage test."""


@dataclass(frozen=True)
class SelfCalibrationSettings:
    """When principal point and radial distortion are adjusted without a board."""

    self_calibrate: bool = True
    """Adjust principal point and radial distortion in bundle adjustment when the photos
    constrain them (a camera calibrated by the board or calibrate.known_intrinsics is
    never adjusted; a turntable's or ring's principal point never: one circular motion
    does not determine it)."""
    max_calibration_std_px: Annotated[float, Range(0.0, None, exclusive_lo=True)] = 1.0
    """A parameter is adjusted only when its standard deviation moves points by less than
    this many pixels (radial distortion: at the frame's farthest corner)."""
    min_frame_coverage: Annotated[float, Range(0.0, 1.0)] = 0.4
    """Self-calibration needs observations in this fraction of a 6x6 grid over the frame:
    distortion and principal point show only towards the edges."""


def frame_coverage(pixels: np.ndarray, width: int, height: int) -> float:
    """The fraction of a 6x6 grid over the frame that holds at least one of ``pixels``."""
    cells = np.clip((np.asarray(pixels).reshape(-1, 2) / [width, height] * GRID).astype(int), 0, GRID - 1)
    return len({(x, y) for x, y in cells}) / GRID**2


def corner_radius(width: int, height: int, focal: float, cx: float, cy: float) -> float:
    """Normalised distance of the frame's farthest corner from the principal point."""
    return max(np.hypot(x - cx, y - cy) for x in (0, width - 1) for y in (0, height - 1)) / focal


def radial_shift_px(k1: float, focal: float, radius: float) -> float:
    """How far radial distortion k1 moves a point at normalised ``radius``, in pixels."""
    return float(abs(k1) * focal * radius**3)


def outline_shift_px(k1: float, focal: float, cx: float, cy: float, masks: list[Path]) -> float:
    """How far radial distortion k1 moves the farthest point of the specimen's outline
    in ``masks`` (a sample of them), in pixels."""
    radius = 0.0
    for path in masks[:: max(1, len(masks) // 8)]:
        found = cv2.findNonZero((cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 127).astype(np.uint8))
        if found is not None:
            radius = max(radius, float(np.max(np.linalg.norm(found.reshape(-1, 2) - [cx, cy], axis=1))) / focal)
    return radial_shift_px(k1, focal, radius)
