"""Stage fit_texture: a colour that varies over the specimen, baked from the photos or
fitted coarse to fine.

Starts from fit_material's scene and replaces one constant of the model by a
texture (pipeline.render.materials.TEXTURE_SLOTS):

==========================  ==============================================================
model                       texture
==========================  ==============================================================
opaque, principled          base_color as a bitmap on the mesh's UVs (uv stage)
volumetric                  the medium's albedo as a grid volume over the specimen's box
                            (a medium has no surface to carry a UV texture)
==========================  ==============================================================

With ``refit_constants`` the model's other constants (roughness, spec_trans and eta;
alpha, eta and sigma_t) are fitted again, from fit_material's values and within its
bounds: first alone (``iterations`` steps, the colour still constant), then along
with the texture at every level. Fitted next to a constant colour they absorb some
of the colour's variation (roughness, most of all). The texture is fitted by
pipeline.fit.engine (the same loop, loss, views and held-out photos as
fit_material). A bitmap starts (``start = photos``) baked from the training photos
under the fitted light and constants (pipeline.fit.bake: per texel, the
least-squares colour of the photos' pixels that see it, from windows of
``bake_max_size`` pixels, finer than the fit's, corrected over ``bake_rounds`` by
what renders with it still miss; a guessed light's level rises until the colours fit
their bound, and the scene files carry the raised light), and is then fitted at
``max_resolution`` texels alone. From the constant (``start = constant``, and always
for a grid) it is fitted at ``levels`` resolutions, each twice the last, ending at
``max_resolution`` (``max_grid_resolution`` along a grid's longest side); every
level starts from the last one's best state, resampled. A smoothness prior
(``smoothness`` times the mean squared difference of neighbouring texels) keeps
texels from absorbing highlights and noise and fills texels no photo sees from their
neighbours.

Model only what the scene needs: with ``texture = "auto"`` the texture is kept
only when it lowers the held-out error by at least ``min_improvement``
(relative) below that of the refitted constants; otherwise the scene keeps the
constant colour, with the refitted constants, and says why.

Outputs, all in textured/ (exported to CAPTURE/output/stages/fit_texture/):

===================  ==========================================================
file                 content
===================  ==========================================================
scene.xml, ...       the scene with the texture in specimen.xml; renders as-is
base_color.exr/.png  the bitmap, linear EXR (what the scene loads) and sRGB PNG
albedo.vol/.png      the grid volume (Mitsuba's format) and its z slices as PNG
params.json          kept or not and why, validation error with and without the
                     texture, per level (and for the constants alone):
                     resolution, iterations, best iteration (or averaged), held-out error at
                     the start and the best, non-finite gradient entries
                     dropped (skipped_gradients); ``baked``: the bake's window, samples,
                     share of texels seen and light_scale (``light``: the raised light); ``params`` and
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

import os
import shutil
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import trimesh

from pipeline import logger
from pipeline.core.config import Range
from pipeline.core.errors import ConfigError
from pipeline.core.stage import Stage, StageInputs, StageResult
from pipeline.fit import engine
from pipeline.fit.bake import bake_bitmap
from pipeline.fit.checkpoint import resumable_stage
from pipeline.fit.outputs import write_fit_log, write_heldout
from pipeline.fit.settings import FitSettings, LoopSettings
from pipeline.fit.texture import TextureFit, fit_constants_then_levels, level_shapes, write_texture
from pipeline.fit.views import CapturePhotos, PhotoGains, Windowing, load_views, read_capture_photos
from pipeline.formats.fit_results import MaterialFit, TexturedFit, read_fitted_scene
from pipeline.formats.scene_description import SceneDescription
from pipeline.formats.scene_folder import HELDOUT, MESH_PLY, PARAMS_JSON, SPECIMEN_XML, copy_scene
from pipeline.render import light as estimated_light
from pipeline.render import materials, mitsuba_variant, scene_xml
from pipeline.render.materials import SPECIMEN

TEXEL_BYTES = 400
"""Memory one texel (or voxel) of the finest texture takes in its fit: measured on 2 cores
at about 350 bytes beyond the rest (0.75 GB of the stage at 1024 x 1024 texels, 1.85 GB
at 2048 x 2048), rounded up."""
MEMORY_SHARE = 0.8
"""Of the machine's memory, what a texture's fit may take: the rest is the system's and
the rendering's."""


@dataclass(frozen=True)
class Config(LoopSettings):
    """Texture fitting, coarse to fine (the loop's settings apply to each level)."""

    iterations: Annotated[int, Range(1, None)] = 30
    """Most Adam steps per level."""
    window: Annotated[int, Range(4, None)] = 20
    """Fewest steps the trend test looks at (per level)."""

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
    smoothness: Annotated[float, Range(0.0, None)] = 0.05
    """Weight of the neighbour-difference prior (see the module docstring)."""
    learning_rate: Annotated[float, Range(0.0, None, exclusive_lo=True)] = 0.03
    """Adam step of every texel (colour units)."""
    max_size: Annotated[int, Range(16, None)] = 128
    """Longer side, in pixels, of the window each view is rendered in."""
    erode_px: Annotated[int, Range(0, None)] = 2
    """Mask erosion at full resolution before scoring pixels."""
    refit_constants: bool = True
    """Fit the model's other constants again, alone and then along with the texture
    (see the module docstring); off: they stay as fit_material left them."""
    start: Literal["photos", "constant"] = "photos"
    """Where a bitmap starts (a grid volume starts from the constant). photos: baked
    from the training photos under the fitted light and constants (pipeline.fit.bake)
    at ``max_resolution``, then fitted at that resolution alone; constant: fit_material's
    constant, fitted coarse to fine over ``levels``."""
    bake_max_size: Annotated[int, Range(16, None)] = 512
    """Longer side, in pixels, of the windows the photos are baked from (a photo is
    never enlarged)."""
    bake_spp: Annotated[int, Range(1, None)] = 32
    """Samples per pixel of the bake's renders."""
    bake_rounds: Annotated[int, Range(1, None)] = 3
    """Rounds of the bake: each after the first moves the colours by what renders with them
    still miss (the specimen's light on itself, pipeline.fit.bake)."""

    def validate(self, name: str) -> None:
        """The finest texture's fit within this machine's memory: refused before anything
        runs (a 12800-texel bitmap was killed for memory after two minutes)."""
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        for setting, cells in (
            ("max_resolution", self.max_resolution**2),
            ("max_grid_resolution", self.max_grid_resolution**3),
        ):
            needed = cells * TEXEL_BYTES
            if needed > MEMORY_SHARE * memory:
                raise ConfigError(
                    f"{name}.{setting} = {getattr(self, setting)} needs about {needed / 2**30:.0f} GiB for the "
                    f"texture's fit, more than {MEMORY_SHARE:.0%} of this machine's {memory / 2**30:.0f} GiB: lower it"
                )


def _keep_texture(conf: Config, constant_error: float | None, texture_error: float) -> tuple[bool, str]:
    """Whether the texture earns its place, and why (``texture``, ``min_improvement``)."""
    if constant_error is None:
        return True, "no held-out photos to decide with: kept"
    improvement = (constant_error - texture_error) / constant_error
    kept = conf.texture == "on" or improvement >= conf.min_improvement
    return kept, (
        f"held-out MSE {constant_error:.4g} with the constant, {texture_error:.4g} with the texture "
        f"({100 * improvement:+.1f} %, threshold {100 * conf.min_improvement:g} %)"
    )


def _final_values(model: str, material: MaterialFit, constants: dict, texture_mean: list | None) -> dict:
    """The scene's values as in fit_material's params.json: the refitted constants,
    and a kept texture's mean in its parameter's place."""
    values = {**material.params, **constants}
    if texture_mean is not None:
        values[materials.TEXTURE_SLOTS[model].parameter] = texture_mean
    return values


def _texture_fit(conf: Config, model: str, bounds: dict, views: list[engine.FitView], held: set[str]) -> TextureFit:
    """The views split by fit_material's held-out photos, the texture's and constants'
    parameters, and the loop's settings for one level."""
    # The texture's own learning rate (conf.learning_rate) is the scale's measure.
    loop = {f.name: getattr(conf, f.name) for f in fields(LoopSettings)}
    # Whitening (pipeline fit's default) is not measured on the stages' fits.
    settings = FitSettings(**loop, learning_rate_scale=1.0, whiten=False)
    parameters = materials.refit_parameters(model, bounds, (conf.learning_rate, conf.smoothness), conf.refit_constants)
    training, validation = [v for v in views if v.name not in held], [v for v in views if v.name in held]
    return TextureFit(training=training, validation=validation, parameters=parameters, settings=settings)


@dataclass
class _Baker:
    """What bakes the texture from the training photos into the training views'
    scenes, as the constants' refit leaves them (``start = photos``, a bitmap)."""

    conf: Config
    slot: materials.TextureSlot
    shape: tuple[int, ...]
    fit: TextureFit
    material: MaterialFit
    scene_dir: Path
    description: SceneDescription
    photos: CapturePhotos
    record: dict | None = None
    """What the bake did (params.json's ``baked``), once it ran."""

    def __call__(self) -> np.ndarray:
        conf, fit = self.conf, self.fit
        scenes = {v.name: v.scene for v in fit.training}
        windowing = Windowing(conf.bake_max_size, conf.erode_px, conf.bake_spp)
        views = load_views(self.scene_dir, self.description, self.photos, windowing, names=set(scenes), scenes=scenes)
        free = self.material.light.level_from == estimated_light.SPECIMEN_LEVEL  # a guessed level may rise
        relit = [v.scene for v in (*fit.training, *fit.validation)] if free else []
        bounds = self.material.bounds[self.slot.parameter]
        texture, seen, scale = bake_bitmap(
            [v for v, _ in views], self.slot.key, SPECIMEN, self.shape, conf.bake_spp, bounds, relit, conf.bake_rounds
        )
        self.record = dict(max_size=conf.bake_max_size, spp=conf.bake_spp, rounds=conf.bake_rounds)
        self.record |= dict(texels_seen=seen, light_scale=scale)
        logger.info("texture baked from %d photos: %.0f %% of texels seen, light x %.3g", len(views), 100 * seen, scale)
        return texture


def _render_heldout(
    conf: Config, textured: Path, description: SceneDescription, photos: CapturePhotos, held: set[str]
) -> None:
    # the photos' gains: a held-out photo's measured one scales its render
    windowing = Windowing(conf.max_size, conf.erode_px, conf.spp)
    views = load_views(textured, description, photos, windowing, names=held)
    write_heldout([view for view, _ in views], textured / HELDOUT)


@resumable_stage
def main(conf: Config, inputs: StageInputs, out_dir: Path) -> StageResult:
    # Longer than 60 lines on purpose: the stage's five steps in their order.
    # 1. fit_material's scene, without its fit results.
    material_dir = inputs.upstream["fit_material"]["fitted_dir"]
    description, material = read_fitted_scene(
        inputs.upstream["scene"]["description"], inputs.upstream["fit_material"]["params"]
    )
    model = description.model
    slot = materials.TEXTURE_SLOTS[model]
    textured = copy_scene(material_dir, out_dir / "textured")
    outputs = {"textured_dir": textured, "params": textured / PARAMS_JSON, "heldout": textured / HELDOUT}
    about = {
        "parameter": slot.parameter,
        "kind": slot.kind,
        "mode": conf.texture,
        "constant": material.params[slot.parameter],
    }
    if conf.texture == "off":
        shutil.copytree(inputs.upstream["fit_material"]["heldout"], textured / HELDOUT)
        TexturedFit(
            model=model,
            params=material.params,
            bounds=material.bounds,
            held_out=material.held_out,
            kept=False,
            details=about | {"reason": "texture = off"},
        ).write(textured / PARAMS_JSON)
        return StageResult(outputs, {"kept": False})

    # 2. The texture at the coarsest level, set to fit_material's constant.
    mesh = trimesh.load(textured / MESH_PLY, force="mesh")
    box = np.array([mesh.bounds[0] - 0.02 * mesh.extents, mesh.bounds[1] + 0.02 * mesh.extents])
    shapes = level_shapes(conf.levels, conf.max_resolution, conf.max_grid_resolution, slot.kind, box[1] - box[0])
    texture = np.broadcast_to(np.float32(material.params[slot.parameter]), (*shapes[0], 3)).copy()
    specimen = textured / SPECIMEN_XML
    parameter_key = materials.PARAMETERS[slot.parameter].key
    scene_xml.set_values(specimen, {}, specimen, textures={parameter_key: write_texture(textured, slot, texture, box)})

    # 3. The views, fit_material's held-out photos, and the fit: constants, then levels.
    mitsuba_variant.activate(inputs.shared["mitsuba"].variant)
    photos = read_capture_photos(
        inputs.upstream["sfm"]["cameras"],
        inputs.upstream["undistort"]["pinhole"],
        inputs.upstream["masks"]["masks_json"],
        PhotoGains.of(material),
    )
    windowing = Windowing(conf.max_size, conf.erode_px, conf.spp)
    views = [view for view, _ in load_views(textured, description, photos, windowing)]
    held = set(material.held_out)
    fit = _texture_fit(conf, model, material.bounds, views, held)
    bake = None
    if conf.start == "photos" and slot.kind == "bitmap":
        bake = _Baker(conf, slot, shapes[-1], fit, material, textured, description, photos)
    levels_fit = fit_constants_then_levels(slot, texture, shapes, fit, bake)
    result, texture, constants = levels_fit.result, levels_fit.texture, levels_fit.constants
    constant_error, texture_error = levels_fit.constant_error, levels_fit.levels[-1]["validation_mse"]
    if bake is not None and bake.record is not None:
        about["baked"] = bake.record
    if levels_fit.constants_fit is not None:
        about["constants_fit"] = levels_fit.constants_fit

    # 4. Keep the texture only if it earns its place.
    kept, reason = _keep_texture(conf, constant_error, texture_error)
    logger.info("texture %s: %s", "kept" if kept else "not kept", reason)
    write_fit_log(textured, levels_fit.log)
    light = None
    if kept:
        write_texture(textured, slot, texture, box)
        constant_values = {n: result.values[n] for n in constants}
        if (scale := about.get("baked", {}).get("light_scale", 1.0)) != 1.0:
            poses = {name: pose for name, (_, pose) in photos.cameras.items()}
            light = estimated_light.rescale_files(
                textured, material.light.chosen, scale, description.view_files(), poses
            )
    else:
        # fit_material's constant scene, with the refitted constants.
        shutil.copy2(material_dir / SPECIMEN_XML, specimen)
        for leftover in textured.glob(f"{slot.parameter}.*"):
            leftover.unlink()
        constant_values = levels_fit.refitted
    scene_xml.set_values(specimen, {materials.PARAMETERS[n].key: v for n, v in constant_values.items()}, specimen)

    # 5. Held-out renders of the scene kept, and params.json.
    if kept or levels_fit.refitted:
        _render_heldout(conf, textured, description, photos, held)
    else:
        shutil.copytree(inputs.upstream["fit_material"]["heldout"], textured / HELDOUT)
    TexturedFit(
        model=model,
        params=_final_values(model, material, constant_values, result.values[slot.parameter] if kept else None),
        bounds=material.bounds,
        held_out=material.held_out,
        kept=kept,
        learning_rate=conf.learning_rate,
        smoothness=conf.smoothness,
        light=light,
        details=about
        | {
            "reason": reason,
            "validation_mse_constant": constant_error,
            "validation_mse_texture": texture_error,
            "levels": levels_fit.levels,
            "texture_mean": [float(v) for v in texture.reshape(-1, 3).mean(axis=0)],
            "files": sorted(p.name for p in textured.glob(f"{slot.parameter}.*")),
        },
    ).write(textured / PARAMS_JSON)
    return StageResult(
        outputs, {"kept": kept, "validation_mse_constant": constant_error, "validation_mse_texture": texture_error}
    )


STAGE = Stage(
    name="fit_texture",
    version=25,
    config=Config,
    main=main,
    needs=(
        "fit_material.fitted_dir",
        "fit_material.params",
        "fit_material.heldout",
        "scene.description",
        "sfm.cameras",
        "undistort.pinhole",
        "masks.masks_json",
    ),
    outputs=("textured_dir", "params", "heldout"),
    shared=("mitsuba",),
    exports=("textured_dir",),
    result=("scene", "textured_dir"),
)
