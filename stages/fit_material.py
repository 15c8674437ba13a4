"""Stage fit_material: the specimen's material constants, fitted to the photos.

The scene stage's model (pipeline.render.materials) is fitted by pipeline.fit.engine: Adam over
its parameters with per-parameter learning rates and box constraints, a loss on the photos'
linear radiance (undistort's EXRs) over each photo's specimen mask cut to the mesh's outline and
eroded by ``erode_px`` (pipeline.fit.views), in a window around it of at most ``max_size``
pixels. ``held_out`` photos, evenly spread over the sorted names, are never fitted: they measure
validation error, and the best-validation state is kept. With ``exposure`` or ``white_balance``
(each photo its own exposure, as phones shoot), a held-out photo's render is first matched to it
by the least-squares gain of as many channels, within the range of the training photos' fitted
gains: an exposure no fit can know would otherwise outweigh every other error and choose the
light, model and texture, and a free gain would forgive the fit's level. Once fitted, where the
scene has the table, each held-out photo's exposure is read off the table it shares with the
nearest training photos (pipeline.fit.exposure): heldout/ and the later stages scale its
renders by that gain and score them in the photo's own units.

When ``[light] model`` is not given, the light is fitted with the material
(pipeline.render.light): each model asked for (auto: constant, envmap, envmap+area, simplest
first) in a fit of its own, the envmap+area one continuing the envmap's; the simplest within
``light.margin`` of the best held-out error is kept and written into every scene file. With the
board in the scene, its print beside the specimen counts in training too: its known reflectance
sets the light's level; without, the map keeps the level the scene stage measured.

Model only what the photos show (pipeline.fit.candidates): when the scene leaves the material
model open (scene.json's ``model_choice``: the capture and the scene stage both say auto), the
light models are fitted with principled, then opaque is fitted under the chosen light, starting
from principled's colour, roughness and the specular reflectance of its eta; volumetric (from
principled's eta, colour as albedo and roughness) only when principled beat opaque by more than
``model_margin``. The simplest within ``model_margin`` of the best held-out error is kept (an
opaque specimen is not given translucency that only absorbs the light's or the mesh's error).
Then the path depth: the held-out photos are rendered at twice the chosen model's depth, and
only when that changes their error by more than the margin is the model refitted deeper.
fit_texture and fit_geometry take the model and integrator from params.json.

All in one folder, fitted/ (exported to CAPTURE/output/stages/fit_material/, and to
the top of CAPTURE/output/ when no later fit stage has run):

==================  =============================================================
file                content
==================  =============================================================
scene.xml, ...      the scene folder with the fitted values written into
                    specimen.xml; renders as-is
params.json         model (and model_choice: every candidate's held-out error and
                    seconds, why the winner won, and the depth check), the
                    integrator fitted with, fitted values, bounds, units, best
                    iteration (averaged: the average of the last steps instead),
                    validation error, why it stopped, photo_gains (each training
                    photo's RGB gain, when exposure or white_balance is fitted: the
                    render times it is the photo; fit_texture, fit_geometry divide by it;
                    gain_channels: the held-out photos' matched gains;
                    heldout_gains: those read off the table), the
                    light (chosen model, why, every candidate's error and seconds)
environment.exr     the fitted environment map (an envmap light)
log.jsonl           per iteration: loss, validation error, values, seconds
loss.png            training loss and validation error against iteration
heldout/            per held-out photo: NAME.render.exr, NAME.reference.exr (the
                    window fitted), NAME.mask.png (the pixels scored), and
                    NAME.reference/render/difference.png to look at
==================  =============================================================

Limitations: a constant material (texture is fit_texture's job). Without the table in the scene
(sfm found no plane) its bounce light goes to the specimen, held-out photos' gains are matched;
empty masks are skipped.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Annotated

from pipeline.core.config import Range
from pipeline.core.errors import ConfigError, PipelineError
from pipeline.core.sections import LightSection
from pipeline.core.stage import Stage, StageInputs, StageResult
from pipeline.fit import engine
from pipeline.fit.candidates import choose
from pipeline.fit.checkpoint import resumable_stage
from pipeline.fit.exposure import table_gains
from pipeline.fit.material import MaterialFitting
from pipeline.fit.outputs import write_fit_log, write_heldout
from pipeline.fit.settings import FitSettings
from pipeline.fit.views import Windowing, read_capture_photos
from pipeline.formats.fit_results import LightChoice, MaterialFit
from pipeline.formats.scene_description import SceneDescription
from pipeline.formats.scene_folder import HELDOUT, PARAMS_JSON, SCENE_XML
from pipeline.render import materials, mitsuba_variant
from pipeline.render.capture_scene import rewrite_integrator


@dataclass(frozen=True)
class Config(FitSettings):
    """Material fitting by differentiable rendering (the loop's settings, and these)."""

    iterations: Annotated[int, Range(1, None)] = 100
    """Most Adam steps."""
    whiten: bool = False
    """Decorrelate the plain values' gradients before Adam's step
    (pipeline.fit.variables.GradientWhitening): `pipeline fit`'s default, measured on
    its suite of kits, not on this stage's fits."""
    image_memory: Annotated[int, Range(0, None)] = 0
    """Carry each view's image from its earlier steps (pipeline.fit.settings.LoopSettings):
    `pipeline fit`'s default where a scene renders a medium, measured on its suite of
    kits, not on this stage's fits."""
    step_halvings: Annotated[int, Range(0, None)] = 0
    """Times the fit, found still, halves its learning rates and fits on
    (pipeline.fit.settings.LoopSettings): `pipeline fit`'s default where a scene renders
    a medium, not measured on this stage's fits."""
    bounds: tuple[str, ...] = ()
    """Bounds overriding pipeline.render.materials' defaults, as "name=lower:upper" (e.g. "eta=1.3:1.6")."""
    max_size: Annotated[int, Range(16, None)] = 128
    """Longer side, in pixels, of the window each view is rendered in."""
    erode_px: Annotated[int, Range(0, None)] = 2
    """Mask erosion at full resolution before scoring pixels."""
    held_out: Annotated[int, Range(0, None)] = 2
    """Photos kept out of fitting to measure validation error (their renders are written
    to heldout/ at pipeline.fit.outputs.HELDOUT_SPP)."""
    model_margin: Annotated[float, Range(0.0, 1.0)] = 0.02
    """When the scene leaves the material model open (scene.json's model_choice), the
    simplest model whose held-out error is within this fraction of the best one's is
    kept: principled's translucency must earn its place over opaque. 2 % lies above the
    run-to-run variation of the held-out error and below what translucency gains on a
    translucent specimen (docs/benchmarks.md, "The material model chosen by evidence")."""

    def validate(self, name: str) -> None:
        """``bounds`` refused before anything runs: each entry name=lower:upper, finite,
        lower below upper (engine.parse_bounds), naming a parameter of some material model."""
        try:
            spans = engine.parse_bounds(self.bounds, f"{name}.bounds")
        except PipelineError as error:
            raise ConfigError(str(error)) from None
        known = {n for parameters in materials.MODEL_PARAMETERS.values() for n in parameters}
        unknown = sorted(set(spans) - known)
        if unknown:
            raise ConfigError(
                f"{name}.bounds names {unknown[0]!r}, no material parameter: use one of {', '.join(sorted(known))}"
            )


def fit_parameters(model: str, bounds: tuple[str, ...], models: list[str]) -> list[engine.FitParameter]:
    """The model's parameters with their bounds, ``bounds`` overriding them; ``bounds``
    may name any parameter of ``models`` (those fit_material chooses between)."""
    overrides = engine.parse_bounds(bounds, "fit_material.bounds")
    known = [n for m in models for n in materials.MODEL_PARAMETERS[m]]
    unknown = set(overrides) - set(known)
    if unknown:
        raise PipelineError(
            f"fit_material.bounds names {', '.join(sorted(unknown))}, not parameters of the "
            f"{' or '.join(models)} model ({', '.join(dict.fromkeys(known))})"
        )
    return materials.fit_parameters(model, overrides)


@resumable_stage
def main(conf: Config, inputs: StageInputs, out_dir: Path) -> StageResult:
    # 1. The scene stage's folder, copied: the fitted values (and light) are written into it.
    description = SceneDescription.read(inputs.upstream["scene"]["description"])
    models = description.model_choice
    mitsuba_variant.activate(inputs.shared["mitsuba"].variant)
    fitted_dir = out_dir / "fitted"
    shutil.copytree(inputs.upstream["scene"]["scene_dir"], fitted_dir)
    light: LightSection = inputs.shared["light"]

    # 2. Every photo as a view in its mask's window, and what every candidate fit shares;
    # held-out photos' gains (PhotoGains) get as many channels as the training photos'.
    upstream = inputs.upstream
    photos = read_capture_photos(
        upstream["sfm"]["cameras"], upstream["undistort"]["pinhole"], upstream["masks"]["masks_json"]
    )
    gain_channels = 3 if conf.white_balance else 1 if conf.exposure else 0
    fitting = MaterialFitting.prepare(
        fitted_dir,
        description,
        photos,
        {m: fit_parameters(m, conf.bounds, models) for m in models},
        light,
        FitSettings(**{f.name: getattr(conf, f.name) for f in fields(FitSettings)}),
        Windowing(conf.max_size, conf.erode_px, conf.spp),
        conf.held_out,
        gain_channels,
    )

    # 3. The light: the scene's model under the given light, or with each light model.
    candidates = fitting.fit_lights()
    chosen, why = choose(candidates, light.margin, "light")

    # 4. The material model, when the scene leaves it open, and the path depth.
    choice = fitting.choose_model(chosen, models, conf.model_margin, conf.validation_spp)
    material = choice.material.level_in_light()  # the gains' mean into an estimated light: the average photo's level
    model, result = material.model, material.result

    # 5. The fitted scene, light, log, held-out exposures (the table's), renders, params.json.
    fitting.write_scene(model, result.values, material.light)
    heldout_gains = table_gains(description, photos, result.photo_gains, material.held, gain_channels)
    write_heldout(
        fitting.heldout_views(material, material.integrator, heldout_gains.get("gains")), fitted_dir / HELDOUT
    )
    rewrite_integrator(fitted_dir, material.integrator)
    write_fit_log(fitted_dir, result.log)
    parameters = fitting.parameters[model]
    material_values = {p.name: result.values[p.name] for p in parameters}
    light_choice = LightChoice(
        chosen=material.light.summary() if material.light else {"model": "given"},
        why=why,
        candidates=[c.summary("light") for c in candidates],
        level=description.light.level,
        level_from=description.light.level_from,
    )
    record = MaterialFit(
        model=model,
        params=material_values,
        bounds={p.name: [p.lower, p.upper] for p in parameters},
        held_out=material.held,
        units={p.name: materials.PARAMETERS[p.name].units for p in parameters},
        integrator=material.integrator,
        light=light_choice,
        photo_gains=result.photo_gains,
        gain_channels=gain_channels,
        heldout_gains=heldout_gains,
        details={
            "model_choice": {
                "chosen": model,
                "why": choice.why,
                "candidates": [c.summary("material") for c in choice.candidates],
                "depth": choice.depth,
            },
            "best_iteration": result.best_iteration,
            "averaged": result.averaged,
            "iterations": len(result.log),
            "validation_mse": result.validation_error,
            "stopped": result.stopped,
            "skipped_gradients": result.skipped_gradients,
        },
    )
    params = record.write(fitted_dir / PARAMS_JSON)
    metrics = {"iterations": len(result.log), "best_iteration": result.best_iteration, "model": model}
    metrics |= {"validation_mse": result.validation_error, "light": light_choice.chosen["model"]}
    metrics |= {n: v if len(v) > 1 else v[0] for n, v in material_values.items()}
    outputs = {
        "fitted_dir": fitted_dir,
        "params": params,
        "heldout": fitted_dir / HELDOUT,
        "scene": fitted_dir / SCENE_XML,
    }
    return StageResult(outputs, metrics)


STAGE = Stage(
    name="fit_material",
    version=26,
    config=Config,
    main=main,
    needs=("scene.scene_dir", "scene.description", "sfm.cameras", "undistort.pinhole", "masks.masks_json"),
    outputs=("fitted_dir", "params", "heldout", "scene"),
    shared=("mitsuba", "light"),
    exports=("fitted_dir", "params", "heldout"),
    result=("scene", "fitted_dir"),
)
