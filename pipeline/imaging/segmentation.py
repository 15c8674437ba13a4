"""Foreground masks of the specimen: from a background plate or by GrabCut.

Used by the masks stage and by ``pipeline check`` (which looks at mask coverage
before the expensive stages run).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

from pipeline.imaging.photo_io import read_photo, srgb_encode

SHADOW_CHROMA_CHANGE = 0.03
"""A shadow darkens the set without changing its colour by more than this (chroma units)."""


def _working_copy(image: np.ndarray, working_size: int) -> np.ndarray:
    """``image`` resized so that its longer side is ``working_size``.

    Small photos are enlarged too: GrabCut's boundary is pixel-exact at the working
    size, so segmenting a 128-pixel photo at 400 pixels places its edges to a third
    of a photo pixel.
    """
    factor = working_size / max(image.shape[:2])
    if abs(factor - 1) < 1e-3:
        return image
    size = (max(1, round(image.shape[1] * factor)), max(1, round(image.shape[0] * factor)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA if factor < 1 else cv2.INTER_LINEAR)


def _photo_size(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    if mask.shape == shape:
        return mask
    shrinking = mask.shape[0] > shape[0]
    soft = cv2.resize(
        mask.astype(np.float32), (shape[1], shape[0]), interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR
    )
    return soft >= 0.5


def grabcut(image: np.ndarray, seeds: np.ndarray, iterations: int) -> np.ndarray:
    """GrabCut on an 8-bit RGB image from a seed map of cv2.GC_* labels; True = foreground."""
    labels = seeds.astype(np.uint8).copy()
    foreground = (labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)
    if foreground.all() or not foreground.any():  # GrabCut needs samples of both
        return foreground
    background_model, foreground_model = np.zeros((1, 65)), np.zeros((1, 65))
    # GrabCut seeds its colour models by k-means from OpenCV's global random state:
    # without a fixed seed a mask depends on what the process did before.
    cv2.setRNGSeed(0)
    cv2.grabCut(image, labels, None, background_model, foreground_model, iterations, cv2.GC_INIT_WITH_MASK)
    return (labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)


def centre_prior_seeds(shape: tuple[int, int], centre_fraction: float) -> np.ndarray:
    """Probably foreground inside a centred box covering ``centre_fraction`` of each side,
    surely background along a thin frame at the border, probably background between."""
    height, width = shape
    seeds = np.full(shape, cv2.GC_PR_BGD, np.uint8)
    border = max(1, round(0.02 * max(shape)))
    seeds[:border], seeds[-border:], seeds[:, :border], seeds[:, -border:] = (cv2.GC_BGD,) * 4
    margin_y, margin_x = round(height * (1 - centre_fraction) / 2), round(width * (1 - centre_fraction) / 2)
    seeds[margin_y : height - margin_y, margin_x : width - margin_x] = cv2.GC_PR_FGD
    return seeds


def segment_centre_prior(srgb: np.ndarray, centre_fraction: float, iterations: int, working_size: int) -> np.ndarray:
    """The object near the image centre, separated from the rest by GrabCut's colour models."""
    small = _working_copy(srgb, working_size)
    mask = grabcut(small, centre_prior_seeds(small.shape[:2], centre_fraction), iterations)
    return _photo_size(mask, srgb.shape[:2])


def chroma(srgb: np.ndarray) -> np.ndarray:
    """Colourfulness in [0, 1]: spread of the (slightly blurred) 8-bit sRGB channels.

    Measured on encoded values, where sensor noise in dark pixels stays small,
    unlike ratios of linear values.
    """
    blurred = cv2.GaussianBlur(srgb.astype(np.float32), (0, 0), 1.0)
    return (blurred.max(axis=-1) - blurred.min(axis=-1)) / 255.0


def segment_neutral_backdrop(
    srgb: np.ndarray, backdrop_chroma: float, centre_fraction: float, iterations: int, working_size: int
) -> np.ndarray:
    """The specimen on a grey, white or black set (table, sweep, printed board).

    Pixels greyer than ``backdrop_chroma`` are backdrop for sure, up to twice that
    probably; pixels three times as colourful are specimen for sure. The centre
    prior and GrabCut's colour models decide the rest, which is what lets a grey
    highlight on the specimen stay foreground.
    """
    small = _working_copy(srgb, working_size)
    colourfulness = chroma(small)
    seeds = centre_prior_seeds(small.shape[:2], centre_fraction)
    inside = seeds == cv2.GC_PR_FGD
    seeds[inside & (colourfulness < 2 * backdrop_chroma)] = cv2.GC_PR_BGD
    seeds[colourfulness < backdrop_chroma] = cv2.GC_BGD
    seeds[inside & (colourfulness > 3 * backdrop_chroma)] = cv2.GC_FGD
    return _photo_size(grabcut(small, seeds, iterations), srgb.shape[:2])


def segment_plate_difference(
    linear: np.ndarray,
    plate: np.ndarray,
    threshold: float,
    iterations: int,
    working_size: int,
    shadows_are_background: bool = True,
) -> np.ndarray:
    """Pixels that differ from the empty-set plate by more than ``threshold`` noise sigmas.

    The noise sigma is estimated robustly (median absolute deviation) from the
    difference itself, most of which is background. A darker pixel whose colour
    did not change is the specimen's shadow on the set, not the specimen (unless
    ``shadows_are_background`` is off, for dark grey specimens on a light set).
    GrabCut then settles the uncertain band.
    """
    small, small_plate = _working_copy(linear, working_size), _working_copy(plate, working_size)
    root, plate_root = np.sqrt(np.clip(small, 0, None)), np.sqrt(np.clip(small_plate, 0, None))
    difference = np.linalg.norm(root - plate_root, axis=-1)
    sigma = 1.4826 * np.median(np.abs(difference - np.median(difference))) + 1e-6
    seeds = np.full(difference.shape, cv2.GC_PR_BGD, np.uint8)
    seeds[difference > threshold * sigma] = cv2.GC_PR_FGD
    seeds[difference > 3 * threshold * sigma] = cv2.GC_FGD
    srgb = np.round(srgb_encode(small) * 255).astype(np.uint8)
    if shadows_are_background:
        plate_srgb = np.round(srgb_encode(small_plate) * 255).astype(np.uint8)
        darker = root.mean(axis=-1) < plate_root.mean(axis=-1)
        same_colour = np.abs(chroma(srgb) - chroma(plate_srgb)) < SHADOW_CHROMA_CHANGE
        seeds[darker & same_colour] = cv2.GC_BGD
    seeds[difference < sigma] = cv2.GC_BGD
    mask = grabcut(srgb, seeds, iterations) if iterations else seeds % 2 == 1
    return _photo_size(mask, linear.shape[:2])


def clean(mask: np.ndarray, min_component_fraction: float, max_hole_fraction: float) -> np.ndarray:
    """Keep components at least ``min_component_fraction`` of the largest; fill the
    holes smaller than ``max_hole_fraction`` of the silhouette's area (specimen pixels
    taken for backdrop), keep larger ones open (the backdrop seen through a colonnade
    or a handle, which the visual hull must carve)."""
    labels, count = ndimage.label(mask)
    if count == 0:
        return mask
    sizes = ndimage.sum_labels(mask, labels, index=np.arange(1, count + 1))
    keep = np.flatnonzero(sizes >= min_component_fraction * sizes.max()) + 1
    mask = np.isin(labels, keep)
    holes, count = ndimage.label(ndimage.binary_fill_holes(mask) & ~mask)
    if count == 0:
        return mask
    hole_sizes = ndimage.sum_labels(np.ones_like(mask), holes, index=np.arange(1, count + 1))
    small = np.flatnonzero(hole_sizes < max_hole_fraction * (mask.sum() + hole_sizes.sum())) + 1
    return mask | np.isin(holes, small)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


def read_user_mask(path: Path) -> np.ndarray:
    """A user's mask as booleans: any nonzero value is specimen (read as linear so that
    8-bit 255 is 1.0 and label images with small values count too)."""
    return read_photo(path, "linear").pixels[..., 0] > 0.5 / 255


def segment(
    srgb: np.ndarray,
    segmenter: str,
    backdrop_chroma: float,
    centre_fraction: float,
    grabcut_iterations: int,
    working_size: int,
) -> np.ndarray:
    """The automatic segmenter ``segmenter`` (the masks stage's choice) on an 8-bit RGB
    photo, before cleaning."""
    if segmenter == "neutral_backdrop":
        return segment_neutral_backdrop(srgb, backdrop_chroma, centre_fraction, grabcut_iterations, working_size)
    return segment_centre_prior(srgb, centre_fraction, grabcut_iterations, working_size)
