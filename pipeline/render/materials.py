"""The specimen's material models: their Mitsuba plugins, parameters and bounds.

Each model states only what it needs (the brief: no medium, texture or parameter
the scene does not require):

===========  ====================================  ===============  =================
model        plugins                               integrator       fitted parameters
===========  ====================================  ===============  =================
opaque       principled, no transmission           prb, depth 4     base_color, roughness, specular
principled   principled with spec_trans            prb, depth 8     base_color, roughness, spec_trans, eta
volumetric   roughdielectric + homogeneous medium  prbvolpath, 32   alpha, eta, albedo, sigma_t
===========  ====================================  ===============  =================

Mitsuba's principled BSDF derives ``specular`` from ``eta`` when it transmits
(specular = ((eta - 1) / (eta + 1))^2 / 0.08) and rejects both at once, so the
translucent model fits eta and the opaque one specular.

Bounds (physically sensible, overridable in the fit stages' config): base_color
and albedo in [0.001, 1], specular and spec_trans in [0, 1]; roughness and alpha
in [0.001, 1] (a perfectly smooth surface is a different plugin); eta in
[1.001, 3]; sigma_t in [0.1, 1e5] per metre. Three lower bounds sit a hair above
the physical edge, because the plugins degenerate there (measured by
pipeline.fit.stability, docs/benchmarks.md, and on the bird): at eta = 1 exactly the
dielectric interface vanishes and roughdielectric's gradients are NaN; at
albedo = 0 prbvolpath's gradient with respect to the albedo is exactly 0, so a
channel clamped there could never come back; a base_color texel at exactly 0
gets infinite or NaN gradients from prb (dark texels then stay stuck at 0), though
the constant at 0 on a sphere does not (the stability probe). sigma_t,
roughness and alpha are optimised as logarithms: they span decades, and a
fixed step in the value overshoots a small roughness into the lower bound,
where a highlight too sharp for the samples gives no gradient back.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Mapping

from pipeline.formats.scene_description import Integrator
from pipeline.render.parameters import FitParameter

MaterialModel = Literal["opaque", "principled", "volumetric"]


@dataclass(frozen=True)
class Parameter:
    """One fitted material parameter."""

    name: str
    """Name in params.json and on the command line (base_color, eta, ...)."""
    key: str
    """Key in ``mi.traverse(scene)``, with the shape id ``specimen``."""
    initial: tuple[float, ...]
    """Starting value (1 or 3 numbers)."""
    lower: float
    upper: float
    units: str
    log: bool = False
    """Optimised as log(value): positive, spanning decades."""
    learning_rate: float = 0.02
    """Adam step size, in the optimised space (log units when ``log``)."""


SPECIMEN = "specimen"

PARAMETERS: dict[str, Parameter] = {
    p.name: p
    for p in (
        Parameter(
            "base_color", f"{SPECIMEN}.bsdf.base_color.value", (0.5, 0.5, 0.5), 0.001, 1.0, "linear RGB reflectance"
        ),
        Parameter(
            "roughness",
            f"{SPECIMEN}.bsdf.roughness.value",
            (0.5,),
            0.001,
            1.0,
            "1 (GGX, Disney)",
            log=True,
            learning_rate=0.05,
        ),
        Parameter("specular", f"{SPECIMEN}.bsdf.specular", (0.5,), 0.0, 1.0, "1 (F0 / 0.08)"),
        Parameter("metallic", f"{SPECIMEN}.bsdf.metallic.value", (0.0,), 0.0, 1.0, "1 (fraction metal)"),
        Parameter("spec_trans", f"{SPECIMEN}.bsdf.spec_trans.value", (0.3,), 0.0, 1.0, "1 (fraction transmitted)"),
        Parameter(
            "eta", f"{SPECIMEN}.bsdf.eta", (1.5,), 1.001, 3.0, "1 (relative index of refraction)", learning_rate=0.01
        ),
        Parameter(
            "alpha",
            f"{SPECIMEN}.bsdf.alpha.value",
            (0.2,),
            0.001,
            1.0,
            "1 (GGX roughness)",
            log=True,
            learning_rate=0.05,
        ),
        Parameter(
            "albedo",
            f"{SPECIMEN}.interior_medium.albedo.value.value",
            (0.8, 0.8, 0.8),
            0.001,
            1.0,
            "linear RGB single-scattering albedo",
        ),
        Parameter(
            "sigma_t",
            f"{SPECIMEN}.interior_medium.sigma_t.value.value",
            (50.0,),
            0.1,
            1e5,
            "1/m (extinction, world units)",
            log=True,
            learning_rate=0.05,
        ),
    )
}

MODEL_PARAMETERS: dict[str, tuple[str, ...]] = {
    "opaque": ("base_color", "roughness", "specular"),
    "principled": ("base_color", "roughness", "spec_trans", "eta"),
    "volumetric": ("alpha", "eta", "albedo", "sigma_t"),
}

INTEGRATORS: dict[str, tuple[str, int]] = {
    # prb: one bounce more than the direct light needs for interreflection; the
    # translucent surface needs in-and-out paths; a medium needs long random walks.
    "opaque": ("prb", 4),
    "principled": ("prb", 8),
    "volumetric": ("prbvolpath", 32),
}
"""The differentiable integrator each model is fitted with, and its path depth."""

RENDER_INTEGRATORS: dict[str, str] = {"prb": "path", "prbvolpath": "volpath"}
"""The integrator a scene file names for a differentiable one: the same image, and one
the ``mitsuba`` command-line renderer has (prb and prbvolpath exist only in Python)."""

MODEL_LADDER: tuple[MaterialModel, ...] = ("opaque", "principled", "volumetric")
"""The models a scene that leaves the model open chooses between, simplest first."""

OPEN_SCENE_MODEL: MaterialModel = "principled"
"""The model a scene that leaves the model open is written with and its light fitted
with: rich enough to take up what an opaque surface cannot show, and several times
cheaper to render than a medium."""


def model_integrator(model: MaterialModel, max_depth: int = 0) -> Integrator:
    """The integrators for ``model``: the render integrator the files name, the
    differentiable one the fits use, and the path depth (0: the model's)."""
    differentiable, depth = INTEGRATORS[model]
    return Integrator(
        type=RENDER_INTEGRATORS[differentiable], max_depth=max_depth or depth, differentiable=differentiable
    )


@dataclass(frozen=True)
class TextureSlot:
    """Where a model's colour varies over the specimen (fit_texture)."""

    parameter: str
    """The constant it replaces (a key of PARAMETERS)."""
    key: str
    """Key of the texture's data tensor in ``mi.traverse``."""
    kind: Literal["bitmap", "gridvolume"]
    """bitmap: on the mesh's UVs; gridvolume: a 3D grid over the specimen's box
    (a medium is a volume: its albedo cannot live on the surface)."""


TEXTURE_SLOTS: dict[str, TextureSlot] = {
    "opaque": TextureSlot("base_color", f"{SPECIMEN}.bsdf.base_color.data", "bitmap"),
    "principled": TextureSlot("base_color", f"{SPECIMEN}.bsdf.base_color.data", "bitmap"),
    "volumetric": TextureSlot("albedo", f"{SPECIMEN}.interior_medium.albedo.data", "gridvolume"),
}


def bsdf_and_medium(model: MaterialModel, values: dict[str, tuple[float, ...]]) -> tuple[dict, dict | None]:
    """The specimen's BSDF and interior medium (or None) as plain dicts of plugin
    properties: {"type": ..., "id": ..., name: number or RGB tuple}."""
    if model == "volumetric":
        bsdf = {
            "type": "roughdielectric",
            "id": "specimen_bsdf",
            "alpha": values["alpha"][0],
            "int_ior": values["eta"][0],
            "ext_ior": 1.0,
        }
        medium = {
            "type": "homogeneous",
            "id": "specimen_medium",
            "albedo": tuple(values["albedo"]),
            "sigma_t": values["sigma_t"][0],
        }
        return bsdf, medium
    bsdf = {
        "type": "principled",
        "id": "specimen_bsdf",
        "base_color": tuple(values["base_color"]),
        "roughness": values["roughness"][0],
    }
    if model == "opaque":
        bsdf["specular"] = values["specular"][0]
    else:
        bsdf["spec_trans"] = values["spec_trans"][0]
        bsdf["eta"] = values["eta"][0]
    return bsdf, None


def fit_parameters(model: MaterialModel, bounds: Mapping[str, tuple[float, float]] | None = None) -> list[FitParameter]:
    """The model's parameters for pipeline.fit.engine, ``bounds`` overriding the defaults
    by name (names that are not the model's are ignored: callers check them)."""
    bounds = bounds or {}
    return [
        FitParameter(
            n,
            PARAMETERS[n].key,
            *bounds.get(n, (PARAMETERS[n].lower, PARAMETERS[n].upper)),
            PARAMETERS[n].log,
            PARAMETERS[n].learning_rate,
        )
        for n in MODEL_PARAMETERS[model]
    ]


def refit_parameters(
    model: MaterialModel,
    bounds: Mapping[str, tuple[float, float]],
    texture: tuple[float, float] | None,
    constants: bool = True,
) -> list[FitParameter]:
    """Parameters of a fit that continues fit_material's, within its ``bounds``: with
    ``texture`` = (learning rate, smoothness), first the texture slot's data in place
    of its constant; then, with ``constants``, the model's other parameters."""
    slot = TEXTURE_SLOTS[model]
    parameters = []
    if texture is not None:
        lower, upper = bounds[slot.parameter]  # the texels keep the constant's bounds (the bake's too)
        parameters.append(FitParameter(slot.parameter, slot.key, lower, upper, False, *texture))
    if constants:
        parameters += [p for p in fit_parameters(model, bounds) if texture is None or p.name != slot.parameter]
    return parameters


def opaque_from_principled(values: dict) -> dict:
    """Opaque values from principled ones: the same colour and roughness, and the
    specular reflectance of the principled eta (Disney's specular = F0 / 0.08)."""
    eta = values["eta"][0]
    specular = min(max(((eta - 1) / (eta + 1)) ** 2 / 0.08, 0.0), 1.0)
    return {"base_color": values["base_color"], "roughness": values["roughness"], "specular": [specular]}


def volumetric_from_principled(values: dict) -> dict:
    """Volumetric start values from principled ones: the same eta, the colour as the
    medium's albedo, GGX alpha = roughness squared (Disney's mapping), the default
    extinction."""
    alpha = min(max(values["roughness"][0] ** 2, PARAMETERS["alpha"].lower), PARAMETERS["alpha"].upper)
    albedo = [min(max(c, PARAMETERS["albedo"].lower), 1.0) for c in values["base_color"]]
    return {"alpha": [alpha], "eta": values["eta"], "albedo": albedo, "sigma_t": list(PARAMETERS["sigma_t"].initial)}


def initial_values(model: MaterialModel) -> dict[str, tuple[float, ...]]:
    return {name: PARAMETERS[name].initial for name in MODEL_PARAMETERS[model]}
