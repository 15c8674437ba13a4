import numpy as np
import pytest

from pipeline.camera import Intrinsics, Pose
from pipeline.visual_hull import Grid, View, bounds, convergence_point, hull_field, surface

RADIUS = 0.05
K = Intrinsics(120, 90, 150.0, 150.0, 59.5, 44.5)


def _sphere_mask(pose: Pose) -> np.ndarray:
    """Exact silhouette of a sphere at the origin: pixels whose ray passes within RADIUS."""
    u, v = np.meshgrid(np.arange(K.width), np.arange(K.height))
    rays = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u, float)], axis=-1)
    rays = rays @ pose.R  # camera to world directions
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    along = -(rays @ pose.center)
    closest = pose.center + along[..., None] * rays
    return np.linalg.norm(closest, axis=-1) < RADIUS


def _views(count: int = 10) -> list[View]:
    views = []
    for i in range(count):
        azimuth, elevation = 2 * np.pi * i / count, np.radians(20 + 30 * (i % 2))
        centre = 0.3 * np.array([np.cos(azimuth) * np.cos(elevation), np.sin(azimuth) * np.cos(elevation), np.sin(elevation)])
        pose = Pose.look_at(centre, [0, 0, 0])
        views.append(View(K, pose, _sphere_mask(pose)))
    return views


def _hull(views, tolerance=0, resolution=48):
    lo, hi = bounds(views, tolerance)
    grid = Grid.around(lo, hi, resolution)
    return surface(hull_field(grid.centres(), views, tolerance), grid)


def test_convergence_point_is_where_the_cameras_look():
    np.testing.assert_allclose(convergence_point(v.pose for v in _views()), 0, atol=1e-9)


def test_hull_of_a_sphere_is_closed_and_slightly_larger():
    mesh = _hull(_views())
    sphere = 4 / 3 * np.pi * RADIUS**3
    assert mesh.is_watertight
    # A hull contains the object; ten views leave it a few per cent larger.
    assert sphere * 0.97 < mesh.volume < sphere * 1.25, mesh.volume / sphere
    distance = np.linalg.norm(mesh.vertices, axis=1)
    assert np.median(np.abs(distance - RADIUS)) < 0.04 * RADIUS


def test_tolerance_survives_one_bad_mask():
    views = _views()
    views[3].mask[:, : K.width // 2 + 8] = False  # half of the specimen missing in one view
    strict, tolerant = _hull(views, 0), _hull(views, 1)
    sphere = 4 / 3 * np.pi * RADIUS**3
    assert strict.volume < 0.8 * sphere
    assert tolerant.volume > 0.97 * sphere


def test_silhouettes_that_miss_each_other_are_an_error():
    views = _views(4)
    views[0].mask[:] = False
    views[0].mask[:5, :5] = True  # a corner blob no other view agrees with
    with pytest.raises(ValueError, match="do not intersect"):
        bounds(views[:2])
