import numpy as np
import pytest

from pipeline.geometry.visual_hull import Grid, bounds, convergence_point, hull_field, surface
from tests.support.sphere_views import RADIUS, K, sphere_views


def _hull(views, tolerance=0, resolution=48):
    lo, hi = bounds(views, tolerance)
    grid = Grid.around(lo, hi, resolution)
    return surface(hull_field(grid.centres(), views, tolerance), grid)


def test_convergence_point_is_where_the_cameras_look():
    np.testing.assert_allclose(convergence_point(v.pose for v in sphere_views()), 0, atol=1e-9)


def test_hull_of_a_sphere_is_closed_and_slightly_larger():
    mesh = _hull(sphere_views())
    sphere = 4 / 3 * np.pi * RADIUS**3
    assert mesh.is_watertight
    # A hull contains the object; ten views leave it a few per cent larger.
    assert sphere * 0.97 < mesh.volume < sphere * 1.25, mesh.volume / sphere
    distance = np.linalg.norm(mesh.vertices, axis=1)
    assert np.median(np.abs(distance - RADIUS)) < 0.04 * RADIUS


def test_tolerance_survives_one_bad_mask():
    views = sphere_views()
    views[3].mask[:, : K.width // 2 + 8] = False  # half of the specimen missing in one view
    strict, tolerant = _hull(views, 0), _hull(views, 1)
    sphere = 4 / 3 * np.pi * RADIUS**3
    assert strict.volume < 0.8 * sphere
    assert tolerant.volume > 0.97 * sphere


def test_silhouettes_that_miss_each_other_are_an_error():
    views = sphere_views(4)
    views[0].mask[:] = False
    views[0].mask[:5, :5] = True  # a corner blob no other view agrees with
    with pytest.raises(ValueError, match="do not intersect"):
        bounds(views[:2])
