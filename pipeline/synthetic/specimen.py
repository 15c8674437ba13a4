"""Procedural specimens for synthetic captures.

The bird is the smooth union of signed distance functions (body, head, eyes, beak,
wings, tail, legs, feet) polygonised by marching cubes: one watertight, genus-0
surface. Overlapping closed parts would do for an opaque object, but a
translucent one would refract at every buried interface. The vase is a body of
revolution: a specimen whose outline cannot tell a turntable's angle.

Coordinates are metres in the world frame of the synthetic captures: z up, the
turntable plate in the plane z = 0, the bird standing on it facing +x.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import trimesh
from skimage import measure

from pipeline.geometry import meshlab


def _ellipsoid(p, centre, radii):
    # Scaled-sphere approximation of the ellipsoid distance; exact enough for
    # shapes that are only blended and meshed, and it keeps gradients smooth.
    q = (p - np.asarray(centre)) / np.asarray(radii)
    return (np.linalg.norm(q, axis=-1) - 1.0) * np.min(radii)


def _capsule(p, a, b, radius):
    a, b = np.asarray(a), np.asarray(b)
    ab = b - a
    h = np.clip(((p - a) @ ab) / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(p - (a + h[..., None] * ab), axis=-1) - radius


def _cone(p, tip, base, base_radius):
    """A rounded cone from ``base`` (radius base_radius) to ``tip``."""
    tip, base = np.asarray(tip), np.asarray(base)
    axis = tip - base
    length = np.linalg.norm(axis)
    h = np.clip(((p - base) @ axis) / length**2, 0.0, 1.0)
    radius = base_radius * (1.0 - h) + 0.0005
    return np.linalg.norm(p - (base + h[..., None] * axis), axis=-1) - radius


def _smooth_union(a, b, k):
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b * (1 - h) + a * h - k * h * (1 - h)


def bird_sdf(p: np.ndarray, size: float = 0.09) -> np.ndarray:
    """Signed distance (metres) of a bird figurine about ``size`` long, feet at z = 0."""
    s = size / 0.09
    p = p / s
    body = _ellipsoid(p, (0.0, 0.0, 0.045), (0.036, 0.024, 0.024))
    head = _ellipsoid(p, (0.030, 0.0, 0.074), (0.015, 0.014, 0.015))
    beak = _cone(p, (0.062, 0.0, 0.071), (0.040, 0.0, 0.073), 0.0065)
    eyes = np.minimum(
        _ellipsoid(p, (0.040, 0.0105, 0.079), (0.004, 0.004, 0.004)),
        _ellipsoid(p, (0.040, -0.0105, 0.079), (0.004, 0.004, 0.004)),
    )
    wings = np.minimum(
        _ellipsoid(p, (-0.006, 0.022, 0.052), (0.028, 0.006, 0.014)),
        _ellipsoid(p, (-0.006, -0.022, 0.052), (0.028, 0.006, 0.014)),
    )
    tail = _ellipsoid(p, (-0.045, 0.0, 0.056), (0.020, 0.012, 0.004))
    legs = np.minimum(
        _capsule(p, (0.004, 0.010, 0.028), (0.006, 0.011, 0.004), 0.0028),
        _capsule(p, (0.004, -0.010, 0.028), (0.006, -0.011, 0.004), 0.0028),
    )
    feet = np.minimum(
        _ellipsoid(p, (0.011, 0.011, 0.0032), (0.010, 0.006, 0.0032)),
        _ellipsoid(p, (0.011, -0.011, 0.0032), (0.010, 0.006, 0.0032)),
    )
    d = _smooth_union(body, head, 0.010)
    d = _smooth_union(d, beak, 0.003)
    d = _smooth_union(d, eyes, 0.002)
    d = _smooth_union(d, wings, 0.006)
    d = _smooth_union(d, tail, 0.008)
    d = _smooth_union(d, legs, 0.006)
    d = _smooth_union(d, feet, 0.003)
    # Flat soles: cut at z = 0 so the bird stands on the plate instead of
    # touching it in a point (which would make the ground contact ill-defined).
    d = np.maximum(d, -p[..., 2])
    return d * s


def bird_mesh(size: float = 0.09, resolution: int = 112, faces: int = 20000) -> trimesh.Trimesh:
    """The bird as a watertight triangle mesh with about ``faces`` faces."""
    lo = np.array([-0.075, -0.045, -0.004]) * size / 0.09
    hi = np.array([0.075, 0.045, 0.100]) * size / 0.09
    spacing = (hi - lo).max() / resolution
    axes = [np.arange(lo[i], hi[i] + spacing, spacing) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    sdf = bird_sdf(grid, size)
    verts, tris, _, _ = measure.marching_cubes(sdf, level=0.0, spacing=(spacing,) * 3)
    mesh = trimesh.Trimesh(verts + lo, tris[:, ::-1], process=True)
    if len(mesh.faces) > faces:
        with tempfile.TemporaryDirectory() as folder:
            full, reduced = Path(folder) / "full.ply", Path(folder) / "reduced.ply"
            mesh.export(full)
            meshlab.run("decimate", full, reduced, {"faces": faces})
            reduced_mesh = trimesh.load(reduced, force="mesh", process=False)
        mesh = trimesh.Trimesh(reduced_mesh.vertices, reduced_mesh.faces, process=True)
    trimesh.repair.fix_normals(mesh)
    return mesh


def vase_mesh(height: float = 0.09, sections: int = 128) -> trimesh.Trimesh:
    """A vase as a watertight body of revolution about z, base at z = 0, as tall as the
    bird: a bulge low down and a narrower neck, so that turned over it is not the same
    shape, but its outline is the same from every side of a turn."""
    z = np.linspace(0.0, height, 60)
    radius = (0.024 + 0.008 * np.sin(1.3 * np.pi * z / height) - 0.006 * (z / height) ** 2) * height / 0.09
    profile = np.column_stack([np.r_[0.0, radius, 0.0], np.r_[0.0, z, height]])
    mesh = trimesh.creation.revolve(profile, sections=sections)
    trimesh.repair.fix_normals(mesh)
    return mesh


BLOTCH_SCALE = 0.003
"""Length scale of ``blotch_colours``' pattern, metres."""


def blotch_colours(points: np.ndarray, base: np.ndarray, seed: int, scale: float = BLOTCH_SCALE) -> np.ndarray:
    """Linear-RGB albedo with blotches one to two centimetres across at the default
    ``scale`` (smaller in proportion to it): features for SIFT.

    A sum of random-phase sinusoids in 3D (band-limited noise), so the pattern is
    continuous on the surface whatever its parameterisation, thresholded into
    spots around ``base``.
    """
    rng = np.random.default_rng(seed)
    noise = np.zeros(len(points))
    for _ in range(24):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        frequency = rng.uniform(0.6, 1.6) / scale
        noise += np.sin(points @ direction * frequency + rng.uniform(0, 2 * np.pi))
    noise /= np.sqrt(12.0)
    spots = np.clip(noise * 1.5, -1.0, 1.0)[:, None]
    dark = base * 0.35
    light = np.minimum(base * 1.6 + 0.05, 0.95)
    colours = np.where(spots > 0, base + spots * (light - base), base - spots * (dark - base))
    return np.clip(colours, 0.0, 1.0)
