"""Depth from photo-consistency inside the visual hull, and the hull carved where the
photos see past it.

A visual hull cannot see a concavity that no silhouette shows (the space between a
temple's columns seen from the front, a dent in a cube's face). The photos can: a
textured surface looks the same from nearby viewpoints only at its true depth.

1. **Hull depths** (:func:`hull_depths`): per pixel, the depths where the ray enters
   and leaves the hull. The true surface lies between them: the search range.
2. **Plane sweep** (:func:`plane_sweep`): fronto-parallel planes of the reference
   camera, evenly spaced in inverse depth over the hull's range; at each, the
   neighbours are warped onto the reference by the plane's homography and compared
   by normalised cross-correlation (NCC) in a square window, which ignores gain and
   offset (exposure, shading that differs between viewpoints). A pixel's score at a
   depth is the mean of its ``best_of`` best neighbours, so that one neighbour which
   sees the point occluded does not veto it. The best depth within the hull's range
   is refined to a fraction of a plane by a parabola through its neighbours' scores.
3. **Consistency** (:func:`consistent_depths`): a depth is kept when its score passes
   ``min_score``, its window has texture and lies inside the mask, and at least
   ``min_agree`` neighbours' depth maps put the same point at the same depth (within
   ``tolerance``).
4. **Carving** (:func:`carve_field`): a point in front of a kept depth, seen from
   that view, is empty space. The field is the ``min_votes``-th smallest
   ``depth of the point - depth seen + margin`` over the views, positive inside: a
   voxel is carved when that many views see past it by more than ``margin``, and the
   field is metric like the hull's, so the two combine with ``min``.

:func:`carve` runs the four for the mesh stage, on its hull field.

| parameter   | meaning                                                              |
|-------------|----------------------------------------------------------------------|
| planes      | depth planes swept per view                                          |
| window      | NCC window side, pixels (odd)                                        |
| best_of     | neighbours whose scores are averaged per pixel and depth             |
| min_score   | NCC below which a depth is not trusted                               |
| min_agree   | neighbours whose depth maps must agree                               |
| tolerance   | agreement between depth maps, world units (the mesh stage: a voxel)  |
| min_votes   | views that must see past a voxel before it is carved                 |

Limitations: textureless surfaces (plaster under flat light, glazed ceramic) give no
depth and keep the hull there; specular highlights and translucency, which move with
the viewpoint, lower the scores, and such depths tend to be dropped; a concavity seen
by fewer than ``min_votes`` views with a neighbour each stays filled. Only carving:
nothing is added outside the hull, which every silhouette bounds.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np
import trimesh

from pipeline import logger
from pipeline.camera.model import Intrinsics, Pose, project, resize_exact, scaled
from pipeline.core import progress
from pipeline.geometry.visual_hull import Grid, View, surface

_CHUNK = 400_000
"""Points per batch in carve_field: bounds memory at about views x 1.6 MB."""


@dataclass
class StereoView:
    """One photo for stereo: grey image, mask and the hull's depth range per pixel."""

    intrinsics: Intrinsics
    pose: Pose
    image: np.ndarray
    """Grey levels, float32, height x width of ``intrinsics``."""
    mask: np.ndarray
    """The specimen's pixels, booleans."""
    near: np.ndarray
    """Depth where each pixel's ray enters the hull (inf where it misses)."""
    far: np.ndarray
    """Depth where it leaves the hull (0 where it misses)."""


def hull_depths(mesh: trimesh.Trimesh, intrinsics: Intrinsics, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, the nearest and farthest depth of ``mesh`` (inf and 0 where it is not
    seen): each face painted with its mean depth, in depth order (the painter's
    algorithm; a face's depth varies across it by less than its size)."""
    pixels, depth = project(mesh.vertices, intrinsics, pose)
    triangles = np.round(pixels[mesh.faces] * 16).astype(np.int32)
    face_depth = depth[mesh.faces].mean(axis=1)
    shape = (intrinsics.height, intrinsics.width)
    near, far = np.full(shape, np.inf, np.float32), np.zeros(shape, np.float32)
    in_front = np.all(depth[mesh.faces] > 1e-6, axis=1)
    order = np.argsort(face_depth)
    order = order[in_front[order]]
    for face in order[::-1]:  # far to near: the nearest face is painted last
        cv2.fillConvexPoly(near, triangles[face], float(face_depth[face]), shift=4)
    for face in order:
        cv2.fillConvexPoly(far, triangles[face], float(face_depth[face]), shift=4)
    return near, far


def neighbours(poses: list[Pose], count: int, min_angle_deg: float, max_angle_deg: float) -> list[list[int]]:
    """For each camera, the ``count`` others whose viewing directions are nearest to its
    own but at least ``min_angle_deg`` apart (too short a baseline gives no depth) and
    at most ``max_angle_deg`` (too wide, and the surface looks different)."""
    axes = np.array([pose.R[2] for pose in poses])
    angles = np.degrees(np.arccos(np.clip(axes @ axes.T, -1.0, 1.0)))
    result = []
    for i in range(len(poses)):
        usable = np.flatnonzero((angles[i] >= min_angle_deg) & (angles[i] <= max_angle_deg))
        result.append(usable[np.argsort(angles[i, usable])][:count].tolist())
    return result


def _box_mean(image: np.ndarray, window: int) -> np.ndarray:
    return cv2.boxFilter(image, cv2.CV_32F, (window, window), borderType=cv2.BORDER_REFLECT)


def _crop(mask: np.ndarray, margin: int) -> tuple[int, int, int, int]:
    """x0, y0, x1, y1 of the mask's bounding box grown by ``margin`` (clipped)."""
    rows, cols = np.nonzero(mask)
    h, w = mask.shape
    return (
        max(int(cols.min()) - margin, 0),
        max(int(rows.min()) - margin, 0),
        min(int(cols.max()) + margin + 1, w),
        min(int(rows.max()) + margin + 1, h),
    )


def plane_sweep(
    reference: StereoView, others: list[StereoView], planes: int, window: int, best_of: int, min_texture: float
) -> tuple[np.ndarray, np.ndarray]:
    """The depth (0 where none) and its NCC score (-1 where none) per pixel of
    ``reference``, searched between the hull's near and far depth."""
    shape = reference.mask.shape
    depth_map, score_map = np.zeros(shape, np.float32), np.full(shape, -1.0, np.float32)
    seen = reference.mask & np.isfinite(reference.near)
    if not seen.any() or not others:
        return depth_map, score_map
    x0, y0, x1, y1 = _crop(seen, window)
    size = (x1 - x0, y1 - y0)
    near, far = reference.near[y0:y1, x0:x1], reference.far[y0:y1, x0:x1]
    inside = seen[y0:y1, x0:x1]
    lo, hi = float(near[inside].min()), float(far[inside].max())
    depths = 1.0 / np.linspace(1.0 / lo, 1.0 / max(hi, lo * 1.0001), planes)  # near to far
    ref = reference.image[y0:y1, x0:x1]
    ref_mean = _box_mean(ref, window)
    ref_std = np.sqrt(np.maximum(_box_mean(ref * ref, window) - ref_mean**2, 0.0))
    # reference pixel (crop) -> normalised camera ray
    to_ray = np.linalg.inv(reference.intrinsics.K) @ np.array([[1.0, 0, x0], [0, 1, y0], [0, 0, 1]])
    scores = np.full((planes, size[1], size[0]), -1.0, np.float32)
    per_neighbour = np.full((len(others), size[1], size[0]), -1.0, np.float32)
    ref_var = ref_std**2
    coverage = [np.ones_like(other.image) for other in others]
    # each neighbour's pose relative to the reference: the plane at depth d maps by
    # K_j (R + t n^T / d) to_ray, n the reference's optical axis
    relative = []
    for other in others:
        R = other.pose.R @ reference.pose.R.T
        relative.append(
            (
                other.intrinsics.K @ R @ to_ray,
                other.intrinsics.K @ np.outer(other.pose.t - R @ reference.pose.t, [0.0, 0.0, 1.0]) @ to_ray,
            )
        )
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    for p, d in enumerate(depths):
        for j, other in enumerate(others):
            rotation, translation = relative[j]
            H = rotation + translation / d
            warped = cv2.warpPerspective(other.image, H, size, flags=flags)
            valid = cv2.warpPerspective(coverage[j], H, size, flags=flags)
            mean = _box_mean(warped, window)
            var = np.maximum(_box_mean(warped * warped, window) - mean**2, 0.0)
            cov = _box_mean(warped * ref, window) - mean * ref_mean
            ncc = cov / np.sqrt(var * ref_var + 1e-12)
            per_neighbour[j] = np.where(valid > 0.999, ncc, -1.0)
        k = min(best_of, len(others))
        scores[p] = -np.partition(-per_neighbour, k - 1, axis=0)[:k].mean(axis=0)
    # only depths within the hull's range count
    within = (depths[:, None, None] >= near[None] * 0.999) & (depths[:, None, None] <= far[None] * 1.001)
    scores = np.where(within, scores, -1.0)
    best = scores.argmax(axis=0)
    rows, cols = np.indices(best.shape)
    best_score = scores[best, rows, cols]
    # a parabola through the scores at the neighbouring planes, in plane units
    before = scores[np.maximum(best - 1, 0), rows, cols]
    after = scores[np.minimum(best + 1, planes - 1), rows, cols]
    curvature = before - 2 * best_score + after
    interior = (best > 0) & (best < planes - 1) & (curvature < 0)
    offset = np.where(interior, 0.5 * (before - after) / np.where(interior, curvature, -1.0), 0.0)
    inverse = np.interp(best + np.clip(offset, -0.5, 0.5), np.arange(planes), 1.0 / depths)
    # a window reaching past the silhouette compares the backdrop, which is not the
    # specimen's and moves between viewpoints: the hull holds the outline anyway
    whole_window = cv2.erode(inside.astype(np.uint8), np.ones((window, window), np.uint8)) > 0
    found = whole_window & (best_score > -1.0) & (ref_std > min_texture)
    depth_map[y0:y1, x0:x1] = np.where(found, 1.0 / inverse, 0.0)
    score_map[y0:y1, x0:x1] = np.where(found, best_score, -1.0)
    return depth_map, score_map


def _depth_seen(points: np.ndarray, view: StereoView, depth_map: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The depth ``depth_map`` holds at each point's nearest pixel in ``view`` (0 where
    none, or the point is out of the frame or behind the camera), and the point's own depth."""
    pixels, depth = project(points, view.intrinsics, view.pose)
    u, v = np.round(pixels[:, 0]).astype(int), np.round(pixels[:, 1]).astype(int)
    h, w = depth_map.shape
    on = (u >= 0) & (u < w) & (v >= 0) & (v < h) & (depth > 0)
    seen = np.zeros(len(points), np.float32)
    seen[on] = depth_map[v[on], u[on]]
    return seen, depth


def consistent_depths(
    views: list[StereoView],
    depths: list[np.ndarray],
    scores: list[np.ndarray],
    neighbour_lists: list[list[int]],
    min_score: float,
    tolerance: float,
    min_agree: int,
) -> list[np.ndarray]:
    """The depth maps with untrusted pixels set to 0: a score below ``min_score``, or
    fewer than ``min_agree`` neighbours whose own depth at the point's projection is
    within ``tolerance`` (world units) of the point's depth in that neighbour."""
    kept = []
    for i, view in enumerate(views):
        rows, cols = np.nonzero((depths[i] > 0) & (scores[i] >= min_score))
        z = depths[i][rows, cols]
        rays = np.stack([cols, rows, np.ones_like(cols)], axis=1).astype(float) @ np.linalg.inv(view.intrinsics.K).T
        points = ((rays * z[:, None]) - view.pose.t) @ view.pose.R  # camera to world
        agree = np.zeros(len(z), int)
        for j in neighbour_lists[i]:
            seen, depth = _depth_seen(points, views[j], depths[j])
            agree += (seen > 0) & (np.abs(seen - depth) <= tolerance)
        result = np.zeros_like(depths[i])
        good = agree >= min_agree
        result[rows[good], cols[good]] = z[good]
        kept.append(result)
    return kept


def carve_field(
    points: np.ndarray, views: list[StereoView], depths: list[np.ndarray], margin: float, min_votes: int
) -> np.ndarray:
    """Per point, positive unless ``min_votes`` views see a kept depth more than
    ``margin`` behind it (world units, like the hull field): the ``min_votes``-th smallest
    of ``depth of the point - depth seen + margin``; views without a depth there, or
    which do not see the point, do not count (+inf)."""
    k = min(min_votes, len(views)) - 1
    field = np.empty(len(points), np.float32)
    for start in range(0, len(points), _CHUNK):
        chunk = points[start : start + _CHUNK]
        behind = np.full((len(views), len(chunk)), np.inf, np.float32)
        for i, view in enumerate(views):
            seen, z = _depth_seen(chunk, view, depths[i])
            behind[i] = np.where(seen > 0, z - seen + margin, np.inf)
        field[start : start + _CHUNK] = np.partition(behind, k, axis=0)[k]
    return field


MIN_TEXTURE = 0.01
"""Grey-level standard deviation (0-1) in a window below which it has no texture to
match: a depth there would be chance."""
MIN_AGREE = 1
"""Neighbouring depth maps that must confirm a depth before it carves."""


@dataclass(frozen=True)
class StereoSettings:
    """The mesh stage's stereo settings (its Config documents each)."""

    max_size: int
    planes: int
    window: int
    neighbours: int
    min_score: float
    min_votes: int


def carve(
    field: np.ndarray,
    grid: Grid,
    centres: np.ndarray,
    views: list[View],
    greys: list[np.ndarray],
    settings: StereoSettings,
) -> tuple[np.ndarray, dict]:
    """The hull ``field`` (on ``grid``, at ``centres``) carved where the photos' depth
    maps see past it; ``greys``: each view's photo as 8-bit grey levels. Returns the
    field and what was found (fractions of the masked pixels with a depth, voxels carved)."""
    started = time.perf_counter()
    hull = surface(field, grid)
    stereo_views = []
    for view, grey in progress.track(zip(views, greys), "hull depths", total=len(views)):
        factor = min(1.0, settings.max_size / max(grey.shape))
        image = resize_exact(grey.astype(np.float32) / 255, factor)
        small = scaled(view.intrinsics, factor, exact=True)
        small.width, small.height = image.shape[1], image.shape[0]
        mask = resize_exact(view.mask.astype(np.float32), factor) > 0.5
        near, far = hull_depths(hull, small, view.pose)
        stereo_views.append(StereoView(small, view.pose, image, mask, near, far))
    neighbour_lists = neighbours([v.pose for v in stereo_views], settings.neighbours, 3.0, 45.0)
    depths, scores = [], []
    for view, others in progress.track(zip(stereo_views, neighbour_lists), "stereo", total=len(stereo_views)):
        best_of = max(1, len(others) // 2)
        depth, score = plane_sweep(
            view, [stereo_views[j] for j in others], settings.planes, settings.window, best_of, MIN_TEXTURE
        )
        depths.append(depth)
        scores.append(score)
    # agreement to a voxel: the grid cannot hold finer depth anyway
    kept = consistent_depths(stereo_views, depths, scores, neighbour_lists, settings.min_score, grid.voxel, MIN_AGREE)
    near_hull = field > -4 * grid.voxel  # the rest is outside the hull, carved or not
    carved = field.copy()
    carved[near_hull] = np.minimum(
        field[near_hull], carve_field(centres[near_hull], stereo_views, kept, grid.voxel, settings.min_votes)
    )
    masked = max(sum(int(v.mask.sum()) for v in stereo_views), 1)
    report = {
        "stereo_pixels_with_depth": sum(int((d > 0).sum()) for d in depths) / masked,
        "stereo_pixels_kept": sum(int((d > 0).sum()) for d in kept) / masked,
        "stereo_voxels_carved": int(((field > 0) & (carved <= 0)).sum()),
        "stereo_voxels_in_hull": int((field > 0).sum()),
        "stereo_seconds": time.perf_counter() - started,
    }
    logger.info(
        "stereo: depth kept for %.0f %% of the masked pixels; %d of the hull's %d voxels carved",
        100 * report["stereo_pixels_kept"],
        report["stereo_voxels_carved"],
        report["stereo_voxels_in_hull"],
    )
    return carved, report
