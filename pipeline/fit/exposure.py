"""Held-out photos' exposures, read off the table they share with the training photos.

A phone sets each photo's exposure and white balance itself; fit_material fits a gain
per training photo (render times gain matches the photo), but a held-out photo, which no
fit saw, needs its gain from pixels that are not scored: the table's. A point of the
table looks the same from nearby cameras (a still light, a matte table), so a held-out
photo's pixel over a training photo's pixel at the same table point is the ratio of
their exposures, and the training photo's fitted gain turns it into the held-out photo's
gain. Nothing is rendered: the table's radiance, which the fitted scene models only as
far as the light fit needed, cancels out (a render-based estimate predicted the
training photos' own gains about twice as far off: docs/decisions.md).

Limitations: the table is the plane z = 0 inside the scene's ground disk, off the board's
print; points the specimen hides in either photo, and pixels clipped or too dark in
either, are left out. A glossy table's highlight moves with the camera, so only the
NEAREST cameras are compared. On a turntable the table turns under a still light, and
the ratios carry the light's change as well as the exposure's.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipeline.camera.model import Intrinsics, Pose, ground_hits, project
from pipeline.core import progress
from pipeline.fit.views import CapturePhotos
from pipeline.formats.scene_description import SceneDescription
from pipeline.render.capture_scene import photo_at_most, table_region

CLIPPED = 0.9
"""Table pixels at or above this linear radiance in a channel (a white table in a phone
photo reaches the sensor's ceiling) do not measure the exposure."""
DARK = 0.01
"""Table pixels below this linear radiance (about 25 of 255 in sRGB) are too coarsely
quantised to measure it."""
PHOTO_PX = 200
"""Photos are compared at most this many pixels on their longer side: the table is
smooth, and a pose or table-plane error of a few full-resolution pixels stays under one."""
NEAREST = 4
"""A photo's gain is the median of the estimates from this many training photos, the
nearest cameras: 2 to 4 predict the training photos' gains within each other's noise,
more reach views whose table looks different; 4 keeps one bad pair from deciding."""
MIN_PIXELS = 50
"""Table points two photos must share for their ratio to count."""


@dataclass(frozen=True)
class TablePixels:
    """One photo at PHOTO_PX: its camera, radiance, dilated specimen mask, and the table
    points (n, 3) its ``table`` pixels see."""

    intrinsics: Intrinsics
    pose: Pose
    radiance: np.ndarray
    specimen: np.ndarray
    points: np.ndarray
    values: np.ndarray


def table_pixels(intrinsics: Intrinsics, pose: Pose, photo: Path, mask: Path, region) -> TablePixels:
    """``photo`` (linear) and its specimen ``mask`` at PHOTO_PX, with the table points
    ``region`` selects whose radiance is measurable (DARK to CLIPPED in every channel)."""
    small, radiance, specimen = photo_at_most(intrinsics, photo, mask, PHOTO_PX)
    specimen = cv2.dilate(specimen.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    hits, distance = ground_hits(small, pose)
    seen = region(hits, distance > 0, specimen) & _measurable(radiance)
    return TablePixels(small, pose, radiance, specimen, hits[seen], radiance[seen])


def _measurable(radiance: np.ndarray) -> np.ndarray:
    return np.all((radiance >= DARK) & (radiance < CLIPPED), axis=-1)


def exposure_ratio(photo: TablePixels, other: TablePixels) -> np.ndarray | None:
    """``photo``'s exposure over ``other``'s (RGB): the median, over the table points both
    see, of their radiance ratio; None below MIN_PIXELS shared points."""
    pixels, depth = project(photo.points, other.intrinsics, other.pose)
    columns, rows = np.round(pixels).astype(int).T
    inside = (depth > 0) & (columns >= 0) & (columns < other.intrinsics.width)
    inside &= (rows >= 0) & (rows < other.intrinsics.height)
    columns, rows = columns[inside], rows[inside]
    theirs = other.radiance[rows, columns]
    shared = ~other.specimen[rows, columns] & _measurable(theirs)
    if np.count_nonzero(shared) < MIN_PIXELS:
        return None
    return np.median(photo.values[inside][shared] / theirs[shared], axis=0)


def predicted_gain(
    name: str, pixels: dict[str, TablePixels], fitted: dict[str, list[float]], nearest: int = NEAREST
) -> np.ndarray | None:
    """``name``'s RGB gain from the ``nearest`` photos of ``fitted`` (not itself) that
    share table with it: the median of their fitted gains times the exposure ratios."""
    center = pixels[name].pose.center
    others = sorted((n for n in fitted if n != name), key=lambda n: np.linalg.norm(pixels[n].pose.center - center))
    estimates = []
    for other in others:
        ratio = exposure_ratio(pixels[name], pixels[other])
        if ratio is not None:
            estimates.append(ratio * np.asarray(fitted[other]))
        if len(estimates) == nearest:
            break
    return np.median(estimates, axis=0) if estimates else None


def table_gains(
    description: SceneDescription,
    photos: CapturePhotos,
    fitted: dict[str, list[float]],
    names: list[str],
    channels: int,
    nearest: int = NEAREST,
) -> dict:
    """The RGB gains of the photos ``names`` (held out: no fit saw them), from the table
    they share with the training photos (predicted_gain); ``fitted``: the training
    photos' gains. Returns {"gains": by name (photos that share too little table left
    out), "training_error": the median, 90th percentile and largest relative error of
    each training photo's gain predicted from the others};
    empty without a table in the scene or fitted gains. ``channels`` 1: one gain, the
    channels' mean; ``nearest``: predicted_gain's."""
    ground = description.ground
    if not ground or not fitted or not names:
        return {}
    cameras, linear, masks = photos.cameras, photos.linear, photos.masks
    region = table_region(ground.radius, description.board_print)
    pixels = {
        name: table_pixels(*cameras[name], linear[name], masks[name], region)
        for name in progress.track(sorted(fitted) + list(names), "exposure from the table")
    }

    def gain(name: str) -> np.ndarray | None:
        value = predicted_gain(name, pixels, fitted, nearest)
        if value is None or channels != 1:
            return value
        return np.full(3, value.mean())

    predicted = {n: gain(n) for n in fitted}
    errors = [np.max(np.abs(g / np.asarray(fitted[n]) - 1)) for n, g in predicted.items() if g is not None]
    if not errors:
        return {}
    held = {n: gain(n) for n in names}
    return {
        "gains": {n: [float(v) for v in g] for n, g in held.items() if g is not None},
        "training_error": {
            "median": float(np.median(errors)),
            "p90": float(np.percentile(errors, 90)),
            "max": float(np.max(errors)),
            "photos": len(errors),
        },
    }
