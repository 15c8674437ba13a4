"""Stage masks: one foreground mask of the specimen per undistorted photo.

Where the masks come from, first match wins (``masks.source = "auto"``):

1. ``masks/`` in the capture: the user's own masks, one PNG per photo named like
   the photo (``view_003.png`` for ``view_003.jpg``), drawn on the original photo;
   they are undistorted like the photos. Nonzero (or > 127) is specimen.
2. ``background/`` in the capture: plates of the empty set, shot with the same
   camera. A plate named like a photo serves that photo; a camera setting with a
   single plate uses it for all its photos (a fixed camera, e.g. a turntable).
   Pixels differing from the plate by more than the noise are specimen; GrabCut
   settles shadows and colours that match the set.
3. Automatic segmentation, ``masks.segmenter``: ``set_colours`` for a turntable or a
   ring without the printed board in its photos (the default there; a board named in
   capture.toml but shot for calibration only is not on the set): the colours along
   the borders of most photos are the set's, whatever they are, and for a turntable's
   fixed camera the pixels that stay as they are while the specimen turns are too (the
   room), but where the photos show the specimen most of the time (its foot on the
   axis); its outline is then snapped to the photo's edge;
   ``neutral_backdrop`` for a specimen on a grey, white or black set (the default
   otherwise, the printed board included, which turns with the specimen): greyness
   says backdrop, colour says specimen; ``centre_prior`` for anything else: GrabCut
   seeded with the specimen near the image centre. GrabCut decides what the evidence
   leaves open.

Every mask is then cleaned: components smaller than a fraction of the largest are
removed, and holes smaller than ``max_hole_fraction`` of the silhouette filled (specimen
pixels taken for backdrop). By default every hole is: holes opened at 1 % let a
colonnade carve the hull between its columns but re-rendered worse end to end; a
ring-shaped specimen needs its hole open.

==================  ============================================================
output              content
==================  ============================================================
masks/NAME.png      8-bit mask, 255 = specimen, size of the undistorted photo
masks.json          per photo: source, foreground fraction, whether it touches
                    the image border (a cut-off specimen spoils the visual hull)
==================  ============================================================

Limitations: the automatic segmenters rely on colour. A white specimen on a white
table (or a grey one on a grey board) needs a background plate or user masks, and so
does a specimen that shares its colour with the set; the specimen's shadow on a
coloured table may be taken with it (the mesh stage cuts the hull at the table).
``pipeline check`` reports masks that cover almost nothing or almost everything.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np

from pipeline import logger
from pipeline.camera.board import found_in_any
from pipeline.camera.model import Intrinsics, undistort
from pipeline.core import progress
from pipeline.core.config import Range
from pipeline.core.errors import ConfigError, PipelineError
from pipeline.core.sections import BoardSection
from pipeline.core.stage import Stage, StageInputs, StageResult
from pipeline.formats.masks import write_masks
from pipeline.formats.pinhole import read_camera_settings, read_photos
from pipeline.imaging.photo_io import read_photo, warn_unread
from pipeline.imaging.segmentation import (
    FixedSet,
    chroma,
    clean,
    learn_fixed_sets,
    read_user_mask,
    resolve_segmenter,
    segment,
    segment_plate_difference,
)


@dataclass(frozen=True)
class Config:
    """Foreground masks: the user's, from background plates, or segmented."""

    source: Literal["auto", "user", "background", "segment"] = "auto"
    """auto: masks/ if present, else background/ plates if present, else segmentation.
    The others force one source (and fail if its files are missing)."""
    segmenter: Literal["auto", "set_colours", "neutral_backdrop", "centre_prior"] = "auto"
    """Automatic method. set_colours: the colours along the borders of most photos are the
    set's (and, on a turntable, what stays still while the specimen turns). neutral_backdrop:
    the set (table, board, sweep) is grey, white or black and the specimen is more colourful.
    centre_prior: GrabCut with the specimen near the centre. auto: set_colours for a
    turntable or ring whose photos do not show the printed board (board.kind none, or
    a board shot for calibration only: one set frames every photo), else neutral_backdrop."""
    backdrop_chroma: Annotated[float, Range(0.0, 1.0, exclusive_lo=True)] = 0.04
    """neutral_backdrop: spread of the 8-bit sRGB channels (as a fraction of 255) below
    which a pixel is surely backdrop; twice this is probably backdrop, three times surely
    specimen. Lower it for pale specimens."""
    centre_fraction: Annotated[float, Range(0.1, 1.0)] = 0.9
    """Fraction of each image side, centred, where the specimen may be; outside is backdrop."""
    background_threshold: Annotated[float, Range(1.0, None)] = 4.0
    """Background plates: difference, in noise standard deviations, above which a pixel is
    probably specimen (three times this: surely)."""
    grabcut_iterations: Annotated[int, Range(0, 20)] = 5
    """GrabCut iterations; 0 keeps the seeds as they are (plates only)."""
    working_size: Annotated[int, Range(64, 4096)] = 400
    """Longer side, in pixels, at which segmentation runs; masks are resized to the photos.
    Smaller photos are enlarged, which places their edges to a fraction of a pixel."""
    min_component_fraction: Annotated[float, Range(0.0, 1.0)] = 0.1
    """Components smaller than this fraction of the largest are dropped (dust, board bits)."""
    max_hole_fraction: Annotated[float, Range(0.0, 1.0)] = 1.0
    """Holes in the silhouette smaller than this fraction of its area (holes included)
    are filled; larger ones are kept open (the backdrop seen through the specimen: a
    handle, a colonnade, 0.01 keeps those). 0 keeps every hole, 1 fills every one."""

    def check_capture(self, name: str, capture_dir: Path) -> None:
        """A forced source whose folder holds no file is refused before anything runs."""
        folder = {"user": "masks", "background": "background"}.get(self.source)
        if folder and not any(p.is_file() and not p.name.startswith(".") for p in (capture_dir / folder).glob("*")):
            raise ConfigError(
                f"{name}.source = {self.source!r} but the capture's {folder}/ folder is empty or missing: put "
                f"the {'masks' if folder == 'masks' else 'background plates'} there, or set {name}.source = 'auto'"
            )


def _user_masks(capture_dir: Path, files: tuple[Path, ...], photos: dict[str, dict]) -> dict[str, Path]:
    by_stem = {p.stem: p for p in files if p.parent == capture_dir / "masks"}
    missing = [name for name in photos if Path(name).stem not in by_stem]
    if missing:
        raise PipelineError(
            f"masks/ has no mask for {', '.join(missing[:5])}{' ...' if len(missing) > 5 else ''}: "
            "add one PNG per photo named like it, or empty masks/ to segment automatically"
        )
    return {name: by_stem[Path(name).stem] for name in photos}


def _plates_for(photos: dict[str, dict], plates: dict[str, dict]) -> dict[str, dict]:
    by_stem = {Path(name).stem: entry for name, entry in plates.items()}
    by_camera: dict[int, list[dict]] = defaultdict(list)
    for entry in plates.values():
        by_camera[entry["camera"]].append(entry)
    chosen = {}
    for name, photo in photos.items():
        if Path(name).stem in by_stem:
            chosen[name] = by_stem[Path(name).stem]
        elif len(by_camera[photo["camera"]]) == 1:
            chosen[name] = by_camera[photo["camera"]][0]
        else:
            raise PipelineError(
                f"background/: no plate for {name} ({len(by_camera[photo['camera']])} plates for its "
                "camera): name each plate like its photo, or keep a single plate per camera setting"
            )
    return chosen


def _choose_source(conf: Config, user_masks: bool, plates: bool) -> str:
    if conf.source != "auto":
        if conf.source == "user" and not user_masks:
            raise PipelineError("masks.source = 'user' but the capture's masks/ folder is empty")
        if conf.source == "background" and not plates:
            raise PipelineError("masks.source = 'background' but the capture's background/ folder is empty")
        return conf.source
    return "user" if user_masks else "background" if plates else "segment"


@dataclass(frozen=True)
class _Source:
    """Where step 2 takes each photo's mask from."""

    kind: str
    """user, background or segment."""
    segmenter: str
    """The automatic segmenter (resolved; segment only)."""
    user_masks: dict[str, Path]
    plates: dict[str, dict]
    fixed_sets: dict[str, tuple[FixedSet, int]]
    """set_colours: each photo's camera setting's set and the photo's index in it."""


def _learn_fixed_sets(conf: Config, photos: dict[str, dict], rig: str) -> dict[str, tuple[FixedSet, int]]:
    """set_colours: the set of each camera setting, learned from all of its photos."""
    settings = []
    for camera in sorted({photo["camera"] for photo in photos.values()}):
        names = [name for name, photo in photos.items() if photo["camera"] == camera]
        srgb = (cv2.cvtColor(cv2.imread(str(photos[n]["srgb"])), cv2.COLOR_BGR2RGB) for n in names)
        settings.append((names, srgb))
    return learn_fixed_sets(settings, conf.working_size, camera_fixed=rig == "turntable")


def _mask(conf: Config, source: _Source, name: str, photo: dict, camera: dict) -> np.ndarray:
    """One photo's mask from the chosen source, cleaned."""
    target = Intrinsics.from_json(camera["intrinsics"])
    if source.kind == "user":
        user_mask = source.user_masks[name]
        drawn = read_user_mask(user_mask)
        source_camera = Intrinsics.from_json(camera["source"])
        if drawn.shape != (source_camera.height, source_camera.width):
            raise PipelineError(
                f"{user_mask} is {drawn.shape[1]}x{drawn.shape[0]} but {name} is "
                f"{source_camera.width}x{source_camera.height}: draw the mask on the original photo"
            )
        mask = undistort(drawn.astype(np.float32), source_camera, target) >= 0.5
    elif source.kind == "background":
        linear = read_photo(photo["linear"]).pixels
        mask = segment_plate_difference(
            linear,
            read_photo(source.plates[name]["linear"]).pixels,
            conf.background_threshold,
            conf.grabcut_iterations,
            conf.working_size,
        )
    else:
        srgb = cv2.cvtColor(cv2.imread(str(photo["srgb"])), cv2.COLOR_BGR2RGB)  # undistort's 8-bit copy
        mask = segment(
            srgb,
            source.segmenter,
            conf.backdrop_chroma,
            conf.centre_fraction,
            conf.grabcut_iterations,
            conf.working_size,
            source.fixed_sets.get(name),
        )
    return clean(mask, conf.min_component_fraction, conf.max_hole_fraction)


GRAYSCALE_CHROMA = 0.01
"""Largest colourfulness (pipeline.imaging.segmentation.chroma) of a grayscale photo."""


def _refuse_grayscale(photos: dict[str, dict], segmenter: str) -> None:
    """``neutral_backdrop`` tells specimen from set by colour: refuse photos without any."""
    if segmenter != "neutral_backdrop":
        return
    grey = [
        name
        for name, photo in photos.items()
        if chroma(cv2.imread(str(photo["srgb"]))).max() <= GRAYSCALE_CHROMA  # undistort's 8-bit copy
    ]
    if grey:
        raise PipelineError(
            f"{len(grey)} of {len(photos)} photos have no colour ({', '.join(grey[:5])}"
            f"{', ...' if len(grey) > 5 else ''}), and masks.segmenter = 'neutral_backdrop' finds the specimen by "
            "its colour: set masks.segmenter = 'centre_prior', add plates of the empty set in background/, "
            "or put your own masks in masks/"
        )


def _refuse_empty_masks(report: dict[str, dict], source: str) -> None:
    """Later stages carve the specimen from the masks: most of them empty is no capture."""
    empty = sorted(name for name, r in report.items() if r["coverage"] < 0.001)
    if len(empty) > len(report) / 2:
        raise PipelineError(
            f"{len(empty)} of {len(report)} masks from {source} are empty ({', '.join(empty[:5])}"
            f"{', ...' if len(empty) > 5 else ''}): the specimen was not found. Check that it is in the photos; "
            "then try masks.segmenter = 'centre_prior', background/ plates, or your own masks in masks/"
        )


def _board_in_photos(board: BoardSection, photos: dict[str, dict]) -> bool:
    """Whether any photo shows the board capture.toml names. A board shot for
    calibration only (calibration/) is not on the set the photos show, and taking it for
    the set's black and white would pick the wrong segmenter."""
    if board.kind == "none":
        return False
    images = (cv2.imread(str(photo["srgb"]), cv2.IMREAD_GRAYSCALE) for photo in photos.values())
    if found_in_any(board, images):
        return True
    logger.warning(
        "board.kind = %r, but no photo in images/ shows the board (shot for calibration only?): "
        "segmenting by the set's colours, as without a board",
        board.kind,
    )
    return False


def main(conf: Config, inputs: StageInputs, out_dir: Path) -> StageResult:
    # 1. Which source the masks come from.
    pinhole_json = inputs.upstream["undistort"]["pinhole"]
    photos, plates = read_photos(pinhole_json, "images"), read_photos(pinhole_json, "background")
    cameras = read_camera_settings(pinhole_json)
    warn_unread(inputs.capture_dir / "masks", "mask")
    has_user_masks = any(p.parent == inputs.capture_dir / "masks" for p in inputs.files)
    kind = _choose_source(conf, has_user_masks, bool(plates))
    segmenter = resolve_segmenter(
        conf.segmenter, inputs.shared["capture.rig"], lambda: _board_in_photos(inputs.shared["board"], photos)
    )
    logger.info("masks from %s", {"user": "masks/", "background": "background plates"}.get(kind, segmenter))
    if kind == "segment":
        _refuse_grayscale(photos, segmenter)
    source = _Source(
        kind,
        segmenter,
        _user_masks(inputs.capture_dir, inputs.files, photos) if kind == "user" else {},
        _plates_for(photos, plates) if kind == "background" else {},
        _learn_fixed_sets(conf, photos, inputs.shared["capture.rig"])
        if kind == "segment" and segmenter == "set_colours"
        else {},
    )

    # 2. One mask per photo, with its coverage and whether it touches the border.
    (out_dir / "masks").mkdir()
    report = {}
    for name, photo in progress.track(photos.items(), "masking"):
        mask = _mask(conf, source, name, photo, cameras[photo["camera"]])
        path = out_dir / "masks" / f"{Path(name).stem}.png"
        cv2.imwrite(str(path), mask.astype(np.uint8) * 255)
        border = np.concatenate([mask[0], mask[-1], mask[:, 0], mask[:, -1]])
        report[name] = {
            "mask": str(path.relative_to(out_dir)),
            "source": kind,
            "coverage": float(mask.mean()),
            "touches_border": bool(border.any()),
        }
        if not 0.005 <= mask.mean() <= 0.9:
            logger.warning("%s: the mask covers %.1f %% of the photo; check it in %s", name, 100 * mask.mean(), path)
    _refuse_empty_masks(report, kind)

    # 3. The listing downstream stages read (pipeline.formats.masks).
    masks_json = write_masks(out_dir / "masks.json", kind, report)
    cut_off = sorted(n for n, r in report.items() if r["touches_border"])
    if cut_off:
        logger.warning("the specimen touches the image border in %s", ", ".join(cut_off))
    coverage = [r["coverage"] for r in report.values()]
    return StageResult(
        {"masks_json": masks_json, "masks": out_dir / "masks"},
        {
            "source": kind,
            "segmenter": segmenter if kind == "segment" else None,
            "mean_coverage": float(np.mean(coverage)),
            "touching_border": len(cut_off),
        },
    )


STAGE = Stage(
    name="masks",
    version=8,
    config=Config,
    main=main,
    needs=("undistort.pinhole",),
    outputs=("masks_json", "masks"),
    reads=("masks/*",),
    shared=("capture.rig", "board"),
)
