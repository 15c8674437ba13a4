"""Checks of camera poses against the photos' silhouettes: a pose that SfM got
wrong shows the specimen where it is not."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipeline import logger
from pipeline.camera.model import Intrinsics, Pose, project
from pipeline.geometry.visual_hull import View, bounds, sample_hull


def splat(points: np.ndarray, radius_px: int, pose: Pose, intrinsics: Intrinsics, shape: tuple[int, int]) -> np.ndarray:
    """The silhouette of hull points seen from ``pose``: each a disc of ``radius_px``."""
    pixels, depth = project(points, intrinsics, pose)
    u, v = np.round(pixels[depth > 1e-6]).astype(int).T
    h, w = shape
    keep = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    rendered = np.zeros((h, w), np.uint8)
    rendered[v[keep], u[keep]] = 1
    if radius_px > 0:
        rendered = cv2.dilate(rendered, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1,) * 2))
    return rendered.astype(bool)


def splat_radius(voxel: float, intrinsics: Intrinsics, depth: float) -> int:
    """Pixels of half a voxel at ``depth``: hull points splatted this wide leave no gaps."""
    return max(int(np.ceil(0.5 * voxel * intrinsics.fx / depth)), 0)


def silhouette_iou(points: np.ndarray, radius_px: int, pose: Pose, intrinsics: Intrinsics, mask: np.ndarray) -> float:
    """IoU of ``mask`` with the splatted projection of hull points seen from ``pose``."""
    rendered = splat(points, radius_px, pose, intrinsics, mask.shape)
    union = np.count_nonzero(rendered | mask)
    return np.count_nonzero(rendered & mask) / union if union else 0.0


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
    min_agreement: float,
) -> tuple[dict[str, float], list[str]]:
    """Each photo's mask against the visual hull of the posed photos seen from its pose
    (IoU), and the photos below ``min_silhouette_iou``: a pose SfM got wrong shows the
    specimen where it is not. The check is only as good as the masks: when the photos
    the hull is made of agree with it less than ``min_agreement`` (median IoU), no
    photo is left out (a white specimen on a white table: masks that catch a face or two
    agree poorly, and the check would drop well-registered photos).

    Two passes. The first hull lets a fifth of the photos disagree, so that several
    wrong poses neither carve it away nor leave no hull at all (two photos posed far
    off can empty the strict hull); it finds the outliers. The second, the hull of the
    rest letting one disagree, gives the scores. Returns ({}, []) when even the first has no inside (the mesh stage then
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
            radius = splat_radius(voxel, intrinsics[name], depth)
            scores[name] = silhouette_iou(points, radius, poses[name], intrinsics[name], mask_of[name])
        consistent = [n for n in names if scores[n] >= min_iou]
        if len(consistent) < 3:
            logger.warning("fewer than three photos agree with the visual hull: not checking the poses")
            return scores, []
    agreement = float(np.median([scores[n] for n in consistent]))
    if agreement < min_agreement:
        logger.warning(
            "the masks agree poorly with each other (median IoU %.2f with the visual hull < %.2f): the poses are "
            "not checked against them; look at the masks before trusting the mesh",
            agreement,
            min_agreement,
        )
        return scores, []
    return scores, [n for n in names if scores[n] < min_iou]


@dataclass(frozen=True)
class Consistency:
    """The poses that agree with the silhouettes and the table, and what was checked."""

    kept: dict[str, Pose]
    silhouette_iou: dict[str, float] | None
    """Each photo's silhouette IoU against the others' hull; None when not checked."""
    below_ground: list[str] | None
    """Photos whose camera SfM put under the table; None without a table."""


def drop_inconsistent(
    poses: dict[str, Pose],
    intrinsics: dict[str, Intrinsics],
    masks: dict[str, Path],
    min_iou: float,
    resolution: int,
    min_agreement: float,
    has_ground: bool,
    check_silhouettes: bool = True,
) -> Consistency:
    """``poses`` less the photos whose silhouettes contradict the hull of the others
    (``silhouette_check``, when ``check_silhouettes``), and the cameras under the table
    when the world frame has one (``has_ground``)."""
    kept = dict(poses)
    ious = None
    if check_silhouettes and len(kept) >= 3:
        mask_of = {n: cv2.imread(str(masks[n]), cv2.IMREAD_GRAYSCALE) > 127 for n in kept}
        ious, off = silhouette_check(kept, intrinsics, mask_of, min_iou, resolution, min_agreement)
        for name in off:
            logger.warning(
                "%s: its silhouette does not match the hull of the other photos at SfM's pose (IoU %.2f "
                "< sfm.min_silhouette_iou = %.2f); leaving the photo out",
                name,
                ious[name],
                min_iou,
            )
            del kept[name]
    below = None
    if has_ground:
        # The world's z = 0 is the table: a camera below it cannot see the specimen on
        # it. SfM does this to a view of a plain, symmetric specimen it mirrors.
        below = sorted(n for n, p in kept.items() if p.center[2] < 0)
        for name in below:
            logger.warning(
                "%s: SfM put the camera below the table (z = %.3f); leaving the photo out",
                name,
                kept.pop(name).center[2],
            )
    return Consistency(kept, ious, below)
