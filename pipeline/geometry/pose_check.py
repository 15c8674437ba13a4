"""Checks of camera poses against the photos' silhouettes: a pose that SfM got
wrong shows the specimen where it is not."""

from __future__ import annotations

import numpy as np

from pipeline import logger
from pipeline.camera.model import Intrinsics, Pose
from pipeline.geometry import turntable
from pipeline.geometry.visual_hull import Grid, View, bounds, hull_field


def hull_points(names: list[str], poses: dict[str, Pose], intrinsics: dict[str, Intrinsics],
                mask_of: dict[str, np.ndarray], resolution: int, tolerance: int = 1) -> tuple[np.ndarray, float]:
    """Voxel centres inside the visual hull of the posed ``names`` (``tolerance``
    photos may disagree), and the voxel size. ValueError when the silhouettes do not meet."""
    views = [View(intrinsics[n], poses[n], mask_of[n]) for n in names]
    lo, hi = bounds(views, tolerance)
    grid = Grid.around(lo, hi, resolution)
    centres = grid.centres()
    return centres[hull_field(centres, views, tolerance) > 0], grid.voxel


def silhouette_check(poses: dict[str, Pose], intrinsics: dict[str, Intrinsics], mask_of: dict[str, np.ndarray],
                     min_iou: float, resolution: int) -> tuple[dict[str, float], list[str]]:
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
