"""Stage fit_geometry: the specimen's vertices refined by differentiable rendering.

The material is frozen as fit_texture left it; only vertex positions move, by
pipeline.fitting.fit_shape: Adam on LargeSteps' differential coordinates
(Nicolet et al. 2021, mi.ad.LargeSteps with cholespy), rendered with a
projective integrator, the only kind whose gradients include silhouette edges.
Only primary visibility is differentiated (``sppi = 0``): edges seen through
reflections, refraction and shadows would need a guiding pass per render that
costs more than the rest of the step on a CPU.

==============  ===================================================================
loss            what is compared, with which integrator
==============  ===================================================================
photometric     the photo over each view's window (specimen, its silhouette and the
                board and table around it), ``prb_projective`` at the model's depth
silhouette      the mask against the specimen's coverage (black specimen under a
                white sky), ``direct_projective``; needs no material at all
==============  ===================================================================

``auto`` picks photometric for surface models and silhouette for the volumetric
one: no Mitsuba integrator differentiates geometry through a participating
medium, so a volumetric specimen's shape is refined by its outline only.

``start = "sphere"`` is the original tool's naive start: an icosphere scaled to
the visual hull's bounding box, refined by the same loop, with fit_material's
constant material (the texture lives on the hull's UVs, which a sphere lacks).

Held-out photos are fit_material's; the state with the lowest held-out error is
kept, so a refinement that does not help leaves the mesh as it was.

Outputs, in geometry/ (exported to CAPTURE/output/geometry/): the scene with the
refined mesh.ply (UVs kept), params.json (loss, start, held-out error before and
after, best iteration, vertices, seconds), log.jsonl, loss.png, and heldout/ as
fit_material writes it, rendered with the final scene's material over the eroded
mask (so ``pipeline score`` scores the scene the pipeline ends with; with
``enabled = false``, fit_texture's heldout/ is passed through).

Limitations: vertices move, connectivity does not (no remeshing), so a start
far from the truth (the sphere) cannot grow handles or thin limbs. The loss is
plain L2 (one render per view, half the dual estimator's cost): its Monte Carlo
variance counts in the loss and may pull the shape slightly towards renders with
less noise. A render and backward step costs seconds even at 32-96 px on a CPU.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np
import trimesh

from pipeline import fitting, logger, materials, mitsuba_variant
from pipeline.camera import read_views, resize_exact
from pipeline.config import Range
from pipeline.errors import PipelineError
from pipeline.stage import Stage, StageInputs, StageResult
from stages.fit_material import load_views, write_heldout
from stages.masks import mask_files
from stages.undistort import photo_files


@dataclass(frozen=True)
class Config:
    """Vertex refinement by differentiable rendering (LargeSteps)."""

    enabled: bool = True
    """False: pass fit_texture's scene through unchanged (the draft preset)."""
    start: Literal["mesh", "sphere"] = "mesh"
    """mesh: the cleaned, unwrapped hull; sphere: an icosphere in the hull's box."""
    loss: Literal["auto", "photometric", "silhouette"] = "auto"
    """What the renders are compared with (see the module docstring)."""
    iterations: Annotated[int, Range(1, None)] = 40
    """Adam steps."""
    batch: Annotated[int, Range(1, None)] = 2
    """Views rendered per step."""
    spp: Annotated[int, Range(1, None)] = 8
    """Samples per pixel of each training render."""
    max_size: Annotated[int, Range(16, None)] = 96
    """Longer side, in pixels, of the window each view is rendered in."""
    step: Annotated[float, Range(0.0, None, exclusive_lo=True)] = 2e-3
    """Adam step as a fraction of the specimen's bounding-box diagonal."""
    smoothing: Annotated[float, Range(0.0, None, exclusive_lo=True)] = 20.0
    """LargeSteps' lambda; larger spreads each gradient further (finer meshes need more)."""
    sphere_subdivisions: Annotated[int, Range(1, 6)] = 4
    """Icosphere subdivisions of the sphere start (4: 2562 vertices)."""
    validate_every: Annotated[int, Range(1, None)] = 10
    """Iterations between held-out renders."""
    validation_spp: Annotated[int, Range(1, None)] = 64
    """Samples per pixel of held-out renders (and 4x that for heldout/)."""
    erode_px: Annotated[int, Range(0, None)] = 2
    """Mask erosion at full resolution of the pixels heldout/ scores (as fit_material's)."""
    seed: int = 0
    """Seed of the batch order and the renders."""


def sphere_in_box(bounds: np.ndarray, subdivisions: int) -> trimesh.Trimesh:
    """An icosphere stretched to fill the axis-aligned box ``bounds`` (2, 3)."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    sphere.apply_scale((bounds[1] - bounds[0]) / 2)
    sphere.apply_translation(bounds.mean(axis=0))
    return sphere


def silhouette_views(views: list[tuple[fitting.FitView, tuple]], mesh_file: Path, masks: dict[str, Path],
                     cameras: dict) -> list[fitting.FitView]:  # fmt: skip
    """The same windows, with a scene holding only the specimen (black, under a white
    sky) and the mask's complement as reference: coverage, material-free."""
    import mitsuba as mi

    scene = mi.load_dict({
        "type": "scene",
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
        "specimen": {"type": "ply", "id": "specimen", "filename": str(mesh_file),
                     "bsdf": {"type": "diffuse", "id": "specimen_bsdf", "reflectance": {"type": "rgb", "value": 0.0}}},
    })  # fmt: skip
    result = []
    for view, (small, crop) in views:
        mask = (cv2.imread(str(masks[view.name]), cv2.IMREAD_GRAYSCALE) > 127).astype(np.float32)
        x, y, w, h = crop
        coverage = resize_exact(mask, small.fx / cameras[view.name][0].fx)[y : y + h, x : x + w]
        reference = np.repeat(1.0 - coverage[..., None], 3, axis=2).astype(np.float32)
        result.append(fitting.FitView(view.name, scene, view.sensor, reference))
    return result


def main(conf: Config, inputs: StageInputs, out_dir: Path) -> StageResult:
    material = json.loads(inputs.upstream["fit_material"]["params"].read_text())
    source = inputs.upstream["fit_material" if conf.start == "sphere" else "fit_texture"]
    source_dir = source["fitted_dir" if conf.start == "sphere" else "textured_dir"]
    description = json.loads(inputs.upstream["scene"]["description"].read_text())
    loss = conf.loss if conf.loss != "auto" else ("silhouette" if description["model"] == "volumetric" else "photometric")
    if loss == "photometric" and description["model"] == "volumetric":
        raise PipelineError("fit_geometry.loss = photometric: no Mitsuba integrator differentiates geometry through "
                            "the volumetric model's medium; use loss = silhouette (or auto)")  # fmt: skip
    geometry = out_dir / "geometry"
    shutil.copytree(source_dir, geometry, ignore=shutil.ignore_patterns("heldout", "log.jsonl", "loss.png", "params.json"))
    report = {"enabled": conf.enabled, "start": conf.start, "model": description["model"]}
    if not conf.enabled:
        shutil.copytree(source_dir / "heldout", geometry / "heldout")
        (geometry / "params.json").write_text(json.dumps(report, indent=1))
        return StageResult({"geometry_dir": geometry}, {"enabled": False})

    hull = trimesh.load(geometry / "mesh.ply", force="mesh", process=False)
    if conf.start == "sphere":
        sphere_in_box(hull.bounds, conf.sphere_subdivisions).export(geometry / "mesh.ply")

    mitsuba_variant.activate(inputs.shared["mitsuba"].variant)
    import mitsuba as mi

    cameras = read_views(inputs.upstream["sfm"]["cameras"])
    linear = {n: p["linear"] for n, p in photo_files(inputs.upstream["undistort"]["pinhole"]).items()}
    masks = mask_files(inputs.upstream["masks"]["masks_json"])
    windowed = load_views(geometry, description, cameras, linear, masks, conf.max_size, 0, conf.spp, sample_border=True)
    if loss == "silhouette":
        views = silhouette_views(windowed, geometry / "mesh.ply", masks, cameras)
        integrator = mi.load_dict({"type": "direct_projective", "sppi": 0})
    else:
        # The silhouette and its surroundings carry the shape: every window pixel counts.
        views = [fitting.FitView(v.name, v.scene, v.sensor, v.reference) for v, _ in windowed]
        integrator = mi.load_dict({"type": "prb_projective", "max_depth": materials.INTEGRATORS[description["model"]][1],
                                   "sppi": 0})  # fmt: skip
    start = np.array(mi.traverse(views[0].scene)["specimen.vertex_positions"], dtype=np.float32).reshape(-1, 3)
    held = set(material["held_out"])
    diagonal = float(np.linalg.norm(hull.extents))
    settings = fitting.ShapeSettings(iterations=conf.iterations, batch=conf.batch, spp=conf.spp,
                                     step=conf.step * diagonal, smoothing=conf.smoothing,
                                     validate_every=conf.validate_every, validation_spp=conf.validation_spp,
                                     seed=conf.seed)  # fmt: skip
    result = fitting.fit_shape("specimen", [v for v in views if v.name not in held], [v for v in views if v.name in held],
                               settings, integrator)  # fmt: skip

    specimen = next(s for s in views[0].scene.shapes() if s.id() == "specimen")
    specimen.write_ply(str(geometry / "mesh.ply"))
    final = load_views(geometry, description, cameras, linear, masks, conf.max_size, conf.erode_px, conf.validation_spp,
                       names=held)  # fmt: skip
    write_heldout([v for v, _ in final], 4 * conf.validation_spp, geometry / "heldout")
    with (geometry / "log.jsonl").open("w") as handle:
        for entry in result.log:
            handle.write(json.dumps(entry) + "\n")
    fitting.plot_loss(result.log, geometry / "loss.png")
    moved = np.linalg.norm(result.positions - start, axis=1)
    report |= {"loss": loss, "iterations": len(result.log), "best_iteration": result.best_iteration,
               "validation_mse_start": result.start_validation_error, "validation_mse": result.validation_error,
               "vertices": int(len(result.positions)), "seconds": result.log[-1]["seconds"] if result.log else 0.0,
               "held_out": sorted(held), "median_vertex_move_of_diagonal": float(np.median(moved)) / diagonal}  # fmt: skip
    (geometry / "params.json").write_text(json.dumps(report, indent=1))
    logger.info("geometry (%s loss, %s start): held-out MSE %s -> %s", loss, conf.start, result.start_validation_error,
                result.validation_error)  # fmt: skip
    return StageResult({"geometry_dir": geometry}, {"validation_mse_start": result.start_validation_error,
                                                    "validation_mse": result.validation_error})  # fmt: skip


STAGE = Stage(
    name="fit_geometry",
    version=2,
    config=Config,
    main=main,
    upstream=("fit_texture", "fit_material", "scene", "sfm", "undistort", "masks"),
    shared=("mitsuba",),
    exports=("geometry_dir",),
)
