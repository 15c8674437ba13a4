"""Procedural textures of the synthetic studio's set: a dark turntable plate with
sparse white dots, and a still, textured room as an equirectangular environment map.

Both are what real captures bring and the board-lit bird does not: the plate gives
a turntable few, isolated features that turn with the specimen; the room gives
many features that do not (a fixed camera sees it unchanged in every photo) and,
as the environment, lights the specimen and shows in its highlights.
"""

from __future__ import annotations

import numpy as np

PLATE_INK, PLATE_DOT = 0.04, 0.80
"""Reflectance of the dark plate and of its white dots."""


def dotted_plate(seed: int, dots: int = 40, dot_radius: float = 0.03, size: int = 1024) -> np.ndarray:
    """(size, size) reflectance of a unit disk with ``dots`` white dots of ``dot_radius``
    (both in units of the disk's radius), in the parameterisation of Mitsuba's disk:
    column u = r, row v = atan2(y, x) / 2 pi (first row at v = 0)."""
    u = (np.arange(size) + 0.5) / size
    v = (np.arange(size) + 0.5) / size
    r, phi = np.meshgrid(u, 2 * np.pi * v)
    x, y = r * np.cos(phi), r * np.sin(phi)
    plate = np.full((size, size), PLATE_INK, np.float32)
    for cx, cy in dot_centres(seed, dots, dot_radius):
        # Only columns within a dot's radius of its centre's radius can hold it.
        near = np.flatnonzero(np.abs(u - np.hypot(cx, cy)) < 1.001 * dot_radius)
        inside = np.hypot(x[:, near] - cx, y[:, near] - cy) < dot_radius
        plate[:, near] = np.where(inside, PLATE_DOT, plate[:, near])
    return plate


def dot_centres(seed: int, dots: int, dot_radius: float) -> list[np.ndarray]:
    """dotted_plate's dot centres (x, y in units of the disk's radius): spread over the
    plate at least two diameters apart, isolated features."""
    rng = np.random.default_rng(seed)
    centres: list[np.ndarray] = []
    while len(centres) < dots:
        candidate = rng.uniform(-0.95, 0.95, 2)
        if np.hypot(*candidate) < 0.95 and all(np.hypot(*(candidate - c)) > 4 * dot_radius for c in centres):
            centres.append(candidate)
    return centres


def room_map(seed: int, width: int = 2048, height: int = 1024) -> np.ndarray:
    """(height, width, 3) linear radiance of a room as an equirectangular map (row 0 at
    the zenith): a bright ceiling, walls with furniture, posters and windows (random
    rectangles, some bright), a darker floor, and fine band-limited texture on every
    surface so that SIFT finds corners and blobs on it at a few pixels per degree."""
    rng = np.random.default_rng(seed)
    azimuth = (np.arange(width) + 0.5) / width * 2 * np.pi
    elevation = np.pi / 2 - (np.arange(height) + 0.5) / height * np.pi
    room = np.empty((height, width, 3), np.float32)
    room[:] = (0.30, 0.27, 0.22)  # walls
    room[elevation > np.radians(50)] = (0.55, 0.55, 0.52)  # ceiling
    room[elevation < np.radians(-15)] = (0.12, 0.10, 0.09)  # floor
    # A rectangle is a band of rows (elevations) times a band of columns (azimuths).
    for _ in range(90):
        left, wide = rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(3, 28))
        bottom, tall = np.radians(rng.uniform(-20, 40)), np.radians(rng.uniform(3, 30))
        rows = np.flatnonzero((elevation > bottom) & (elevation < bottom + tall))
        columns = np.flatnonzero((azimuth - left) % (2 * np.pi) < wide)
        colour = rng.uniform(0.03, 0.7, 3) * (rng.uniform(2.0, 4.0) if rng.uniform() < 0.08 else 1.0)
        room[np.ix_(rows, columns)] = colour
    # Fine texture: random-phase sinusoids on the sphere, a few degrees across; a
    # direction's dot product with an axis splits into a row term and a column term.
    cos_el, sin_el = np.cos(elevation)[:, None], np.sin(elevation)[:, None]
    cos_az, sin_az = np.cos(azimuth)[None, :], np.sin(azimuth)[None, :]
    texture = np.zeros((height, width), np.float32)
    for _ in range(16):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        along = cos_el * (cos_az * axis[0] + sin_az * axis[1]) + sin_el * axis[2]
        texture += np.sin(along * rng.uniform(60, 240) + rng.uniform(0, 2 * np.pi)).astype(np.float32)
    room *= (1 + 0.25 * texture / np.sqrt(8))[..., None]
    return np.clip(room, 0.0, None)
