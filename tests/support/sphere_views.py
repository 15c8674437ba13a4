"""Views of a sphere of radius RADIUS at the origin, with exact masks: a specimen
whose visual hull is known, for the hull and the pose checks built on it."""

import numpy as np

from pipeline.camera.model import Intrinsics, Pose
from pipeline.geometry.visual_hull import View

RADIUS = 0.05
K = Intrinsics(120, 90, 150.0, 150.0, 59.5, 44.5)


def sphere_mask(pose: Pose) -> np.ndarray:
    """Exact silhouette of a sphere at the origin: pixels whose ray passes within RADIUS."""
    u, v = np.meshgrid(np.arange(K.width), np.arange(K.height))
    rays = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u, float)], axis=-1)
    rays = rays @ pose.R  # camera to world directions
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    along = -(rays @ pose.center)
    closest = pose.center + along[..., None] * rays
    return np.linalg.norm(closest, axis=-1) < RADIUS


def ring_poses(count: int, distance: float, low_deg: float, high_deg: float) -> list[Pose]:
    """``count`` cameras ``distance`` from the origin looking at it, evenly round it,
    alternately at ``low_deg`` and ``high_deg`` of elevation."""
    poses = []
    for i in range(count):
        azimuth, elevation = 2 * np.pi * i / count, np.radians(low_deg if i % 2 == 0 else high_deg)
        centre = distance * np.array(
            [np.cos(azimuth) * np.cos(elevation), np.sin(azimuth) * np.cos(elevation), np.sin(elevation)]
        )
        poses.append(Pose.look_at(centre, [0, 0, 0]))
    return poses


def sphere_views(count: int = 10) -> list[View]:
    """``count`` cameras 0.3 from the sphere, round it at alternating elevations."""
    views = []
    for pose in ring_poses(count, 0.3, 20.0, 50.0):
        views.append(View(K, pose, sphere_mask(pose)))
    return views
