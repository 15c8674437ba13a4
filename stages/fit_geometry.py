"""Stage fit_geometry: the specimen's shape refined by differentiable rendering, in
alternation with its material (pipeline.fit.passes).

Each of ``rounds`` rounds is a geometry pass, then a material pass:

- Geometry pass: only vertex positions move (pipeline.fit.engine.fit_shape: Adam on
  LargeSteps' differential coordinates, Nicolet et al. 2021), the material frozen.
  Only primary visibility is differentiated (``sppi = 0``): edges seen through
  reflections, refraction and shadows would need a guiding pass per render that
  costs more than the rest of the step on a CPU. The moved mesh is kept only if its
  best held-out error is ``geometry_min_improvement`` (relative) below where it started.
- Material pass (``material_iterations`` > 0): the constants, and the texture if
  fit_texture kept one, fitted again on the refined mesh with fit_material's loop,
  the geometry frozen; kept only if its best held-out error is
  ``material_min_improvement`` (relative) below where it started.

==============  ===================================================================
loss            what is compared, with which integrator
==============  ===================================================================
photometric     the whole window: the photo in the mask and on the table, the
                scene's own backdrop beyond (passes.backdrop_views). Surface
                models: ``prb_projective``, silhouette edges included.
                Volumetric: ``prbvolpath`` (no projective integrator handles a
                medium), interior terms only, evaluated loops (Dr.Jit 1.5 needs
                them for vertex gradients)
silhouette      the mask against the specimen's coverage (black specimen under a
                white sky), ``direct_projective``; needs no material
auto            photometric for surface models, silhouette for the volumetric one
==============  ===================================================================

``start = "sphere"`` is the original tool's naive start: an icosphere in the
visual hull's bounding box with fit_material's constant material. Held-out
photos are fit_material's; every pass keeps its best held-out state, so a pass
that does not help leaves the scene as it was. A geometry pass scores its whole
window, so the rounds are kept only when they lower the held-out error over the
specimen as fit_texture measures it; otherwise its scene is passed through
(params.json: ``kept``, ``specimen_validation_mse``). The measurements behind these
choices: docs/decisions.md, "Fitting's windows and geometry".

Outputs, in geometry/ (exported to CAPTURE/output/stages/fit_geometry/ and, as the
final scene, to the top of CAPTURE/output/), a scene folder
(pipeline.formats.scene_folder): the scene with the refined mesh.ply (UVs kept)
and material; params.json (loss, start, per round each pass's held-out error
before and after, best iteration (or averaged), non-finite gradient entries dropped
(skipped_gradients), whether the pass was kept;
``params`` and ``bounds`` as in fit_texture's; vertices, seconds); log.jsonl
(every iteration with its round and pass); loss.png; heldout/ rendered with
the final scene in windows of ``material_max_size`` pixels, the size fit_material's
and fit_texture's are scored at in every preset, so that the stages' held-out PSNR
compare (with ``enabled = false``, the start scene's passed through).

Limitations: vertices move, connectivity does not (no remeshing), so a start far
from the truth (the sphere) cannot grow handles or thin limbs. The geometry loss
is plain L2 (one render per view): its Monte Carlo variance counts in the loss.
No render differentiates geometry and a medium at once. A step costs seconds on a
CPU (volumetric photometric: about 4.8 s at 96 px, 8 spp, two views, 2 cores).
"""

from __future__ import annotations

import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import trimesh

from pipeline import logger
from pipeline.core.config import Range
from pipeline.core.stage import Stage, StageInputs, StageResult
from pipeline.fit import engine
from pipeline.fit.checkpoint import resumable_stage
from pipeline.fit.outputs import write_fit_log, write_heldout
from pipeline.fit.passes import material_pass, pass_summary, shape_pass, specimen_error, sphere_in_box
from pipeline.fit.views import CapturePhotos, PhotoGains, Windowing, load_views, read_capture_photos
from pipeline.formats.fit_results import FittedValues, GeometryFit, TexturedFit, read_fitted_scene
from pipeline.formats.scene_description import SceneDescription
from pipeline.formats.scene_folder import HELDOUT, MESH_PLY, PARAMS_JSON, copy_scene
from pipeline.render import materials, mitsuba_variant


@dataclass(frozen=True)
class Config:
    """Vertex refinement by differentiable rendering (LargeSteps)."""

    enabled: bool = True
    """False: pass fit_texture's scene through unchanged (the draft preset)."""
    start: Literal["mesh", "sphere"] = "mesh"
    """mesh: the cleaned, unwrapped hull; sphere: an icosphere in the hull's box."""
    loss: Literal["auto", "photometric", "silhouette"] = "auto"
    """What the renders are compared with (see the module docstring)."""
    rounds: Annotated[int, Range(1, None)] = 2
    """Geometry passes, each followed by a material pass."""
    iterations: Annotated[int, Range(1, None)] = 150
    """Adam steps of each geometry pass."""
    batch: Annotated[int, Range(1, None)] = 2
    """Views rendered per step (both passes)."""
    spp: Annotated[int, Range(1, None)] = 8
    """Samples per pixel of each geometry-pass render."""
    max_size: Annotated[int, Range(16, None)] = 96
    """Longer side, in pixels, of the window each view is rendered in by the geometry pass."""
    step: Annotated[float, Range(0.0, None, exclusive_lo=True)] = 4e-3
    """Adam step as a fraction of the specimen's bounding-box diagonal."""
    material_iterations: Annotated[int, Range(0, None)] = 40
    """Adam steps of each material pass; 0 freezes the material as fit_texture left it."""
    material_spp: Annotated[int, Range(1, None)] = 16
    """Samples per pixel of each material-pass render."""
    material_max_size: Annotated[int, Range(16, None)] = 128
    """Longer side, in pixels, of the window each view is rendered in by the material pass."""
    geometry_min_improvement: Annotated[float, Range(0.0, 1.0)] = 0.02
    """Relative drop of held-out error a geometry pass must bring for its mesh to
    replace the one it started from; smaller gains are within the held-out renders'
    noise, and a mesh moved for them can leave the specimen worse (docs/decisions.md)."""
    material_min_improvement: Annotated[float, Range(0.0, 1.0)] = 0.02
    """Relative drop of held-out error a material pass must bring for its values to
    replace the ones it started from; smaller gains are within the held-out renders' noise."""
    smoothing: Annotated[float, Range(0.0, None, exclusive_lo=True)] = 20.0
    """LargeSteps' lambda; larger spreads each gradient further (finer meshes need more)."""
    sphere_subdivisions: Annotated[int, Range(1, 6)] = 4
    """Icosphere subdivisions of the sphere start (4: 2562 vertices)."""
    validate_every: Annotated[int, Range(1, None)] = 10
    """Iterations between held-out renders (both passes)."""
    validation_spp: Annotated[int, Range(1, None)] = 64
    """Samples per pixel of held-out renders (heldout/'s: pipeline.fit.outputs.HELDOUT_SPP)."""
    erode_px: Annotated[int, Range(0, None)] = 2
    """Mask erosion at full resolution of the pixels heldout/ scores (as fit_material's)."""
    seed: int = 0
    """Seed of the batch order and the renders."""


def _shape_settings(conf: Config, diagonal: float, seed: int) -> engine.ShapeSettings:
    return engine.ShapeSettings(
        iterations=conf.iterations,
        batch=conf.batch,
        spp=conf.spp,
        step=conf.step * diagonal,
        smoothing=conf.smoothing,
        validate_every=conf.validate_every,
        validation_spp=conf.validation_spp,
        seed=seed,
    )


def _material_settings(conf: Config, seed: int) -> engine.FitSettings:
    """fit_material's loop, run to its iterations (no early stop), without whitening,
    image memory or step halvings (`pipeline fit`'s defaults, not measured on the
    stages' fits)."""
    return engine.FitSettings(
        iterations=conf.material_iterations,
        whiten=False,
        image_memory=0,
        step_halvings=0,
        batch=conf.batch,
        spp=conf.material_spp,
        learning_rate_scale=1.0,
        validate_every=conf.validate_every,
        validation_spp=conf.validation_spp,
        still_threshold=0.0,
        seed=seed,
    )


def _rounds(
    conf: Config,
    geometry: Path,
    description: SceneDescription,
    loss: str,
    photos: CapturePhotos,
    held: set[str],
    parameters: list[engine.FitParameter],
    diagonal: float,
    values: dict,
) -> tuple[list[dict], list[dict]]:
    """``rounds`` alternations of a geometry and a material pass on geometry/;
    ``values`` takes a kept material pass's values. Returns (per round summary, log)."""
    rounds, log = [], []

    def record(result, round_index: int, name: str, kept: bool, threshold: float) -> dict:
        """A pass's steps into the log and a line into the run's; its summary."""
        offset = len(log)
        log.extend(
            {"iteration": e["iteration"] + offset, "round": round_index, "pass": name}
            | {k: v for k, v in e.items() if k != "iteration"}
            for e in result.log
        )
        logger.info(
            "round %d, %s: held-out error %s -> %s (%s)",
            round_index + 1,
            name,
            result.start_validation_error,
            result.validation_error,
            "kept" if kept else f"gain below {threshold:.0%}, not kept",
        )
        return pass_summary(result) | {"kept": kept}

    for round_index in range(conf.rounds):
        seed = conf.seed + round_index
        threshold = conf.geometry_min_improvement
        shape_settings = _shape_settings(conf, diagonal, seed)
        shape, moved = shape_pass(geometry, description, loss, photos, held, conf.max_size, shape_settings, threshold)
        rounds.append({"geometry": record(shape, round_index, "geometry", moved, threshold)})
        if conf.material_iterations:
            threshold = conf.material_min_improvement
            settings = _material_settings(conf, seed)
            refit, kept = material_pass(
                geometry,
                description,
                photos,
                held,
                parameters,
                Windowing(conf.material_max_size, conf.erode_px, settings.spp),
                settings,
                threshold,
            )
            rounds[-1]["material"] = record(refit, round_index, "material", kept, threshold)
            if kept:
                values |= refit.values
    return rounds, log


@resumable_stage
def main(conf: Config, inputs: StageInputs, out_dir: Path) -> StageResult:
    # 1. The scene to start from: fit_texture's, or fit_material's for the sphere.
    description, material = read_fitted_scene(
        inputs.upstream["scene"]["description"], inputs.upstream["fit_material"]["params"]
    )
    source = "fit_material" if conf.start == "sphere" else "fit_texture"
    source_dir = inputs.upstream[source]["fitted_dir" if source == "fit_material" else "textured_dir"]
    start_fit: FittedValues = (
        material if source == "fit_material" else TexturedFit.read(inputs.upstream["fit_texture"]["params"])
    )
    model = description.model
    loss = conf.loss if conf.loss != "auto" else ("silhouette" if model == "volumetric" else "photometric")
    geometry = copy_scene(source_dir, out_dir / "geometry")
    outputs = {"geometry_dir": geometry, "params": geometry / PARAMS_JSON, "heldout": geometry / HELDOUT}
    about = {"enabled": conf.enabled, "start": conf.start}
    values, bounds, held_out = dict(start_fit.params), start_fit.bounds, start_fit.held_out
    if not conf.enabled:
        shutil.copytree(inputs.upstream[source]["heldout"], geometry / HELDOUT)
        unchanged = GeometryFit(model=model, params=values, bounds=bounds, held_out=held_out, kept=False, details=about)
        unchanged.write(geometry / PARAMS_JSON)
        return StageResult(outputs, {"enabled": False})
    hull = trimesh.load(geometry / MESH_PLY, force="mesh", process=False)
    if conf.start == "sphere":
        sphere_in_box(hull.bounds, conf.sphere_subdivisions).export(geometry / MESH_PLY)

    # 2. The rounds of geometry and material passes.
    mitsuba_variant.activate(inputs.shared["mitsuba"].variant)
    photos = read_capture_photos(
        inputs.upstream["sfm"]["cameras"],
        inputs.upstream["undistort"]["pinhole"],
        inputs.upstream["masks"]["masks_json"],
        PhotoGains.of(material),
    )
    held = set(held_out)
    diagonal = float(np.linalg.norm(hull.extents))
    start = trimesh.load(geometry / MESH_PLY, force="mesh", process=False).vertices.copy()
    kept_texture = isinstance(start_fit, TexturedFit) and start_fit.kept
    texture = (start_fit.learning_rate, start_fit.smoothness) if kept_texture else None
    parameters = materials.refit_parameters(model, bounds, texture)
    started = time.perf_counter()
    measured = Windowing(conf.material_max_size, conf.erode_px, conf.validation_spp)
    specimen = {"start": specimen_error(geometry, description, photos, held, measured), "start_values": dict(values)}
    rounds, log = _rounds(conf, geometry, description, loss, photos, held, parameters, diagonal, values)
    # Kept only when the specimen's error ends lower (not the sphere: no result to keep).
    specimen["end"] = specimen_error(geometry, description, photos, held, measured)
    specimen["kept"] = conf.start == "sphere" or specimen["end"] < specimen["start"]
    if not specimen["kept"]:
        logger.info("specimen's held-out error %.4g -> %.4g: the start scene kept", specimen["start"], specimen["end"])
        shutil.rmtree(geometry)
        copy_scene(source_dir, geometry)
        values = specimen["start_values"]

    # 3. Held-out renders of the final scene, the log and params.json.
    final = load_views(geometry, description, photos, measured, names=held)
    write_heldout([v for v, _ in final], geometry / HELDOUT)
    write_fit_log(geometry, log)
    positions = trimesh.load(geometry / MESH_PLY, force="mesh", process=False).vertices
    moved = np.linalg.norm(positions - start, axis=1)
    first, last = rounds[0]["geometry"], rounds[-1]["geometry"]
    about |= {
        "loss": loss,
        "rounds": rounds,
        "validation_mse_start": first["validation_start"],
        "validation_mse": last["validation"],
        "specimen_validation_mse": {"start": specimen["start"], "end": specimen["end"]},
        "vertices": int(len(positions)),
        "seconds": time.perf_counter() - started,
        "median_vertex_move_of_diagonal": float(np.median(moved)) / diagonal,
    }
    refined = GeometryFit(
        model=model, params=values, bounds=bounds, held_out=sorted(held), kept=specimen["kept"], details=about
    )
    refined.write(geometry / PARAMS_JSON)
    return StageResult(
        outputs, {"validation_mse_start": first["validation_start"], "validation_mse": last["validation"]}
    )


STAGE = Stage(
    name="fit_geometry",
    version=28,
    config=Config,
    main=main,
    needs=(
        "fit_texture.textured_dir",
        "fit_texture.params",
        "fit_texture.heldout",
        "fit_material.fitted_dir",
        "fit_material.params",
        "fit_material.heldout",
        "scene.description",
        "sfm.cameras",
        "undistort.pinhole",
        "masks.masks_json",
    ),
    outputs=("geometry_dir", "params", "heldout"),
    shared=("mitsuba",),
    exports=("geometry_dir",),
    result=("scene", "geometry_dir"),
)
