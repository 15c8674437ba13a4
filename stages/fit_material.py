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
                    iteration, validation error, why it stopped, photo_gains (each training
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
import time
from dataclasses import dataclass, fields, replace
from functools import partial
from pathlib import Path
from typing import Annotated

import numpy as np
import trimesh

from pipeline import logger
from pipeline.core.config import Range
from pipeline.core.errors import PipelineError
from pipeline.core.sections import LightSection
from pipeline.core.stage import Stage, StageInputs, StageResult
from pipeline.fit import engine
from pipeline.fit.candidates import Candidate, choose, improves
from pipeline.fit.checkpoint import resumable_stage
from pipeline.fit.exposure import table_gains
from pipeline.fit.outputs import write_fit_log, write_heldout
from pipeline.fit.settings import FitSettings
from pipeline.fit.views import BoardPixels, PhotoGains, Windowing, held_out_names, load_views, read_capture_photos
from pipeline.formats.scene_folder import HELDOUT, MESH_PLY, PARAMS_JSON, SCENE_XML, SPECIMEN_XML, read_json, write_json
from pipeline.render import light as estimated_light
from pipeline.render import materials, mitsuba_variant
from pipeline.render.capture_scene import rewrite_integrator, rewrite_specimen_material


@dataclass(frozen=True)
class Config(FitSettings):
    """Material fitting by differentiable rendering (the loop's settings, and these)."""

    iterations: Annotated[int, Range(1, None)] = 100
    """Most Adam steps."""
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
    kept: principled's translucency must earn its place over opaque. 2 %: the
    translucent bird's principled fit is 2.6-3.3 % better than opaque, an opaque
    paint's 0.1 % worse; the held-out error varied 0.7 % between runs."""


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


def light_models(requested: str, estimated: bool) -> list[str]:
    """The light models to fit, simplest first: none when the light is given."""
    if not estimated:
        return []
    return list(estimated_light.LIGHT_MODELS) if requested == "auto" else [requested]


@resumable_stage
def main(conf: Config, inputs: StageInputs, out_dir: Path) -> StageResult:
    # 1. The scene stage's folder, copied: the fitted values (and light) are written into it.
    description = read_json(inputs.upstream["scene"]["description"])
    models = description.get("model_choice", [description["model"]])
    parameters = {m: fit_parameters(m, conf.bounds, models) for m in models}
    mitsuba_variant.activate(inputs.shared["mitsuba"].variant)
    fitted = out_dir / "fitted"
    shutil.copytree(inputs.upstream["scene"]["scene_dir"], fitted)
    light: LightSection = inputs.shared["light"]

    # 2. Every photo as a view in its mask's window; a few held out for validation.
    upstream = inputs.upstream
    photos = read_capture_photos(
        upstream["sfm"]["cameras"], upstream["undistort"]["pinhole"], upstream["masks"]["masks_json"]
    )
    cameras = photos.cameras

    initial = {name: entry["value"] for name, entry in description["parameters"].items()}
    poses = {name: pose for name, (_, pose) in cameras.items()}
    mesh = trimesh.load(fitted / MESH_PLY, force="mesh", process=False)
    level_from = description.get("light", {}).get("level_from")  # where an estimated light's level was measured
    # With the board's print in the fit, its known reflectance sets the light's level
    # where the specimen stands (the measured level is the print's mean, shadow and a
    # near light's falloff included): the level is the loss's, not held.
    board_print = description.get("board_print") if light.estimated else None
    held_level = light.estimated and not board_print
    measured_on = estimated_light.measured_surface(level_from, mesh, poses, light.frame) if held_level else None
    # held-out photos' gains (PhotoGains): as many channels as the training photos'
    gain_channels = 3 if conf.white_balance else 1 if conf.exposure else 0

    def write_scene(model: str, values: dict, fitted_light) -> None:
        """The material's values and the light (None: the given one) into fitted/."""
        rewrite_specimen_material(fitted / SPECIMEN_XML, model, values)
        if fitted_light is not None:
            estimated_light.write(fitted_light, fitted, description, poses)

    def views_of(model: str, integrator: dict, names=None, count_board=False, fitted_gains=None, measured=None):
        seen = description | {"model": model, "integrator": integrator}
        board = BoardPixels(tuple(board_print), count_board) if board_print else None
        gains = PhotoGains(fitted_gains or {}, gain_channels, measured or {})
        windowing = Windowing(conf.max_size, conf.erode_px, conf.spp)
        windowed = load_views(fitted, seen, replace(photos, gains=gains), windowing, names=names, board=board)
        return [v for v, _ in windowed]

    def fit(model: str, start_light, start_values: dict = initial, integrator: dict | None = None) -> Candidate:
        started = time.perf_counter()
        integrator = integrator or description["integrators"][model]
        write_scene(model, start_values, start_light)
        # the board's print counts in training only: held out, the specimen is scored
        views = views_of(model, integrator, count_board=start_light is not None)
        held = set(held_out_names([v.name for v in views], conf.held_out))
        validation = [v for v in views if v.name in held] if not board_print else views_of(model, integrator, held)
        fitted_parameters = parameters[model] + (
            estimated_light.parameters(start_light, light.smoothness, measured_on) if start_light else []
        )
        settings = FitSettings(**{f.name: getattr(conf, f.name) for f in fields(FitSettings)})
        result = engine.fit(fitted_parameters, [v for v in views if v.name not in held], validation, settings)
        end_light = None
        if start_light is not None:
            end_light = estimated_light.fitted(start_light, {**result.values, **result.textures})
            logger.info("light %s: held-out error %.4g", end_light.model, result.validation_error or float("nan"))
        return Candidate(model, end_light, integrator, result, sorted(held), time.perf_counter() - started)

    def heldout_views(candidate: Candidate, integrator: dict, measured=None) -> list[engine.FitView]:
        """The candidate's held-out photos, its values and light written into fitted/."""
        write_scene(candidate.model, candidate.result.values, candidate.light)
        gains = candidate.result.photo_gains
        return views_of(candidate.model, integrator, set(candidate.held), fitted_gains=gains, measured=measured)

    # 3. The fit: the scene's model under the given light, or with each light model, simplest first.
    scene_model = description["model"]
    light_candidates = light_models(light.model, light.estimated)
    if not light_candidates:
        candidates = [fit(scene_model, None)]
    else:
        level = np.array(description["light"]["level"], np.float32)
        candidates = []
        for light_model in light_candidates:
            if light_model == "envmap+area":
                envmap = next((c for c in candidates if c.light.model == "envmap"), None) or fit(
                    scene_model, estimated_light.start("envmap", light.frame, level, light.environment_width)
                )
                area = estimated_light.with_area(
                    envmap.light, *estimated_light.specimen_sphere(mesh.vertices, light, poses)
                )
                candidates.append(fit(scene_model, area, envmap.result.values))
            else:
                start = estimated_light.start(light_model, light.frame, level, light.environment_width)
                candidates.append(fit(scene_model, start))
    chosen, why = choose(candidates, light.margin, "light")

    # 4. The material model, when the scene leaves it open: opaque under the chosen light (from principled's
    # fit), volumetric only when principled beat opaque by more than model_margin; then the path depth.
    material_candidates, depth = [chosen], None
    if len(models) > 1:
        material_candidates.insert(
            0, fit("opaque", chosen.light, materials.opaque_from_principled(chosen.result.values))
        )
        if "volumetric" in models and improves(chosen, material_candidates[0], conf.model_margin):
            start = materials.volumetric_from_principled(chosen.result.values)
            material_candidates.append(fit("volumetric", chosen.light, start))
    material, model_why = choose(material_candidates, conf.model_margin, "material")
    if len(models) > 1:
        deeper = material.integrator | {"max_depth": 2 * material.integrator["max_depth"]}
        refit = partial(fit, material.model, material.light, material.result.values, deeper)
        material, depth = _deeper(material, heldout_views(material, deeper), conf, refit)
    material = material.level_in_light()  # the gains' mean into an estimated light: the average photo's level
    model, result = material.model, material.result

    # 5. The fitted scene, light, log, held-out exposures (the table's), renders, params.json.
    write_scene(model, result.values, material.light)
    heldout_gains = table_gains(description, photos, result.photo_gains, material.held, gain_channels)
    held = heldout_views(material, material.integrator, heldout_gains.get("gains"))
    write_heldout(held, fitted / HELDOUT)
    rewrite_integrator(fitted, material.integrator)
    write_fit_log(fitted, result.log)
    material_values = {p.name: result.values[p.name] for p in parameters[model]}
    light_report = {
        "chosen": material.light.summary() if material.light else {"model": "given"},
        "why": why,
        "candidates": [c.summary("light") for c in candidates],
        "level": description.get("light", {}).get("level"),
        "level_from": level_from,
    }
    params = write_json(
        fitted / PARAMS_JSON,
        {
            "model": model,
            "params": material_values,
            "bounds": {p.name: [p.lower, p.upper] for p in parameters[model]},
            "units": {p.name: materials.PARAMETERS[p.name].units for p in parameters[model]},
            "model_choice": {
                "chosen": model,
                "why": model_why,
                "candidates": [c.summary("material") for c in material_candidates],
                "depth": depth,
            },
            "integrator": material.integrator,
            "best_iteration": result.best_iteration,
            "iterations": len(result.log),
            "validation_mse": result.validation_error,
            "held_out": material.held,
            "stopped": result.stopped,
            "photo_gains": result.photo_gains,
            "gain_channels": gain_channels,
            "heldout_gains": heldout_gains,
            "light": light_report,
            "skipped_gradients": result.skipped_gradients,
        },
    )
    metrics = {"iterations": len(result.log), "best_iteration": result.best_iteration, "model": model}
    metrics |= {"validation_mse": result.validation_error, "light": light_report["chosen"]["model"]}
    metrics |= {n: v if len(v) > 1 else v[0] for n, v in material_values.items()}
    outputs = {"fitted_dir": fitted, "params": params, "heldout": fitted / HELDOUT, "scene": fitted / SCENE_XML}
    return StageResult(outputs, metrics)


def _deeper(material: Candidate, held: list[engine.FitView], conf: Config, refit) -> tuple[Candidate, dict]:
    """The chosen fit, or one at twice its path depth: the ``held`` photos (the chosen
    values, the deeper integrator) rendered first; only when that changes their error by
    more than model_margin is the model refitted deeper (``refit()``) and the simplest
    within the margin kept. Returns the winner and what was measured."""
    shallow_error = material.result.validation_error
    if not held or shallow_error is None:
        return material, {"why": "no held-out photos"}
    max_depth = 2 * material.integrator["max_depth"]
    deep_error = engine.heldout_error(held, conf.validation_spp, held[0].integrator)
    del held  # their scenes, before the refit's (see Candidate.held)
    report = {"max_depth": material.integrator["max_depth"], "deeper_validation_mse": deep_error}
    change = abs(deep_error - shallow_error) / shallow_error
    if change <= conf.model_margin:
        why = f"rendered at max_depth {max_depth}, the held-out error changes by {change:.1%}: kept"
        return material, report | {"why": why}
    candidates = [material, refit()]
    winner, why = choose(candidates, conf.model_margin, "depth")
    return winner, report | {"why": why, "candidates": [c.summary("depth") for c in candidates]}


STAGE = Stage(
    name="fit_material",
    version=25,
    config=Config,
    main=main,
    needs=("scene.scene_dir", "scene.description", "sfm.cameras", "undistort.pinhole", "masks.masks_json"),
    outputs=("fitted_dir", "params", "heldout", "scene"),
    shared=("mitsuba", "light"),
    exports=("fitted_dir", "params", "heldout"),
    result=("scene", "fitted_dir"),
)
