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

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np

from pipeline import logger
from pipeline.fit import engine
from pipeline.render import materials
from pipeline.render import mitsuba_variant
from pipeline.render import scene_xml
from pipeline.camera.model import Intrinsics, Pose, read_views, resize_exact, scaled
from pipeline.core.config import Range
from pipeline.core.errors import PipelineError
from pipeline.imaging.photo_io import read_photo, write_image
from pipeline.core.stage import Stage, StageInputs, StageResult
from stages.masks import mask_files
from stages.undistort import photo_files


@dataclass(frozen=True)
class Config:
    """Material fitting by differentiable rendering."""

    iterations: Annotated[int, Range(1, None)] = 100
    """Most Adam steps."""
    batch: Annotated[int, Range(1, None)] = 2
    """Views rendered per step; their gradients add up before the step."""
    spp: Annotated[int, Range(1, None)] = 16
    """Samples per pixel of each training render."""
    loss: Literal["l2", "dual"] = "dual"
    """l2: mean squared error; dual: Deng et al.'s dual-buffer estimator (two renders,
    unbiased by Monte Carlo noise; twice the cost per view)."""
    learning_rate_scale: Annotated[float, Range(0.0, None, exclusive_lo=True)] = 1.0
    """Multiplies every parameter's learning rate (pipeline.render.materials)."""
    bounds: tuple[str, ...] = ()
    """Bounds overriding pipeline.render.materials' defaults, as "name=lower:upper" (e.g. "eta=1.3:1.6")."""
    max_size: Annotated[int, Range(16, None)] = 128
    """Longer side, in pixels, of the window each view is rendered in."""
    erode_px: Annotated[int, Range(0, None)] = 2
    """Mask erosion at full resolution before scoring pixels."""
    held_out: Annotated[int, Range(0, None)] = 2
    """Photos kept out of fitting to measure validation error."""
    validate_every: Annotated[int, Range(1, None)] = 10
    """Iterations between validation renders."""
    validation_spp: Annotated[int, Range(1, None)] = 64
    """Samples per pixel of validation renders (and 4x that for heldout/)."""
    tolerance: Annotated[float, Range(0.0, None)] = 1e-3
    """Stop when the mean loss over ``window`` iterations improves by less than this (relative);
    0: never (run ``iterations``)."""
    window: Annotated[int, Range(1, None)] = 20
    """Iterations per window of the tolerance test."""
    time_budget_s: Annotated[float, Range(0.0, None)] = 0.0
    """Stop after this many seconds of fitting; 0 for no limit."""
    exposure: bool = False
    """Fit one exposure scale per photo (photos shot with automatic exposure)."""
    seed: int = 0
    """Seed of the batch order and the renders."""


def fit_parameters(model: str, bounds: tuple[str, ...]) -> list[engine.FitParameter]:
    """The model's parameters with their bounds, ``bounds`` overriding them."""
    overrides = engine.parse_bounds(bounds, "fit_material.bounds")
    unknown = set(overrides) - set(materials.MODEL_PARAMETERS[model])
    if unknown:
        raise PipelineError(f"fit_material.bounds names {', '.join(sorted(unknown))}, not parameters of the {model} "
                            f"model ({', '.join(materials.MODEL_PARAMETERS[model])})")  # fmt: skip
    return materials.fit_parameters(model, overrides)


def _window(mask: np.ndarray, max_size: int, margin: int = 8) -> tuple[float, tuple[int, int, int, int]] | None:
    """(scale, crop in scaled pixels) of the mask's bounding box plus ``margin``."""
    rows, cols = np.nonzero(mask)
    if len(rows) == 0:
        return None
    lo = np.maximum([cols.min() - margin, rows.min() - margin], 0)
    hi = np.minimum([cols.max() + margin + 1, rows.max() + margin + 1], mask.shape[::-1])
    scale = min(1.0, max_size / float(max(hi - lo)))
    lo_s = np.floor((lo + 0.5) * scale - 0.5).clip(0).astype(int)
    hi_s = np.ceil((hi + 0.5) * scale - 0.5).astype(int)
    return scale, (int(lo_s[0]), int(lo_s[1]), int(hi_s[0] - lo_s[0]), int(hi_s[1] - lo_s[1]))


def load_views(scene_dir: Path, description: dict, cameras: dict[str, tuple[Intrinsics, Pose]],
               linear: dict[str, Path], masks: dict[str, Path], max_size: int, erode_px: int,
               spp: int, sample_border: bool = False,
               names: set[str] | None = None) -> list[tuple[engine.FitView, tuple]]:  # fmt: skip
    """Every photo (or those in ``names``) as a FitView in its window (longer side at most
    ``max_size`` px), with the window's scaled camera and crop; weights are the mask
    eroded by ``erode_px``."""
    import mitsuba as mi

    shared_scene = mi.load_file(str(scene_dir / "scene.xml")) if description["light_frame"] == "world" else None
    views = []
    for name in sorted(description["views"] if names is None else set(description["views"]) & names):
        mask = cv2.imread(str(masks[name]), cv2.IMREAD_GRAYSCALE) > 127
        window = _window(mask, max_size)
        if window is None:
            logger.warning("%s: empty mask, left out of fitting", name)
            continue
        scale, crop = window
        intrinsics, pose = cameras[name]
        small = scaled(intrinsics, scale, exact=True)
        x, y, w, h = crop
        w, h = min(w, small.width - x), min(h, small.height - y)
        crop = (x, y, w, h)
        photo = read_photo(linear[name]).pixels
        reference = resize_exact(photo, scale)[y : y + h, x : x + w]
        if erode_px:
            mask = cv2.erode(mask.astype(np.uint8), np.ones((2 * erode_px + 1,) * 2, np.uint8)) > 0
        coverage = resize_exact(mask.astype(np.float32), scale)
        weight = (coverage[y : y + h, x : x + w] > 0.999).astype(np.float32)
        scene = shared_scene or mi.load_file(str(scene_dir / description["views"][name]["xml"]))
        sensor = scene_xml.load_sensor(scene_xml.sensor_properties(small, pose, spp,
                                                                   description["near_clip"], crop, sample_border))  # fmt: skip
        views.append((engine.FitView(name, scene, sensor, np.ascontiguousarray(reference), weight), (small, crop)))
    return views


def held_out_names(names: list[str], count: int) -> list[str]:
    """``count`` names evenly spread over the sorted list (none when fewer than 3 photos)."""
    if count == 0 or len(names) < 3:
        return []
    count = min(count, len(names) - 1)
    return [sorted(names)[i] for i in np.linspace(0, len(names) - 1, count + 2)[1:-1].round().astype(int)]


def write_heldout(views: list[engine.FitView], spp: int, folder: Path) -> None:
    import mitsuba as mi

    folder.mkdir()
    for index, view in enumerate(views):
        image = np.asarray(mi.render(view.scene, sensor=view.sensor, spp=spp, seed=10_000 + index), dtype=np.float32)
        write_image(folder / f"{view.name}.render.exr", image)
        write_image(folder / f"{view.name}.reference.exr", view.reference)
        cv2.imwrite(str(folder / f"{view.name}.mask.png"), (view.weight > 0).astype(np.uint8) * 255)


def main(conf: Config, inputs: StageInputs, out_dir: Path) -> StageResult:
    scene_source = inputs.upstream["scene"]["scene_dir"]
    description = json.loads(inputs.upstream["scene"]["description"].read_text())
    model = description["model"]
    parameters = fit_parameters(model, conf.bounds)
    cameras = read_views(inputs.upstream["sfm"]["cameras"])
    linear = {n: p["linear"] for n, p in photo_files(inputs.upstream["undistort"]["pinhole"]).items()}
    masks = mask_files(inputs.upstream["masks"]["masks_json"])

    mitsuba_variant.activate(inputs.shared["mitsuba"].variant)
    fitted = out_dir / "fitted"
    shutil.copytree(scene_source, fitted)
    views = [view for view, _ in load_views(fitted, description, cameras, linear, masks, conf.max_size,
                                                     conf.erode_px, conf.spp)]
    held = set(held_out_names([v.name for v in views], conf.held_out))
    settings = engine.FitSettings(**{f: getattr(conf, f) for f in engine.FitSettings.__dataclass_fields__})
    result = engine.fit(parameters, [v for v in views if v.name not in held], [v for v in views if v.name in held],
                         settings)  # fmt: skip

    keys = {p.name: p.key for p in parameters}
    scene_xml.set_values(fitted / "specimen.xml", {keys[n]: v for n, v in result.values.items()}, fitted / "specimen.xml")
    with (fitted / "log.jsonl").open("w") as log:
        for entry in result.log:
            log.write(json.dumps(entry) + "\n")
    engine.plot_loss(result.log, fitted / "loss.png")
    write_heldout([v for v in views if v.name in held], 4 * conf.validation_spp, fitted / "heldout")
    params = {
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
    }
    (fitted / "params.json").write_text(json.dumps(params, indent=1))
    metrics = {"iterations": len(result.log), "best_iteration": result.best_iteration,
               "validation_mse": result.validation_error, **{n: v if len(v) > 1 else v[0] for n, v in result.values.items()}}  # fmt: skip
    outputs = {"fitted_dir": fitted, "params": fitted / "params.json", "heldout": fitted / "heldout",
               "scene": fitted / "scene.xml"}  # fmt: skip
    return StageResult(outputs, metrics)


STAGE = Stage(
    name="fit_material",
    version=5,
    config=Config,
    main=main,
    upstream=("scene", "sfm", "undistort", "masks"),
    shared=("mitsuba",),
    exports=("fitted_dir", "params", "heldout"),
)
