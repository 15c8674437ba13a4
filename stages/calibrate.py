"""Stage calibrate: intrinsics and lens distortion for each camera setting in ``images/``.

Photos are grouped by camera setting (EXIF make, model and focal length, and the
image size): each group gets its own intrinsics. A group is calibrated from the
board shots in ``calibration/`` taken with the same setting; without enough of
them it falls back to the EXIF focal length, and without that to COLMAP's prior
(focal = 1.2 x the longer side), leaving the refinement to structure-from-motion.
``calibration.json`` says which source each group used. A calibration made elsewhere
(``known_intrinsics``) replaces all of that for a capture of one camera setting.

=====================  ==========================================================
output                 content
=====================  ==========================================================
calibration.json       every group: photos, source, intrinsics, RMS overall and per
                       board shot, dropped shots with the reason, focal uncertainty
intrinsics.json        intrinsics of the largest group (exported; scored by
                       ``pipeline score``)
=====================  ==========================================================

Limitations: the board is assumed flat and printed at the configured size (the
scale error of the print enters the focal length only through the board's
aspect, not at all in pixels, but it enters the sfm stage's metric scale).
Distortion is OpenCV's radial-tangential model; fisheye lenses are not supported.
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np

from pipeline import logger
from pipeline.camera.board import BoardDetection, BoardDetector
from pipeline.camera.model import Intrinsics
from pipeline.core import progress
from pipeline.core.config import InputFile, Range, input_file_path
from pipeline.core.errors import PipelineError
from pipeline.core.sections import BoardSection, CamerasSection
from pipeline.core.stage import Stage, StageInputs, StageResult
from pipeline.formats.external_cameras import read_external_cameras
from pipeline.formats.known_intrinsics import OPENCV_SUFFIXES, fitted_to, read_known_intrinsics
from pipeline.imaging.photo_io import (
    PHOTO_SUFFIXES,
    camera_setting,
    gray_uint8,
    photo_files,
    read_metadata,
    read_photo,
    warn_unread,
)

COLMAP_FOCAL_PRIOR = 1.2
"""COLMAP's default focal length guess, as a multiple of the longer image side."""
DIAGONAL_35MM = 43.27
"""Diagonal of a 36 x 24 mm frame; EXIF's 35 mm-equivalent focal length refers to it."""
_MM_PER_UNIT = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}  # EXIF FocalPlaneResolutionUnit


@dataclass(frozen=True)
class Config:
    """Camera calibration from board shots, with EXIF and self-calibration fallbacks."""

    min_corners: Annotated[int, Range(4, 1000)] = 8
    """Board corners a shot must show to be used; fewer constrain distortion poorly."""
    min_shots: Annotated[int, Range(3, 200)] = 4
    """Usable board shots a camera setting needs; with fewer it falls back to EXIF."""
    distortion: Literal["radial2", "radial_tangential", "full"] = "radial_tangential"
    """Distortion terms estimated. radial2: k1, k2. radial_tangential: k1, k2, p1, p2.
    full: also k3, which trades off against k2 unless the shots reach the frame's corners."""
    outlier_factor: Annotated[float, Range(1.0, None)] = 3.0
    """A shot whose RMS reprojection error exceeds this multiple of the median is dropped
    (one at a time, worst first, recalibrating after each)."""
    outlier_floor_px: Annotated[float, Range(0.0, None)] = 0.5
    """Shots below this RMS (pixels) are never dropped, however small the median."""
    sensor_width_mm: Annotated[float, Range(0.0, None)] = 0.0
    """Long side of the sensor in mm, for the EXIF fallback when the photos carry a focal
    length in mm but no focal-plane resolution; 0 when unknown."""
    known_intrinsics: Annotated[str, InputFile(suffixes=(".json", *OPENCV_SUFFIXES))] = ""
    """A calibration made elsewhere (a lab's, or another capture's intrinsics.json) for
    every photo in images/, relative to the capture folder: JSON or OpenCV YAML/XML
    (pipeline/formats/known_intrinsics.py). It replaces board shots and EXIF, is scaled
    to photos of the same frame at another resolution, and sfm holds it fixed. Empty:
    the board, EXIF or self-calibration as above."""


@dataclass
class BoardCalibration:
    intrinsics: Intrinsics
    rms_px: float
    shot_rms_px: dict[str, float]
    dropped: dict[str, str]
    focal_std_px: float


def _distortion_flags(model: str) -> int:
    return {
        "radial2": cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3,
        "radial_tangential": cv2.CALIB_FIX_K3,
        "full": 0,
    }[model]


@contextmanager
def _one_opencv_thread():
    """Threaded calibration adds up in a varying order: the intrinsics then differ in
    the 11th digit from run to run, and every later stage inherits the difference."""
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(threads)


def calibrate_from_board(
    detections: dict[str, BoardDetection], size: tuple[int, int], conf: Config
) -> BoardCalibration:
    """OpenCV calibration, dropping the worst outlier shot until none is left."""
    kept = dict(detections)
    dropped: dict[str, str] = {}
    while True:
        names = sorted(kept)
        object_points = [kept[n].object_points.astype(np.float32) for n in names]
        image_points = [kept[n].image_points.astype(np.float32) for n in names]
        with _one_opencv_thread():
            rms, K, dist, rvecs, tvecs, std_intrinsics, _, per_view = cv2.calibrateCameraExtended(
                object_points, image_points, size, None, None, flags=_distortion_flags(conf.distortion)
            )
        shot_rms = dict(zip(names, per_view.ravel().tolist()))
        limit = max(conf.outlier_factor * float(np.median(per_view)), conf.outlier_floor_px)
        worst = max(shot_rms, key=shot_rms.get)
        if shot_rms[worst] <= limit or len(kept) <= conf.min_shots:
            break
        dropped[worst] = f"RMS {shot_rms[worst]:.2f} px > {limit:.2f} px ({conf.outlier_factor} x median)"
        del kept[worst]
    dist = np.asarray(dist, dtype=float).ravel()[:5]
    intrinsics = Intrinsics(size[0], size[1], K[0, 0], K[1, 1], K[0, 2], K[1, 2], dist.tolist())
    focal_std = float(np.hypot(std_intrinsics[0, 0], std_intrinsics[1, 0]) / math.sqrt(2))
    return BoardCalibration(intrinsics, float(rms), shot_rms, dropped, focal_std)


def exif_focal_px(
    metadata: dict[str, object], size: tuple[int, int], sensor_width_mm: float
) -> tuple[float, str] | None:
    """Focal length in pixels from EXIF, and how it was derived; None without EXIF."""
    focal_mm = float(metadata.get("Exif:FocalLength") or 0)
    resolution = float(metadata.get("Exif:FocalPlaneXResolution") or 0)
    unit = int(metadata.get("Exif:FocalPlaneResolutionUnit") or 2)
    if focal_mm and resolution and unit in _MM_PER_UNIT:
        return focal_mm * resolution / _MM_PER_UNIT[unit], "EXIF focal length and focal-plane resolution"
    if focal_mm and sensor_width_mm:
        return focal_mm * max(size) / sensor_width_mm, "EXIF focal length and calibrate.sensor_width_mm"
    focal_35mm = float(metadata.get("Exif:FocalLengthIn35mmFilm") or 0)
    if focal_35mm:
        return focal_35mm * math.hypot(*size) / DIAGONAL_35MM, "EXIF 35 mm-equivalent focal length"
    return None


def _folder(path: Path, capture_dir: Path) -> str:
    return path.relative_to(capture_dir).parts[0]


def _group_by_setting(paths: list[Path]) -> dict[str, list[tuple[Path, dict]]]:
    groups: dict[str, list[tuple[Path, dict]]] = defaultdict(list)
    for path in paths:
        metadata, size = read_metadata(path)
        groups[camera_setting(metadata, size)].append((path, metadata | {"size": size}))
    return groups


def _detect_shots(shots: list[tuple[Path, dict]], board: BoardSection, conf: Config):
    detector = BoardDetector(board, min_corners=conf.min_corners)
    detections: dict[str, BoardDetection] = {}
    rejected: dict[str, str] = {}
    for path, _ in progress.track(shots, "detecting the board"):
        found = detector.detect(gray_uint8(read_photo(path).pixels))
        if found is None:
            rejected[path.name] = f"board not found, or fewer than {conf.min_corners} corners"
        else:
            detections[path.name] = found
    return detections, rejected


def calibrate_group(
    setting: str, photos: list[tuple[Path, dict]], shots: list[tuple[Path, dict]], board: BoardSection, conf: Config
) -> dict:
    size = photos[0][1]["size"]
    metadata = photos[0][1]
    group: dict = {"camera": setting, "images": [p.name for p, _ in photos], "board_shots": len(shots)}
    if shots and board.kind != "none":
        detections, rejected = _detect_shots(shots, board, conf)
        if len(detections) >= conf.min_shots:
            result = calibrate_from_board(detections, size, conf)
            logger.info(
                "%s: calibrated from %d board shots, RMS %.3f px, focal %.2f ± %.2f px",
                setting,
                len(detections) - len(result.dropped),
                result.rms_px,
                result.intrinsics.fx,
                result.focal_std_px,
            )
            for name, reason in {**rejected, **result.dropped}.items():
                logger.warning("calibration/%s not used: %s", name, reason)
            return group | {
                "source": "board",
                "refine_in_sfm": False,
                "intrinsics": result.intrinsics.to_json(),
                "rms_px": result.rms_px,
                "focal_std_px": result.focal_std_px,
                "shots_used": len(detections) - len(result.dropped),
                "shots": {
                    name: {"corners": len(d.ids), "rms_px": result.shot_rms_px.get(name)}
                    for name, d in sorted(detections.items())
                },
                "dropped": {**rejected, **result.dropped},
            }
        logger.warning(
            "%s: only %d of %d board shots are usable (calibrate.min_shots = %d); falling back. "
            "Shoot the board closer and from more angles, or check the [board] section.",
            setting,
            len(detections),
            len(shots),
            conf.min_shots,
        )
    focal = exif_focal_px(metadata, size, conf.sensor_width_mm)
    if focal is None:
        focal_px, source, how = COLMAP_FOCAL_PRIOR * max(size), "prior", "no EXIF focal length: COLMAP's prior"
    else:
        (focal_px, how), source = focal, "exif"
    logger.info("%s: focal %.1f px from %s; sfm will refine it", setting, focal_px, how)
    intrinsics = Intrinsics(size[0], size[1], focal_px, focal_px, (size[0] - 1) / 2, (size[1] - 1) / 2)
    return group | {"source": source, "how": how, "refine_in_sfm": True, "intrinsics": intrinsics.to_json()}


def known_group(setting: str, photos: list[tuple[Path, dict]], shots: int, known: Intrinsics, source: Path) -> dict:
    """A camera setting with the given calibration, fitted to its photos' size."""
    intrinsics = fitted_to(known, photos[0][1]["size"], source, "calibrate.known_intrinsics")
    if shots:
        logger.warning("%s: %d board shots not used: calibrate.known_intrinsics gives the intrinsics", setting, shots)
    logger.info("%s: intrinsics from %s (focal %.1f px), held fixed", setting, source, intrinsics.fx)
    return {
        "camera": setting,
        "images": [p.name for p, _ in photos],
        "board_shots": shots,
        "source": "known",
        "how": f"calibrate.known_intrinsics = {source}",
        "refine_in_sfm": False,
        "intrinsics": intrinsics.to_json(),
    }


def _external_groups(
    source: str, capture_dir: Path, photo_groups: dict[str, list[tuple[Path, dict]]]
) -> tuple[list[dict], dict[str, list[tuple[Path, dict]]]]:
    """Groups of the photos the external cameras hold, one per distinct camera, and
    the photo groups left for calibration (photos the source does not hold)."""
    path = input_file_path(capture_dir, source)
    sizes = {p.name: meta["size"] for members in photo_groups.values() for p, meta in members}
    external = read_external_cameras(path, sorted(sizes))
    by_camera: dict[str, list[str]] = defaultdict(list)
    for name, intrinsics in sorted(external.intrinsics.items()):
        if (intrinsics.width, intrinsics.height) != tuple(sizes[name]):
            raise PipelineError(
                f"{path} has {name} at {intrinsics.width}x{intrinsics.height}, but images/{name} is "
                f"{sizes[name][0]}x{sizes[name][1]}: give the photos the tool saw, at their size"
            )
        by_camera[json.dumps(intrinsics.to_json(), sort_keys=True)].append(name)
    groups = [
        {
            "camera": f"{external.tool} camera {index + 1}",
            "images": names,
            "board_shots": 0,
            "source": "external",
            "how": f"{external.tool} cameras in {source}",
            "refine_in_sfm": False,
            "intrinsics": json.loads(key),
        }
        for index, (key, names) in enumerate(sorted(by_camera.items(), key=lambda item: -len(item[1])))
    ]
    logger.info("intrinsics of %d photos from %s (%d camera(s))", len(external.intrinsics), path, len(groups))
    left = {
        setting: kept
        for setting, members in photo_groups.items()
        if (kept := [(p, meta) for p, meta in members if p.name not in external.intrinsics])
    }
    if left:
        logger.warning(
            "%s holds no camera for %d photo(s) (%s): they are calibrated as usual and will lack a pose",
            path,
            sum(len(m) for m in left.values()),
            ", ".join(p.name for m in left.values() for p, _ in m[:3]),
        )
    return groups, left


def main(conf: Config, inputs: StageInputs, out_dir: Path) -> StageResult:
    files = photo_files(list(inputs.files))
    photos = [p for p in files if _folder(p, inputs.capture_dir) == "images"]
    shots = [p for p in files if _folder(p, inputs.capture_dir) == "calibration"]
    warn_unread(inputs.capture_dir / "calibration")
    if not photos:
        raise PipelineError(
            f"{inputs.capture_dir / 'images'} has no photos ({', '.join(PHOTO_SUFFIXES)}): "
            "put the specimen photos there (`pipeline new` sets up a capture)"
        )
    board: BoardSection = inputs.shared["board"]
    photo_groups, shot_groups = _group_by_setting(photos), _group_by_setting(shots)
    for setting, unmatched in shot_groups.items():
        if setting not in photo_groups:
            logger.warning(
                "%d board shots (%s, ...) were taken with %s, which no photo in images/ uses; ignored",
                len(unmatched),
                unmatched[0][0].name,
                setting,
            )
    cameras: CamerasSection = inputs.shared["cameras"]
    groups = []
    if cameras.source:
        groups, photo_groups = _external_groups(cameras.source, inputs.capture_dir, photo_groups)
    largest_first = sorted(photo_groups.items(), key=lambda item: -len(item[1]))
    if conf.known_intrinsics and largest_first:
        source = input_file_path(inputs.capture_dir, conf.known_intrinsics)
        known = read_known_intrinsics(source, "calibrate.known_intrinsics")
        if len(largest_first) > 1:
            raise PipelineError(
                f"calibrate.known_intrinsics gives one camera, but images/ holds photos of {len(largest_first)} camera "
                f"settings ({'; '.join(setting for setting, _ in largest_first)}): keep the photos of the calibrated "
                "setting only, or leave calibrate.known_intrinsics empty"
            )
        ((setting, members),) = largest_first
        groups.append(known_group(setting, members, len(shot_groups.get(setting, [])), known, source))
    else:
        groups += [
            calibrate_group(setting, members, shot_groups.get(setting, []), board, conf)
            for setting, members in largest_first
        ]
    calibration = out_dir / "calibration.json"
    calibration.write_text(json.dumps({"groups": groups}, indent=1))
    intrinsics = out_dir / "intrinsics.json"
    intrinsics.write_text(json.dumps(groups[0]["intrinsics"], indent=1))
    metrics = {
        "camera_settings": len(groups),
        "source": groups[0]["source"],
        "focal_px": groups[0]["intrinsics"]["fx"],
    }
    if groups[0]["source"] == "board":
        metrics |= {"rms_px": groups[0]["rms_px"], "shots_used": groups[0]["shots_used"]}
    return StageResult({"calibration": calibration, "intrinsics": intrinsics}, metrics)


STAGE = Stage(
    name="calibrate",
    version=3,
    config=Config,
    main=main,
    outputs=("calibration", "intrinsics"),
    reads=("images/*", "calibration/*"),
    shared=("board", "cameras"),
    exports=("calibration", "intrinsics"),
)
