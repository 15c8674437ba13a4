"""Checks of camera poses against the photos' silhouettes: a pose that SfM got
wrong shows the specimen where it is not."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from pipeline import logger
from pipeline.camera.model import Intrinsics, Pose
from pipeline.geometry import turntable
from pipeline.geometry.visual_hull import View, bounds, sample_hull


def hull_points(
    names: list[str],
    poses: dict[str, Pose],
    intrinsics: dict[str, Intrinsics],
    mask_of: dict[str, np.ndarray],
    resolution: int,
    tolerance: int = 1,
) -> tuple[np.ndarray, float]:
    """Voxel centres inside the visual hull of the posed ``names`` (``tolerance``
    photos may disagree), and the voxel size. ValueError when the silhouettes do not meet."""
    views = [View(intrinsics[n], poses[n], mask_of[n]) for n in names]
    lo, hi = bounds(views, tolerance)
    grid, centres, field = sample_hull(views, lo, hi, resolution, tolerance)
    return centres[field > 0], grid.voxel


def silhouette_check(
    poses: dict[str, Pose],
    intrinsics: dict[str, Intrinsics],
    mask_of: dict[str, np.ndarray],
    min_iou: float,
    resolution: int,
) -> tuple[dict[str, float], list[str]]:
    """Each photo's mask against the visual hull of the posed photos seen from its pose
    (IoU), and the photos below ``min_silhouette_iou``: a pose SfM got wrong shows the
    specimen where it is not.

    Two passes. The first hull lets a fifth of the photos disagree, so that several
    wrong poses neither carve it away nor leave no hull at all (two photos posed 164
    and 42 degrees off did that to the strict hull on bird_volumetric); it finds the
    outliers. The second, the hull of the rest letting one disagree, gives the
    scores. Returns ({}, []) when even the first has no inside (the mesh stage then
    says so)."""
    names = sorted(poses)
    consistent = names
    for tolerance in (max(1, len(names) // 5), 1):
        try:
            points, voxel = hull_points(consistent, poses, intrinsics, mask_of, resolution, tolerance)
        except ValueError as error:
            logger.warning("cannot check the poses against the silhouettes: %s", error)
            return {}, []
        scores = {}
        for name in names:
            depth = np.linalg.norm(poses[name].center - points.mean(axis=0))
            radius = turntable.splat_radius(voxel, intrinsics[name], depth)
            scores[name] = turntable.silhouette_iou(points, radius, poses[name], intrinsics[name], mask_of[name])
        consistent = [n for n in names if scores[n] >= min_iou]
        if len(consistent) < 3:
            logger.warning("fewer than three photos agree with the visual hull: not checking the poses")
            return scores, []
    return scores, [n for n in names if scores[n] < min_iou]


def drop_inconsistent(
    poses: dict[str, Pose],
    intrinsics: dict[str, Intrinsics],
    masks: dict[str, Path],
    min_iou: float,
    resolution: int,
    report: dict,
    check_silhouettes: bool = True,
) -> None:
    """Leave out (from ``poses``) photos whose silhouettes contradict the hull of the
    others (``silhouette_check``, when ``check_silhouettes``), and cameras under the
    table when ``report``'s frame has a ground plane; ``report`` records both."""
    if check_silhouettes and len(poses) >= 3:
        mask_of = {n: cv2.imread(str(masks[n]), cv2.IMREAD_GRAYSCALE) > 127 for n in poses}
        report["silhouette_iou"], off = silhouette_check(poses, intrinsics, mask_of, min_iou, resolution)
        for name in off:
            logger.warning(
                "%s: its silhouette does not match the hull of the other photos at SfM's pose (IoU %.2f "
                "< sfm.min_silhouette_iou = %.2f); leaving the photo out",
                name,
                report["silhouette_iou"][name],
                min_iou,
            )
            del poses[name]
    if report["frame"].get("ground_plane") is not None:
        # The world's z = 0 is the table: a camera below it cannot see the specimen on
        # it. SfM does this to a view of a plain, symmetric specimen it mirrors.
        report["below_ground"] = sorted(n for n, p in poses.items() if p.center[2] < 0)
        for name in report["below_ground"]:
            logger.warning(
                "%s: SfM put the camera below the table (z = %.3f); leaving the photo out",
                name,
                poses.pop(name).center[2],
            )
