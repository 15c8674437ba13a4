"""Colour correction from a ColorChecker 24 (Macbeth) chart in a photo.

The chart is found by OpenCV's ``mcc`` detector on an 8-bit copy; each patch's mean
is then taken on the linear photo, inside the patch shrunk to its central part (the
detector's corners are a few pixels loose, and the patch edges are blurred). A 3x3
matrix M is fitted by least squares so that M @ measured matches the patches'
reference colours (linear sRGB primaries, D65): it undoes the light's colour, the
camera's channel mixing and the exposure at once, so corrected photos read the
chart's white patch at its reflectance.

===============  ===================================================================
quantity         meaning
===============  ===================================================================
matrix           3x3, applied to every linear photo: corrected = M @ rgb
delta_e_before   CIEDE2000 between the patches and their references after only the
                 best single gain (the exposure): the colour error the photo had
delta_e_after    the same after the matrix
===============  ===================================================================

Limitations: the correction is right for the light and exposure of the chart's shot;
photos under another light are not made right by it (their exposure difference is
undone where both shots record it in EXIF). Patches with a clipped channel are left
out of the fit. Only the 24-patch chart is looked for.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from skimage.color import deltaE_ciede2000, rgb2lab

from pipeline.imaging.photo_io import srgb_encode, to_uint8

# The X-Rite ColorChecker Classic's published sRGB values (D65), 8-bit, in reading
# order: dark skin ... black.
COLORCHECKER_24_SRGB8 = np.array(
    [
        (115, 82, 68), (194, 150, 130), (98, 122, 157), (87, 108, 67), (133, 128, 177), (103, 189, 170),
        (214, 126, 44), (80, 91, 166), (193, 90, 99), (94, 60, 108), (157, 188, 64), (224, 163, 46),
        (56, 61, 150), (70, 148, 73), (175, 54, 60), (231, 199, 31), (187, 86, 149), (8, 133, 161),
        (243, 243, 242), (200, 200, 200), (160, 160, 160), (122, 122, 121), (85, 85, 85), (52, 52, 52),
    ],
    dtype=float,
)  # fmt: skip
PATCH_SHRINK = 0.5
"""Fraction of a patch's size (about its centre) whose pixels are averaged."""
CLIPPED = 0.98
"""A patch with a channel at or above this (of the sensor's range) is left out."""


def reference_linear() -> np.ndarray:
    """The 24 patches' reference colours, linear sRGB primaries, (24, 3)."""
    encoded = COLORCHECKER_24_SRGB8 / 255
    return np.where(encoded <= 0.04045, encoded / 12.92, ((encoded + 0.055) / 1.055) ** 2.4)


def find_chart(linear: np.ndarray) -> np.ndarray | None:
    """The corners of the 24 patches, (24, 4, 2) pixels in reading order, or None
    (also when a patch lies partly outside the photo)."""
    detector = cv2.mcc.CCheckerDetector_create()
    detector.setColorChartType(cv2.mcc.MCC24)
    if not detector.process(np.ascontiguousarray(to_uint8(linear)[..., ::-1]), 1):
        return None
    checkers = detector.getListColorChecker()
    if not checkers:
        return None
    corners = np.asarray(checkers[0].getColorCharts(), dtype=float).reshape(24, 4, 2)
    height, width = linear.shape[:2]
    inside = (corners >= 0).all() and (corners[..., 0] < width).all() and (corners[..., 1] < height).all()
    return corners if inside else None  # a chart partly out of frame, or a false find


def patch_means(linear: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Each patch's mean linear colour over its central part, (24, 3)."""
    means = np.empty((len(corners), 3))
    for i, quad in enumerate(corners):
        centre = quad.mean(axis=0)
        inner = np.round(centre + (quad - centre) * PATCH_SHRINK).astype(np.int32)
        mask = np.zeros(linear.shape[:2], np.uint8)
        cv2.fillConvexPoly(mask, inner, 1)
        if not mask.any():  # a patch of a few pixels: its centre
            mask[int(centre[1]), int(centre[0])] = 1
        means[i] = linear[mask > 0].mean(axis=0)
    return means


def delta_e(colours: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """CIEDE2000 between linear colours (clipped to [0, 1]) and references, per row."""
    lab = rgb2lab(srgb_encode(colours)[None])[0]
    return deltaE_ciede2000(lab, rgb2lab(srgb_encode(reference)[None])[0])


@dataclass(frozen=True)
class ColourCorrection:
    matrix: np.ndarray
    """3x3: corrected linear RGB = matrix @ measured linear RGB."""
    used: int
    """Patches the fit used (those without a clipped channel)."""
    delta_e_before: float
    """Mean CIEDE2000 of the patches after only the best gain (the exposure)."""
    delta_e_after: float
    """Mean CIEDE2000 of the patches after the matrix."""
    delta_e_after_max: float
    """The worst patch after the matrix."""

    def apply(self, linear: np.ndarray) -> np.ndarray:
        return (linear @ self.matrix.T.astype(np.float32)).astype(np.float32)

    def to_json(self) -> dict:
        return {
            "matrix": self.matrix.tolist(),
            "patches_used": self.used,
            "delta_e_before": self.delta_e_before,
            "delta_e_after": self.delta_e_after,
            "delta_e_after_max": self.delta_e_after_max,
        }


def fit_correction(measured: np.ndarray) -> ColourCorrection:
    """The 3x3 matrix taking ``measured`` (24, 3) patch colours to the references. The
    detector's order is tried both ways round (a chart upside down reads backwards)."""
    reference = reference_linear()
    usable = (measured < CLIPPED).all(axis=1)
    best = None
    for order in (np.arange(24), np.arange(24)[::-1]):
        ordered, kept = measured[order], usable[order]
        matrix = np.linalg.lstsq(ordered[kept], reference[kept], rcond=None)[0].T
        after = delta_e(ordered[kept] @ matrix.T, reference[kept])
        if best is None or after.mean() < best[1].mean():
            gain = float(ordered[kept].ravel() @ reference[kept].ravel() / (ordered[kept].ravel() ** 2).sum())
            best = (matrix, after, delta_e(ordered[kept] * gain, reference[kept]))
    matrix, after, before = best
    return ColourCorrection(matrix, int(usable.sum()), float(before.mean()), float(after.mean()), float(after.max()))


def exposure(metadata: dict[str, object]) -> float | None:
    """Relative exposure (time x ISO / f-number squared) from EXIF, or None when a part is missing."""
    try:
        time = float(metadata["ExposureTime"])
        iso = float(metadata["Exif:ISOSpeedRatings"])
        f_number = float(metadata["FNumber"])
    except (KeyError, TypeError, ValueError):
        return None
    return time * iso / f_number**2 if time > 0 and iso > 0 and f_number > 0 else None


__all__ = ["ColourCorrection", "delta_e", "exposure", "find_chart", "fit_correction", "patch_means", "reference_linear"]
