"""A bitmap baked from the photos: each texel the least-squares value that the photos
seeing it ask for under the scene's light and the other constants, before any
gradient step.

A principled BSDF's diffuse lobe is linear in its base colour and its specular lobe
does not depend on it, so a pixel's radiance is ``I = a D + S``: ``S`` rendered with
the bitmap at 0, ``D + S`` with it at 1. Over the pixels whose centre's ray meets the
specimen at texel ``t`` in every view, per channel,
``a_t = sum D (I - S) / sum D^2``: the photos' detail at their own resolution,
which a gradient fit through small windows and a few dozen steps does not reach
(docs/decisions.md, "Texture"). Texels no pixel sees take
the value of the nearest texel seen (chart gutters: bilinear lookups near a
chart's edge read them).

The specimen's light reflected onto itself makes ``I`` only nearly linear in ``a``:
``D`` holds the bounces at colour 1, which a darker surface does not return, so the
first solution renders darker than the photos where the surface sees itself (a
temple's colonnade), and the render's pixel filter and bilinear lookups blur what
the nearest texel assumed. Each further round (``rounds``) renders the scenes with
the bitmap as it stands (``R``) and moves every texel by
``sum D (I - R) / sum D^2``: a Gauss-Newton step with ``D`` for the Jacobian, whose
fixed point is where the renders themselves match the photos in least squares.

Where the light's level is only a guess (no surface of known reflectance fixed it,
pipeline.render.light), it may be too dim for the photos' brightest texels, which
then ask for colours above the upper bound and are cut to it: the texture loses its
contrast. Given the scenes to relight, the bake then finds the smallest factor
``k >= 1`` on every emitter at which all but ``HEADROOM`` of the seen texels fit under
the bound, multiplies their light by it and, the whole render being scaled by ``k``,
solves ``a_t = (sum D I - k sum D S) / (k sum D^2)``. A later round that brightens
more than ``HEADROOM`` of the texels past the bound raises the light again, by the
factor that brings them under it, and divides the texels by it (the next round
corrects what the specimen's light on itself makes of that).

Limitations: each pixel weighs by its ``D^2`` alone (no grazing-angle or
resolution weight beyond it); a highlight the light does not explain, or an edge
the mesh misses, pulls its texels by least squares (no robust loss); a texel is
the nearest one to the ray's UV (no bilinear splat); a round's render brings its
Monte Carlo noise into the step.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from pipeline.core import progress
from pipeline.fit.loop import FitView, seed
from pipeline.render.light import rescale_scenes

SEEN = 1e-6
"""A texel counts as seen when its sum of D^2 exceeds this fraction of the largest."""
HEADROOM = 0.01
"""Fraction of the seen texels whose colour may stay cut to the upper bound when the
light is raised: a few specular glints or mesh edges the light cannot explain should
not dim everything else."""


def _put_bitmaps(scenes: dict, key: str, values: dict) -> None:
    """``values[id(scene)]`` (a tensor) as each scene's bitmap at ``key``."""
    import mitsuba as mi

    for index, scene in scenes.items():
        params = mi.traverse(scene)
        params[key] = values[index]
        params.update()


def pixel_rays(sensor):
    """The rays through the centres of ``sensor``'s film pixels (row by row) and the
    film's (height, width)."""
    import mitsuba as mi

    film = sensor.film().size()
    width, height = int(film[0]), int(film[1])
    x, y = np.meshgrid((np.arange(width) + 0.5) / width, (np.arange(height) + 0.5) / height)
    rays, _ = sensor.sample_ray(0.0, 0.0, mi.Point2f(x.ravel(), y.ravel()), mi.Point2f(0.5, 0.5))
    return rays, (height, width)


def texels_hit(view: FitView, shape_id: str, size: tuple[int, int]) -> np.ndarray:
    """(h, w) flat index of the texel (in a ``size`` = (rows, columns) bitmap) that the
    ray through each pixel's centre meets on the shape ``shape_id``; -1 where the ray
    meets nothing or another shape. Rows follow v, columns u (Mitsuba's bitmap
    lookup: texel (i, j) covers v in [i, i + 1) / rows, u in [j, j + 1) / columns)."""
    import drjit as dr
    import mitsuba as mi

    rays, (height, width) = pixel_rays(view.sensor)
    hit = view.scene.ray_intersect(rays)
    target = [s for s in view.scene.shapes() if s.id() == shape_id]
    on_shape = hit.is_valid() & (hit.shape == mi.ShapePtr(target[0])) if target else dr.zeros(mi.Bool, 1)
    uv = np.array(hit.uv)
    rows, columns = size
    row = np.clip(np.floor(np.mod(uv[1], 1.0) * rows), 0, rows - 1).astype(np.int64)
    column = np.clip(np.floor(np.mod(uv[0], 1.0) * columns), 0, columns - 1).astype(np.int64)
    index = np.where(np.array(on_shape, dtype=bool), row * columns + column, -1)
    return index.reshape(height, width)


def bake_bitmap(
    views: list[FitView],
    key: str,
    shape_id: str,
    size: tuple[int, int],
    spp: int,
    bounds: tuple[float, float],
    relit: list | None = None,
    rounds: int = 1,
) -> tuple[np.ndarray, float, float]:
    """The (rows, columns, 3) bitmap at ``key`` (the base colour of shape ``shape_id``)
    that fits ``views``' photos by least squares (module docstring), held in
    ``bounds``, the fraction of texels some pixel saw, and the factor on the light
    that the bitmap assumes: 1, or with scenes in ``relit`` (whose light's level is
    free) the smallest that keeps the texels under the upper bound, by which their
    light is then multiplied (pipeline.render.light.rescale_scenes). Each view renders
    twice at ``spp`` with its own integrator, and once more in each of the
    ``rounds - 1`` rounds after the first (none when no texel is seen); its weight's
    pixels count. The scenes' bitmap is put back as it was."""
    import mitsuba as mi

    scenes = {id(v.scene): v.scene for v in views}
    before = {index: mi.TensorXf(mi.traverse(scene)[key]) for index, scene in scenes.items()}
    rows, columns = size
    texels = rows * columns
    renders: dict[float, dict[str, np.ndarray]] = {}
    for value in (0.0, 1.0):
        _put_bitmaps(scenes, key, dict.fromkeys(scenes, mi.TensorXf(np.full((2, 2, 3), value, np.float32))))
        renders[value] = {
            v.name: render_view(v, spp, i)
            for i, v in enumerate(progress.track(views, f"bake: renders with the colour at {value:g}"))
        }
    # per view, the pixels that count: their texel, D and the photo; per texel and
    # channel: sum D I, sum D S and sum D^2
    pixels = []
    lit, dark, denominator = np.zeros((texels, 3)), np.zeros((texels, 3)), np.zeros((texels, 3))
    for view in progress.track(views, "bake: photos onto texels"):
        texel = texels_hit(view, shape_id, size)
        counts = (texel >= 0) & (view.weight > 0 if view.weight is not None else True)
        specular = renders[0.0][view.name][counts]
        shading = renders[1.0][view.name][counts] - specular
        photo, at = view.reference[counts], texel[counts]
        lit += _per_texel(at, shading * photo, texels)
        dark += _per_texel(at, shading * specular, texels)
        denominator += _per_texel(at, shading**2, texels)
        pixels.append((view, counts, at, shading, photo))
    del renders
    seen = denominator.min(axis=1) > SEEN * denominator.max()
    free = bool(relit) and seen.any()  # a light whose level may rise, and texels to say by how much
    scale = _light_scale(lit[seen], dark[seen], denominator[seen], bounds[1]) if free else 1.0
    if scale != 1.0:  # an update with nothing changed would still rebuild every scene's emitters
        rescale_scenes(relit, scale)
    numerator = lit - scale * dark
    # after a rescale every render, D included, is ``scale`` times brighter
    texture = np.divide(numerator, scale * denominator, out=np.zeros_like(numerator), where=denominator > 0)
    texture = fill_unseen(np.clip(texture, *bounds), seen, size)
    for round_ in range(1, rounds if seen.any() else 1):  # no texel seen: nothing to move
        _put_bitmaps(scenes, key, dict.fromkeys(scenes, mi.TensorXf(texture.reshape(rows, columns, 3))))
        step = np.zeros((texels, 3))
        for i, (view, counts, at, shading, photo) in enumerate(progress.track(pixels, f"bake: round {round_ + 1}")):
            residual = photo - render_view(view, spp, (round_ + 1) * len(views) + i)[counts]
            step += _per_texel(at, shading * residual, texels)
        texture = texture + np.divide(step, scale * denominator, out=np.zeros_like(step), where=denominator > 0)
        # the rounds brighten what the first solution darkened: the light rises again
        # where more than HEADROOM of the texels would pass the bound
        needed = float(np.quantile(texture[seen].max(axis=1), 1.0 - HEADROOM)) / bounds[1] if free else 1.0
        if needed > 1.0:
            rescale_scenes(relit, needed)
            scale, texture = scale * needed, texture / needed
        texture = fill_unseen(np.clip(texture, *bounds), seen, size)
    _put_bitmaps(scenes, key, before)
    return texture.reshape(rows, columns, 3).astype(np.float32), float(seen.mean()), scale


def render_view(view: FitView, spp: int, index: int) -> np.ndarray:
    """``view`` rendered with its own integrator at ``spp``, seeded by ``index`` (as an array)."""
    import mitsuba as mi

    return np.array(mi.render(view.scene, sensor=view.sensor, integrator=view.integrator, spp=spp, seed=seed(index)))


def _per_texel(at: np.ndarray, values: np.ndarray, texels: int) -> np.ndarray:
    """(texels, channels): ``values`` (pixels, channels) summed per texel ``at``."""
    return np.stack([np.bincount(at, values[:, c], texels) for c in range(values.shape[1])], axis=1)


def fill_unseen(texture: np.ndarray, seen: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(texels, 3) ``texture`` whose unseen texels take their nearest seen texel's value."""
    if not seen.any():
        return texture
    _, (near_row, near_column) = ndimage.distance_transform_edt(~seen.reshape(size), return_indices=True)
    return texture.reshape(*size, 3)[near_row, near_column].reshape(-1, 3)


def _light_scale(lit: np.ndarray, dark: np.ndarray, denominator: np.ndarray, upper: float) -> float:
    """The smallest ``k >= 1`` at which all but HEADROOM of the texels (rows: sums of
    D I, D S and D^2 per channel) have ``(lit - k dark) / (k denominator) <= upper``
    in every channel: per texel, ``k >= lit / (upper denominator + dark)``."""
    needed = np.divide(lit, upper * denominator + dark, out=np.zeros_like(lit), where=denominator > 0)
    return max(1.0, float(np.quantile(needed.max(axis=1), 1.0 - HEADROOM)))
