"""Plane-sweep stereo and carving on a textured cube with a dent no silhouette shows."""

import numpy as np
import pytest
import trimesh
from scipy import ndimage

from pipeline.camera.model import Pose
from pipeline.geometry import stereo
from pipeline.geometry.visual_hull import View, bounds, sample_hull, surface
from tests.support import dented_cube
from tests.support.sphere_views import K as SPHERE_K


def _hull(views: list[View], resolution: int = 64):
    """The hull as the mesh stage makes it: cut at the table (the cube's bottom face)
    and closed by a voxel."""
    lo, hi = bounds(views)
    grid, centres, field = sample_hull(views, lo, hi, resolution)
    field = np.minimum(field, centres[:, 2] + dented_cube.HALF)
    return grid, centres, field


def _close(field: np.ndarray, grid) -> np.ndarray:
    return ndimage.grey_closing(field.reshape(grid.shape), size=(3, 3, 3)).ravel()


def _stereo_views(poses, shots, hull: trimesh.Trimesh, texture: bool = True) -> list[stereo.StereoView]:
    result = []
    for pose, (image, mask) in zip(poses, shots):
        near, far = stereo.hull_depths(hull, dented_cube.K, pose)
        grey = image if texture else np.where(mask, 0.5, 0.02).astype(np.float32)
        result.append(stereo.StereoView(dented_cube.K, pose, grey, mask, near, far))
    return result


@pytest.fixture(scope="module")
def cube():
    poses = dented_cube.cameras(12)
    shots = [dented_cube.render(pose) for pose in poses]
    views = [View(dented_cube.K, pose, mask) for pose, (_, mask) in zip(poses, shots)]
    grid, centres, field = _hull(views)
    hull = surface(_close(field, grid), grid)
    return poses, shots, grid, centres, field, hull


def _sweep(views: list[stereo.StereoView]):
    neighbour_lists = stereo.neighbours([v.pose for v in views], 4, 3.0, 70.0)
    sweeps = [stereo.plane_sweep(v, [views[j] for j in n], 64, 7, 2, 0.01) for v, n in zip(views, neighbour_lists)]
    return neighbour_lists, [s[0] for s in sweeps], [s[1] for s in sweeps]


def _true_depth(pose: Pose) -> np.ndarray:
    """Ray-marched depth of the dented cube along each pixel's optical axis distance."""
    K = dented_cube.K
    u, v = np.meshgrid(np.arange(K.width), np.arange(K.height))
    camera_rays = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u, float)], axis=-1)
    rays = camera_rays @ pose.R
    lengths = np.linalg.norm(rays, axis=-1)
    rays /= lengths[..., None]
    t = np.zeros(rays.shape[:-1])
    for _ in range(100):
        distance = dented_cube.signed_distance(pose.center + t[..., None] * rays)
        t += np.where(distance > 1e-6, distance, 0.0)
    return t / lengths  # along the ray -> along the optical axis


def test_hull_depths_are_where_rays_enter_and_leave_a_sphere():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    pose = Pose.look_at([0.3, 0.0, 0.0], [0, 0, 0])
    near, far = stereo.hull_depths(sphere, SPHERE_K, pose)
    centre = (round(SPHERE_K.cy), round(SPHERE_K.cx))
    assert near[centre] == pytest.approx(0.25, abs=1e-3) and far[centre] == pytest.approx(0.35, abs=1e-3)
    assert np.isinf(near[0, 0]) and far[0, 0] == 0  # a corner pixel misses the sphere


def test_neighbours_are_the_nearest_viewpoints_within_the_angles():
    poses = [Pose.look_at([np.cos(a), np.sin(a), 0.3], [0, 0, 0]) for a in np.radians([0, 1, 10, 20, 90])]
    # 1 degree is too short a baseline, 90 too wide; 10 is nearer than 20
    assert stereo.neighbours(poses, 2, 3.0, 45.0)[0] == [2, 3]


def test_plane_sweep_finds_the_depth_of_a_textured_surface(cube):
    poses, shots, grid, _, _, hull = cube
    views = _stereo_views(poses, shots, hull)
    _, depths, scores = _sweep(views)
    truth = _true_depth(poses[0])
    found = depths[0] > 0
    assert found.sum() > 0.7 * shots[0][1].sum()  # all but a band of half a window along the outline
    trusted = found & (scores[0] > 0.5)
    error, hull_error = np.abs(depths[0] - truth)[trusted], np.abs(views[0].near - truth)[trusted]
    # about a pixel's footprint (1.8 mm), against the hull's 7 mm
    assert np.median(error) < 0.6 * grid.voxel and np.median(error) < 0.3 * np.median(hull_error)


def test_carving_opens_the_dent_that_no_silhouette_shows(cube):
    poses, shots, grid, centres, field, hull = cube
    views = _stereo_views(poses, shots, hull)
    neighbour_lists, depths, scores = _sweep(views)
    kept = stereo.consistent_depths(views, depths, scores, neighbour_lists, 0.5, grid.voxel, 1)
    carved_field = _close(np.minimum(field, stereo.carve_field(centres, views, kept, grid.voxel, 2)), grid)
    carved = surface(carved_field, grid)

    def inside(values: np.ndarray, point) -> bool:
        index = np.round((np.asarray(point) - grid.origin) / grid.voxel).astype(int)
        return bool(values.reshape(grid.shape)[tuple(index)] > 0)

    in_dent, in_cube = (0.0, 0.0, 0.035), (0.0, 0.0, 0.0)  # 15 mm above the dent's bottom; the centre
    assert inside(_close(field, grid), in_dent) and not inside(carved_field, in_dent)
    assert inside(carved_field, in_cube)
    assert carved.is_watertight and carved.euler_number == 2
    hull_error = np.abs(dented_cube.signed_distance(hull.sample(5000, seed=1))).mean()
    carved_error = np.abs(dented_cube.signed_distance(carved.sample(5000, seed=1))).mean()
    assert carved_error < 0.5 * hull_error, (carved_error, hull_error)


def test_a_surface_without_texture_gives_no_depth_and_carves_nothing_of_the_specimen(cube):
    poses, shots, grid, centres, field, hull = cube
    views = _stereo_views(poses, shots, hull, texture=False)
    neighbour_lists, depths, scores = _sweep(views)
    kept = stereo.consistent_depths(views, depths, scores, neighbour_lists, 0.5, grid.voxel, 1)
    # windows (7 px) that reach the silhouette see its edge: texture enough
    square = np.ones((9, 9), bool)
    interior = sum(int((ndimage.binary_erosion(v.mask, square) & (d > 0)).sum()) for v, d in zip(views, kept))
    assert interior == 0
    # only the silhouettes' edges have depths, and what they carve is hull, not cube
    carve = stereo.carve_field(centres, views, kept, grid.voxel, 2)
    in_cube = dented_cube.signed_distance(centres) < -grid.voxel
    assert (in_cube & (carve <= 0)).sum() < 0.005 * in_cube.sum()
