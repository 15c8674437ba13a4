"""The photos as views to fit: each photo's linear radiance in a window around
its specimen mask, with the window's sensor and the pixels that count, and the
choice of the photos held out for validation.

Each view is rendered only in a window around its mask, scaled so that its
longer side has at most ``max_size`` pixels: pixels are the budget on a CPU. Every
window of a capture has the same size (mask_windows), so that every view renders
with the same kernels. The pixels that count are those inside both the photo's mask
and the scene mesh's outline in that photo: a segmentation that took in some of a
busy backdrop is cut back to the specimen (the mesh, a visual hull at first, is
carved by every mask, so one mask's excess does not reach it). They are then eroded
by ``erode_px`` at full resolution, so that silhouette pixels, where the mesh's error
shows, do not count. While a light is estimated on a capture with a board, the board's
print beside the specimen counts too (BoardPixels). A window's render is filtered as
its photo was made (pixel_filter): the photo's own blur, scaled down with it, and each
window pixel's average over its square.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import trimesh

from pipeline import logger
from pipeline.camera.model import Intrinsics, Pose, ground_hits, mesh_coverage, resize_exact, scaled
from pipeline.fit.loop import FitView, gain_range
from pipeline.formats.cameras import read_views
from pipeline.formats.fit_results import MaterialFit
from pipeline.formats.masks import read_masks
from pipeline.formats.pinhole import linear_photos
from pipeline.formats.scene_description import SceneDescription
from pipeline.formats.scene_folder import MESH_PLY, SCENE_XML
from pipeline.imaging.photo_io import read_photo
from pipeline.render import scene_xml


@dataclass(frozen=True)
class Window:
    """Where a view is rendered: the photo scaled by ``scale`` (square pixels), then the
    ``width`` x ``height`` pixels from column ``x``, row ``y``, which may reach past the
    photo's edge (pixels there are not scored)."""

    scale: float
    x: int
    y: int
    width: int
    height: int
    photo_shape: tuple[int, int]
    """The photo's (height, width) at full resolution."""

    def intrinsics(self, full: Intrinsics) -> Intrinsics:
        """The pinhole camera whose whole image is the window: a film of exactly the
        window's size with the principal point moved, not a crop of a larger film."""
        small = scaled(full, self.scale, exact=True)
        return Intrinsics(self.width, self.height, small.fx, small.fy, small.cx - self.x, small.cy - self.y)

    def cut(self, image: np.ndarray) -> np.ndarray:
        """``image`` (the photo's resolution) scaled and cut to the window; zero past the
        photo's edge."""
        small = resize_exact(image, self.scale)
        window = np.zeros((self.height, self.width, *small.shape[2:]), small.dtype)
        x0, y0 = max(self.x, 0), max(self.y, 0)
        x1, y1 = min(self.x + self.width, small.shape[1]), min(self.y + self.height, small.shape[0])
        if x1 > x0 and y1 > y0:
            window[y0 - self.y : y1 - self.y, x0 - self.x : x1 - self.x] = small[y0:y1, x0:x1]
        return window

    def inside(self) -> np.ndarray:
        """(height, width) float weights: 1 on the window's pixels inside the photo."""
        return (self.cut(np.ones(self.photo_shape, np.float32)) > 0.999).astype(np.float32)


def mask_windows(
    masks: dict[str, np.ndarray], max_size: int, margin: int = 8, board_margin: float = 0.0
) -> dict[str, Window]:
    """Each mask's window, all of one size (masks with no pixel have none): each photo
    scaled so that its mask's bounding box plus ``margin`` pixels and ``board_margin``
    of the box's longer side has at most ``max_size`` px along its longer side, the
    window centred on that box and as large as the largest box. One film size for
    every view means one set of kernels (Dr.Jit bakes the film size and a crop offset
    into them as literals; the principal point it does not) and one dr.freeze
    recording replayed for every view."""
    boxes = {}
    for name, mask in masks.items():
        rows, cols = np.nonzero(mask)
        if len(rows) == 0:
            continue
        reach = margin + int(board_margin * max(cols.max() - cols.min(), rows.max() - rows.min()))
        lo = np.maximum([cols.min() - reach, rows.min() - reach], 0)
        hi = np.minimum([cols.max() + reach + 1, rows.max() + reach + 1], mask.shape[::-1])
        boxes[name] = (lo, hi, min(1.0, max_size / float(max(hi - lo))))
    if not boxes:
        return {}
    # less a rounding error's worth: (hi - lo) * (max_size / (hi - lo)) may land just above
    # max_size (for 105 box sizes in 49-2000 at 48 px), and the ceiling a pixel past it
    sizes = [np.ceil((hi - lo) * scale - 1e-6) for lo, hi, scale in boxes.values()]
    width, height = np.max(sizes, axis=0).astype(int)
    windows = {}
    for name, (lo, hi, scale) in boxes.items():
        centre = (lo + hi) / 2 * scale
        x, y = (int(round(c)) for c in centre - [width / 2, height / 2])
        windows[name] = Window(scale, x, y, int(width), int(height), masks[name].shape[:2])
    return windows


PHOTO_BLUR_PX = 0.75
"""The photos' own blur at full resolution, as a Gaussian's standard deviation in pixels:
a lens and demosaicing, and undistortion's bilinear resampling (about 0.4 px alone);
the synthetic captures' photos are rendered with Mitsuba's 0.5 px filter and resampled
twice (distortion, then undistortion): about 0.75 px."""


def pixel_filter(scale: float) -> dict:
    """The reconstruction filter of a window's sensor (a ``mi.load_dict`` dict) for
    photos scaled by ``scale``: a Gaussian whose variance is that of the photo's own
    blur scaled with it, plus that of a window pixel's square (1/12 px^2: the photo is
    averaged down over each pixel's square, ``cv2.INTER_AREA``; exactly its variance is
    (1 - scale^2) / 12, so at scale 1 this is 0.05 px wider than the photo). Mitsuba's
    default (0.5 px) is about right for photos halved, and blurs a render past a photo
    averaged down 3-5 times (docs/decisions.md, "Fitting's windows and geometry")."""
    return {"type": "gaussian", "stddev": float(np.sqrt(1 / 12 + (PHOTO_BLUR_PX * scale) ** 2))}


@dataclass(frozen=True)
class BoardPixels:
    """The board's print in the fit: its reflectance is known, so its pixels fix the
    level of an estimated light (what a light and the specimen's albedo otherwise
    trade off), and its shading beside the specimen shows where the light comes from."""

    half_extent: tuple[float, float]
    """Half the print's width and height, metres, centred at the world's origin on
    z = 0 (the board's frame, pipeline.camera.board)."""
    count: bool
    """Whether the print's pixels are weighted (training views), or only framed
    (held-out views, scored on the specimen alone, in windows of the same size)."""


@dataclass(frozen=True)
class PhotoGains:
    """What fit_material found of each photo's own exposure (params.json), as the
    fits after it use it."""

    fitted: dict[str, list[float]]
    """Each training photo's RGB gain (render times gain matches the photo): those
    photos are divided by theirs, as fit_material saw them."""
    channels: int
    """0 when one exposure held for the whole capture; else 1 (exposure) or 3 (exposure
    and white balance) per photo: a held-out photo's render is matched to it by a gain
    of that many channels, within the range of ``fitted``, before its error is scored
    (FitView.heldout_gain), unless ``measured`` has its gain."""
    measured: dict[str, list[float]] = field(default_factory=dict)
    """Held-out photos' RGB gains read off the table they share with the training photos
    (pipeline.fit.exposure): their renders are scaled by them (FitView.gain), so that
    they are scored, as they are written, in the photo's own units."""

    @staticmethod
    def of(material: MaterialFit) -> PhotoGains:
        """fit_material's photo_gains, gain_channels and heldout_gains."""
        measured = (material.heldout_gains or {}).get("gains") or {}
        return PhotoGains(material.photo_gains or {}, material.gain_channels, measured)


@dataclass(frozen=True)
class CapturePhotos:
    """The capture's photos as the fits read them, by photo name."""

    cameras: dict[str, tuple[Intrinsics, Pose]]
    """Each photo's intrinsics and pose (sfm's cameras.json)."""
    linear: dict[str, Path]
    """Each photo's linear EXR (undistort)."""
    masks: dict[str, Path]
    """Each photo's mask (masks)."""
    gains: PhotoGains | None = None
    """What fit_material found of the photos' exposure; None in fit_material itself."""


def read_capture_photos(
    cameras_json: Path, pinhole_json: Path, masks_json: Path, gains: PhotoGains | None = None
) -> CapturePhotos:
    """The photos of sfm's cameras.json, undistort's pinhole.json and masks' masks.json."""
    return CapturePhotos(read_views(cameras_json), linear_photos(pinhole_json), read_masks(masks_json), gains)


@dataclass(frozen=True)
class Windowing:
    """How each photo is cut and sampled for a fit."""

    max_size: int
    """Longer side of a view's window, pixels (the photo reduced to fit)."""
    erode_px: int
    """Pixels the mask is eroded by before it weights the loss."""
    spp: int
    """Samples per pixel of the view's renders."""
    sample_border: bool = False
    """Sample the film's border too (geometry passes: the silhouette reaches it)."""


BOARD_MARGIN = 0.3
"""With the board in the fit, windows reach this fraction of the mask's box further on
each side: the specimen's shadow and the print's shading beside it."""


def board_weight(window: Window, intrinsics: Intrinsics, pose: Pose, board: BoardPixels, specimen: np.ndarray):
    """(height, width) of the window: 1 where a pixel's ray meets the print (5 mm in
    from its edges) outside the specimen's dilated outline."""
    hits, distance = ground_hits(window.intrinsics(intrinsics), pose)
    on_print = (distance > 0) & np.all(np.abs(hits[..., :2]) < np.asarray(board.half_extent) - 0.005, axis=-1)
    near_specimen = cv2.dilate(specimen.astype(np.uint8), np.ones((9, 9), np.uint8))
    return on_print & (window.cut(near_specimen.astype(np.float32)) == 0)


def load_views(
    scene_dir: Path,
    description: SceneDescription,
    photos: CapturePhotos,
    windowing: Windowing,
    names: set[str] | None = None,
    board: BoardPixels | None = None,
    scenes: dict[str, Any] | None = None,
) -> list[tuple[FitView, Window]]:
    """Every photo (or those in ``names``) as a FitView in its window (mask_windows over
    every photo of the scene, so a view's window does not depend on ``names``); weights
    are the mask eroded by ``windowing.erode_px``; ``photos.gains`` divide the training
    photos and match the held-out ones. ``board``: windows wider by BOARD_MARGIN, and the
    print's pixels weighted too when it says so. ``scenes``: each view's scene already
    loaded (another fit's views', so that what that fit changed holds), instead of the
    files'."""
    import mitsuba as mi

    shared_scene = None
    if scenes is None and description.light_frame == "world":
        shared_scene = mi.load_file(str(scene_dir / SCENE_XML))
    # The scene files name a render integrator (path): the fit renders with its
    # differentiable counterpart, at the same depth.
    integrator = mi.load_dict(
        {"type": description.integrator.differentiable, "max_depth": description.integrator.max_depth}
    )
    cameras, linear, gains = photos.cameras, photos.linear, photos.gains
    every = specimen_masks(scene_dir / MESH_PLY, cameras, {n: photos.masks[n] for n in sorted(description.views)})
    windows = mask_windows(every, windowing.max_size, board_margin=BOARD_MARGIN if board else 0.0)
    # one filter for every window (Dr.Jit bakes it into the kernels), at their median scale
    rfilter = pixel_filter(float(np.median([w.scale for w in windows.values()]))) if windows else None
    # held out, a render is matched to its photo by a gain (FitView.heldout_gain)
    matched = (gains.channels, gain_range(gains.fitted) if gains.fitted else None) if gains else (0, None)
    views = []
    for name in sorted(every if names is None else set(every) & names):
        if name not in windows:
            logger.warning("%s: empty mask, left out of fitting", name)
            continue
        window, mask = windows[name], every[name]
        intrinsics, pose = cameras[name]
        reference = window.cut(read_photo(linear[name]).pixels)
        if gains and name in gains.fitted:
            reference = reference / np.asarray(gains.fitted[name], np.float32)
        if windowing.erode_px:
            size = 2 * windowing.erode_px + 1
            mask = cv2.erode(mask.astype(np.uint8), np.ones((size, size), np.uint8)) > 0
        weight = window.inside() * (window.cut(mask.astype(np.float32)) > 0.999)
        if board is not None and board.count:
            weight = np.maximum(weight, window.inside() * board_weight(window, intrinsics, pose, board, every[name]))
        if scenes is not None:
            scene = scenes[name]
        else:
            scene = shared_scene or mi.load_file(str(scene_dir / description.views[name].xml))
        sensor = scene_xml.load_sensor(
            scene_xml.sensor_properties(
                window.intrinsics(intrinsics),
                pose,
                windowing.spp,
                description.near_clip,
                sample_border=windowing.sample_border,
                rfilter=rfilter,
            )
        )
        # a held-out photo whose gain was measured: its renders are scaled by it (FitView.gain
        # comes before heldout_gain's match)
        measured = np.asarray(gains.measured[name], np.float32) if gains and name in gains.measured else None
        view = FitView(name, scene, sensor, np.ascontiguousarray(reference), weight, integrator, *matched, measured)
        views.append((view, window))
    return views


_NAMED: set[tuple[str, ...]] = set()
"""Warnings of specimen_masks already given in this process: a stage loads its views
several times (once per candidate), and the same photos need naming once."""


def specimen_masks(
    mesh_file: Path, cameras: dict[str, tuple[Intrinsics, Pose]], masks: dict[str, Path], excess: float = 0.2
) -> dict[str, np.ndarray]:
    """Each photo's mask cut to the mesh's outline in it, with a warning naming the
    photos whose mask reached past that outline by more than ``excess`` of its area."""
    mesh = trimesh.load(mesh_file, force="mesh", process=False)
    result, spilled = {}, []
    for name, path in masks.items():
        mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 127
        intrinsics, pose = cameras[name]
        # a closed mesh's outline is that of its faces turned towards the camera
        front = np.einsum("ij,ij->i", mesh.face_normals, pose.center - mesh.triangles_center) > 0
        outline = mesh_coverage(mesh.vertices, mesh.faces[front], intrinsics, pose, factor=1) > 0.5
        result[name] = mask & outline
        if mask.sum() > (1 + excess) * result[name].sum():
            spilled.append(f"{name} ({mask.sum() / max(result[name].sum(), 1) - 1:.0%})")
    if spilled and (str(mesh_file), *spilled) not in _NAMED:
        _NAMED.add((str(mesh_file), *spilled))
        logger.warning(
            "%d masks reach past the mesh's outline (%s): only pixels inside both count; "
            "a backdrop the segmentation took in? (masks.segmenter, or masks/ in the capture)",
            len(spilled),
            ", ".join(spilled[:4]) + (", ..." if len(spilled) > 4 else ""),
        )
    return result


def held_out_names(names: list[str], count: int) -> list[str]:
    """``count`` names evenly spread over the sorted list (none when fewer than 3 photos),
    all but one at most. Fewer than asked is said in a warning."""
    if count == 0:
        return []
    if len(names) < 3:
        logger.warning("held_out = %d, but %d photo(s) are too few to hold any out: none held out", count, len(names))
        return []
    kept = min(count, len(names) - 1)
    if kept < count:
        logger.warning(
            "held_out = %d, but with %d photos at most %d are held out, so that one is fitted",
            count,
            len(names),
            kept,
        )
    return [sorted(names)[i] for i in np.linspace(0, len(names) - 1, kept + 2)[1:-1].round().astype(int)]
