"""A texture fitted coarse to fine: its shape at each level, resampling between
levels, and the files and scene element that carry it (a bitmap on the mesh's
UVs, or a grid volume over the specimen's box for a medium's albedo)."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np
from scipy import ndimage

from pipeline import logger
from pipeline.fit import engine
from pipeline.fit.outputs import write_texture_files
from pipeline.render import materials, scene_xml


def level_shapes(
    levels: int, max_resolution: int, max_grid_resolution: int, kind: str, box_extent: np.ndarray
) -> list[tuple[int, ...]]:
    """Spatial shape of the texture at each level, coarsest first: (side, side) for a
    bitmap, (z, y, x) proportional to the box for a grid."""
    shapes = []
    for level in range(levels):
        factor = 2 ** (levels - 1 - level)
        if kind == "bitmap":
            side = max(max_resolution // factor, 2)
            shapes.append((side, side))
        else:
            longest = max(max_grid_resolution // factor, 2)
            x, y, z = np.maximum(np.round(longest * box_extent / box_extent.max()), 2).astype(int)
            shapes.append((int(z), int(y), int(x)))
    return shapes


def resample(texture: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """Linear resampling to a new spatial shape, texel centres aligned."""
    factors = [new / old for new, old in zip(shape, texture.shape[:-1])] + [1.0]
    return ndimage.zoom(texture, factors, order=1, mode="nearest", grid_mode=True).astype(np.float32)


def write_texture(folder: Path, slot: materials.TextureSlot, texture: np.ndarray, box: np.ndarray) -> ET.Element:
    """Write the texture's files into ``folder``; the XML element that loads them."""
    write_texture_files(folder, slot, texture)
    holder = ET.Element("holder")
    name = slot.parameter
    if slot.kind == "bitmap":
        return scene_xml.plugin(
            holder, "texture", {"type": "bitmap", "id": f"specimen_{name}", "filename": f"{name}.exr"}
        )
    element = scene_xml.plugin(
        holder, "volume", {"type": "gridvolume", "id": f"specimen_{name}", "filename": f"{name}.vol"}
    )
    lower, upper = box
    to_world = np.diag([*(upper - lower), 1.0])
    to_world[:3, 3] = lower
    scene_xml.transform_matrix(element, to_world)
    return element


@dataclass
class TextureFit:
    """What the levels are fitted on."""

    training: list[engine.FitView]
    validation: list[engine.FitView]
    parameters: list[engine.FitParameter]
    """The texture first, then the constants refitted with it."""
    settings: engine.FitSettings


@dataclass
class LevelsFit:
    """The constants' refit and the texture's levels, as fit_constants_then_levels left them."""

    result: engine.FitResult
    """The last level's fit."""
    texture: np.ndarray
    """The texture after the last level."""
    constants: list[str]
    """The model's other parameters, fitted along with the texture."""
    refitted: dict[str, list[float]]
    """The constants' values from their refit alone (empty without constants)."""
    constant_error: float | None
    """The constant model's held-out error, which the texture must beat."""
    log: list[dict]
    """Every fit's steps, joined, each with its level and resolution."""
    levels: list[dict]
    """Per level: resolution, iterations, best step, held-out error before and after."""
    constants_fit: dict | None
    """The same for the constants' refit; None without constants."""


def fit_constants_then_levels(
    slot: materials.TextureSlot,
    texture: np.ndarray,
    shapes: list[tuple[int, ...]],
    fit: TextureFit,
    start: Callable[[], np.ndarray] | None = None,
) -> LevelsFit:
    """The constants alone (texture constant), then the texture level by level.
    ``start``: the finest level's starting texture, made once the constants are
    refitted (a bake from the photos, pipeline.fit.bake); only that level is then
    fitted."""
    import mitsuba as mi

    log, levels = [], []

    def record(result: engine.FitResult, level: int | str, shape: tuple[int, ...] | None) -> dict:
        offset = len(log)
        log.extend(
            {**e, "iteration": e["iteration"] + offset, "level": level, "resolution": shape and list(shape)}
            for e in result.log
        )
        return {
            "resolution": shape and list(shape),
            "iterations": len(result.log),
            "best_iteration": result.best_iteration,
            "averaged": result.averaged,
            "start_validation_mse": result.start_validation_error,
            "validation_mse": result.validation_error,
            "stopped": result.stopped,
            "skipped_gradients": result.skipped_gradients,
        }

    constants = [p.name for p in fit.parameters[1:]]
    refitted, constant_error, constants_fit = {}, None, None
    if constants:
        # The constants alone first, the colour still constant: the texture must then
        # earn its place against the refitted constant model, not against
        # fit_material's (a texture-free specimen's texture was kept on what the
        # constants alone gained).
        result = engine.fit(fit.parameters[1:], fit.training, fit.validation, fit.settings)
        refitted, constant_error = {n: result.values[n] for n in constants}, result.validation_error
        constants_fit = record(result, "constants", None)
        logger.info("constants refitted: held-out MSE %s", result.validation_error)
    scenes = {id(v.scene): v.scene for v in fit.training + fit.validation}
    if start is not None:
        if constant_error is None and fit.validation:
            # the first level starts from the bake: the constant's error is measured here
            integrator = fit.validation[0].integrator
            constant_error = engine.heldout_error(fit.validation, fit.settings.validation_spp, integrator)
        texture, shapes = start(), shapes[-1:]
    for level, shape in enumerate(shapes):
        texture = resample(texture, shape)
        for scene in scenes.values():
            params = mi.traverse(scene)
            params[slot.key] = mi.TensorXf(texture)
            params.update()
        result = engine.fit(
            fit.parameters, fit.training, fit.validation, replace(fit.settings, seed=fit.settings.seed + level + 1)
        )
        texture = result.textures[slot.parameter]
        if constant_error is None:
            constant_error = result.start_validation_error
        levels.append(record(result, level, shape))
        logger.info("level %d (%s texels): held-out MSE %s", level, "x".join(map(str, shape)), result.validation_error)
    return LevelsFit(result, texture, constants, refitted, constant_error, log, levels, constants_fit)
