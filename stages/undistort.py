"""Stage undistort: the photos as an ideal pinhole camera sees them, in two encodings.

Every photo in ``images/`` (and every background plate in ``background/``) is read
through OpenImageIO (JPEG, PNG, 8- or 16-bit TIFF, EXR; EXIF orientation applied),
decoded to linear radiance, colour-corrected when the colour stage found a chart
(scaled by the exposure difference to the chart's shot where EXIF records both),
remapped to the distortion-free camera of its camera setting, optionally reduced to a
working resolution, and written twice:

==================  =============================================================
output              content
==================  =============================================================
undistorted/        8-bit sRGB PNGs, for feature matching and previews
linear/             half-float linear-radiance EXRs, for masks and fitting
pinhole.json        per camera setting: the calibrated (source) and the pinhole
                    (target) intrinsics; per photo and plate: its setting and files
==================  =============================================================

Limitations: sRGB-encoded inputs are assumed to use the sRGB transfer curve (true
for JPEGs from cameras and phones; a camera's picture style or tone curve is not
undone, so fitting is only as linear as the photos). Files whose metadata names a
linear colour space, and float files, are taken as linear.
"""

from __future__ import annotations

import hashlib
from collections import defaultdict
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated

import numpy as np

from pipeline import logger
from pipeline.camera.model import Intrinsics, ideal_pinhole, scaled, undistort
from pipeline.core import progress
from pipeline.core.config import Range
from pipeline.core.errors import PipelineError
from pipeline.core.stage import Stage, StageInputs, StageResult
from pipeline.formats.calibration import read_camera_groups
from pipeline.formats.colour import ColourRecord, read_colour
from pipeline.formats.pinhole import write_pinhole
from pipeline.imaging.colour_chart import exposure
from pipeline.imaging.photo_io import (
    Encoding,
    camera_setting,
    photo_files,
    read_metadata,
    read_photo,
    to_uint8,
    warn_unread,
    write_image,
)
from pipeline.render.scene_xml import sensor_id


@dataclass(frozen=True)
class Config:
    """Undistortion to a pinhole camera, and the working resolution."""

    max_size: Annotated[int, Range(0, None)] = 0
    """Longer side of the working images in pixels; 0 keeps the photos' size. Smaller
    images make every later stage faster (fitting cost grows with the pixel count)."""
    alpha: Annotated[float, Range(0.0, 1.0)] = 0.0
    """0: crop to pixels the photo covers (no black borders); 1: keep every photo pixel."""
    input_encoding: Encoding = "auto"
    """How 8- and 16-bit values map to radiance. auto: sRGB unless the file's metadata
    names a linear colour space; float files (EXR) and RAW files are always linear."""


def _output_names(paths: list[Path]) -> dict[Path, str]:
    stems = [p.stem for p in paths]
    clashes = sorted({s for s in stems if stems.count(s) > 1})
    if clashes:
        raise PipelineError(
            f"photos {', '.join(p.name for p in paths if p.stem in clashes)} differ only in their "
            "extension: rename one of each pair, the undistorted files are named by stem"
        )
    return {p: p.stem for p in paths}


def _check_sensor_ids(photos: list[Path]) -> None:
    """Refuse two photos whose names give the scene's cameras one id."""
    ids: dict[str, Path] = {}
    for path in photos:
        same = ids.setdefault(sensor_id(path.stem), path)
        if same is not path:
            raise PipelineError(
                f"photos {same} and {path} would get the same camera id in the scene "
                f"({sensor_id(path.stem)}; ids keep only letters, digits, _ and -): rename one of them"
            )


def _decode_reduction(size: tuple[int, int], target: dict) -> int:
    """The largest power of two a photo of ``size`` can be reduced by while decoding
    and still have at least the working resolution: a 12000 px photo for a 1280 px
    working size is decoded at 1500 px, never whole."""
    reduce = 1
    while size[0] // (2 * reduce) >= target["width"] and size[1] // (2 * reduce) >= target["height"]:
        reduce *= 2
    return reduce


def decoded_camera(source: Intrinsics, reduce: int, size: tuple[int, int]) -> Intrinsics:
    """The camera of a photo box-filtered by ``reduce`` while decoding, whose upright
    size is ``size`` (the decoder drops the last rows and columns of an incomplete box)."""
    if reduce == 1:
        return source
    return replace(scaled(source, 1 / reduce, exact=True), width=size[0], height=size[1])


MIN_DISTINCT_PHOTOS = 3
"""Fewer views than this cannot be posed and carved into a specimen."""


def _check_distinct(copies: list[list[str]]) -> None:
    """Refuse a capture without enough different photos; warn about exact copies."""
    for names in copies:
        if len(names) > 1:
            logger.warning("photos %s have identical pixels: only one of them adds a view", ", ".join(names))
    if len(copies) < MIN_DISTINCT_PHOTOS:
        total = sum(len(names) for names in copies)
        raise PipelineError(
            f"images/ holds {total} photo(s) but only {len(copies)} different one(s): the pipeline needs at least "
            f"{MIN_DISTINCT_PHOTOS} photos of the specimen from different viewpoints (ideally 20 or more all around it)"
        )


def _colour_corrected(pixels: np.ndarray, metadata: dict[str, object], colour: ColourRecord) -> np.ndarray:
    """The chart's correction, times the exposure ratio to the chart's shot when EXIF
    gives both (a photo shot one stop brighter is halved)."""
    if colour.correction is None:
        return pixels
    own = exposure(metadata)
    scale = colour.exposure / own if colour.exposure is not None and own is not None else 1.0
    return np.maximum(colour.correction.apply(pixels) * np.float32(scale), np.float32(0.0))


def main(conf: Config, inputs: StageInputs, out_dir: Path) -> StageResult:
    groups = read_camera_groups(inputs.upstream["calibrate"]["calibration"])
    colour = read_colour(inputs.upstream["colour"]["colour"])
    setting_index = {group["camera"]: i for i, group in enumerate(groups)}
    image_group = {name: i for i, group in enumerate(groups) for name in group["images"]}
    cameras = []
    for group in groups:
        source = Intrinsics.from_json(group["intrinsics"])
        target = ideal_pinhole(source, conf.alpha, conf.max_size)
        cameras.append(
            {
                "camera": group["camera"],
                "calibrated_by": group["source"],
                "source": source.to_json(),
                "intrinsics": target.to_json(),
            }
        )

    folders = {"images": [], "background": []}
    for path in photo_files(list(inputs.files)):
        folders[path.relative_to(inputs.capture_dir).parts[0]].append(path)
    _check_sensor_ids(folders["images"])
    for folder in folders:
        warn_unread(inputs.capture_dir / folder)
    (out_dir / "undistorted").mkdir()
    (out_dir / "linear").mkdir()
    listing: dict[str, dict[str, dict]] = {"images": {}, "background": {}}
    same_pixels: dict[str, list[str]] = defaultdict(list)
    for folder, paths in folders.items():
        names = _output_names(paths)
        for path in progress.track(paths, f"undistorting {folder}/"):
            metadata, size = read_metadata(path)
            if folder == "images":
                index = image_group[path.name]
            else:
                setting = camera_setting(metadata, size)
                if setting not in setting_index:
                    raise PipelineError(
                        f"background/{path.name} was taken with {setting}, which no photo in images/ "
                        "uses: shoot the plate with the same camera, zoom and size, or remove it"
                    )
                index = setting_index[setting]
            reduce = _decode_reduction(size, cameras[index]["intrinsics"])
            photo = read_photo(path, conf.input_encoding, reduce)
            source = decoded_camera(Intrinsics.from_json(cameras[index]["source"]), reduce, photo.size)
            target = Intrinsics.from_json(cameras[index]["intrinsics"])
            linear = undistort(_colour_corrected(photo.pixels, metadata, colour), source, target)
            prefix = "" if folder == "images" else "background_"
            srgb_path = write_image(out_dir / "undistorted" / f"{prefix}{names[path]}.png", to_uint8(linear))
            linear_path = write_image(out_dir / "linear" / f"{prefix}{names[path]}.exr", linear.astype(np.float32))
            if folder == "images":
                same_pixels[hashlib.sha256(linear.tobytes()).hexdigest()].append(path.name)
            listing[folder][path.name] = {
                "camera": index,
                "srgb": str(srgb_path.relative_to(out_dir)),
                "linear": str(linear_path.relative_to(out_dir)),
                "encoding": photo.encoding,
                "bits": photo.bits,
            }
    _check_distinct(list(same_pixels.values()))
    pinhole = write_pinhole(out_dir / "pinhole.json", cameras, listing)
    size = cameras[0]["intrinsics"]
    logger.info(
        "undistorted %d photos and %d background plates to %dx%d",
        len(listing["images"]),
        len(listing["background"]),
        size["width"],
        size["height"],
    )
    return StageResult(
        {"pinhole": pinhole, "undistorted": out_dir / "undistorted", "linear": out_dir / "linear"},
        {
            "photos": len(listing["images"]),
            "plates": len(listing["background"]),
            "width": size["width"],
            "height": size["height"],
        },
    )


STAGE = Stage(
    name="undistort",
    version=5,
    config=Config,
    main=main,
    needs=("calibrate.calibration", "colour.colour"),
    outputs=("pinhole", "undistorted", "linear"),
    reads=("images/*", "background/*"),
)
