"""COLMAP models from and to the pipeline's cameras: writing a model, models from
known poses or tracks, and the trusted sparse points."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap

from pipeline.camera.model import Intrinsics, Pose, Similarity
from pipeline.colmap import COLMAP_PIXEL_OFFSET


def write_model(
    model: pycolmap.Reconstruction | None,
    database: Path,
    to_world: Similarity,
    poses: dict[str, Pose],
    stem_of: dict[str, str],
    folder: Path,
) -> Path:
    """The model in the world frame with the final poses (turntable-placed photos
    registered too, without observations), in COLMAP's binary format. The points
    stay where SfM triangulated them."""
    if model is None:  # SfM failed or disagreed with the board: cameras and poses only
        model = pycolmap.Reconstruction()
    model.transform(pycolmap.Sim3d(to_world.scale, pycolmap.Rotation3d(to_world.R), to_world.t))
    with pycolmap.Database.open(database) as db:
        for name, pose in poses.items():
            rigid = pycolmap.Rigid3d(pycolmap.Rotation3d(pose.R), pose.t)
            image = model.find_image_with_name(stem_of[name])
            if image is not None:
                model.frame(image.frame_id).rig_from_world = rigid
                continue
            stored = db.read_image_with_name(stem_of[name])
            if not model.exists_camera(stored.camera_id):
                model.add_camera_with_trivial_rig(db.read_camera(stored.camera_id))
            model.add_image_with_trivial_frame(
                pycolmap.Image(name=stored.name, camera_id=stored.camera_id, image_id=stored.image_id), rigid
            )
    folder.mkdir()
    model.write_binary(folder)
    return folder


def model_from_poses(
    intrinsics: dict[str, Intrinsics], poses: dict[str, Pose], stem_of: dict[str, str], folder: Path
) -> Path:
    """A COLMAP model holding only cameras and poses (cameras another tool made), in
    COLMAP's binary format: one PINHOLE camera per distinct intrinsics."""
    model = pycolmap.Reconstruction()
    camera_ids: dict[tuple, int] = {}
    for image_id, (name, pose) in enumerate(sorted(poses.items()), start=1):
        K = intrinsics[name]
        params = (K.fx, K.fy, K.cx + COLMAP_PIXEL_OFFSET, K.cy + COLMAP_PIXEL_OFFSET)
        key = (K.width, K.height, *params)
        if key not in camera_ids:
            camera_ids[key] = len(camera_ids) + 1
            model.add_camera_with_trivial_rig(
                pycolmap.Camera(
                    model="PINHOLE", width=K.width, height=K.height, params=list(params), camera_id=camera_ids[key]
                )
            )
        image = pycolmap.Image(name=stem_of[name], camera_id=camera_ids[key], image_id=image_id)
        model.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(pose.R), pose.t))
    folder.mkdir()
    model.write_binary(folder)
    return folder


def model_from_tracks(
    database: Path,
    intrinsics: Intrinsics,
    poses: dict[str, Pose],
    points: np.ndarray,
    tracks: list[dict[str, int]],
    stem_of: dict[str, str],
    folder: Path,
) -> Path:
    """A COLMAP model of one camera (SIMPLE_RADIAL: the pinhole and k1 of
    ``intrinsics``), the posed photos with their keypoints from ``database``, and
    ``points`` with their ``tracks`` (photo name -> keypoint index), in COLMAP's binary
    format; every point's reprojection error is computed."""
    model = pycolmap.Reconstruction()
    K = intrinsics
    camera = pycolmap.Camera(
        model="SIMPLE_RADIAL",
        width=K.width,
        height=K.height,
        params=[K.fx, K.cx + COLMAP_PIXEL_OFFSET, K.cy + COLMAP_PIXEL_OFFSET, K.dist[0]],
        camera_id=1,
    )
    model.add_camera_with_trivial_rig(camera)
    image_ids = {}
    with pycolmap.Database.open(database) as db:
        for image_id, name in enumerate(sorted(poses), start=1):
            stored = db.read_image_with_name(stem_of[name])
            keypoints = db.read_keypoints(stored.image_id)[:, :2].astype(float)
            image = pycolmap.Image(name=stem_of[name], keypoints=keypoints, camera_id=1, image_id=image_id)
            pose = poses[name]
            model.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(pose.R), pose.t))
            image_ids[name] = image_id
    for xyz, track in zip(points, tracks):
        elements = pycolmap.Track()
        for name, keypoint in track.items():
            elements.add_element(image_ids[name], keypoint)
        model.add_point3D(np.asarray(xyz, float), elements)
    model.update_point_3d_errors()
    folder.mkdir()
    model.write_binary(folder)
    return folder


def trusted_points(sparse: Path, min_track_length: int, max_error_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The model's points seen by at least ``min_track_length`` photos with at most
    ``max_error_px`` reprojection error and, for each, the mean direction towards the
    cameras that saw it."""
    model = pycolmap.Reconstruction(sparse)
    centres = {image_id: image.projection_center() for image_id, image in model.images.items() if image.has_pose}
    points, towards = [], []
    for point in model.points3D.values():
        if point.track.length() < min_track_length or point.error > max_error_px:
            continue
        directions = [centres[e.image_id] - point.xyz for e in point.track.elements if e.image_id in centres]
        directions = [d / np.linalg.norm(d) for d in directions]
        points.append(point.xyz)
        towards.append(np.mean(directions, axis=0))
    return np.reshape(points, (-1, 3)), np.reshape(towards, (-1, 3))
