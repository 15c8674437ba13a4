"""Stage fit_material: the specimen's material constants, fitted to the photos.

The scene stage's model (pipeline.render.materials) is fitted by pipeline.fit.engine: Adam
over its parameters with per-parameter learning rates and box constraints, a
loss on the photos' linear radiance (undistort's EXRs) over each photo's
specimen mask, eroded by ``erode_px`` so that silhouette pixels, where the
mesh's error shows, do not count. Pixels are the budget on a CPU: each view is
rendered only in a window around its mask, scaled so that its longer side has
at most ``max_size`` pixels. ``held_out`` photos, evenly spread over the sorted
names, are never fitted: they measure validation error, and the best-validation
state is kept.

All in one folder, fitted/ (exported to CAPTURE/output/fitted/, with params.json
and heldout/ also exported on their own for ``pipeline score``):

==================  =============================================================
file                content
==================  =============================================================
scene.xml, ...      the scene folder with the fitted values written into
                    specimen.xml; renders as-is
params.json         model, fitted values, bounds, units, best iteration,
                    validation error, why it stopped, exposures (when fitted)
log.jsonl           per iteration: loss, validation error, values, seconds
loss.png            training loss and validation error against iteration
heldout/            per held-out photo: NAME.render.exr, NAME.reference.exr (the
                    window fitted) and NAME.mask.png (the pixels scored)
==================  =============================================================

Limitations: a constant material; texture is fit_texture's job. The table beyond
the board is not in the scene, so its bounce light is attributed to the
specimen. Views whose mask is empty are skipped.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Annotated

from pipeline.core.config import Range
from pipeline.core.errors import PipelineError
from pipeline.core.stage import Stage, StageInputs, StageResult
from pipeline.fit import engine
from pipeline.fit.checkpoint import resumable_stage
from pipeline.fit.outputs import write_fit_log, write_heldout
from pipeline.fit.settings import FitSettings
from pipeline.fit.views import held_out_names, load_views
from pipeline.formats.cameras import read_views
from pipeline.formats.masks import read_masks
from pipeline.formats.pinhole import linear_photos
from pipeline.formats.scene_folder import HELDOUT, PARAMS_JSON, SCENE_XML, SPECIMEN_XML, read_json, write_json
from pipeline.render import materials, mitsuba_variant, scene_xml


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
    """Photos kept out of fitting to measure validation error (their renders at 4x
    validation_spp are written to heldout/)."""


def fit_parameters(model: str, bounds: tuple[str, ...]) -> list[engine.FitParameter]:
    """The model's parameters with their bounds, ``bounds`` overriding them."""
    overrides = engine.parse_bounds(bounds, "fit_material.bounds")
    unknown = set(overrides) - set(materials.MODEL_PARAMETERS[model])
    if unknown:
        raise PipelineError(
            f"fit_material.bounds names {', '.join(sorted(unknown))}, not parameters of the {model} "
            f"model ({', '.join(materials.MODEL_PARAMETERS[model])})"
        )
    return materials.fit_parameters(model, overrides)


@resumable_stage
def main(conf: Config, inputs: StageInputs, out_dir: Path) -> StageResult:
    # 1. The scene stage's folder, copied: the fitted values are written into it.
    description = read_json(inputs.upstream["scene"]["description"])
    model = description["model"]
    parameters = fit_parameters(model, conf.bounds)
    mitsuba_variant.activate(inputs.shared["mitsuba"].variant)
    fitted = out_dir / "fitted"
    shutil.copytree(inputs.upstream["scene"]["scene_dir"], fitted)

    # 2. Every photo as a view in its mask's window; a few held out for validation.
    cameras = read_views(inputs.upstream["sfm"]["cameras"])
    linear = linear_photos(inputs.upstream["undistort"]["pinhole"])
    masks = read_masks(inputs.upstream["masks"]["masks_json"])
    views = [
        view
        for view, _ in load_views(fitted, description, cameras, linear, masks, conf.max_size, conf.erode_px, conf.spp)
    ]
    held = set(held_out_names([v.name for v in views], conf.held_out))

    # 3. The fit.
    settings = FitSettings(**{f.name: getattr(conf, f.name) for f in fields(FitSettings)})
    result = engine.fit(
        parameters, [v for v in views if v.name not in held], [v for v in views if v.name in held], settings
    )

    # 4. The fitted scene, its log, held-out renders and params.json.
    keys = {p.name: p.key for p in parameters}
    specimen = fitted / SPECIMEN_XML
    scene_xml.set_values(specimen, {keys[n]: v for n, v in result.values.items()}, specimen)
    write_fit_log(fitted, result.log)
    write_heldout([v for v in views if v.name in held], 4 * conf.validation_spp, fitted / HELDOUT)
    params = write_json(
        fitted / PARAMS_JSON,
        {
            "model": model,
            "params": result.values,
            "bounds": {p.name: [p.lower, p.upper] for p in parameters},
            "units": {p.name: materials.PARAMETERS[p.name].units for p in parameters},
            "best_iteration": result.best_iteration,
            "iterations": len(result.log),
            "validation_mse": result.validation_error,
            "held_out": sorted(held),
            "stopped": result.stopped,
            "exposures": result.exposures,
        },
    )
    metrics = {
        "iterations": len(result.log),
        "best_iteration": result.best_iteration,
        "validation_mse": result.validation_error,
        **{n: v if len(v) > 1 else v[0] for n, v in result.values.items()},
    }
    outputs = {"fitted_dir": fitted, "params": params, "heldout": fitted / HELDOUT, "scene": fitted / SCENE_XML}
    return StageResult(outputs, metrics)


STAGE = Stage(
    name="fit_material",
    version=6,
    config=Config,
    main=main,
    needs=("scene.scene_dir", "scene.description", "sfm.cameras", "undistort.pinhole", "masks.masks_json"),
    outputs=("fitted_dir", "params", "heldout", "scene"),
    shared=("mitsuba",),
    exports=("fitted_dir", "params", "heldout"),
)
