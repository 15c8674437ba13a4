"""Photos of a textured cube with a bowl-shaped dent in its top face, ray-marched in
numpy: a concavity that no silhouette shows (the visual hull keeps the top flat) but
that the photos' texture does, for stereo."""

import numpy as np

from pipeline.camera.model import Intrinsics, Pose
from tests.support.sphere_views import ring_poses

HALF = 0.04
"""Half the cube's side, metres; the cube is centred at the origin."""
DENT_CENTRE = np.array([0.0, 0.0, HALF + 0.01])
DENT_RADIUS = 0.03
"""The dent is the cube minus this sphere: 2 cm deep, 5.7 cm wide on the 8 cm face."""
K = Intrinsics(120, 120, 190.0, 190.0, 59.5, 59.5)


def signed_distance(points: np.ndarray) -> np.ndarray:
    """A bound on the distance to the dented cube, negative inside."""
    q = np.abs(points) - HALF
    box = np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)
    sphere = np.linalg.norm(points - DENT_CENTRE, axis=-1) - DENT_RADIUS
    return np.maximum(box, -sphere)


def _albedo(points: np.ndarray) -> np.ndarray:
    """A solid texture (the same colour from every view), a few millimetres in scale."""
    rng = np.random.default_rng(7)
    value = np.full(points.shape[:-1], 0.5)
    for _ in range(12):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        value += 0.08 * np.sin(points @ direction * rng.uniform(150, 500) + rng.uniform(0, 2 * np.pi))
    return np.clip(value, 0.05, 0.95)


def render(pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """Grey image (float32, shaded by a light from above) and the exact mask."""
    u, v = np.meshgrid(np.arange(K.width), np.arange(K.height))
    rays = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u, float)], axis=-1) @ pose.R
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    t = np.zeros(rays.shape[:-1])
    for _ in range(100):
        distance = signed_distance(pose.center + t[..., None] * rays)
        t += np.where(distance > 1e-6, distance, 0.0)  # a ray stops where it meets the surface
    points = pose.center + t[..., None] * rays
    hit = signed_distance(points) < 1e-5
    step = 1e-5
    normals = np.stack(
        [signed_distance(points + step * e) - signed_distance(points - step * e) for e in np.eye(3)], axis=-1
    )
    normals /= np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-12)
    light = np.array([0.3, 0.2, 1.0]) / np.linalg.norm([0.3, 0.2, 1.0])
    shade = 0.35 + 0.65 * np.clip(normals @ light, 0.0, 1.0)
    image = np.where(hit, _albedo(points) * shade, 0.02)
    return image.astype(np.float32), hit


def cameras(count: int = 12) -> list[Pose]:
    """``count`` cameras 0.35 m from the cube, round it at 40 and 60 degrees of elevation."""
    return ring_poses(count, 0.35, 40.0, 60.0)
