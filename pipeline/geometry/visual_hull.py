"""The visual hull: the largest shape consistent with every silhouette.

A point belongs to the hull when it projects inside the mask of every view. We
store more than that bit: for every voxel, each view's signed distance from the
silhouette edge (pixels, positive inside the mask) scaled by depth / focal length
to metres, and keep the smallest over the views (or the ``tolerance + 1``-th
smallest, so that one bad mask cannot cut the hull). Marching cubes on that field
at level 0 places the surface between voxels instead of on the voxel grid.

Points projecting outside a photo take the distance at the nearest border pixel:
a specimen cut off by the frame is extended straight out of it rather than cut,
and anything else outside the frame is outside the hull. Points behind a camera
are unconstrained by it.

Limitations: a visual hull cannot see concavities (the inside of a cup, the
space between a bird's legs seen from the side only); the mesh stage adds the
sparse points for that. The field is an upper bound on the true distance, exact
only where the nearest silhouette edge lies in the view plane.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import cv2
import numpy as np
import trimesh
from scipy.ndimage import map_coordinates
from skimage.measure import marching_cubes

from pipeline.camera.model import Intrinsics, Pose, project

_CHUNK = 400_000
"""Points per batch: bounds memory at about views x 3 MB."""


@dataclass
class View:
    """One registered photo: its pinhole camera, pose and specimen mask."""

    intrinsics: Intrinsics
    pose: Pose
    mask: np.ndarray
    """Booleans, height x width of ``intrinsics``."""

    def signed_distance(self) -> np.ndarray:
        """Pixels from the silhouette edge, positive inside (cached on first use)."""
        if not hasattr(self, "_distance"):
            mask = self.mask.astype(np.uint8)
            inside = cv2.distanceTransform(mask, cv2.DIST_L2, 5)
            outside = cv2.distanceTransform(1 - mask, cv2.DIST_L2, 5)
            # The edge lies half a pixel from the centres on either side of it.
            self._distance = np.where(self.mask, inside - 0.5, 0.5 - outside).astype(np.float32)
        return self._distance

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (N, 2) and depths (N,) of world points."""
        return project(points, self.intrinsics, self.pose)


@dataclass
class Grid:
    """An axis-aligned voxel grid: ``origin`` is the centre of voxel (0, 0, 0)."""

    origin: np.ndarray
    voxel: float
    shape: tuple[int, int, int]

    @classmethod
    def around(cls, lo: np.ndarray, hi: np.ndarray, resolution: int) -> "Grid":
        """``resolution`` voxels along the box's longest side."""
        voxel = float(np.max(hi - lo)) / resolution
        shape = tuple(int(n) for n in np.maximum(np.ceil((hi - lo) / voxel), 1).astype(int))
        return cls(np.asarray(lo, dtype=float) + voxel / 2, voxel, shape)  # type: ignore[arg-type]

    def centres(self) -> np.ndarray:
        axes = [self.origin[i] + self.voxel * np.arange(n) for i, n in enumerate(self.shape)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def hull_field(points: np.ndarray, views: list[View], tolerance: int = 0) -> np.ndarray:
    """Metric signed distance-like value per point, positive inside the hull."""
    k = min(tolerance, len(views) - 1)
    values = np.empty(len(points), dtype=np.float32)
    for start in range(0, len(points), _CHUNK):
        chunk = points[start : start + _CHUNK]
        per_view = np.empty((len(views), len(chunk)), dtype=np.float32)
        for i, view in enumerate(views):
            pixels, depth = view.project(chunk)
            h, w = view.mask.shape
            u = np.clip(pixels[:, 0], 0, w - 1)
            v = np.clip(pixels[:, 1], 0, h - 1)
            distance = map_coordinates(view.signed_distance(), [v, u], order=1, mode="nearest")
            per_view[i] = np.where(depth > 1e-9, distance * depth / view.intrinsics.fx, np.inf)
        values[start : start + _CHUNK] = np.partition(per_view, k, axis=0)[k] if k else per_view.min(axis=0)
    return values


def sample_hull(
    views: list[View], lo: np.ndarray, hi: np.ndarray, resolution: int, tolerance: int = 0
) -> tuple[Grid, np.ndarray, np.ndarray]:
    """The hull field on a grid of ``resolution`` voxels along the longest side of the
    box (``lo``, ``hi``): the grid, its voxel centres and the field at them."""
    grid = Grid.around(lo, hi, resolution)
    centres = grid.centres()
    return grid, centres, hull_field(centres, views, tolerance)


def convergence_point(poses: Iterable[Pose]) -> np.ndarray:
    """The point nearest to every camera's optical axis: where the photos look."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for pose in poses:
        axis = pose.R[2]
        projector = np.eye(3) - np.outer(axis, axis)
        A += projector
        b += projector @ pose.center
    return np.linalg.solve(A, b)


def bounds(views: list[View], tolerance: int = 0, coarse: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """A box around the hull: a generous cube at the cameras' convergence point is
    carved coarsely, and the occupied part is kept with a margin of two voxels."""
    centre = convergence_point(v.pose for v in views)
    radii = []
    for view in views:
        (pixel,), (depth,) = view.project(centre[None])
        rows, cols = np.nonzero(view.mask)
        if depth <= 0 or not len(rows):
            continue
        farthest = np.sqrt(((cols - pixel[0]) ** 2 + (rows - pixel[1]) ** 2).max())
        radii.append(farthest * depth / view.intrinsics.fx)
    if not radii:
        raise ValueError("no view sees a specimen in front of its camera")
    radius = 1.2 * max(radii)
    grid = Grid.around(centre - radius, centre + radius, coarse)
    points = grid.centres()
    inside = points[hull_field(points, views, tolerance) > 0]
    if not len(inside):
        raise ValueError("the silhouettes do not intersect: the masks or the poses are wrong")
    margin = 2 * grid.voxel
    return inside.min(axis=0) - margin, inside.max(axis=0) + margin


def surface(values: np.ndarray, grid: Grid) -> trimesh.Trimesh:
    """The level-0 surface of a field sampled on ``grid`` (positive inside), as one
    closed mesh with outward normals: its largest connected part."""
    volume = np.full(tuple(n + 2 for n in grid.shape), -1.0, dtype=np.float32)
    volume[1:-1, 1:-1, 1:-1] = np.clip(values.reshape(grid.shape), -grid.voxel * 4, grid.voxel * 4)
    if volume.max() <= 0:
        raise ValueError("the field has no inside")
    vertices, faces, _, _ = marching_cubes(volume, level=0.0, spacing=(grid.voxel,) * 3)
    mesh = trimesh.Trimesh(vertices + grid.origin - grid.voxel, faces, process=True)
    parts = mesh.split(only_watertight=False)
    mesh = max(parts, key=lambda part: len(part.faces)) if len(parts) > 1 else mesh
    if mesh.volume < 0:
        mesh.invert()
    return mesh
