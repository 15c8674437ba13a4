"""How far fit_geometry's material pass lands from the truth on a fixed mesh, and how much
of that is its wander and how much the mesh.

On a synthetic capture run through a fit stage, the stage's final scene is copied once
per arm and seed and its material fitted again with the geometry frozen
(pipeline.fit.passes.material_pass, every value kept):

==================  ==================================================================
arm                 what runs
==================  ==================================================================
stage               fit_geometry's material pass as the preset configures it
long                the same, run until the loop finds it still (up to
                    ``--iterations``), its learning rates halved twice on the way
                    (``step_halvings``): the pass's own optimum, its wander narrowed
true-normals        ``stage`` on the mesh with each vertex's shading normal taken from
                    the true surface's nearest point (positions kept)
long-true           ``long`` on that mesh
geometry            one more round: fit_geometry's geometry pass as the preset
                    configures it, then ``stage``
geometry-half-step  the same with the geometry pass's step halved
geometry-128px      the same with the geometry pass in 128-px windows
==================  ==================================================================

What ``long`` gives against ``stage`` is the wander's share of a pass's error; what
``true-normals`` gives against ``stage`` is the shading normals' share; the geometry
arms say what a further round, and which kind of round, does to the normals and the
values.

Limitations: synthetic captures only (the truth scores the arms); each arm starts from
the stage's own values, as the pass does in fit_geometry's later rounds.

Usage: ``.venv/bin/python -m bench.studies.material_bias --capture DIR --work DIR
[--after fit_texture|fit_geometry] [--arms stage,long] [--seeds 4] [--iterations N]``
(runs the capture's stages up to ``--after`` first, cached; prints and writes
report.json in the work folder, which a rerun on the same stage run's scene reads back for
the arms and seeds it has).
Results: docs/decisions.md, "Fitting's windows and geometry".
"""

from __future__ import annotations

import argparse
import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import trimesh

from bench.common import truth_in_reconstruction
from bench.fitting import shading_normals_towards_truth
from bench.studies.fitted_capture import FittedCapture, load_fitted_capture
from bench.studies.shading_normal_fit import shading_error
from pipeline import logger
from pipeline.fit.passes import material_pass, shape_pass
from pipeline.fit.views import Windowing
from pipeline.formats.scene_folder import MESH_PLY, copy_scene
from pipeline.synthetic.score import score_material
from stages import fit_geometry

ARMS = ("stage", "long", "true-normals", "long-true", "geometry", "geometry-half-step", "geometry-128px")
GEOMETRY_ARMS = {"geometry": {}, "geometry-half-step": {"step_scale": 0.5}, "geometry-128px": {"max_size": 128}}
"""The geometry arms' changes to fit_geometry's geometry pass."""


def _arm_settings(arm: str, stage_settings, iterations: int):
    """The material pass's loop settings for ``arm``."""
    if arm.startswith("long"):
        return replace(stage_settings, iterations=iterations, still_threshold=2.0, step_halvings=2)
    return stage_settings


def _run_arm(study: FittedCapture, arm: str, seed_value: int, folder: Path, iterations: int) -> dict:
    """One arm with one seed on a fresh copy of the stage's scene in ``folder``: its report entry."""
    conf = study.conf
    shutil.rmtree(folder, ignore_errors=True)
    geometry = copy_scene(study.source, folder)
    if arm in ("true-normals", "long-true"):
        _, true_mesh = truth_in_reconstruction(study.capture, study.outputs)
        shading_normals_towards_truth(geometry / MESH_PLY, true_mesh, 1.0)
    entry = {}
    if arm in GEOMETRY_ARMS:
        change = GEOMETRY_ARMS[arm]
        diagonal = float(np.linalg.norm(trimesh.load(geometry / MESH_PLY, force="mesh").extents))
        shape_settings = fit_geometry._shape_settings(conf, diagonal * change.get("step_scale", 1.0), seed_value)
        size = change.get("max_size", conf.max_size)
        volumetric = study.description.model == "volumetric"
        loss = conf.loss if conf.loss != "auto" else ("silhouette" if volumetric else "photometric")
        shape, _ = shape_pass(geometry, study.description, loss, study.photos, study.held, size, shape_settings, 0.0)
        entry["geometry"] = {"validation": [shape.start_validation_error, shape.validation_error]}
    entry["mesh"] = shading_error(study.capture, geometry / MESH_PLY, study.similarity)
    settings = _arm_settings(arm, fit_geometry._material_settings(conf, seed_value), iterations)
    windowing = Windowing(conf.material_max_size, conf.erode_px, conf.material_spp)
    refit, _ = material_pass(
        geometry, study.description, study.photos, study.held, study.parameters, windowing, settings, 0.0
    )
    values = dict(study.start["params"]) | refit.values
    return entry | {
        "values": values,
        "errors": score_material({"model": study.description.model, "params": values}, study.truth),
        "iterations": len(refit.log),
        "stopped": refit.stopped,
        "averaged": refit.averaged,
        "validation": [refit.start_validation_error, refit.validation_error],
    }


def _print_summary(report: dict, arms: list[str], seeds: int, truth: dict) -> None:
    """Per arm: each error's median and range over the seeds, and each scalar's fitted values."""
    for arm in arms:
        errors = [report[f"{arm} {s}"]["errors"] for s in range(seeds)]
        for name in sorted(errors[0]):
            if name.endswith("_error"):
                column = np.array([e[name] for e in errors])
                print(
                    f"{arm:18s} {name:22s} median {np.median(column):.3f} range {column.min():.3f}-{column.max():.3f}"
                )
        for name, true in truth.items():
            if isinstance(true, float) and name in report[f"{arm} 0"]["values"]:
                fitted = [float(np.ravel(report[f"{arm} {s}"]["values"][name])[0]) for s in range(seeds)]
                print(f"{arm:18s} {name:22s} fitted {' '.join(f'{v:.3f}' for v in fitted)} (truth {true})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--capture", type=Path, required=True, help="a synthetic capture folder")
    parser.add_argument("--work", type=Path, required=True, help="folder for the arms' scene folders")
    parser.add_argument("--after", choices=("fit_texture", "fit_geometry"), default="fit_geometry")
    parser.add_argument("--arms", default="stage,long", help=f"comma-separated, of {', '.join(ARMS)}")
    parser.add_argument("--seeds", type=int, default=4, help="seeds 0 to N-1 per arm")
    parser.add_argument("--iterations", type=int, default=400, help="most steps of the long arms")
    args = parser.parse_args()
    arms = args.arms.split(",")
    if unknown := set(arms) - set(ARMS):
        parser.error(f"unknown arms {sorted(unknown)}; choose from {', '.join(ARMS)}")

    study = load_fitted_capture(args.capture, args.after)
    args.work.mkdir(parents=True, exist_ok=True)
    report_file = args.work / "report.json"
    report = json.loads(report_file.read_text()) if report_file.is_file() else {}
    if report.get("source") != str(study.source):
        report = {"source": str(study.source)}  # another stage run's scene: its arms are not this one's
    report["start"] = {
        "values": study.start["params"],
        "errors": score_material(study.start, study.truth),
        "mesh": shading_error(args.capture, study.source / MESH_PLY, study.similarity),
    }
    for arm in arms:
        for seed_value in range(args.seeds):
            key = f"{arm} {seed_value}"
            if key not in report:
                report[key] = _run_arm(study, arm, seed_value, args.work / arm / str(seed_value), args.iterations)
                logger.info("%s: %s", key, json.dumps(report[key]))
                report_file.write_text(json.dumps(report, indent=1))
    _print_summary(report, arms, args.seeds, study.truth)


if __name__ == "__main__":
    main()
