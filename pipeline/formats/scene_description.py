"""scene.json: what the scene stage tells the fit stages about its scene folder.

==============  ===========================================================
field           content
==============  ===========================================================
model           the material model the files are written with
integrator      Integrator: the render integrator, the differentiable one, depth
light_frame     world (one light for every photo) or camera (a turntable's:
                each view file has its own)
near_clip       the sensors' near clip (scene units)
board_print     the board print's half width and height (metres, at the
                origin), or None
ground          Ground (a disc under the specimen), or None
parameters      the material's parameters: MaterialParameter by name
views           ViewFiles by photo name
model_choice    the models fit_material chooses among (one: the model is given)
integrators     Integrator by model of model_choice
light           LightStart: the light's model and an estimated light's level
==============  ===========================================================
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from pipeline.formats.records import JsonRecord


@dataclass(frozen=True)
class Integrator:
    """The integrators a scene renders and is fitted with, at one path depth."""

    type: str
    """What the scene files name (path, volpath)."""
    max_depth: int
    """Longest path."""
    differentiable: str
    """What the fits render with (prb, prbvolpath)."""

    def deeper(self) -> Integrator:
        """The same integrators at twice the path depth."""
        return dataclasses.replace(self, max_depth=2 * self.max_depth)


@dataclass(frozen=True)
class MaterialParameter:
    """One material parameter as the scene starts it."""

    key: str
    """Its Mitsuba key (mi.traverse)."""
    value: list[float]
    lower: float
    upper: float
    units: str


@dataclass(frozen=True)
class ViewFiles:
    """One photo's scene file and sensor."""

    xml: str
    """The view's scene file, relative to the folder."""
    sensor: str
    """The sensor's id in scene.xml."""


@dataclass(frozen=True)
class Ground:
    """The table under the specimen, as a disc of measured albedo."""

    radius: float
    albedo: list[float]


@dataclass(frozen=True)
class LightStart:
    """The light the scene starts with."""

    model: str
    """given (the files' light, from [light]) or the estimated light's model."""
    level: list[float] | None = None
    """An estimated light's starting radiance (linear RGB)."""
    level_from: str | None = None
    """What the level was measured on (board, ground, or the specimen itself)."""


@dataclass(kw_only=True)
class SceneDescription(JsonRecord):
    """scene.json (see the module docstring)."""

    PARTS = {"integrator": Integrator, "ground": Ground, "light": LightStart}
    PART_MAPS = {"parameters": MaterialParameter, "views": ViewFiles, "integrators": Integrator}

    model: str
    integrator: Integrator
    light_frame: str
    near_clip: float
    board_print: list[float] | None
    ground: Ground | None
    parameters: dict[str, MaterialParameter]
    views: dict[str, ViewFiles]
    model_choice: list[str]
    integrators: dict[str, Integrator]
    light: LightStart

    def fitted_with(self, model: str, integrator: Integrator) -> SceneDescription:
        """The description as a fit saw it: ``model`` rendered with ``integrator``
        (fit_material may choose another model than the files', and a deeper path)."""
        return dataclasses.replace(self, model=model, integrator=integrator)

    def view_files(self) -> dict[str, str]:
        """Each photo's scene file, relative to the folder."""
        return {name: view.xml for name, view in self.views.items()}

    def initial_values(self) -> dict[str, list[float]]:
        """The material's starting values by parameter name."""
        return {name: parameter.value for name, parameter in self.parameters.items()}


__all__ = ["Ground", "Integrator", "LightStart", "MaterialParameter", "SceneDescription", "ViewFiles"]
