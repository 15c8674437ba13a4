"""Numerical stability of the material models at the edges of their bounds.

A fit that starts at, or is clamped to, a bound must not turn into NaN: a GGX
lobe at alpha = 0.001 is nearly a delta, a medium with sigma_t = 1e5 /m is a
random walk cut off by the path depth, eta = 1 makes the interface vanish.
``probe`` puts one parameter of a model at such a value on a small sphere (the
model's own plugins and integrator, pipeline.render.materials), and reports whether the
render and the gradient of an L2 loss are finite, then whether a few Adam steps
of pipeline.fit.engine (every parameter of the model free) stay finite and inside
the bounds, and whether the parameter moved toward the reference's value.

Used by tests/pipeline/test_stability.py (tiny renders) and bench/fitting.py.
Limitations: one geometry (a sphere 10 cm across under a softbox and a constant
sky), so it shows the plugins' behaviour, not every scene's.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.camera.model import Intrinsics, Pose
from pipeline.fit import engine
from pipeline.render import materials, scene_xml

RADIUS = 0.05
EYES = ([0.3, 0.0, 0.12], [0.0, 0.3, 0.15], [-0.25, -0.15, 0.18])


@dataclass(frozen=True)
class ProbeResult:
    model: str
    parameter: str
    value: float
    render_finite: bool
    gradient: float
    """Gradient of the loss with respect to the parameter (first channel), at ``value``."""
    steps_finite: bool
    """Every parameter stayed finite over the Adam steps."""
    in_bounds: bool
    """Every parameter stayed inside its bounds."""
    after: float
    """The parameter after the steps."""
    toward_reference: bool
    seconds_per_step: float
    skipped_gradients: int
    """Non-finite gradient entries the fit dropped (and counted) before its steps."""


def sphere_scene(folder: Path, model: materials.MaterialModel, width: int, spp: int, mesh: str | None = None) -> Path:
    """scene.xml: a sphere of the model at its initial values, three sensors; ``mesh``,
    a PLY file name relative to ``folder``, in place of the analytic sphere."""
    root = scene_xml.new_scene()
    integrator, depth = materials.INTEGRATORS[model]
    scene_xml.plugin(root, "integrator", {"type": integrator, "id": "integrator", "max_depth": depth})
    intrinsics = Intrinsics(width, width * 3 // 4, 1.1 * width, 1.1 * width, width / 2, width * 3 / 8)
    for index, eye in enumerate(EYES):
        pose = Pose.look_at(eye, [0.0, 0.0, 0.0], up=[0.0, 0.0, 1.0])
        scene_xml.sensor(root, f"view{index}", scene_xml.sensor_properties(intrinsics, pose, spp, 0.01))
    scene_xml.plugin(root, "emitter", {"type": "constant", "id": "sky", "radiance": (0.3, 0.3, 0.3)})
    scene_xml.area_light(root, "softbox", [0.2, 0.25, 0.35], [0, 0, 0], [0, 0, 1], 0.2, (10.0, 10.0, 10.0))
    surface = {"type": "sphere", "radius": RADIUS} if mesh is None else {"type": "ply", "filename": mesh}
    shape = scene_xml.plugin(root, "shape", surface | {"id": materials.SPECIMEN})
    bsdf, medium = materials.bsdf_and_medium(model, materials.initial_values(model))
    scene_xml.plugin(shape, "bsdf", bsdf)
    if medium is not None:
        scene_xml.plugin(shape, "medium", medium, name="interior")
    folder.mkdir(parents=True, exist_ok=True)
    return scene_xml.write(root, folder / "scene.xml")


def references(scene_file: Path, spp: int) -> list[np.ndarray]:
    """Renders of the scene as written (the initial values): what the probes fit back to."""
    import mitsuba as mi

    scene = mi.load_file(str(scene_file))
    return [
        np.asarray(mi.render(scene, sensor=s, spp=spp, seed=1000 + i), np.float32)
        for i, s in enumerate(scene.sensors())
    ]


def probe(
    scene_file: Path,
    reference: list[np.ndarray],
    model: materials.MaterialModel,
    name: str,
    value: float,
    spp: int,
    steps: int,
    bounds: dict[str, tuple[float, float]] | None = None,
) -> ProbeResult:
    """``name`` set to ``value`` (all channels), the rest at their initial values;
    ``bounds`` overrides pipeline.render.materials' bounds of the Adam steps (to probe a value
    outside the defaults)."""
    import drjit as dr
    import mitsuba as mi

    spec = materials.PARAMETERS[name]
    scene = mi.load_file(str(scene_file))
    params = mi.traverse(scene)
    # A fresh variable, as engine.fit does: the traversed value itself may be
    # replaced by the plugin on update (principled recomputes specular from eta).
    variable = type(params[spec.key])(value)
    dr.enable_grad(variable)
    params[spec.key] = variable
    params.update()
    sensor = scene.sensors()[0]
    rendered = mi.render(scene, params, sensor=sensor, spp=spp, seed=1)
    # A degenerate value can cut the render off the parameter: that is a zero gradient.
    dr.backward(
        dr.mean(dr.square(rendered - mi.TensorXf(reference[0])), axis=None),
        flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad,
    )
    gradient = float(np.ravel(dr.grad(variable))[0])
    image = np.asarray(dr.detach(rendered))

    views = [engine.FitView(f"view{i}", scene, s, reference[i]) for i, s in enumerate(scene.sensors())]
    parameters = materials.fit_parameters(model, bounds)
    started = time.perf_counter()
    result = engine.fit(
        parameters, views, [], engine.FitSettings(iterations=steps, batch=1, spp=spp, loss="l2", still_threshold=0.0)
    )
    seconds = (time.perf_counter() - started) / steps
    trajectory = [e["params"] for e in result.log]
    steps_finite = all(np.all(np.isfinite(v)) for entry in trajectory for v in entry.values())
    in_bounds = all(p.lower <= x <= p.upper for entry in trajectory for p in parameters for x in entry[p.name])
    after = result.values[name][0]
    initial = spec.initial[0]
    return ProbeResult(
        model,
        name,
        value,
        bool(np.all(np.isfinite(image))),
        gradient,
        steps_finite,
        in_bounds,
        after,
        abs(after - initial) < abs(value - initial),
        seconds,
        result.skipped_gradients,
    )


def extremes(model: materials.MaterialModel) -> list[tuple[str, float]]:
    """(parameter, value) at both bounds of each of the model's parameters."""
    return [
        (n, v)
        for n in materials.MODEL_PARAMETERS[model]
        for v in (materials.PARAMETERS[n].lower, materials.PARAMETERS[n].upper)
    ]
