"""The photos as views to fit: each photo's linear radiance in a window around
its specimen mask, with the window's sensor and the pixels that count, and the
choice of the photos held out for validation.

Each view is rendered only in a window around its mask, scaled so that its
longer side has at most ``max_size`` pixels: pixels are the budget on a CPU. The
weights are the mask eroded by ``erode_px`` at full resolution, so that
silhouette pixels, where the mesh's error shows, do not count.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from pipeline import logger
from pipeline.camera.model import Intrinsics, Pose, resize_exact, scaled
from pipeline.fit.loop import FitView
from pipeline.formats.scene_folder import SCENE_XML
from pipeline.imaging.photo_io import read_photo
from pipeline.render import scene_xml


def mask_window(mask: np.ndarray, max_size: int, margin: int = 8) -> tuple[float, tuple[int, int, int, int]] | None:
    """(scale, crop in scaled pixels) of the mask's bounding box plus ``margin``."""
    rows, cols = np.nonzero(mask)
    if len(rows) == 0:
        return None
    lo = np.maximum([cols.min() - margin, rows.min() - margin], 0)
    hi = np.minimum([cols.max() + margin + 1, rows.max() + margin + 1], mask.shape[::-1])
    scale = min(1.0, max_size / float(max(hi - lo)))
    lo_s = np.floor((lo + 0.5) * scale - 0.5).clip(0).astype(int)
    hi_s = np.ceil((hi + 0.5) * scale - 0.5).astype(int)
    return scale, (int(lo_s[0]), int(lo_s[1]), int(hi_s[0] - lo_s[0]), int(hi_s[1] - lo_s[1]))


def load_views(
    scene_dir: Path,
    description: dict,
    cameras: dict[str, tuple[Intrinsics, Pose]],
    linear: dict[str, Path],
    masks: dict[str, Path],
    max_size: int,
    erode_px: int,
    spp: int,
    sample_border: bool = False,
    names: set[str] | None = None,
    gains: dict[str, list[float]] | None = None,
) -> list[tuple[FitView, tuple]]:
    """Every photo (or those in ``names``) as a FitView in its window (longer side at most
    ``max_size`` px), with the window's scaled camera and crop; weights are the mask
    eroded by ``erode_px``. ``gains``: photos' RGB gains fitted by fit_material (exposure,
    white balance); those photos are divided by theirs, as that fit saw them."""
    import mitsuba as mi

    shared_scene = mi.load_file(str(scene_dir / SCENE_XML)) if description["light_frame"] == "world" else None
    # The scene files name a render integrator (path): the fit renders with its
    # differentiable counterpart, at the same depth.
    integrator = mi.load_dict(
        {"type": description["integrator"]["differentiable"], "max_depth": description["integrator"]["max_depth"]}
    )
    views = []
    for name in sorted(description["views"] if names is None else set(description["views"]) & names):
        mask = cv2.imread(str(masks[name]), cv2.IMREAD_GRAYSCALE) > 127
        window = mask_window(mask, max_size)
        if window is None:
            logger.warning("%s: empty mask, left out of fitting", name)
            continue
        scale, crop = window
        intrinsics, pose = cameras[name]
        small = scaled(intrinsics, scale, exact=True)
        x, y, w, h = crop
        w, h = min(w, small.width - x), min(h, small.height - y)
        crop = (x, y, w, h)
        photo = read_photo(linear[name]).pixels
        reference = resize_exact(photo, scale)[y : y + h, x : x + w]
        if gains and name in gains:
            reference = reference / np.asarray(gains[name], np.float32)
        if erode_px:
            mask = cv2.erode(mask.astype(np.uint8), np.ones((2 * erode_px + 1,) * 2, np.uint8)) > 0
        coverage = resize_exact(mask.astype(np.float32), scale)
        weight = (coverage[y : y + h, x : x + w] > 0.999).astype(np.float32)
        scene = shared_scene or mi.load_file(str(scene_dir / description["views"][name]["xml"]))
        sensor = scene_xml.load_sensor(
            scene_xml.sensor_properties(small, pose, spp, description["near_clip"], crop, sample_border)
        )
        view = FitView(name, scene, sensor, np.ascontiguousarray(reference), weight, integrator)
        views.append((view, (small, crop)))
    return views


def held_out_names(names: list[str], count: int) -> list[str]:
    """``count`` names evenly spread over the sorted list (none when fewer than 3 photos)."""
    if count == 0 or len(names) < 3:
        return []
    count = min(count, len(names) - 1)
    return [sorted(names)[i] for i in np.linspace(0, len(names) - 1, count + 2)[1:-1].round().astype(int)]
