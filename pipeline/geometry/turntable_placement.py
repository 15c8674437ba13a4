"""Poses of a turntable capture: one circle about one axis fitted to the photos'
measured poses (board or SfM), and every photo placed on it: at its measured
pose when the circle agrees, else at the angle its feature matches with posed
photos agree on, else at the angle where its silhouette best matches the hull of
the posed photos."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipeline import logger
from pipeline.camera.model import Intrinsics, Pose
from pipeline.core.errors import PipelineError
from pipeline.geometry import turntable
from pipeline.geometry.pose_check import hull_points


@dataclass(frozen=True)
class PlacementSettings:
    """How photos are placed on the circle (the sfm stage's settings)."""

    min_pose_inliers: int
    """Verified matches with posed photos, agreeing on one angle, that place a photo."""
    silhouette_resolution: int
    """Voxels along the hull's longest side for placement by silhouette."""
    model_poses: bool
    """True: every photo exactly on the fitted circle; False: a measured pose is kept."""


def turntable_poses(
    settings: PlacementSettings,
    order: list[str],
    measured: dict[str, dict[str, Pose]],
    intrinsics: dict[str, Intrinsics],
    masks: dict[str, Path],
    keypoints: dict[str, np.ndarray],
    matches: dict[tuple[str, str], dict[int, int]],
):
    """The turntable fitted to the measured poses (per photo its board pose, else its
    SfM pose; a board turns with the specimen and does not depend on SfM's luck with
    a plain specimen), and a pose for every photo: a measured one the model agrees
    with, else its angle from feature matches with posed photos, else from its
    silhouette. Returns (model, poses, report)."""
    first_choice = measured["sfm"] | measured["board"]
    if len(first_choice) < 3:
        raise PipelineError(f"only {len(first_choice)} photos registered: a turntable needs three to find its axis")
    table, off_circle = turntable.fit_robust(first_choice, order)
    fitted = {n: p for n, p in first_choice.items() if n not in off_circle}
    limit = max(3 * float(np.median([r for r, _ in table.residuals(fitted).values()])), 1.0)
    method = {n: "board" if n in measured["board"] else "sfm" for n in fitted}
    poses = dict(fitted)
    for name in order:
        for source in ("board", "sfm"):
            pose = measured[source].get(name)
            if name in poses or pose is None:
                continue
            angle = table.angle_of(pose)
            rotation, centre = table.residuals_at(pose, angle)
            if rotation <= limit and centre <= 0.1:
                table.angles[name], poses[name], method[name] = angle, pose, source
    for name in off_circle:
        logger.warning("%s: its measured pose is off the turntable's circle", name)
    missing = [n for n in order if n not in poses]
    by_matches = _place_by_matches(settings, table, order, missing, poses, intrinsics, keypoints, matches)
    missing = [n for n in missing if n not in by_matches]
    by_silhouette = _place_by_silhouette(settings, table, order, missing, poses, intrinsics, masks) if missing else {}
    placed = by_matches | by_silhouette
    method |= {n: "matches" for n in by_matches} | {n: "silhouette" for n in by_silhouette}
    report = {
        "off_circle": off_circle,
        "pose_source": {
            source: sorted(n for n in method if method[n] == source)
            for source in ("board", "sfm", "matches", "silhouette")
        },
        "rotation_residual_deg_max": max(r for r, _ in table.residuals(fitted).values()),
        "centre_residual_of_radius_max": max(c for _, c in table.residuals(fitted).values()),
        "placed": placed,
    }
    poses |= {n: table.pose(table.angles[n]) for n in placed}
    if settings.model_poses:
        poses = {n: table.pose(table.angles[n]) for n in poses}
    return table, poses, report


def _place_by_matches(
    settings: PlacementSettings,
    table: turntable.Turntable,
    order: list[str],
    missing: list[str],
    poses: dict[str, Pose],
    intrinsics: dict[str, Intrinsics],
    keypoints: dict[str, np.ndarray],
    matches: dict[tuple[str, str], dict[int, int]],
) -> dict[str, dict]:
    """Angles for photos with at least ``min_pose_inliers`` verified matches with
    posed photos that agree on one angle (recorded in ``table.angles``)."""
    placed = {}
    for name in missing:
        partners = []
        for partner in poses:
            pairs = matches.get((name, partner))
            if pairs:
                mine, theirs = (np.array(side) for side in zip(*pairs.items()))
                partners.append(
                    turntable.Matches(
                        poses[partner], intrinsics[partner], keypoints[name][mine], keypoints[partner][theirs]
                    )
                )
        if sum(len(m.points) for m in partners) < settings.min_pose_inliers:
            continue
        low, high = turntable.bracket(table, order, name)
        angle, agreeing = turntable.angle_from_matches(table, low, high, intrinsics[name], partners)
        supporting = sum(len(m.points) for m in agreeing)
        if supporting < settings.min_pose_inliers:
            logger.info("%s: no posed photo's matches agree on an angle; trying its silhouette", name)
            continue
        table.angles[name] = angle
        placed[name] = {
            "method": "matches",
            "angle_deg": float(np.degrees(angle)),
            "matches": supporting,
            "partners": len(agreeing),
            "partners_dropped": len(partners) - len(agreeing),
        }
        logger.info(
            "%s placed on the turntable at %.2f degrees by its feature matches (posed photos: %d agree, %d disagree)",
            name,
            placed[name]["angle_deg"],
            len(agreeing),
            placed[name]["partners_dropped"],
        )
    return placed


def _place_by_silhouette(
    settings: PlacementSettings,
    table: turntable.Turntable,
    order: list[str],
    missing: list[str],
    poses: dict[str, Pose],
    intrinsics: dict[str, Intrinsics],
    masks: dict[str, Path],
) -> dict[str, dict]:
    """Angles for the ``missing`` photos from their silhouettes against the hull of
    the posed photos (recorded in ``table.angles``)."""
    placed: dict[str, dict] = {}
    mask_of = {n: cv2.imread(str(masks[n]), cv2.IMREAD_GRAYSCALE) > 127 for n in order}
    try:
        hull, voxel = hull_points(
            [n for n in order if n in poses], poses, intrinsics, mask_of, settings.silhouette_resolution
        )
    except ValueError as error:
        raise PipelineError(f"cannot place {', '.join(missing)} on the turntable by silhouette: {error}") from error
    for name in missing:
        low, high = turntable.bracket(table, order, name)
        angle, iou = turntable.angle_from_silhouette(table, low, high, hull, voxel, intrinsics[name], mask_of[name])
        table.angles[name] = angle
        placed[name] = {"method": "silhouette", "angle_deg": float(np.degrees(angle)), "silhouette_iou": iou}
        log = logger.warning if iou < 0.8 else logger.info
        log(
            "%s placed on the turntable by its silhouette at %.2f degrees (IoU %.3f%s)",
            name,
            placed[name]["angle_deg"],
            iou,
            ", unreliable" if iou < 0.8 else "",
        )
    return placed
