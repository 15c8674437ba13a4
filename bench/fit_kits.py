"""The kits bench/fit_speed.py fits, the targets, and the original tool's loop.

A kit is a scene built like the original tool's synthetic test scenes and drawn from
its seed (``draw_kit``): a shape on a grey floor (a blob with random bumps, a stretched
blob, or the sample bird's true mesh), one square area light (position, size and
radiance drawn) and a constant environment (level drawn), 2-8 views at 128-512 px
round it at a drawn elevation, written as a scene file the usual way (the material
declared once, used through ``<ref>``; the render integrator, path or volpath), and
references rendered from it at 512 spp. True values are drawn over the parameters'
ranges: Disney principled (base_color and roughness, with spec_trans and eta on half
the kits, metallic on a quarter, specular on a quarter: metallic and specular both
scale the highlight, and fitted together they trade off where the base colour is
grey) or a rough dielectric with a homogeneous medium (alpha, eta, albedo, sigma_t).
Every fit starts from the same values, the middle of each range.

The targets: colours within 0.03 (every channel); roughness, alpha, spec_trans, eta,
metallic and specular within 0.05; sigma_t within 15 %. A run's time to target is
the first moment (wall clock from the call, scene loading and kernel compilation
included) at which every parameter is within its target (``Clock``).

The original tool's loop (``original_loop``): per view, render twice at 8 spp, the
dual loss, backward, an Adam step (lr 0.03 for every parameter, no log space),
clamp; its parameters are read after every step (the reading is not timed); it stops
at the target or after its budget. It runs only this module's code and Mitsuba's
(``ORIGINAL_CODE``), so its stored outcomes outlive changes to the pipeline's fitting
code.

A run's outcome is stored in its kit's folder (``outcome_path``) with the conditions
it ran under; a caller reuses it while they hold (bench/fit_speed.py: ``run``).
"""

from __future__ import annotations

import json
import math
import re
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from bench.common import ROOT

ORIGINAL_CODE = ("bench/common.py", "bench/fit_kits.py")
"""What the original loop's runs execute besides Mitsuba."""

TARGETS = {
    "base_color": 0.03,
    "albedo": 0.03,
    "roughness": 0.05,
    "alpha": 0.05,
    "spec_trans": 0.05,
    "eta": 0.05,
    "metallic": 0.05,
    "specular": 0.05,
}
"""Absolute error targets; sigma_t's is relative (SIGMA_T_TARGET)."""
SIGMA_T_TARGET = 0.15

RANGES = {
    "base_color": (0.05, 0.95),
    "roughness": (0.08, 0.8),
    "spec_trans": (0.0, 0.9),
    "eta": (1.15, 1.9),
    "metallic": (0.0, 0.5),
    "specular": (0.2, 0.8),
    "alpha": (0.05, 0.5),
    "albedo": (0.3, 0.95),
    "sigma_t": (10.0, 150.0),
}
"""Where true values are drawn (sigma_t log-uniformly, per metre: optical depths of
about 1 to 30 through the shape)."""
BOUNDS = {
    "base_color": (0.0, 1.0),
    "albedo": (0.001, 0.999),
    "roughness": (0.01, 1.0),
    "alpha": (0.01, 1.0),
    "spec_trans": (0.0, 1.0),
    "eta": (1.001, 2.5),
    "sigma_t": (1.0, 500.0),
    "metallic": (0.0, 1.0),
    "specular": (0.0, 1.0),
}
"""The original loop's clamp."""
INTEGRATORS = {"principled": ("path", "prb", 8), "volumetric": ("volpath", "prbvolpath", 16)}
"""Per material: the integrator the scene file names, the differentiable one the
original tool rendered with, and their path depth."""
SIZES = (128, 192, 256, 384, 512)
REFERENCE_SPP = 512


@dataclass(frozen=True)
class Kit:
    """One scene of the suite (see the module docstring)."""

    seed: int
    material: str
    shape: str
    """blob, stretched blob or bird."""
    views: int
    size: int
    elevation_deg: float
    light_position: tuple[float, float, float]
    light_size: float
    """Half the square light's side, metres."""
    light_radiance: float
    environment: float
    truth: dict

    def describe(self) -> str:
        fitted = ", ".join(self.truth)
        return (
            f"{self.shape}, {self.views} views at {self.size} px, {self.elevation_deg:.0f} deg up, "
            f"light {self.light_size * 200:.0f} cm at {np.linalg.norm(self.light_position):.2f} m, "
            f"environment {self.environment:.2f}; {fitted}"
        )

    def start(self) -> dict:
        """Every fit's start: the middle of each parameter's range."""
        middle = {name: sum(RANGES[name]) / 2 for name in self.truth}
        if "sigma_t" in middle:
            middle["sigma_t"] = math.sqrt(RANGES["sigma_t"][0] * RANGES["sigma_t"][1])
        return {name: [value] * 3 if name in ("base_color", "albedo") else value for name, value in middle.items()}


def draw_kit(seed: int, material: str) -> Kit:
    """The kit of ``seed``: shape, views, light and true values drawn from it."""
    rng = np.random.default_rng([seed, 0 if material == "principled" else 1])

    def uniform(name: str) -> float:
        return float(rng.uniform(*RANGES[name]))

    if material == "principled":
        truth = {"base_color": [uniform("base_color") for _ in range(3)], "roughness": uniform("roughness")}
        variant = rng.random()
        if variant < 1 / 4:
            truth["metallic"] = uniform("metallic")
        elif variant < 1 / 2:
            truth["specular"] = uniform("specular")
        else:
            truth |= {"spec_trans": uniform("spec_trans"), "eta": uniform("eta")}
    else:
        low, high = np.log(RANGES["sigma_t"])
        truth = {
            "alpha": uniform("alpha"),
            "eta": uniform("eta"),
            "albedo": [uniform("albedo") for _ in range(3)],
            "sigma_t": float(np.exp(rng.uniform(low, high))),
        }
    azimuth, elevation = rng.uniform(0, 2 * np.pi), rng.uniform(np.radians(25), np.radians(70))
    distance = rng.uniform(0.45, 0.9)
    light = distance * np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), 1.0])
    size = float(rng.uniform(0.05, 0.2))
    # about the same irradiance at the shape whatever the light's distance and size
    radiance = float(rng.uniform(0.6, 1.5) * 15 * (0.15 / size) ** 2 * (distance / 0.6) ** 2)
    return Kit(
        seed=seed,
        material=material,
        shape=str(rng.choice(["blob", "stretched blob", "bird"])),
        views=int(rng.integers(2, 9)),
        size=int(rng.choice(SIZES)),
        elevation_deg=float(rng.uniform(10, 50)),
        light_position=tuple(float(v) for v in light),
        light_size=size,
        light_radiance=radiance,
        environment=float(rng.uniform(0.1, 0.6)),
        truth=truth,
    )


def shape_file(kit: Kit, folder: Path) -> Path:
    """The kit's shape as a PLY, about 0.2 m across, standing on z = 0; its absolute
    path (a scene file's relative names are read against the scene file's folder)."""
    import trimesh

    if kit.shape == "bird":
        mesh = trimesh.load(ROOT / "sample_captures" / "bird" / "ground_truth" / "mesh.ply", force="mesh")
        vertices = mesh.vertices * (0.2 / mesh.extents.max())
        faces = mesh.faces
    else:
        rng = np.random.default_rng(kit.seed)
        sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
        v = sphere.vertices
        a, b, c = rng.integers(2, 6, 3)
        bumps = 1 + rng.uniform(0.05, 0.15) * np.sin(a * v[:, 0] + 1) * np.cos(b * v[:, 1])
        bumps += rng.uniform(0.03, 0.1) * np.sin(c * v[:, 2])
        stretch = np.array([1.6, 0.8, 0.9]) if kit.shape == "stretched blob" else np.ones(3)
        vertices, faces = 0.1 * v * bumps[:, None] * stretch, sphere.faces
    vertices = vertices - [*vertices[:, :2].mean(axis=0), vertices[:, 2].min()]
    path = folder.resolve() / "shape.ply"
    trimesh.Trimesh(vertices, faces, process=False).export(path)
    return path


def _numbers(value) -> str:
    return ", ".join(f"{v:g}" for v in np.ravel(value))


def _material_xml(material: str, values: dict) -> tuple[str, str]:
    """The material declared once, and how the shape uses it."""
    if material == "principled":
        properties = "".join(
            f'<rgb name="{name}" value="{_numbers(value)}"/>'
            if name == "base_color"
            else f'<float name="{name}" value="{value:g}"/>'
            for name, value in values.items()
        )
        return f'<bsdf type="principled" id="shape_bsdf">{properties}</bsdf>', '<ref id="shape_bsdf"/>'
    material_xml = (
        f'<bsdf type="roughdielectric" id="shape_bsdf"><float name="alpha" value="{values["alpha"]:g}"/>'
        f'<float name="int_ior" value="{values["eta"]:g}"/></bsdf>'
        f'<medium type="homogeneous" id="shape_medium"><rgb name="albedo" value="{_numbers(values["albedo"])}"/>'
        f'<float name="sigma_t" value="{values["sigma_t"]:g}"/></medium>'
    )
    return material_xml, '<ref id="shape_bsdf"/><ref name="interior" id="shape_medium"/>'


def kit_xml(kit: Kit, values: dict, folder: Path) -> Path:
    """The kit as a scene file with the material at ``values``."""
    integrator, _, depth = INTEGRATORS[kit.material]
    material, uses = _material_xml(kit.material, values)
    sensors = []
    elevation = np.radians(kit.elevation_deg)
    for i, azimuth in enumerate(np.radians(np.arange(kit.views) * 360 / kit.views + 20)):
        direction = np.array(
            [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)]
        )
        origin = ", ".join(f"{v:.6f}" for v in 0.6 * direction + [0, 0, 0.08])
        sensors.append(
            f'<sensor type="perspective" id="view_{i}"><float name="fov" value="30"/>'
            f'<transform name="to_world"><lookat origin="{origin}" target="0, 0, 0.08" up="0, 0, 1"/></transform>'
            f'<film type="hdrfilm"><integer name="width" value="{kit.size}"/>'
            f'<integer name="height" value="{kit.size}"/><string name="pixel_format" value="rgb"/></film>'
            '<sampler type="independent"><integer name="sample_count" value="8"/></sampler></sensor>'
        )
    light = ", ".join(f"{v:.6f}" for v in kit.light_position)
    scene = f"""<scene version="3.0.0">
<integrator type="{integrator}" id="integrator"><integer name="max_depth" value="{depth}"/></integrator>
{material}
<shape type="ply" id="shape"><string name="filename" value="{shape_file(kit, folder)}"/>
<boolean name="face_normals" value="false"/>{uses}</shape>
<shape type="rectangle" id="floor"><bsdf type="diffuse" id="floor_bsdf"><rgb name="reflectance" value="0.5"/></bsdf></shape>
<shape type="rectangle" id="light"><transform name="to_world"><scale x="{kit.light_size:g}" y="{kit.light_size:g}"/>
<lookat origin="{light}" target="0, 0, 0.08" up="0, 0, 1"/></transform>
<emitter type="area" id="light_emitter"><rgb name="radiance" value="{kit.light_radiance:g}"/></emitter></shape>
<emitter type="constant" id="environment"><rgb name="radiance" value="{kit.environment:g}"/></emitter>
{chr(10).join(sensors)}
</scene>
"""
    path = folder / f"{kit.material}.xml"
    path.write_text(scene)
    return path


def references(kit: Kit, folder: Path, mi) -> Path:
    """The truth's renders at REFERENCE_SPP, one EXR per sensor, in ``folder``/references
    (kept from an earlier run of the same kit)."""
    out = folder / "references"
    if out.is_dir() and len(list(out.glob("view_*.exr"))) == kit.views:
        return out
    scene = mi.load_file(str(kit_xml(kit, kit.truth, folder)))
    out.mkdir(exist_ok=True)
    for i in range(kit.views):
        mi.Bitmap(mi.render(scene, sensor=i, spp=REFERENCE_SPP, seed=100 + i)).write(str(out / f"view_{i}.exr"))
    return out


def errors(kit: Kit, values: dict) -> dict[str, float]:
    """Each parameter's error: the largest channel's absolute one; sigma_t's relative."""
    result = {}
    for name, truth in kit.truth.items():
        difference = np.abs(np.ravel(values[name]) - np.ravel(truth))
        result[name] = float(difference.max() / (np.ravel(truth)[0] if name == "sigma_t" else 1.0))
    return result


def target(name: str) -> float:
    """The parameter's target: an absolute error, sigma_t's relative."""
    return SIGMA_T_TARGET if name == "sigma_t" else TARGETS[name]


def within(kit: Kit, values: dict) -> bool:
    return all(error <= target(name) for name, error in errors(kit, values).items())


class Clock:
    """When the parameters first met every target; the parameters are read outside the timing."""

    def __init__(self, kit: Kit, budget: float):
        self.kit, self.budget = kit, budget
        self.started = time.perf_counter()
        self.paused = 0.0
        self.reached: float | None = None
        self.last: dict = {}
        self.steps = 0

    def elapsed(self) -> float:
        return time.perf_counter() - self.started - self.paused

    def record(self, seconds: float, values: dict) -> None:
        """A step's values at ``seconds`` from the start, read from a fit's log."""
        self.steps += self.reached is None
        self.last = values
        if self.reached is None and within(self.kit, values):
            self.reached = seconds

    def check(self, values: dict) -> bool:
        """True when the run should stop (target met or budget spent)."""
        now = self.elapsed()
        pause = time.perf_counter()
        self.steps += 1
        self.last = values
        if self.reached is None and within(self.kit, values):
            self.reached = now
        self.paused += time.perf_counter() - pause
        return self.reached is not None or now > self.budget


def original_loop(kit: Kit, folder: Path, clock: Clock, mi, dr) -> None:
    """The original tool's loop: per view, two renders at 8 spp, the dual loss, backward,
    an Adam step at lr 0.03, clamp; on the scene loaded as the tool loaded it (with its
    differentiable integrator) and the references at full size."""
    _, differentiable, depth = INTEGRATORS[kit.material]
    scene = mi.load_file(str(kit_xml(kit, kit.start(), folder)))
    integrator = mi.load_dict({"type": differentiable, "max_depth": depth})
    params = mi.traverse(scene)
    # the material's keys, "shape_bsdf.roughness.value" or "shape_medium.albedo.value.value"
    keys = {key.split(".")[1]: key for key in params.keys() if key.startswith("shape_")}
    keys = {name: key for name, key in keys.items() if name in kit.truth}
    optimizer = mi.ad.Adam(lr=0.03)
    for key in keys.values():
        optimizer[key] = params[key]
    params.update(optimizer)
    targets = [mi.TensorXf(mi.Bitmap(str(folder / "references" / f"view_{i}.exr"))) for i in range(kit.views)]
    iteration = 0
    while True:
        for view in range(kit.views):
            seed = 2 * (iteration * kit.views + view)
            first = mi.render(scene, params, sensor=view, integrator=integrator, spp=8, seed=seed)
            second = mi.render(scene, params, sensor=view, integrator=integrator, spp=8, seed=seed + 1)
            loss = dr.mean((first - targets[view]) * (second - targets[view]), axis=None)
            dr.backward(loss)
            optimizer.step()
            for name, key in keys.items():
                lo, hi = BOUNDS[name]
                optimizer[key] = dr.clip(optimizer[key], lo, hi)
            params.update(optimizer)
            values = {name: np.ravel(np.array(optimizer[key])).tolist() for name, key in keys.items()}
            if clock.check({n: v if len(v) > 1 else v[0] for n, v in values.items()}):
                return
        iteration += 1


@dataclass
class Outcome:
    """One run on one kit."""

    reached: float | None
    """Seconds to every target (None: never)."""
    steps: int
    final: dict
    """The values it ends with (the original loop: its last)."""
    stopped: str
    seconds: float
    """Until it ended (the original loop: at the target or the budget)."""


def outcome_path(folder: Path, run: str) -> Path:
    """Where the run ``run``'s outcome on the kit in ``folder`` is stored."""
    return folder / f"outcome-{re.sub(r'[^a-z0-9]+', '-', run)}.json"


def stored_outcome(folder: Path, run: str, conditions: dict | None = None) -> Outcome | None:
    """The run's stored outcome (one stored under ``conditions`` only, when given), if any."""
    path = outcome_path(folder, run)
    if not path.is_file():
        return None
    record = json.loads(path.read_text())
    return Outcome(**record["outcome"]) if conditions is None or record["conditions"] == conditions else None


def store_outcome(folder: Path, run: str, conditions: dict, outcome: Outcome) -> None:
    outcome_path(folder, run).write_text(json.dumps({"conditions": conditions, "outcome": asdict(outcome)}, indent=1))
