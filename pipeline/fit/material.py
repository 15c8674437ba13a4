"""A capture's material fitted by evidence: the candidate fits fit_material compares.

A MaterialFitting holds what every candidate shares: the scene folder it writes each
candidate's values (and light) into before fitting, the photos in their windows, the
parameters of each material model, the loop's settings. Its steps, in the order the
stage calls them:

================  ==================================================================
step              what it fits and keeps
================  ==================================================================
fit_lights        the scene's model under the given light, or under each light model
                  (pipeline.render.light), simplest first; "envmap+area" starts from
                  the environment map's fit with an area light added
choose_model      when the scene leaves the model open: opaque from principled's
                  values, volumetric only when principled beat opaque by more than the
                  margin, the simplest within the margin kept; then the path depth: the
                  held-out photos rendered at twice the depth, the model refitted
                  deeper only when that changes their error by more than the margin
================  ==================================================================

Choosing is pipeline.fit.candidates' rule. Limitations: every candidate is fitted
on the same budget, not to convergence; a candidate's scenes are not kept (see
Candidate.held).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any, Callable

import numpy as np
import trimesh

from pipeline import logger
from pipeline.camera.model import Pose
from pipeline.core.sections import LightSection
from pipeline.fit import engine
from pipeline.fit.candidates import Candidate, choose, improves
from pipeline.fit.settings import FitSettings
from pipeline.fit.views import BoardPixels, CapturePhotos, PhotoGains, Windowing, held_out_names, load_views
from pipeline.formats.scene_description import Integrator, SceneDescription
from pipeline.formats.scene_folder import MESH_PLY, SPECIMEN_XML
from pipeline.render import light as estimated_light
from pipeline.render import materials
from pipeline.render.capture_scene import rewrite_specimen_material


def light_models(requested: str, estimated: bool) -> list[str]:
    """The light models to fit, simplest first: none when the light is given."""
    if not estimated:
        return []
    return list(estimated_light.LIGHT_MODELS) if requested == "auto" else [requested]


@dataclass(frozen=True)
class ModelChoice:
    """What choose_model found."""

    material: Candidate
    """The winner (at the depth chosen)."""
    candidates: list[Candidate]
    """The material models fitted, simplest first."""
    why: str
    depth: dict | None
    """The path depth's test (None when the model was the scene's)."""


@dataclass
class MaterialFitting:
    """What every candidate fit of one capture shares (see the module docstring)."""

    folder: Path
    """The scene folder each candidate's values and light are written into."""
    description: SceneDescription
    photos: CapturePhotos
    parameters: dict[str, list[engine.FitParameter]]
    """Each material model's parameters with their bounds."""
    light: LightSection
    settings: FitSettings
    windowing: Windowing
    held_out: int
    """Photos kept out of every fit to measure its error."""
    gain_channels: int
    """Gains per photo: 0 (one exposure), 1 (exposure) or 3 (and white balance)."""
    poses: dict[str, Pose]
    mesh: trimesh.Trimesh
    board_print: list | None
    """The board's print in the scene when the light is estimated: its known reflectance
    then sets the light's level, and it counts in training."""
    measured_on: Any
    """Where an estimated light's level was measured, when it is held (no print)."""

    @staticmethod
    def prepare(
        folder: Path,
        description: SceneDescription,
        photos: CapturePhotos,
        parameters: dict[str, list[engine.FitParameter]],
        light: LightSection,
        settings: FitSettings,
        windowing: Windowing,
        held_out: int,
        gain_channels: int,
    ) -> MaterialFitting:
        poses = {name: pose for name, (_, pose) in photos.cameras.items()}
        mesh = trimesh.load(folder / MESH_PLY, force="mesh", process=False)
        level_from = description.light.level_from
        # With the board's print in the fit, its known reflectance sets the light's level
        # where the specimen stands (the measured level is the print's mean, shadow and a
        # near light's falloff included): the level is the loss's, not held.
        board_print = description.board_print if light.estimated else None
        held_level = light.estimated and not board_print
        measured_on = estimated_light.measured_surface(level_from, mesh, poses, light.frame) if held_level else None
        return MaterialFitting(
            folder,
            description,
            photos,
            parameters,
            light,
            settings,
            windowing,
            held_out,
            gain_channels,
            poses,
            mesh,
            board_print,
            measured_on,
        )

    def write_scene(self, model: str, values: dict, fitted_light) -> None:
        """The material's values and the light (None: the given one) into the folder."""
        rewrite_specimen_material(self.folder / SPECIMEN_XML, model, values)
        if fitted_light is not None:
            estimated_light.write(fitted_light, self.folder, self.description.view_files(), self.poses)

    def views(
        self, model: str, integrator: Integrator, names=None, count_board=False, fitted_gains=None, measured=None
    ):
        seen = self.description.fitted_with(model, integrator)
        board = BoardPixels(tuple(self.board_print), count_board) if self.board_print else None
        gains = PhotoGains(fitted_gains or {}, self.gain_channels, measured or {})
        photos = replace(self.photos, gains=gains)
        return [v for v, _ in load_views(self.folder, seen, photos, self.windowing, names=names, board=board)]

    def fit(self, model: str, start_light, start_values: dict | None = None, integrator: Integrator | None = None):
        """One candidate: ``model`` from ``start_values`` (the scene's) under ``start_light``."""
        started = time.perf_counter()
        integrator = integrator or self.description.integrators[model]
        initial = self.description.initial_values() if start_values is None else start_values
        self.write_scene(model, initial, start_light)
        # the board's print counts in training only: held out, the specimen is scored
        views = self.views(model, integrator, count_board=start_light is not None)
        held = set(held_out_names([v.name for v in views], self.held_out))
        validation = (
            [v for v in views if v.name in held] if not self.board_print else self.views(model, integrator, held)
        )
        fitted_parameters = self.parameters[model] + (
            estimated_light.parameters(start_light, self.light.smoothness, self.measured_on) if start_light else []
        )
        result = engine.fit(fitted_parameters, [v for v in views if v.name not in held], validation, self.settings)
        end_light = None
        if start_light is not None:
            end_light = estimated_light.fitted(start_light, {**result.values, **result.textures})
            logger.info("light %s: held-out error %.4g", end_light.model, result.validation_error or float("nan"))
        return Candidate(model, end_light, integrator, result, sorted(held), time.perf_counter() - started)

    def heldout_views(self, candidate: Candidate, integrator: Integrator, measured=None) -> list[engine.FitView]:
        """The candidate's held-out photos, its values and light written into the folder."""
        self.write_scene(candidate.model, candidate.result.values, candidate.light)
        gains = candidate.result.photo_gains
        return self.views(candidate.model, integrator, set(candidate.held), fitted_gains=gains, measured=measured)

    def fit_lights(self) -> list[Candidate]:
        """The scene's model under the given light, or under each light model, simplest first."""
        model, light = self.description.model, self.light
        candidate_lights = light_models(light.model, light.estimated)
        if not candidate_lights:
            return [self.fit(model, None)]
        level = np.array(self.description.light.level, np.float32)
        candidates: list[Candidate] = []
        for light_model in candidate_lights:
            if light_model == "envmap+area":
                envmap = next((c for c in candidates if c.light.model == "envmap"), None) or self.fit(
                    model, estimated_light.start("envmap", light.frame, level, light.environment_width)
                )
                area = estimated_light.with_area(
                    envmap.light, *estimated_light.specimen_sphere(self.mesh.vertices, light, self.poses)
                )
                candidates.append(self.fit(model, area, envmap.result.values))
            else:
                start = estimated_light.start(light_model, light.frame, level, light.environment_width)
                candidates.append(self.fit(model, start))
        return candidates

    def choose_model(self, chosen: Candidate, models: list[str], margin: float, validation_spp: int) -> ModelChoice:
        """The material model under the chosen light when the scene leaves it open
        (``models``), then the path depth (see the module docstring)."""
        candidates = [chosen]
        if len(models) > 1:
            candidates.insert(
                0, self.fit("opaque", chosen.light, materials.opaque_from_principled(chosen.result.values))
            )
            if "volumetric" in models and improves(chosen, candidates[0], margin):
                start = materials.volumetric_from_principled(chosen.result.values)
                candidates.append(self.fit("volumetric", chosen.light, start))
        material, why = choose(candidates, margin, "material")
        depth = None
        if len(models) > 1:
            deeper = material.integrator.deeper()
            refit = partial(self.fit, material.model, material.light, material.result.values, deeper)
            material, depth = deeper_or_not(
                material, self.heldout_views(material, deeper), margin, validation_spp, refit
            )
        return ModelChoice(material, candidates, why, depth)


def deeper_or_not(
    material: Candidate, held: list[engine.FitView], margin: float, spp: int, refit: Callable[[], Candidate]
) -> tuple[Candidate, dict]:
    """The chosen fit, or one at twice its path depth: the ``held`` photos (the chosen
    values, the deeper integrator) rendered first; only when that changes their error by
    more than ``margin`` is the model refitted deeper (``refit()``) and the simplest
    within the margin kept. Returns the winner and what was measured."""
    shallow_error = material.result.validation_error
    if not held or shallow_error is None:
        return material, {"why": "no held-out photos"}
    max_depth = material.integrator.deeper().max_depth
    deep_error = engine.heldout_error(held, spp, held[0].integrator)
    del held  # their scenes, before the refit's (see Candidate.held)
    report = {"max_depth": material.integrator.max_depth, "deeper_validation_mse": deep_error}
    change = abs(deep_error - shallow_error) / shallow_error
    if change <= margin:
        why = f"rendered at max_depth {max_depth}, the held-out error changes by {change:.1%}: kept"
        return material, report | {"why": why}
    candidates = [material, refit()]
    winner, why = choose(candidates, margin, "depth")
    return winner, report | {"why": why, "candidates": [c.summary("depth") for c in candidates]}


__all__ = ["MaterialFitting", "ModelChoice", "deeper_or_not", "light_models"]
