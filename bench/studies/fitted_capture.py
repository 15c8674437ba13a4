"""A synthetic capture run through a fit stage, loaded as the studies of fit_geometry's
passes read it: the stage's scene, the photos, the held-out views, the parameters the
passes refit, the truth and the camera alignment."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench.common import run_stages
from pipeline.core.config import load_config
from pipeline.core.sections import schema
from pipeline.fit.views import CapturePhotos, PhotoGains, read_capture_photos
from pipeline.formats.cameras import read_cameras, read_views
from pipeline.formats.fit_results import TexturedFit, read_fitted_scene
from pipeline.formats.scene_description import SceneDescription
from pipeline.formats.scene_folder import PARAMS_JSON
from pipeline.render import materials, mitsuba_variant
from pipeline.synthetic.score import score_cameras
from stages import STAGES, fit_geometry


@dataclass
class FittedCapture:
    capture: Path
    outputs: dict
    """Each stage's outputs (bench.common.run_stages)."""
    source: Path
    """The chosen stage's scene folder."""
    description: SceneDescription
    photos: CapturePhotos
    held: set[str]
    """fit_texture's held-out views."""
    parameters: list
    """The material parameters fit_geometry's material pass refits."""
    conf: fit_geometry.Config
    """fit_geometry's section of the standard preset."""
    truth: dict
    """ground_truth/material.json."""
    similarity: Any
    """Reconstruction to truth (the camera alignment)."""
    start: dict
    """The chosen stage's params.json."""


def load_fitted_capture(capture: Path, after: str) -> FittedCapture:
    """``capture``'s stages run up to ``after`` (fit_texture or fit_geometry; cached), and
    Mitsuba's variant activated."""
    outputs, _ = run_stages(capture, after)
    description, material = read_fitted_scene(outputs["scene"]["description"], outputs["fit_material"]["params"])
    mitsuba_variant.activate("auto")
    photos = read_capture_photos(
        outputs["sfm"]["cameras"],
        outputs["undistort"]["pinhole"],
        outputs["masks"]["masks_json"],
        PhotoGains.of(material),
    )
    texture_fit = TexturedFit.read(outputs["fit_texture"]["params"])
    source = Path(outputs["fit_texture"]["textured_dir"] if after == "fit_texture" else outputs[after]["geometry_dir"])
    texture = (texture_fit.learning_rate, texture_fit.smoothness) if texture_fit.kept else None
    _, true_poses = read_cameras(capture / "ground_truth" / "cameras.json")
    _, similarity = score_cameras({n: p for n, (_, p) in read_views(outputs["sfm"]["cameras"]).items()}, true_poses)
    return FittedCapture(
        capture,
        outputs,
        source,
        description,
        photos,
        set(texture_fit.held_out),
        materials.refit_parameters(description.model, texture_fit.bounds, texture),
        load_config(schema(STAGES), capture, "standard", [])["fit_geometry"],
        json.loads((capture / "ground_truth" / "material.json").read_text()),
        similarity,
        json.loads((source / PARAMS_JSON).read_text()),
    )
