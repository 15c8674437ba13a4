"""Stage sfm: camera poses of the undistorted photos, in a metric, upright world frame.

1. **Features and matches** (pipeline.colmap.features): SIFT on
   undistort's 8-bit photos, upsampled and DSP-SIFT on small photos; for a
   turntable only from what changes between photos (the still room masked out) and
   matched with ring neighbours, with the photos whose outlines look alike (a
   second turn) and with those that share the most descriptors on the specimen
   (another set), else exhaustively (sequentially past 150 photos).
2. **Poses.** Handheld: COLMAP's incremental mapping; a calibrated camera (board,
   ``calibrate.known_intrinsics``) stays fixed, a guessed one (EXIF, prior) has its
   focal length refined, and principal point and radial distortion when the photos
   constrain them (pipeline.camera.self_calibration; values, deviations and
   decisions in sfm.json). Turntable and ring (``capture.rig``): the rig is the
   model (pipeline.geometry.circular_motion): one axis, one camera offset, one angle
   per photo, bundle-adjusted with the focal length and distortion and with the
   silhouette coherence of the photos' outlines (``silhouette_coherence``), each
   photo's angle uncertainty reported. Where pairs of ``min_pose_inliers`` leave
   photos out of the ring, weak pairs (a dozen matches one turn explains, verified
   or not) are tried, and their ring kept only where the outlines agree with it
   (sfm.json ``weak_pairs``); an arc of the ring that matching left apart
   is joined to it where its outlines fix its offset and the ring solved with both
   agrees with them (sfm.json ``joined_groups``), else placed by its silhouettes at
   once (marked uncertain: outlines alone); a photo the features cannot place by its
   board pose, by even steps (a timed table) or by its silhouette, else left out
   with a warning naming it (pipeline.geometry.turntable_placement). A capture shot
   in sets (the camera moved up or down, or the specimen turned over, between turns)
   is found from where its photos' cameras stand posed freely, each set solved alone
   and joined to the first by its matches on the specimen, or left out with one warning naming its
   photos (pipeline.geometry.turntable_sets), then all adjusted together with the
   matches across sets shared (pipeline.geometry.sets_adjustment; sfm.json ``circular.sets``, and per
   photo its set, what placed it and its angle's uncertainty in ``circular.photos``). Fewer than
   ``min_registered_fraction`` posed photos is an error naming the others and the
   likely cause for each. A rerun gives the same model: photos are numbered in
   sorted order, RANSAC and the mapper are seeded, and bundle adjustment runs on one
   thread (with COLMAP's threaded defaults, reruns gave different poses).
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
through the board (or, on a turntable, its shading's matches, which the outlines
correct, and its silhouette). Without a board the scale is arbitrary. A handheld
photo SfM cannot register is dropped. Self-calibrated radial distortion improves
the poses and is reported, but the photos stay as undistort made them (pinhole, without it): the
stage warns when it displaces the specimen's outline by more than half a pixel
(board shots in calibration/ let undistort remove it).
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import pycolmap

from pipeline import logger
from pipeline.camera.board import board_poses
from pipeline.camera.model import Intrinsics, Pose, Similarity
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
from pipeline.formats.sfm_report import SfmReport
from pipeline.geometry import world_frame
from pipeline.geometry.pose_check import drop_inconsistent
from pipeline.geometry.turntable_placement import PlacementSettings, RigSettings, circular_poses


@dataclass(frozen=True)
class Config(features.FeatureSettings, RigSettings, SelfCalibrationSettings):
    """Structure from motion with pycolmap (or the rig's circular motion), and the world frame."""

    min_pose_inliers: Annotated[int, Range(6, None)] = 15
    """2D-3D inliers a photo needs to be registered (COLMAP's default, 30, leaves out
    photos of low-texture specimens that share only a few dozen points); on a turntable
    or ring, the inlier observations that place a photo, and that make a pair of photos
    strong, in the ring of strong pairs."""
    min_angle_inliers: Annotated[int, Range(3, None)] = 6
    """Turntable or ring, where the strong pairs leave photos out and weak pairs are
    tried: inlier observations that place a photo by its features. A photo there has one
    unknown, its angle, where a free pose has six: a small or plain specimen's photos at
    the seams of a turn share a handful of points, and whether they fit is the misfit
    test's and the reported uncertainty's to say."""
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


@dataclass
class _Posed:
    """Step 2's poses and what came with them."""

    poses: dict[str, Pose]
    causes: dict[str, str]
    """Why each photo without a pose has none."""
    intrinsics: dict[str, Intrinsics]
    points: np.ndarray
    poses_from: str
    details: dict = field(default_factory=dict)
    """What sfm.json adds for this way of posing."""
    database: Path | None = None
    """The COLMAP database the poses came from (None: another tool's poses)."""
    model: pycolmap.Reconstruction | None = None
    """COLMAP's incremental model, when it posed the photos."""
    solution: Any = None
    """The rig's circular-motion solution, when it posed the photos."""
    table: Any = None
    """The turntable the rig's solution found."""
    cameras: list[tuple] = field(default_factory=list)
    """(focal, cx, cy, k1) of each camera the poses were solved with."""


@dataclass(frozen=True)
class _Photos:
    """Step 1's photos, their cameras and masks."""

    order: list[str]
    records: dict[str, dict]
    """undistort's photo records (``srgb``, ``camera``)."""
    cameras: list[dict]
    """undistort's camera settings."""
    masks: dict[str, Path]
    stem_of: dict[str, str]
    """Each photo's file name (COLMAP's image name)."""
    intrinsics: dict[str, Intrinsics]


def main(conf: Config, inputs: StageInputs, out_dir: Path) -> StageResult:
    rig: str = inputs.shared["capture.rig"]
    photos = _read_photos(inputs)
    board: BoardSection = inputs.shared["board"]
    board_found, board_errors = board_poses(
        board, photos.records, photos.intrinsics, conf.board_min_corners, conf.board_max_error_px
    )
    posed = _pose(conf, inputs, rig, photos, board_found, out_dir / "colmap")
    # A board pose is as good as a registration (in the board frame), and SfM may
    # fail on a plain specimen.
    if len(set(posed.poses) | set(board_found)) < conf.min_registered_fraction * len(photos.order):
        _too_few(conf, set(posed.poses) | set(board_found), photos.order, posed.causes)
    registered = len(posed.poses)
    if posed.database is not None:
        posed.details |= _residual_distortion(posed.cameras, list(photos.masks.values()))
    frame, to_world = _world_frame(conf, rig, posed, board_found)
    _drop_inconsistent(conf, rig, photos, posed, frame)
    sparse, cameras_json = _write_model(out_dir, photos, posed, frame, to_world)
    report = SfmReport(
        photos=len(photos.order),
        poses_from=posed.poses_from,
        registered=registered,
        unregistered=posed.causes,
        frame=frame,
        points=None if posed.database is None else len(posed.points),
        mean_reprojection_error_px=posed.details.pop("mean_reprojection_error_px", None),
        mean_track_length=posed.details.pop("mean_track_length", None),
        board_reprojection_px=board_errors,
        details=posed.details,
    )
    sfm_json = report.write(out_dir / "sfm.json")
    metrics = {"registered": registered, "photos": report.photos}
    metrics |= {"mean_reprojection_error_px": report.mean_reprojection_error_px}
    metrics |= {"mean_track_length": report.mean_track_length, "frame": frame["source"]}
    if "circular" in posed.details:  # the one line the log gave: sets, joins, outlines, left out
        metrics["placed"] = posed.details["circular"]["summary"]
    return StageResult({"cameras": cameras_json, "sparse": sparse, "report": sfm_json}, metrics)


def _read_photos(inputs: StageInputs) -> _Photos:
    """1. The photos, their cameras (as calibrated) and masks."""
    pinhole_json = inputs.upstream["undistort"]["pinhole"]
    cameras = read_camera_settings(pinhole_json)
    records = read_photos(pinhole_json, "images")
    order = sorted(records)
    return _Photos(
        order=order,
        records=records,
        cameras=cameras,
        masks=read_masks(inputs.upstream["masks"]["masks_json"]),
        stem_of={name: Path(records[name]["srgb"]).name for name in order},
        intrinsics={name: Intrinsics.from_json(cameras[records[name]["camera"]]["intrinsics"]) for name in order},
    )


def _pose(
    conf: Config, inputs: StageInputs, rig: str, photos: _Photos, board_found: dict[str, Pose], work: Path
) -> _Posed:
    """2. The poses: another tool's, the rig's circular motion, or COLMAP's incremental model."""
    # A calibrated camera (board, known intrinsics, another tool's) stays as it is; a
    # guessed one (EXIF, prior) is refined.
    refine_focal = any(c["calibrated_by"] not in ("board", "known", "external") for c in photos.cameras)
    external: CamerasSection = inputs.shared["cameras"]
    work.mkdir()
    if external.source:
        poses, causes = external_poses(
            input_file_path(inputs.capture_dir, external.source), external.source, photos.order
        )
        return _Posed(poses, causes, photos.intrinsics, np.zeros((0, 3)), f"[cameras] source = {external.source}")
    plan = features.FeaturePlan.of(conf, rig, photos.records, photos.cameras, photos.masks, work)
    database = features.features_and_matches(plan, photos.records, photos.cameras, work)
    if rig in ("turntable", "ring"):
        keypoints, matches = features.verified_matches(database, photos.order, photos.stem_of)
        # A still camera's matches that do not move are its room's and its highlights'.
        still_px = features.STATIONARY_PX if plan.still_camera else 0.0
        unverified = features.unverified_matches(database, photos.order, photos.stem_of, still_px)
        settings = PlacementSettings.of(
            conf, conf, rig == "turntable", conf.min_pose_inliers, conf.min_angle_inliers, refine_focal
        )
        table, poses, solution, circular = circular_poses(
            settings, photos.order, photos.intrinsics, photos.masks, keypoints, matches, board_found, unverified
        )
        K = solution.intrinsics
        return _Posed(
            poses,
            circular["unplaced"],
            {name: K.without_distortion() for name in photos.order},
            solution.points,
            f"circular motion ({rig})",
            details={
                "circular": circular,
                "mean_reprojection_error_px": circular["reprojection_error_px_median"],
                "mean_track_length": float(np.mean([len(t) for t in solution.tracks])) if solution.tracks else None,
            },
            database=database,
            solution=solution,
            table=table,
            cameras=[(K.fx, K.cx, K.cy, K.dist[0])],
        )
    image_dir = next(iter(photos.records.values()))["srgb"].parent
    model = mapping.incremental_map(database, image_dir, work / "models", refine_focal, conf.min_pose_inliers)
    details = {}
    if model is not None and refine_focal and conf.self_calibrate:
        details["self_calibration"] = mapping.self_calibrate(model, conf)
    name_of = {s: n for n, s in photos.stem_of.items()}
    poses = mapping.registered_poses(model, name_of, photos.intrinsics, refine_focal)
    unregistered = [n for n in photos.order if n not in poses]
    causes = features.unregistered_causes(database, unregistered, photos.stem_of) if unregistered else {}
    points = np.array([p.xyz for p in model.points3D.values()]).reshape(-1, 3) if model else np.zeros((0, 3))
    offset = COLMAP_PIXEL_OFFSET
    solved = [c.params for c in model.cameras.values()] if model else []
    cameras = [(f, cx - offset, cy - offset, k1) for f, cx, cy, k1 in solved]
    return _Posed(
        poses,
        causes,
        photos.intrinsics,
        points,
        "SfM",
        details=details | mapping.model_metrics(model),
        database=database,
        model=model,
        cameras=cameras,
    )


def _world_frame(conf: Config, rig: str, posed: _Posed, board_found: dict[str, Pose]) -> tuple[dict, Similarity]:
    """3. The world frame: the board's when the poses agree with it, else the turntable's,
    the ground's or the cameras'. Moves the poses and points into it; returns its
    record (cameras.json's frame) and the move from the poses' first frame."""
    circular = rig in ("turntable", "ring")
    tie = world_frame.tie_to_board(
        conf.frame, conf.board_max_disagreement, board_found, posed.poses, posed.points, circular
    )
    frame, posed.poses, posed.points = tie.frame, tie.poses, tie.points
    posed.model = None if tie.dropped else posed.model
    if tie.replaced_by_board is not None:
        posed.details["replaced_by_board"] = tie.replaced_by_board
    to_world = frame or Similarity.identity()
    if frame is not None and not circular:
        posed.details["posed_by_board"] = sorted(set(board_found) - set(posed.poses))
        posed.poses |= {n: board_found[n] for n in posed.details["posed_by_board"]}
    if frame is not None:
        return tie.record, to_world
    level, record = world_frame.frame_without_board(conf.frame, posed.poses, posed.points, posed.table)
    posed.poses = {n: level.pose(p) for n, p in posed.poses.items()}
    posed.points = level.points(posed.points) if len(posed.points) else posed.points
    return record, to_world.then(level)


def _drop_inconsistent(conf: Config, rig: str, photos: _Photos, posed: _Posed, frame: dict) -> None:
    """4. Poses the silhouettes or the table contradict are left out (the circular
    placement checked its photos against the silhouettes already)."""
    consistent = drop_inconsistent(
        posed.poses,
        posed.intrinsics,
        photos.masks,
        conf.min_silhouette_iou,
        conf.silhouette_resolution,
        conf.min_mask_agreement,
        frame.get("ground_plane") is not None,
        rig not in ("turntable", "ring"),
    )
    posed.poses = consistent.kept
    for name, value in (("silhouette_iou", consistent.silhouette_iou), ("below_ground", consistent.below_ground)):
        if value is not None:
            posed.details[name] = value
    order = photos.order
    if len(posed.poses) < conf.min_registered_fraction * len(order):
        _too_few(conf, set(posed.poses), order, posed.causes)
    if len(posed.poses) < len(order):
        logger.warning(
            "%d of %d photos are not registered and are left out: %s",
            len(order) - len(posed.poses),
            len(order),
            ", ".join(n for n in order if n not in posed.poses),
        )


def _write_model(out_dir: Path, photos: _Photos, posed: _Posed, frame: dict, to_world: Similarity) -> tuple[Path, Path]:
    """5. The sparse model (COLMAP's format) and cameras.json, in the world frame."""
    sparse = out_dir / "sparse"
    poses, intrinsics, stem_of = posed.poses, posed.intrinsics, photos.stem_of
    if posed.database is None:
        # Where a mesh from the same tool ([mesh] source) must be moved to.
        frame["from_source"] = to_world.to_json()
        model_io.model_from_poses(intrinsics, poses, stem_of, sparse)
    elif posed.solution is not None:
        solution = posed.solution
        model_io.model_from_tracks(
            posed.database, solution.intrinsics, poses, posed.points, solution.tracks, stem_of, sparse
        )
    else:
        model_io.write_model(posed.model, posed.database, to_world, poses, stem_of, sparse)
    cameras_json = out_dir / "cameras.json"
    write_cameras(cameras_json, {n: intrinsics[n] for n in poses}, poses, frame=frame)
    if (out_dir / "colmap" / "models").exists():
        shutil.rmtree(out_dir / "colmap" / "models")
    return sparse, cameras_json


def _residual_distortion(cameras: list[tuple], masks: list[Path]) -> dict:
    """Radial distortion self-calibration found in the undistorted photos (used
    without it), and how far it moves the specimen's outline (sfm.json's
    ``residual_distortion``): a warning past half a pixel."""
    found = {}
    for focal, cx, cy, k1 in cameras:
        if k1 == 0:
            continue
        shift = outline_shift_px(k1, focal, cx, cy, masks)
        found["residual_distortion"] = {"k1": float(k1), "specimen_shift_px": shift}
        if shift > 0.5:
            logger.warning(
                "self-calibration found radial distortion (k1 = %.4f) that moves the specimen's outline by up to "
                "%.1f px; the photos are used without correcting it: add board shots to calibration/ so that "
                "undistort removes it",
                k1,
                shift,
            )
    return found


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
    version=17,
    config=Config,
    main=main,
    needs=("undistort.pinhole", "masks.masks_json"),
    outputs=("cameras", "sparse", "report"),
    shared=("capture.rig", "board", "cameras"),
    exports=("cameras",),
)
