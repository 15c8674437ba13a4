"""Whether fitting the mesh's shading normals takes a fitted roughness to its truth.

A material fitted on a reconstructed mesh sees the mesh's shading normals; where they
are off the true surface's by a few degrees, a glossy highlight spreads by as much and
the fitted roughness makes up for it (docs/benchmarks.md: the visual hull's shading
normals, and the texture oracle's roughness on the hull against the true mesh).
fit_geometry's passes move the vertices, which leave the normals about as far off
(docs/decisions.md, "Fitting's windows and geometry"). This study fits the vertex
normals themselves instead, the positions fixed:

1. **control**: fit_geometry's material pass (its loop, windows, samples and steps)
   on the scene as the chosen stage left it;
2. **normals**: first a pass on the vertex normals alone, the material frozen (unit
   normals through LargeSteps' differential coordinates, so that a gradient moves a
   smooth patch of them; the views' own ``prb``, as normals change shading, not
   outlines), then the same material pass.

Each arm reports the held-out error, the fitted values' errors against the synthetic
capture's truth and the shading normals' error against the true surface
(``pipeline score``'s, in the true frame). Both arms use the same seeds.

Limitations: a normal field is not a surface; positions and normals then disagree,
which only shading sees. Synthetic captures only (the truth scores the arms).

Usage: ``.venv/bin/python -m bench.studies.shading_normal_fit --capture DIR --work DIR
[--after fit_texture|fit_geometry] [--iterations N] [--step S] [--smoothing L]
[--max-size PX]`` (a synthetic capture; runs its stages up to ``--after`` first,
cached; prints and writes report.json in the work folder). Results:
docs/decisions.md, "Fitting's windows and geometry".
"""

from __future__ import annotations

import argparse
import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import trimesh

from bench.studies.fitted_capture import load_fitted_capture
from pipeline import logger
from pipeline.fit import engine, loop
from pipeline.fit.passes import material_pass
from pipeline.fit.variables import ShapeVariables
from pipeline.fit.views import Windowing, load_views
from pipeline.formats.scene_folder import MESH_PLY, copy_scene
from pipeline.synthetic.score import score_material, score_mesh
from stages import fit_geometry


class NormalVariables(ShapeVariables):
    """A mesh's vertex normals in every view's scene, as LargeSteps' differential
    coordinates (welded at the UV seams by its construction from the positions),
    renormalised to unit length before every render. Snapshots are ShapeVariables'
    (the un-normalised normals, under its ``positions`` key)."""

    def __init__(self, shape_id: str, traversed: dict, step: float, smoothing: float):
        super().__init__(shape_id, traversed, step, smoothing)  # the Laplacian of the positions' mesh
        self.key = f"{shape_id}.vertex_normals"
        # before any step: Adam's state is still its initial one
        self.optimizer["u"] = self.steps.to_differential(next(iter(traversed.values()))[self.key])

    def apply(self, scene_key: int) -> None:
        normals = self.dr.normalize(
            self.dr.unravel(self.mi.Vector3f, self.steps.from_differential(self.optimizer["u"]))
        )
        self.traversed[scene_key][self.key] = self.dr.ravel(normals)
        self.traversed[scene_key].update()


def normal_pass(geometry: Path, description, photos, held: set[str], windowing: Windowing, settings) -> dict:
    """The vertex normals of the scene folder's mesh fitted with the material frozen;
    written into mesh.ply when the held-out error falls at all."""
    import mitsuba as mi

    views = [v for v, _ in load_views(geometry, description, photos, windowing)]
    traversed = {id(v.scene): mi.traverse(v.scene) for v in views}
    variables = NormalVariables("specimen", traversed, settings.step, settings.smoothing)
    result = loop.run(
        variables, [v for v in views if v.name not in held], [v for v in views if v.name in held], settings
    )
    kept = result.best_error < result.start_error
    shape = next(s for s in views[0].scene.shapes() if s.id() == "specimen")
    written = np.array(mi.traverse(shape)["vertex_normals"]).reshape(-1, 3)
    if kept:
        shape.write_ply(str(geometry / MESH_PLY))
    return {
        "kept": kept,
        "validation_start": result.start_error,
        "validation": result.best_error,
        "best_iteration": result.best_iteration,
        "unit_normals": bool(np.allclose(np.linalg.norm(written, axis=1), 1.0, atol=1e-4)),
    }


def shading_error(capture: Path, mesh_file: Path, similarity) -> dict:
    """pipeline score's mesh scores of ``mesh_file`` with the vertex normals it holds
    (not ones recomputed from its faces), moved into the true frame with them."""
    mesh = trimesh.load(mesh_file, process=False)  # force="mesh" would drop the normals
    matrix = similarity.matrix()
    normals = np.asarray(mesh.vertex_normals) @ matrix[:3, :3].T
    moved = trimesh.Trimesh(
        np.asarray(mesh.vertices) @ matrix[:3, :3].T + matrix[:3, 3],
        mesh.faces,
        vertex_normals=normals / np.linalg.norm(normals, axis=1, keepdims=True),
        process=False,
    )
    return score_mesh(moved, trimesh.load(capture / "ground_truth" / "mesh.ply", force="mesh"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--capture", type=Path, required=True, help="a synthetic capture folder")
    parser.add_argument("--work", type=Path, required=True, help="folder for the arms' scene folders")
    parser.add_argument("--after", choices=("fit_texture", "fit_geometry"), default="fit_texture")
    parser.add_argument("--iterations", type=int, default=100, help="steps of the normal pass")
    parser.add_argument("--step", type=float, default=0.01, help="Adam step on the normals' differential coordinates")
    parser.add_argument("--smoothing", type=float, default=20.0, help="LargeSteps' lambda for the normals")
    parser.add_argument(
        "--max-size", type=int, default=0, help="window of the normal pass, px (0: the material pass's)"
    )
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    fitted = load_fitted_capture(args.capture, args.after)
    description, photos, held, parameters = fitted.description, fitted.photos, fitted.held, fitted.parameters
    source, start, truth, similarity = fitted.source, fitted.start, fitted.truth, fitted.similarity
    conf = fitted.conf  # fit_geometry's material pass as the standard preset configures it
    windowing = Windowing(conf.material_max_size, conf.erode_px, conf.material_spp)
    material_settings = fit_geometry._material_settings(conf, args.seed)
    normal_settings = engine.ShapeSettings(
        iterations=args.iterations,
        batch=conf.batch,
        spp=conf.material_spp,
        step=args.step,
        smoothing=args.smoothing,
        validate_every=conf.validate_every,
        validation_spp=conf.validation_spp,
        seed=args.seed,
    )
    report = {
        "start": {
            "material": score_material(start, truth),
            "mesh": shading_error(args.capture, Path(source) / MESH_PLY, similarity),
        }
    }
    for arm in ("control", "normals"):
        folder = args.work / arm
        shutil.rmtree(folder, ignore_errors=True)
        geometry = copy_scene(Path(source), folder)
        entry = {}
        if arm == "normals":
            normal_windows = replace(windowing, max_size=args.max_size or windowing.max_size)
            entry["normal_pass"] = normal_pass(geometry, description, photos, held, normal_windows, normal_settings)
        refit, kept = material_pass(geometry, description, photos, held, parameters, windowing, material_settings, 0.0)
        values = dict(start["params"]) | (refit.values if kept else {})
        entry |= {
            "material_pass": {
                "kept": kept,
                "validation_start": refit.start_validation_error,
                "validation": refit.validation_error,
            },
            "material": score_material({"model": description.model, "params": values}, truth),
            "mesh": shading_error(args.capture, geometry / MESH_PLY, similarity),
        }
        report[arm] = entry
        logger.info("%s: %s", arm, json.dumps(entry))
    (args.work / "report.json").write_text(json.dumps(report, indent=1))
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
