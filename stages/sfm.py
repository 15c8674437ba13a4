"""Stage sfm: camera poses of the undistorted photos, in a metric, upright world frame.

1. **Features**: SIFT (pycolmap, CPU) on undistort's 8-bit photos, each camera
   setting one COLMAP camera (SIMPLE_PINHOLE: undistorted, square pixels). Where
   features may come from is ``sfm.feature_mask``: for a turntable, only pixels
   that change between photos (what turns) plus the dilated specimen mask, so a
   still room cannot pull every pose towards "nothing moved".
2. **Matching**: exhaustive up to ``exhaustive_max_images`` photos, else sequential
   in file order with loop detection off (no vocabulary tree ships with pycolmap).
3. **Mapping**: incremental; a calibrated camera (board) stays fixed, a guessed
   one (EXIF, prior) has its focal length refined. The largest model is kept.
   Fewer than ``min_registered_fraction`` registered photos is an error that
   names the unregistered photos and the likely cause for each. A rerun gives
   the same model: photos are numbered in sorted order, RANSAC and the mapper
   are seeded, and bundle adjustment runs on one thread (COLMAP's defaults gave
   bird_volumetric rotation errors anywhere from 0.7 to 164 degrees).
4. **Turntable** (``capture.rig = "turntable"``): the poses are explained by one
   circle about one axis (pipeline.geometry.turntable), fitted to each photo's board pose
   (the board turns with the specimen) or else its SfM pose, poses off the circle
   dropped. SfM poses that disagree with the board's are not used at all: a plain
   specimen on a repetitive set makes COLMAP join photos wrongly. Photos without a
   pose get their angle from their verified feature matches with posed photos,
   else from their silhouette.
5. **World frame** (``frame``): from the ChArUco board when it is seen in at least
   three registered photos whose SfM centres agree with it (PnP per photo,
   similarity to the SfM centres; on a turntable the board poses alone do; metres,
   z up, origin at the board's centre as pipeline.camera.board.board_to_world); else from
   the turntable axis (up) and the table plane if one is found; else from a ground
   plane (the sparse points' dominant plane, lowered to where the points near the
   specimen end); else centred on where the cameras look, scaled to
   a median camera distance of 1, with z along the cameras' average up. Only the
   board gives metric scale; the stage says which frame it used.
6. **Silhouette check** (not on a turntable): a registered photo whose mask
   does not match the visual hull of the others seen from its pose is left out
   (``min_silhouette_iou``), as is a camera below the ground plane.

==================  =============================================================
output              content
==================  =============================================================
sparse/             the model in COLMAP's binary format (cameras.bin, images.bin,
                    points3D.bin, frames.bin, rigs.bin), in the world frame
cameras.json        pinhole intrinsics and pose per photo (pipeline.camera.model), with
                    the world frame's description; keyed by the original photo name
sfm.json            registered and unregistered photos (with causes), metrics,
                    board and turntable residuals
==================  =============================================================

Limitations: SIFT needs texture. A plain specimen on a plain set registers only
through the board (or, on a turntable, its matches on the table and silhouette;
the board's markers need about 10 px to decode, so below ~384 px wide a turntable
capture loses its board poses and accuracy: 0.5-2.4 degrees at 256x192). Without a board the scale
is arbitrary. A handheld photo SfM cannot register is dropped.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np

from pipeline import colmap, logger
from pipeline.camera.board import board_poses
from pipeline.camera.model import Intrinsics, Pose, Similarity
from pipeline.core.config import Range, input_file_path
from pipeline.core.errors import PipelineError
from pipeline.core.sections import BoardSection, CamerasSection, CaptureSection
from pipeline.core.stage import Stage, StageInputs, StageResult
from pipeline.formats.cameras import write_cameras
from pipeline.formats.external_cameras import read_external_cameras
from pipeline.formats.masks import read_masks
from pipeline.formats.pinhole import read_camera_settings, read_photos
from pipeline.geometry import world_frame
from pipeline.geometry.pose_check import drop_inconsistent
from pipeline.geometry.turntable_placement import PlacementSettings, turntable_poses


@dataclass(frozen=True)
class Config:
    """Structure from motion with pycolmap, and the world frame."""

    max_features: Annotated[int, Range(256, 65536)] = 8192
    """Most SIFT features kept per photo."""
    feature_mask: Literal["auto", "everywhere", "specimen", "moving"] = "auto"
    """Where features are extracted. everywhere: the whole photo (a handheld capture,
    where the set is as still as the specimen); specimen: the dilated specimen mask;
    moving: the specimen plus whatever changes between photos of a fixed camera (the
    turning table and board), not the still room. auto: moving for a turntable, else
    everywhere."""
    mask_dilation: Annotated[float, Range(0.0, 0.5)] = 0.03
    """Margin added around the specimen mask, as a fraction of the image diagonal:
    features on the silhouette's edge are among the best."""
    matcher: Literal["auto", "exhaustive", "sequential", "ring"] = "auto"
    """exhaustive: every pair; sequential: each photo with the next sequential_overlap in
    file order; ring: with the next ring_neighbours, wrapping round (a turntable's
    revolution). auto: ring for a turntable, else exhaustive up to exhaustive_max_images
    photos and sequential beyond. Exhaustive matching of a turntable finds false pairs
    between opposite sides of a repetitive set (a checkerboard from 180 degrees away)."""
    exhaustive_max_images: Annotated[int, Range(2, None)] = 150
    """Largest capture matched exhaustively (pairs grow with the square of the count)."""
    sequential_overlap: Annotated[int, Range(1, None)] = 20
    """Sequential matching: each photo is matched with this many following ones."""
    ring_neighbours: Annotated[int, Range(1, None)] = 4
    """Ring matching: each photo is matched with this many following ones, cyclically."""
    min_pose_inliers: Annotated[int, Range(6, None)] = 15
    """2D-3D inliers a photo needs to be registered (COLMAP's default, 30, leaves out
    photos of low-texture specimens that share only a few dozen points)."""
    turntable_poses: Literal["model", "measured"] = "model"
    """Turntable: model puts every photo exactly on the fitted circle (the rig allows one
    angle per photo, so per-photo noise averages out); measured keeps the board or SfM
    pose of each photo that has one."""
    min_registered_fraction: Annotated[float, Range(0.0, 1.0)] = 0.5
    """Below this fraction of registered photos the stage fails; above, it warns."""
    frame: Literal["auto", "board", "turntable", "ground_plane", "normalised"] = "auto"
    """World frame source; auto tries them in this order. Forcing one that cannot be
    found is an error."""
    board_min_corners: Annotated[int, Range(4, None)] = 8
    """Board corners a photo needs for its board pose to count."""
    board_max_error_px: Annotated[float, Range(0.0, None, exclusive_lo=True)] = 2.0
    """Board poses with a larger RMS reprojection error are ignored (a misdetection)."""
    board_max_disagreement: Annotated[float, Range(0.0, 1.0, exclusive_lo=True)] = 0.02
    """SfM is aligned to the board only when their camera centres agree to this fraction
    of the camera's distance from the board (median over photos)."""
    min_silhouette_iou: Annotated[float, Range(0.0, 1.0)] = 0.2
    """A registered photo whose mask overlaps the visual hull of the consistent photos,
    seen from its pose, by less than this (IoU) is left out: SfM posed it wrongly. Wrong poses
    score near 0 (0.00-0.04 on bird_volumetric); right poses with masks that take in
    some of the table score 0.37-0.48 (porous cube), so the default sits between."""
    silhouette_resolution: Annotated[int, Range(16, 256)] = 64
    """Voxels along the hull's longest side used to place turntable photos by silhouette."""


def _reconstruct(
    conf: Config, rig: str, photo_paths: dict[str, dict], cameras: list[dict], masks: dict[str, Path], work: Path
):
    """Features, matches and COLMAP's incremental model (or None); the database."""
    mode = conf.feature_mask if conf.feature_mask != "auto" else ("moving" if rig == "turntable" else "everywhere")
    mask_dir = colmap.feature_masks(mode, conf.mask_dilation, photo_paths, masks, work)
    matcher = conf.matcher
    if matcher == "auto":
        matcher = (
            "ring"
            if rig == "turntable"
            else "exhaustive"
            if len(photo_paths) <= conf.exhaustive_max_images
            else "sequential"
        )
    database = work / "database.db"
    image_dir = next(iter(photo_paths.values()))["srgb"].parent
    colmap.extract_and_match(
        photo_paths,
        cameras,
        mask_dir,
        image_dir,
        database,
        conf.max_features,
        matcher,
        conf.sequential_overlap,
        conf.ring_neighbours,
        still_camera=rig == "turntable",
    )
    refine_focal = any(c["source"] != "board" for c in cameras)
    model = colmap.incremental_map(database, image_dir, work / "models", refine_focal, conf.min_pose_inliers)
    return model, database, refine_focal


def _board_frame(conf: Config, board_found: dict[str, Pose], model, poses: dict[str, Pose], points, report: dict):
    """SfM's model moved into the board's frame when they agree; the board poses alone
    when they do not but the board is seen in three photos; else no frame (None).
    Returns (frame, model, poses, points)."""
    frame = world_frame.frame_from_board(conf.frame, conf.board_max_disagreement, board_found, poses, report)
    if frame is not None:
        poses = {n: frame.pose(p) for n, p in poses.items()}
        points = frame.points(points) if len(points) else points
        report["replaced_by_board"] = world_frame.replace_by_board(conf.board_max_disagreement, poses, board_found)
    elif len(board_found) >= 3 and conf.frame in ("auto", "board"):
        # The board poses alone define the world; SfM's model, not tied to them, is dropped.
        logger.warning("SfM's %d photos could not be tied to the board: using the board poses alone", len(poses))
        frame, model, poses, points = Similarity.identity(), None, {}, np.zeros((0, 3))
        report["frame"] = world_frame.board_frame(photos=len(board_found))
    return frame, model, poses, points


def main(conf: Config, inputs: StageInputs, out_dir: Path) -> StageResult:
    # Longer than 60 lines on purpose: the stage's seven steps in their order, each a few
    # calls into pipeline.colmap and pipeline.geometry; split further, the order would hide.
    # 1. The photos, their cameras and masks.
    capture: CaptureSection = inputs.shared["capture"]
    board: BoardSection = inputs.shared["board"]
    pinhole_json = inputs.upstream["undistort"]["pinhole"]
    cameras = read_camera_settings(pinhole_json)
    photo_paths = read_photos(pinhole_json, "images")
    masks = read_masks(inputs.upstream["masks"]["masks_json"])
    order = sorted(photo_paths)
    stem_of = {name: Path(photo_paths[name]["srgb"]).name for name in order}
    name_of = {stem: name for name, stem in stem_of.items()}
    intrinsics = {name: Intrinsics.from_json(cameras[photo_paths[name]["camera"]]["intrinsics"]) for name in order}

    # 2. COLMAP's model (or the poses another tool made), and the board's pose in
    # every photo that shows it.
    work = out_dir / "colmap"
    work.mkdir()
    external: CamerasSection = inputs.shared["cameras"]
    model, database, refine_focal = (
        (None, None, False) if external.source else _reconstruct(conf, capture.rig, photo_paths, cameras, masks, work)
    )
    # The board's poses with the cameras as calibrated, before SfM refines them.
    board_found, board_errors = board_poses(
        board, photo_paths, intrinsics, conf.board_min_corners, conf.board_max_error_px
    )
    if external.source:
        poses, causes = _external_poses(external.source, inputs.capture_dir, order)
    else:
        poses = colmap.registered_poses(model, name_of, intrinsics, refine_focal)
        unregistered = [n for n in order if n not in poses]
        causes = colmap.unregistered_causes(database, unregistered, stem_of) if unregistered else {}
    # A board pose is as good as a registration (in the board frame), and SfM may
    # fail on a plain specimen.
    if len(set(poses) | set(board_found)) < conf.min_registered_fraction * len(order):
        _too_few(conf, set(poses) | set(board_found), order, causes)
    points = np.array([p.xyz for p in model.points3D.values()]) if model is not None else np.zeros((0, 3))
    report: dict = {
        "poses_from": f"[cameras] source = {external.source}" if external.source else "SfM",
        "registered": len(poses),
        "photos": len(order),
        "unregistered": causes,
        "mean_reprojection_error_px": model.compute_mean_reprojection_error() if model else None,
        "mean_track_length": model.compute_mean_track_length() if model else None,
        "points": len(points),
    }

    # 3. The board's frame, when SfM agrees with it.
    frame, model, poses, points = _board_frame(conf, board_found, model, poses, points, report)
    to_world = frame or Similarity.identity()
    if frame is not None and capture.rig != "turntable":
        report["posed_by_board"] = sorted(set(board_found) - set(poses))
        poses |= {n: board_found[n] for n in report["posed_by_board"]}

    # 4. A turntable's circle, with every photo placed on it (poses another tool
    # made are taken as they are).
    table = None
    if capture.rig == "turntable" and database is not None:
        measured = {"board": board_found if frame is not None else {}, "sfm": poses}
        keypoints, matches = colmap.verified_matches(database, order, stem_of)
        settings = PlacementSettings(
            conf.min_pose_inliers, conf.silhouette_resolution, model_poses=conf.turntable_poses == "model"
        )
        table, poses, report["turntable"] = turntable_poses(
            settings, order, measured, intrinsics, masks, keypoints, matches
        )

    # 5. Without the board: the world frame from the turntable, the ground or the cameras.
    if frame is None:
        level = world_frame.frame_without_board(conf.frame, poses, points, table, report)
        poses = {n: level.pose(p) for n, p in poses.items()}
        points = level.points(points) if len(points) else points
        to_world = to_world.then(level)

    # 6. Poses the silhouettes or the table contradict are left out.
    # A turntable's placement already checked its photos against the silhouettes.
    check_silhouettes = capture.rig != "turntable"
    drop_inconsistent(
        poses, intrinsics, masks, conf.min_silhouette_iou, conf.silhouette_resolution, report, check_silhouettes
    )
    if len(poses) < conf.min_registered_fraction * len(order):
        _too_few(conf, set(poses), order, causes)
    if len(poses) < len(order):
        logger.warning(
            "%d of %d photos are not registered and are left out: %s",
            len(order) - len(poses),
            len(order),
            ", ".join(n for n in order if n not in poses),
        )

    # 7. The model, cameras.json and sfm.json.
    if database is None:
        # Where a mesh from the same tool ([mesh] source) must be moved to.
        report["frame"]["from_source"] = to_world.to_json()
        sparse = colmap.model_from_poses(intrinsics, poses, stem_of, out_dir / "sparse")
    else:
        sparse = colmap.write_model(model, database, to_world, poses, stem_of, out_dir / "sparse")
    cameras_json = out_dir / "cameras.json"
    write_cameras(cameras_json, {n: intrinsics[n] for n in poses}, poses, frame=report["frame"])
    report["board_reprojection_px"] = board_errors
    sfm_json = out_dir / "sfm.json"
    sfm_json.write_text(json.dumps(report, indent=1))
    if (work / "models").exists():
        shutil.rmtree(work / "models")
    metrics = {k: report[k] for k in ("registered", "photos", "mean_reprojection_error_px", "mean_track_length")}
    metrics["frame"] = report["frame"]["source"]
    return StageResult({"cameras": cameras_json, "sparse": sparse, "report": sfm_json}, metrics)


def _external_poses(source: str, capture_dir: Path, order: list[str]) -> tuple[dict[str, Pose], dict[str, str]]:
    """Poses from ``[cameras] source``, in its frame, and why the others have none."""
    path = input_file_path(capture_dir, source)
    external = read_external_cameras(path, order)
    causes = {name: f"not in {source}" for name in order if name not in external.poses}
    logger.info("poses of %d of %d photos from %s (%s)", len(external.poses), len(order), source, external.tool)
    return external.poses, causes


def _too_few(conf: Config, posed: set[str], order: list[str], causes: dict[str, str]) -> None:
    listing = "; ".join(
        f"{n}: {causes.get(n, 'a pose SfM got wrong (see the warnings above)')}" for n in order if n not in posed
    )
    raise PipelineError(
        f"only {len(posed)} of {len(order)} photos registered (sfm.min_registered_fraction = "
        f"{conf.min_registered_fraction}). Unregistered: {listing}. "
        "Check them with `pipeline check`; add texture or a board near the specimen, or reshoot with more overlap"
    )


STAGE = Stage(
    name="sfm",
    version=6,
    config=Config,
    main=main,
    needs=("undistort.pinhole", "masks.masks_json"),
    outputs=("cameras", "sparse", "report"),
    shared=("capture", "board", "cameras"),
    exports=("cameras",),
)
