"""params.json: what each fit stage hands on.

Every fit stage writes the material's values with their bounds and the photos it
held out (FittedValues); fit_material adds what the later fits take over (MaterialFit),
fit_texture whether its texture was kept (TexturedFit), fit_geometry whether its
mesh was (GeometryFit). The rest of each file (``details``: iterations, candidates,
held-out errors, rounds) is the stage's account for people and the report.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from pipeline.formats.records import JsonRecord
from pipeline.formats.scene_description import Integrator, SceneDescription


@dataclass(frozen=True)
class LightChoice:
    """fit_material's light: the one chosen among the candidates, and why."""

    chosen: dict
    """The light's summary (pipeline.render.light): its model, and for an estimated
    light its fitted values; ``{"model": "given"}`` for the files' light."""
    why: str
    candidates: list[dict]
    """Each candidate's summary (pipeline.fit.candidates): model and held-out errors."""
    level: list[float] | None
    """An estimated light's starting level (scene.json's; None for the files' light)."""
    level_from: str | None
    """What that level was measured on (scene.json's)."""

    @property
    def estimated(self) -> bool:
        return self.chosen.get("model", "given") != "given"


@dataclass(kw_only=True)
class FittedValues(JsonRecord):
    """What every fit stage's params.json holds."""

    model: str
    """The material model fitted."""
    params: dict[str, list[float]]
    """The material's values by parameter name (a kept texture's mean in its parameter's place)."""
    bounds: dict[str, list[float]]
    """Each parameter's [lower, upper]."""
    held_out: list[str]
    """The photos kept out of the fit to measure it."""


@dataclass(kw_only=True)
class MaterialFit(FittedValues):
    """fit_material's params.json."""

    PARTS = {"integrator": Integrator, "light": LightChoice}

    units: dict[str, str]
    """Each parameter's units."""
    integrator: Integrator
    """What the fit rendered with (the path depth chosen)."""
    light: LightChoice
    photo_gains: dict[str, list[float]]
    """Each training photo's fitted exposure (and white balance) gain."""
    gain_channels: int
    """Channels of each gain: 0 (none fitted), 1 or 3."""
    heldout_gains: dict
    """The held-out photos' gains measured on the table (pipeline.fit.exposure), if any."""


@dataclass(kw_only=True)
class TexturedFit(FittedValues):
    """fit_texture's params.json."""

    kept: bool
    """Whether the texture earned its place (else the scene is fit_material's constant one)."""
    learning_rate: float | None = None
    """The texture's learning rate (fit_geometry's material passes go on with it)."""
    smoothness: float | None = None
    """The texture's smoothness prior's weight."""
    light: dict | None = None
    """The summary of fit_material's light rescaled, when baking the texture changed its
    level (pipeline.render.light)."""


@dataclass(kw_only=True)
class GeometryFit(FittedValues):
    """fit_geometry's params.json."""

    kept: bool
    """Whether the refined mesh was kept (else the scene is the start's)."""


def read_fitted_scene(description_json: Path, material_json: Path) -> tuple[SceneDescription, MaterialFit]:
    """scene.json as fit_material's fit saw it (the model it chose, the integrator it
    rendered with: it may have chosen opaque over the scene's principled), and
    fit_material's params.json."""
    material = MaterialFit.read(material_json)
    return SceneDescription.read(description_json).fitted_with(material.model, material.integrator), material


__all__ = ["FittedValues", "GeometryFit", "LightChoice", "MaterialFit", "TexturedFit", "read_fitted_scene"]
