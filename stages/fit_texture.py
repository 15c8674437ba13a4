"""Stage fit_texture: a colour that varies over the specimen, fitted coarse to fine.

Starts from fit_material's scene and replaces one constant of the model by a
texture initialised to that constant (pipeline.render.materials.TEXTURE_SLOTS):

==========================  ==============================================================
model                       texture
==========================  ==============================================================
opaque, principled          base_color as a bitmap on the mesh's UVs (uv stage)
volumetric                  the medium's albedo as a grid volume over the specimen's box
                            (a medium has no surface to carry a UV texture)
==========================  ==============================================================

With ``refit_constants`` the model's other constants (roughness, spec_trans and
eta; alpha, eta and sigma_t) are fitted again, from fit_material's values and
within its bounds: first alone (``iterations_per_level`` steps, the colour still
constant), then along with the texture at every level. Fitted next to a
constant colour they absorb some of the colour's variation (on the sample bird
roughness ended 0.15 off the truth). The texture is fitted by pipeline.fit.engine
(the same loop, loss, views and held-out photos as fit_material) at ``levels``
resolutions, each twice the last, ending at
``max_resolution`` texels a side (``max_grid_resolution`` along a grid's longest
side); every level starts from the last one's best state, resampled. A
smoothness prior (``smoothness`` times the mean squared difference of
neighbouring texels) keeps texels from absorbing highlights and noise and fills
texels no photo sees from their neighbours.

Model only what the scene needs: with ``texture = "auto"`` the texture is kept
only when it lowers the held-out error by at least ``min_improvement``
(relative) below that of the refitted constants; otherwise the scene keeps the
constant colour, with the refitted constants, and says why.

Outputs, all in textured/ (exported to CAPTURE/output/textured/):

===================  ==========================================================
file                 content
===================  ==========================================================
scene.xml, ...       the scene with the texture in specimen.xml; renders as-is
base_color.exr/.png  the bitmap, linear EXR (what the scene loads) and sRGB PNG
albedo.vol/.png      the grid volume (Mitsuba's format) and its z slices as PNG
params.json          kept or not and why, validation error with and without the
                     texture, per level (and for the constants alone):
                     resolution, iterations, best iteration; ``params`` and
                     ``bounds``: the scene's values as in fit_material's
                     params.json (a kept texture's mean for the textured one);
                     the texture's ``smoothness`` and ``learning_rate``, which
                     fit_geometry's material passes continue with
log.jsonl            per iteration: level, resolution, loss, validation error,
                     the texture's per-channel mean, seconds
loss.png             training loss and validation error against iteration
heldout/             held-out renders, references and masks (as fit_material's)
===================  ==========================================================

Limitations: the prior links texels that are neighbours in the atlas, also
across chart seams; UV charts (xatlas) leave texels between charts that only
the prior sets. Held-out photos are fit_material's.
"""

from __future__ import annotations

import shutil
import xml.etree.ElementTree as ET
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import trimesh
from scipy import ndimage

from pipeline import logger
from pipeline.core.config import Range
from pipeline.core.stage import Stage, StageInputs, StageResult
from pipeline.fit import engine
from pipeline.fit.outputs import write_fit_log, write_heldout, write_texture_files
from pipeline.fit.views import load_views
from pipeline.formats.cameras import read_views
from pipeline.formats.masks import read_masks
from pipeline.formats.pinhole import linear_photos
from pipeline.formats.scene_folder import (
    HELDOUT,
    MESH_PLY,
    PARAMS_JSON,
    SPECIMEN_XML,
    copy_scene,
    read_json,
    write_json,
)
from pipeline.render import materials, mitsuba_variant, scene_xml

@dataclass(frozen=True)
class Config:
    """Texture fitting, coarse to fine."""

    texture: Literal["auto", "on", "off"] = "auto"
    """auto: keep the texture only when it lowers the held-out error by
    ``min_improvement``; on: always keep it; off: keep fit_material's constant."""
    min_improvement: Annotated[float, Range(0.0, 1.0)] = 0.05
    """Relative drop of held-out MSE a texture must bring to be kept (auto)."""
    levels: Annotated[int, Range(1, None)] = 3
    """Resolutions fitted, each twice the last."""
    max_resolution: Annotated[int, Range(4, None)] = 128
    """Texels per side of the finest bitmap."""
    max_grid_resolution: Annotated[int, Range(4, None)] = 32
    """Voxels along the longest side of the finest albedo grid (volumetric model)."""
    iterations_per_level: Annotated[int, Range(1, None)] = 30
    """Most Adam steps per level."""
    smoothness: Annotated[float, Range(0.0, None)] = 0.05
    """Weight of the neighbour-difference prior (see the module docstring)."""
    learning_rate: Annotated[float, Range(0.0, None, exclusive_lo=True)] = 0.03
    """Adam step of every texel (colour units)."""
    batch: Annotated[int, Range(1, None)] = 2
    """Views rendered per step; their gradients add up before the step."""
    spp: Annotated[int, Range(1, None)] = 16
    """Samples per pixel of each training render."""
    loss: Literal["l2", "dual"] = "dual"
    """l2 or Deng et al.'s dual-buffer estimator (see fit_material)."""
    max_size: Annotated[int, Range(16, None)] = 128
    """Longer side, in pixels, of the window each view is rendered in."""
    erode_px: Annotated[int, Range(0, None)] = 2
    """Mask erosion at full resolution before scoring pixels."""
    validate_every: Annotated[int, Range(1, None)] = 10
    """Iterations between validation renders."""
    validation_spp: Annotated[int, Range(1, None)] = 64
    """Samples per pixel of validation renders (and 4x that for heldout/)."""
    tolerance: Annotated[float, Range(0.0, None)] = 1e-3
    """Stop a level when its mean loss over ``window`` iterations improves by less than this."""
    window: Annotated[int, Range(1, None)] = 10
    """Iterations per window of the tolerance test."""
    refit_constants: bool = True
    """Fit the model's other constants again, alone and then along with the texture
    (see the module docstring); off: they stay as fit_material left them."""
    seed: int = 0
    """Seed of the batch order and the renders."""


def level_shapes(conf: Config, kind: str, box_extent: np.ndarray) -> list[tuple[int, ...]]:
    """Spatial shape of the texture at each level, coarsest first: (side, side) for a
    bitmap, (z, y, x) proportional to the box for a grid."""
    shapes = []
    for level in range(conf.levels):
        factor = 2 ** (conf.levels - 1 - level)
        if kind == "bitmap":
            side = max(conf.max_resolution // factor, 2)
            shapes.append((side, side))
        else:
            longest = max(conf.max_grid_resolution // factor, 2)
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
        return scene_xml.plugin(holder, "texture", {"type": "bitmap", "id": f"specimen_{name}",
                                                    "filename": f"{name}.exr"})  # fmt: skip
    element = scene_xml.plugin(holder, "volume", {"type": "gridvolume", "id": f"specimen_{name}",
                                                  "filename": f"{name}.vol"})  # fmt: skip
    lower, upper = box
    to_world = np.diag([*(upper - lower), 1.0])
    to_world[:3, 3] = lower
    scene_xml.transform_matrix(element, to_world)
    return element


@dataclass
class _Training:
    """What the levels are fitted on."""

    training: list[engine.FitView]
    validation: list[engine.FitView]
    parameters: list[engine.FitParameter]
    """The texture first, then the constants refitted with it."""
    settings: engine.FitSettings


def _fit_constants_then_levels(conf: Config, slot: materials.TextureSlot, texture: np.ndarray,
                               shapes: list[tuple[int, ...]], fit: _Training, report: dict) -> dict:
    """The constants alone (texture constant), then the texture level by level; fills
    ``report`` and returns the last level's result with the texture, the refitted
    constants, the constant model's held-out error and the joined log."""
    import mitsuba as mi

    log, levels = [], []

    def record(result: engine.FitResult, level: int | str, shape: tuple[int, ...] | None) -> dict:
        offset = len(log)
        log.extend({**e, "iteration": e["iteration"] + offset, "level": level, "resolution": shape and list(shape)}
                   for e in result.log)
        return {"resolution": shape and list(shape), "iterations": len(result.log),
                "best_iteration": result.best_iteration, "validation_mse": result.validation_error,
                "stopped": result.stopped}

    constants = [p.name for p in fit.parameters[1:]]
    refitted, constant_error = {}, None
    if constants:
        # The constants alone first, the colour still constant: the texture must then
        # earn its place against the refitted constant model, not against
        # fit_material's (a texture-free specimen's texture was kept on what the
        # constants alone gained).
        result = engine.fit(fit.parameters[1:], fit.training, fit.validation, fit.settings)
        refitted, constant_error = {n: result.values[n] for n in constants}, result.validation_error
        report["constants_fit"] = record(result, "constants", None)
        logger.info("constants refitted: held-out MSE %s", result.validation_error)
    scenes = {id(v.scene): v.scene for v in fit.training + fit.validation}
    for level, shape in enumerate(shapes):
        texture = resample(texture, shape)
        for scene in scenes.values():
            params = mi.traverse(scene)
            params[slot.key] = mi.TensorXf(texture)
            params.update()
        result = engine.fit(fit.parameters, fit.training, fit.validation,
                            replace(fit.settings, seed=conf.seed + level + 1))
        texture = result.textures[slot.parameter]
        if constant_error is None:
            constant_error = result.start_validation_error
        levels.append(record(result, level, shape))
        logger.info("level %d (%s texels): held-out MSE %s", level, "x".join(map(str, shape)), result.validation_error)
    report["levels"] = levels
    return {"result": result, "texture": texture, "constants": constants, "refitted": refitted,
            "constant_error": constant_error, "log": log}


def _keep_texture(conf: Config, constant_error: float | None, texture_error: float) -> tuple[bool, str]:
    """Whether the texture earns its place, and why (``texture``, ``min_improvement``)."""
    if constant_error is None:
        return True, "no held-out photos to decide with: kept"
    improvement = (constant_error - texture_error) / constant_error
    kept = conf.texture == "on" or improvement >= conf.min_improvement
    return kept, (f"held-out MSE {constant_error:.4g} with the constant, {texture_error:.4g} with the texture "
                  f"({100 * improvement:+.1f} %, threshold {100 * conf.min_improvement:g} %)")


def main(conf: Config, inputs: StageInputs, out_dir: Path) -> StageResult:
    # 1. fit_material's scene, without its fit results.
    material_dir = inputs.upstream["fit_material"]["fitted_dir"]
    material = read_json(inputs.upstream["fit_material"]["params"])
    description = read_json(inputs.upstream["scene"]["description"])
    model = description["model"]
    slot = materials.TEXTURE_SLOTS[model]
    textured = copy_scene(material_dir, out_dir / "textured")
    outputs = {"textured_dir": textured, "params": textured / PARAMS_JSON, "heldout": textured / HELDOUT}
    report = {"model": model, "parameter": slot.parameter, "kind": slot.kind, "mode": conf.texture,
              "constant": material["params"][slot.parameter], "held_out": material["held_out"]}
    if conf.texture == "off":
        shutil.copytree(inputs.upstream["fit_material"]["heldout"], textured / HELDOUT)
        report |= {"kept": False, "reason": "texture = off", "params": material["params"], "bounds": material["bounds"]}
        write_json(textured / PARAMS_JSON, report)
        return StageResult(outputs, {"kept": False})

    # 2. The texture at the coarsest level, set to fit_material's constant.
    mesh = trimesh.load(textured / MESH_PLY, force="mesh")
    box = np.array([mesh.bounds[0] - 0.02 * mesh.extents, mesh.bounds[1] + 0.02 * mesh.extents])
    shapes = level_shapes(conf, slot.kind, box[1] - box[0])
    texture = np.broadcast_to(np.float32(material["params"][slot.parameter]), (*shapes[0], 3)).copy()
    specimen = textured / SPECIMEN_XML
    parameter_key = materials.PARAMETERS[slot.parameter].key
    scene_xml.set_values(specimen, {}, specimen, textures={parameter_key: write_texture(textured, slot, texture, box)})

    # 3. The views, fit_material's held-out photos, and the fit: constants, then levels.
    mitsuba_variant.activate(inputs.shared["mitsuba"].variant)
    cameras = read_views(inputs.upstream["sfm"]["cameras"])
    linear = linear_photos(inputs.upstream["undistort"]["pinhole"])
    masks = read_masks(inputs.upstream["masks"]["masks_json"])
    views = [view for view, _ in load_views(textured, description, cameras, linear, masks, conf.max_size,
                                            conf.erode_px, conf.spp)]
    held = set(material["held_out"])
    fit = _Training(
        training=[v for v in views if v.name not in held], validation=[v for v in views if v.name in held],
        parameters=materials.refit_parameters(model, material["bounds"], (conf.learning_rate, conf.smoothness),
                                              conf.refit_constants),
        settings=engine.FitSettings(iterations=conf.iterations_per_level, batch=conf.batch, spp=conf.spp,
                                    loss=conf.loss, validate_every=conf.validate_every,
                                    validation_spp=conf.validation_spp, tolerance=conf.tolerance, window=conf.window,
                                    seed=conf.seed),
    )
    fitted = _fit_constants_then_levels(conf, slot, texture, shapes, fit, report)
    result, texture, constants = fitted["result"], fitted["texture"], fitted["constants"]
    constant_error, texture_error = fitted["constant_error"], report["levels"][-1]["validation_mse"]

    # 4. Keep the texture only if it earns its place.
    kept, reason = _keep_texture(conf, constant_error, texture_error)
    logger.info("texture %s: %s", "kept" if kept else "not kept", reason)
    write_fit_log(textured, fitted["log"])
    if kept:
        write_texture(textured, slot, texture, box)
        constant_values = {n: result.values[n] for n in constants}
    else:
        # fit_material's constant scene, with the refitted constants.
        shutil.copy2(material_dir / SPECIMEN_XML, specimen)
        for leftover in textured.glob(f"{slot.parameter}.*"):
            leftover.unlink()
        constant_values = fitted["refitted"]
    scene_xml.set_values(specimen, {materials.PARAMETERS[n].key: v for n, v in constant_values.items()}, specimen)

    # 5. Held-out renders of the scene kept, and params.json.
    if kept or fitted["refitted"]:
        held_views = [view for view, _ in load_views(textured, description, cameras, linear, masks, conf.max_size,
                                                     conf.erode_px, conf.spp, names=held)]
        write_heldout(held_views, 4 * conf.validation_spp, textured / HELDOUT)
    else:
        shutil.copytree(inputs.upstream["fit_material"]["heldout"], textured / HELDOUT)
    report["params"] = {**material["params"], **constant_values}
    if kept:
        report["params"][slot.parameter] = result.values[slot.parameter]  # the texture's mean
    report["bounds"] = material["bounds"]
    levels = report.pop("levels")
    report |= {"kept": kept, "reason": reason, "smoothness": conf.smoothness, "learning_rate": conf.learning_rate,
               "validation_mse_constant": constant_error, "validation_mse_texture": texture_error, "levels": levels,
               "texture_mean": [float(v) for v in texture.reshape(-1, 3).mean(axis=0)],
               "files": sorted(p.name for p in textured.glob(f"{slot.parameter}.*"))}
    write_json(textured / PARAMS_JSON, report)
    return StageResult(outputs, {"kept": kept, "validation_mse_constant": constant_error,
                                 "validation_mse_texture": texture_error})



STAGE = Stage(
    name="fit_texture",
    version=6,
    config=Config,
    main=main,
    needs=("fit_material.fitted_dir", "fit_material.params", "fit_material.heldout", "scene.description",
           "sfm.cameras", "undistort.pinhole", "masks.masks_json"),
    outputs=("textured_dir", "params", "heldout"),
    shared=("mitsuba",),
    exports=("textured_dir",),
)
