"""Cameras made by another tool: a COLMAP sparse model or an Agisoft Metashape
cameras XML export (``[cameras] source``).

Both are read into the pipeline's conventions (pipeline.camera.model): OpenCV
intrinsics with the first pixel's centre at (0, 0) and distortion
[k1, k2, p1, p2, k3], and world-to-camera poses (x_cam = R x_world + t, camera
looking along +z with y down) in the *source's* frame, keyed by the photo's file
name. The sfm stage then moves them into its world frame and records that
similarity, so that a mesh from the same tool (``[mesh] source``) follows.

==============  ==============================================================
format          what is read
==============  ==============================================================
COLMAP          a folder with cameras and images (``.bin`` or ``.txt``) or the
                path of one of those files; camera models SIMPLE_PINHOLE,
                PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV; pixel centres at +0.5
                in COLMAP, so cx and cy move by -0.5
Metashape       ``<sensors>`` (resolution; calibration f, cx, cy as offsets from
                the image centre, b1 affinity, k1-k3, p1, p2) and ``<cameras>``
                (``label``, ``sensor_id``, a 4x4 camera-to-chunk ``transform``),
                and the chunk's ``<transform>`` (rotation, translation, scale)
                when there is one; Metashape's P1 is OpenCV's p2 and its P2
                OpenCV's p1; pixel centres at +0.5 as in COLMAP
==============  ==============================================================

A photo is matched by its file name, or by its name without extension
(Metashape labels). Limitations: fisheye and other COLMAP models, Metashape's b2
(skew) and k4 are refused or ignored with the reason given; photos must be the
same size the tool saw (upright after EXIF orientation).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline import logger
from pipeline.camera.model import Intrinsics, Pose
from pipeline.core.errors import PipelineError
from pipeline.core.interrupts import after_native_import

PIXEL_CENTRE = 0.5
"""COLMAP and Metashape put the first pixel's centre at (0.5, 0.5); OpenCV at (0, 0)."""


@dataclass(frozen=True)
class ExternalCameras:
    """Per photo: its distorted camera and its pose in the source's frame."""

    tool: str
    intrinsics: dict[str, Intrinsics]
    poses: dict[str, Pose]


def _match_names(found: dict[str, object], photo_names: list[str], source: Path) -> dict[str, str]:
    """The source's image name for each photo in ``photo_names`` it holds."""
    by_key: dict[str, str] = {}
    for name in found:
        base = Path(name).name
        by_key.setdefault(base, name)
        by_key.setdefault(Path(base).stem, name)
    matched = {}
    for photo in photo_names:
        for key in (photo, Path(photo).stem):
            if key in by_key:
                matched[photo] = by_key[key]
                break
    if not matched:
        raise PipelineError(
            f"{source} names none of the photos in images/ (it has e.g. {', '.join(sorted(found)[:3])}): "
            "export the cameras of this capture's photos, with their file names"
        )
    return matched


def _colmap_intrinsics(camera, source: Path) -> Intrinsics:
    model = camera.model.name
    p = [float(v) for v in camera.params]
    if model == "SIMPLE_PINHOLE":
        fx = fy = p[0]
        cx, cy, dist = p[1], p[2], []
    elif model == "PINHOLE":
        fx, fy, cx, cy, dist = p[0], p[1], p[2], p[3], []
    elif model == "SIMPLE_RADIAL":
        fx = fy = p[0]
        cx, cy, dist = p[1], p[2], [p[3], 0.0, 0.0, 0.0, 0.0]
    elif model == "RADIAL":
        fx = fy = p[0]
        cx, cy, dist = p[1], p[2], [p[3], p[4], 0.0, 0.0, 0.0]
    elif model == "OPENCV":
        fx, fy, cx, cy = p[:4]
        dist = [p[4], p[5], p[6], p[7], 0.0]
    else:
        raise PipelineError(
            f"{source}: camera model {model} is not supported (use SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, "
            "RADIAL or OPENCV, e.g. `colmap image_undistorter` or a re-run with one of these)"
        )
    return Intrinsics(int(camera.width), int(camera.height), fx, fy, cx - PIXEL_CENTRE, cy - PIXEL_CENTRE, dist)


def read_colmap(source: Path, photo_names: list[str]) -> ExternalCameras:
    import pycolmap

    after_native_import()
    folder = source if source.is_dir() else source.parent
    try:
        model = pycolmap.Reconstruction(folder)
    except (RuntimeError, ValueError) as error:
        raise PipelineError(f"{folder} is not a COLMAP sparse model COLMAP can read: {error}") from error
    images = {image.name: image for image in model.images.values() if image.has_pose}
    intrinsics, poses = {}, {}
    for photo, name in _match_names(images, photo_names, source).items():
        image = images[name]
        rigid = image.cam_from_world()
        poses[photo] = Pose(np.asarray(rigid.rotation.matrix()), np.asarray(rigid.translation))
        intrinsics[photo] = _colmap_intrinsics(image.camera, source)
    return ExternalCameras("COLMAP", intrinsics, poses)


def _floats(element: ET.Element | None, tag: str, default: float = 0.0) -> float:
    found = element.find(tag) if element is not None else None
    return float(found.text) if found is not None and found.text else default


def _metashape_sensor(sensor: ET.Element, source: Path) -> Intrinsics:
    resolution = sensor.find("resolution")
    calibration = sensor.find("calibration[@class='adjusted']")
    if calibration is None:
        calibration = sensor.find("calibration")
    if resolution is None or calibration is None:
        raise PipelineError(f"{source}: sensor {sensor.get('id')} has no resolution or calibration")
    width, height = int(resolution.get("width")), int(resolution.get("height"))
    f = _floats(calibration, "f")
    cx = width / 2 + _floats(calibration, "cx") - PIXEL_CENTRE
    cy = height / 2 + _floats(calibration, "cy") - PIXEL_CENTRE
    k1, k2, k3 = (_floats(calibration, k) for k in ("k1", "k2", "k3"))
    p1, p2 = _floats(calibration, "p1"), _floats(calibration, "p2")
    return Intrinsics(width, height, f + _floats(calibration, "b1"), f, cx, cy, [k1, k2, p2, p1, k3])


def read_metashape(source: Path, photo_names: list[str]) -> ExternalCameras:
    try:
        root = ET.parse(source).getroot()
    except ET.ParseError as error:
        raise PipelineError(f"{source} is not valid XML: {error}") from error
    chunk = root.find("chunk") if root.tag != "chunk" else root
    if chunk is None:
        raise PipelineError(f"{source} has no <chunk>: export the cameras from Metashape (File > Export > Cameras)")
    sensors = {s.get("id"): _metashape_sensor(s, source) for s in chunk.iter("sensor")}
    chunk_to_world = np.eye(4)
    chunk_transform = chunk.find("transform")
    if chunk_transform is not None:
        rotation = np.array(chunk_transform.findtext("rotation", "1 0 0 0 1 0 0 0 1").split(), float).reshape(3, 3)
        translation = np.array(chunk_transform.findtext("translation", "0 0 0").split(), float)
        scale = float(chunk_transform.findtext("scale", "1"))
        chunk_to_world[:3, :3], chunk_to_world[:3, 3] = scale * rotation, translation
    cameras = {
        c.get("label"): c
        for c in chunk.iter("camera")
        if c.find("transform") is not None and c.get("enabled", "true") != "false"
    }
    intrinsics, poses = {}, {}
    for photo, label in _match_names(cameras, photo_names, source).items():
        camera = cameras[label]
        camera_to_world = chunk_to_world @ np.array(camera.findtext("transform").split(), float).reshape(4, 4)
        scale = np.cbrt(np.linalg.det(camera_to_world[:3, :3]))
        rotation = camera_to_world[:3, :3] / scale  # camera axes in the world
        centre = camera_to_world[:3, 3]
        poses[photo] = Pose(rotation.T, -rotation.T @ centre)
        intrinsics[photo] = sensors[camera.get("sensor_id")]
    return ExternalCameras("Metashape", intrinsics, poses)


def read_external_cameras(source: Path, photo_names: list[str]) -> ExternalCameras:
    """The cameras in ``source`` (format from its name and content) for ``photo_names``."""
    if source.suffix.lower() == ".xml":
        return read_metashape(source, photo_names)
    return read_colmap(source, photo_names)


def external_poses(path: Path, source: str, order: list[str]) -> tuple[dict[str, Pose], dict[str, str]]:
    """Poses of the photos ``order`` in the cameras file ``path`` (``[cameras] source`` =
    ``source``), in its frame, and why the others have none."""
    external = read_external_cameras(path, order)
    causes = {name: f"not in {source}" for name in order if name not in external.poses}
    logger.info("poses of %d of %d photos from %s (%s)", len(external.poses), len(order), source, external.tool)
    return external.poses, causes


__all__ = ["ExternalCameras", "external_poses", "read_colmap", "read_external_cameras", "read_metashape"]
