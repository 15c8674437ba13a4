"""Stage sfm: camera poses of the undistorted photos, in a metric, upright world frame.

1. **Features and matches** (pipeline.features.features_and_matches): SIFT on
   undistort's 8-bit photos, upsampled and DSP-SIFT on small photos; for a
   turntable only from what changes between photos (the still room masked out) and
   matched with ring neighbours, else exhaustively (sequentially past 150 photos).
2. **Poses.** Handheld: COLMAP's incremental mapping; a camera the board
   calibrated stays fixed, a guessed one (EXIF, prior) has its focal length
   refined, and principal point and radial distortion when the photos constrain
   them (pipeline.camera.self_calibration; values, deviations and decisions in
   sfm.json). Turntable and ring (``capture.rig``): the rig is the model
   (pipeline.geometry.circular_motion): one axis, one camera offset, one angle per
   photo, bundle-adjusted with the focal length and distortion, each photo's angle
   uncertainty reported; an arc of the ring that matching left apart is placed by
   its silhouettes at once, a photo the features cannot place by its board pose, by
   even steps (a timed table) or by its silhouette, else left out with a warning
   naming it (pipeline.geometry.turntable_placement). Fewer than ``min_registered_fraction``
   posed photos is an error naming the others and the likely cause for each. A
   rerun gives the same model: photos are numbered in sorted order, RANSAC and
   the mapper are seeded, and bundle adjustment runs on one thread (with COLMAP's
   threaded defaults, reruns gave different poses).
3. **World frame** (``frame``): from the ChArUco board when it is seen in at least
   three registered photos whose SfM centres agree with it (PnP per photo,
   similarity to the SfM centres; metres, z up, origin at the board's centre as
   pipeline.camera.board.board_to_world); else from the turntable axis (up) and the
   table plane if one is found; else from a ground plane (the sparse points'
   dominant plane, lowered to where the points near the specimen end); else
   centred on where the cameras look, scaled to a median camera distance of 1,
   with z along the cameras' average up. Only the board gives metric scale; the
   stage says which frame it used.
4. **Silhouette check** (handheld): a registered photo whose mask does not match
   the visual hull of the others seen from its pose is left out
   (``min_silhouette_iou``, when the masks agree well enough to judge), as is a
   camera below the ground plane.

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
through the board (or, on a turntable, its matches on the table and its
silhouette). Without a board the scale is arbitrary. A handheld photo SfM cannot
register is dropped. Self-calibrated radial distortion improves the poses and is
reported, but the photos stay as undistort made them (pinhole, without it): the
stage warns when it displaces the specimen's outline by more than half a pixel
(board shots in calibration/ let undistort remove it).
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np

from pipeline import logger
from pipeline.camera.board import board_poses
from pipeline.camera.model import Intrinsics, Similarity
from pipeline.camera.self_calibration import SelfCalibrationSettings, outline_shift_px
from pipeline.colmap import COLMAP_PIXEL_OFFSET, features, mapping, model_io
from pipeline.core.config import Range, input_file_path
from pipeline.core.errors import PipelineError
from pipeline.core.sections import BoardSection, CamerasSection
from pipeline.core.stage import Stage, StageInputs, StageResult
from pipeline.formats.cameras import write_cameras
from pipeline.formats.external_cameras import external_poses
from pipeline.formats.masks import read_masks
from pipeline.formats.pinhole import read_camera_settings, read_photos
from pipeline.geometry import world_frame
from pipeline.geometry.pose_check import drop_inconsistent
from pipeline.geometry.turntable_placement import PlacementSettings, RigSettings, circular_poses


@dataclass(frozen=True)
class Config(features.FeatureSettings, RigSettings, SelfCalibrationSettings):
    """Structure from motion with pycolmap (or the rig's circular motion), and the world frame."""

    min_pose_inliers: Annotated[int, Range(6, None)] = 15
    """2D-3D inliers a photo needs to be registered (COLMAP's default, 30, leaves out
    photos of low-texture specimens that share only a few dozen points); on a turntable
    or ring, the inlier observations that place a photo by its features."""
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
    score near 0; right poses with masks that take in some of the table score about 0.4,
    so the default sits between."""
    min_mask_agreement: Annotated[float, Range(0.0, 1.0)] = 0.5
    """The silhouette check leaves photos out only when the masks agree with the visual hull
    at least this well (median IoU of the photos it is made of): poor masks would drop right
    poses (a white cube on a white table agrees at 0.26; good masks at 0.8-0.95)."""
    silhouette_resolution: Annotated[int, Range(16, 256)] = 64
    """Voxels along the hull's longest side of the silhouette check."""


def _note(report: dict, **entries) -> None:
    """Record in sfm.json the entries a step found (None: the step had nothing to say)."""
    report.update({name: value for name, value in entries.items() if value is not None})


def main(conf: Config, inputs: StageInputs, out_dir: Path) -> StageResult:
    # Longer than 60 lines on purpose: the stage's steps in their order, each a few
    # calls into pipeline.colmap and pipeline.geometry; split further, the order would hide.
    # 1. The photos, their cameras and masks; the board's poses with the cameras as calibrated.
    rig: str = inputs.shared["capture.rig"]
    pinhole_json = inputs.upstream["undistort"]["pinhole"]
    cameras = read_camera_settings(pinhole_json)
    photos = read_photos(pinhole_json, "images")
    masks = read_masks(inputs.upstream["masks"]["masks_json"])
    order = sorted(photos)
    stem_of = {name: Path(photos[name]["srgb"]).name for name in order}
    intrinsics = {name: Intrinsics.from_json(cameras[photos[name]["camera"]]["intrinsics"]) for name in order}
    board: BoardSection = inputs.shared["board"]
    board_found, board_errors = board_poses(board, photos, intrinsics, conf.board_min_corners, conf.board_max_error_px)
    # A camera the board calibrated stays as it is; a guessed one (EXIF, prior) is refined.
    refine_focal = any(c["calibrated_by"] not in ("board", "external") for c in cameras)
    circular = rig in ("turntable", "ring")

    # 2. The poses: another tool's, the rig's circular motion, or COLMAP's incremental model.
    external: CamerasSection = inputs.shared["cameras"]
    work = out_dir / "colmap"
    work.mkdir()
    report: dict = {"photos": len(order)}
    model, database, table, solution, points = None, None, None, None, np.zeros((0, 3))
    if external.source:
        poses, causes = external_poses(input_file_path(inputs.capture_dir, external.source), external.source, order)
        report["poses_from"] = f"[cameras] source = {external.source}"
    elif circular:
        database = features.features_and_matches(conf, rig, photos, cameras, masks, work)
        keypoints, matches = features.verified_matches(database, order, stem_of)
        settings = PlacementSettings.of(conf, conf, rig == "turntable", conf.min_pose_inliers, refine_focal)
        table, poses, solution, report["circular"] = circular_poses(
            settings, order, intrinsics, masks, keypoints, matches, board_found
        )
        intrinsics = {name: solution.intrinsics.without_distortion() for name in order}
        causes, points = report["circular"]["unplaced"], solution.points
        report |= {"poses_from": f"circular motion ({rig})", "points": len(points)}
        report["mean_reprojection_error_px"] = report["circular"]["reprojection_error_px_median"]
        report["mean_track_length"] = float(np.mean([len(t) for t in solution.tracks])) if solution.tracks else None
        residual_k1 = [
            (solution.intrinsics.fx, solution.intrinsics.cx, solution.intrinsics.cy, solution.intrinsics.dist[0])
        ]
    else:
        database = features.features_and_matches(conf, rig, photos, cameras, masks, work)
        image_dir = next(iter(photos.values()))["srgb"].parent
        model = mapping.incremental_map(database, image_dir, work / "models", refine_focal, conf.min_pose_inliers)
        if model is not None and refine_focal and conf.self_calibrate:
            report["self_calibration"] = mapping.self_calibrate(model, conf)
        poses = mapping.registered_poses(model, {s: n for n, s in stem_of.items()}, intrinsics, refine_focal)
        unregistered = [n for n in order if n not in poses]
        causes = features.unregistered_causes(database, unregistered, stem_of) if unregistered else {}
        points = np.array([p.xyz for p in model.points3D.values()]).reshape(-1, 3) if model else points
        report |= {"poses_from": "SfM", "points": len(points), **mapping.model_metrics(model)}
        offset = COLMAP_PIXEL_OFFSET
        cameras_params = [c.params for c in model.cameras.values()] if model else []
        residual_k1 = [(f, cx - offset, cy - offset, k1) for f, cx, cy, k1 in cameras_params]
    # A board pose is as good as a registration (in the board frame), and SfM may
    # fail on a plain specimen.
    if len(set(poses) | set(board_found)) < conf.min_registered_fraction * len(order):
        _too_few(conf, set(poses) | set(board_found), order, causes)
    report |= {"registered": len(poses), "unregistered": causes}
    if database is not None:
        _residual_distortion(report, residual_k1, list(masks.values()))

    # 3. The world frame: the board's when the poses agree with it, else the turntable's,
    # the ground's or the cameras'.
    tie = world_frame.tie_to_board(conf.frame, conf.board_max_disagreement, board_found, poses, points, circular)
    frame, poses, points = tie.frame, tie.poses, tie.points
    model = None if tie.dropped else model
    _note(report, frame=tie.record, replaced_by_board=tie.replaced_by_board)
    to_world = frame or Similarity.identity()
    if frame is not None and not circular:
        report["posed_by_board"] = sorted(set(board_found) - set(poses))
        poses |= {n: board_found[n] for n in report["posed_by_board"]}
    if frame is None:
        level, report["frame"] = world_frame.frame_without_board(conf.frame, poses, points, table)
        poses = {n: level.pose(p) for n, p in poses.items()}
        points = level.points(points) if len(points) else points
        to_world = to_world.then(level)

    # 4. Poses the silhouettes or the table contradict are left out (the circular
    # placement checked its photos against the silhouettes already).
    check = (conf.min_silhouette_iou, conf.silhouette_resolution, conf.min_mask_agreement)
    consistent = drop_inconsistent(
        poses, intrinsics, masks, *check, report["frame"].get("ground_plane") is not None, not circular
    )
    poses = consistent.kept
    _note(report, silhouette_iou=consistent.silhouette_iou, below_ground=consistent.below_ground)
    if len(poses) < conf.min_registered_fraction * len(order):
        _too_few(conf, set(poses), order, causes)
    if len(poses) < len(order):
        logger.warning(
            "%d of %d photos are not registered and are left out: %s",
            len(order) - len(poses),
            len(order),
            ", ".join(n for n in order if n not in poses),
        )

    # 5. The model, cameras.json and sfm.json.
    sparse = out_dir / "sparse"
    if database is None:
        # Where a mesh from the same tool ([mesh] source) must be moved to.
        report["frame"]["from_source"] = to_world.to_json()
        model_io.model_from_poses(intrinsics, poses, stem_of, sparse)
    elif solution is not None:
        model_io.model_from_tracks(database, solution.intrinsics, poses, points, solution.tracks, stem_of, sparse)
    else:
        model_io.write_model(model, database, to_world, poses, stem_of, sparse)
    cameras_json = out_dir / "cameras.json"
    write_cameras(cameras_json, {n: intrinsics[n] for n in poses}, poses, frame=report["frame"])
    report["board_reprojection_px"] = board_errors
    sfm_json = out_dir / "sfm.json"
    sfm_json.write_text(json.dumps(report, indent=1))
    if (work / "models").exists():
        shutil.rmtree(work / "models")
    metrics = {k: report.get(k) for k in ("registered", "photos", "mean_reprojection_error_px", "mean_track_length")}
    metrics["frame"] = report["frame"]["source"]
    return StageResult({"cameras": cameras_json, "sparse": sparse, "report": sfm_json}, metrics)


def _residual_distortion(report: dict, cameras: list[tuple], masks: list[Path]) -> None:
    """Radial distortion self-calibration found in the undistorted photos (used
    without it), and how far it moves the specimen's outline: a warning past half a pixel."""
    for focal, cx, cy, k1 in cameras:
        if k1 == 0:
            continue
        shift = outline_shift_px(k1, focal, cx, cy, masks)
        report["residual_distortion"] = {"k1": float(k1), "specimen_shift_px": shift}
        if shift > 0.5:
            logger.warning(
                "self-calibration found radial distortion (k1 = %.4f) that moves the specimen's outline by up to "
                "%.1f px; the photos are used without correcting it: add board shots to calibration/ so that "
                "undistort removes it",
                k1,
                shift,
            )


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
    version=11,
    config=Config,
    main=main,
    needs=("undistort.pinhole", "masks.masks_json"),
    outputs=("cameras", "sparse", "report"),
    shared=("capture.rig", "board", "cameras"),
    exports=("cameras",),
)
