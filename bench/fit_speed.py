"""`pipeline fit` against the original tool's loop on a suite of kits drawn from seeds.

    .venv/bin/python -m bench.fit_speed [--kits 20] [--materials principled volumetric]
                                        [--configs defaults ...] [--budget 300] [--repeat 1]
                                        [--first-seed 0] [--write]

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
grey) or a
rough dielectric with a homogeneous medium (alpha, eta, albedo, sigma_t). Every fit
starts from the same values, the middle of each range.

The targets: colours within 0.03 (every channel); roughness, alpha, spec_trans, eta,
metallic and specular within 0.05; sigma_t within 15 %. A run's time to target is
the first moment (wall clock from the call, scene loading and kernel compilation
included) at which every parameter is within its target. A run that does not get
there says "never" and how far it got. A run's seconds are those to its end (what a
user waits for `pipeline fit`).

Runs:

- ``original``: the original tool's loop. Per view: render twice at 8 spp, the dual
  loss, backward, an Adam step (lr 0.03 for every parameter, no log space), clamp;
  its parameters are read after every step (the reading is not timed); it stops at
  the target or after ``--budget`` seconds.
- `pipeline fit` (pipeline.fit.scene_fit.fit_scene) with named settings
  (``CONFIGS``; ``defaults`` are the command's), the parameters named by property
  as a user names them; it runs to its own stopping rule and its log says when it
  met the targets; its result is the state it ends in.

Each run is repeated ``--repeat`` times and the last is reported (later runs find
Dr.Jit's kernels compiled). A run's outcome is stored in its kit's folder under
``--work``; a later call with the same folder reuses it when the code a fit runs
(``FIT_CODE``) is as committed then (no uncommitted change there), on the same
machine and variant, with the same budget and repeats: a suite too long for one
sitting is run in parts (``--kits``, ``--first-seed``, ``--materials``), over
sessions that change other parts of the pipeline, and written whole by a last call
over every kit.

The table has one row per kit and run; the summary per material and configuration:
the share of kits whose result meets every target, the median ratio of the original
loop's time to target to the configuration's (a kit the original never reached
counts at its budget: a lower bound) and the median seconds to the end. The
machine's variant is Mitsuba's automatic choice (cuda_ad_rgb where a GPU works).
``--write`` puts the table into docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from bench.common import ROOT, code_version, machine, write_section
from pipeline.cli.fit import FitOptions
from pipeline.fit import engine
from pipeline.fit.scene_fit import FilmSizes
from pipeline.render import mitsuba_variant
from pipeline.render.user_scene import DIFFERENTIABLE

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
INTEGRATORS = {"principled": ("path", 8), "volumetric": ("volpath", 16)}
SIZES = (128, 192, 256, 384, 512)
REFERENCE_SPP = 512
DEFAULT_SIZES = FilmSizes(
    FitOptions.__dataclass_fields__["max_size"].default, FitOptions.__dataclass_fields__["coarse_to_fine"].default
)

FIT_CODE = (
    "pipeline/__init__.py",
    "pipeline/camera",
    "pipeline/core",
    "pipeline/fit",
    "pipeline/formats",
    "pipeline/imaging",
    "pipeline/render",
    "pipeline/cli/fit.py",
    "pipeline/cli/options.py",
    "pipeline/cli/registry.py",
    "bench/common.py",
    "bench/fit_speed.py",
)
"""What a kit's runs execute (the packages `pipeline fit` imports, and this bench):
a stored outcome is reused while these are unchanged."""

CONFIGS = {
    "defaults": (engine.FitSettings(), DEFAULT_SIZES),
    "not whitened": (engine.FitSettings(whiten=False), DEFAULT_SIZES),
    "defaults, not frozen": (engine.FitSettings(freeze=False), DEFAULT_SIZES),
    "defaults at full size": (engine.FitSettings(), FilmSizes(0)),
    "max_size only": (engine.FitSettings(), FilmSizes(DEFAULT_SIZES.max_size, coarse_to_fine=False)),
}
"""`pipeline fit`'s settings to compare with the original loop: the loop's settings and
the films' sizes. ``defaults`` are those `pipeline fit` runs with when given no option;
``max_size only`` is ``--no-coarse-to-fine``."""


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
    """The kit's shape as a PLY, about 0.2 m across, standing on z = 0."""
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
    path = folder / "shape.ply"
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
    integrator, depth = INTEGRATORS[kit.material]
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


def within(kit: Kit, values: dict) -> bool:
    return all(e <= (SIGMA_T_TARGET if n == "sigma_t" else TARGETS[n]) for n, e in errors(kit, values).items())


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
    from pipeline.fit.scene_fit import property_name

    render_integrator, depth = INTEGRATORS[kit.material]
    scene = mi.load_file(str(kit_xml(kit, kit.start(), folder)))
    integrator = mi.load_dict({"type": DIFFERENTIABLE[render_integrator], "max_depth": depth})
    params = mi.traverse(scene)
    keys = {
        property_name(key): key for key in params.keys() if key.startswith("shape_") and property_name(key) in kit.truth
    }
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


def pipeline_fit(kit: Kit, folder: Path, settings: engine.FitSettings, sizes: FilmSizes, clock: Clock) -> dict:
    """`pipeline fit` (pipeline.fit.scene_fit.fit_scene, what the command calls) on the
    kit's file, the parameters named by property as a user names them; it runs to its own
    stopping rule. Its log's parameters after each step are checked against the targets;
    the time before the loop (loading the scene and the references) counts. Returns its
    params.json (the values it ends with, and why it stopped)."""
    from pipeline.fit.scene_fit import SceneFit, fit_scene, property_name

    out = folder / "fit_out"
    loop_started = []
    fit = engine.fit

    def timed_fit(*args, **kwargs):
        loop_started.append(time.perf_counter())
        return fit(*args, **kwargs)

    engine.fit = timed_fit
    started = time.perf_counter()
    try:
        request = SceneFit(
            kit_xml(kit, kit.start(), folder),
            folder / "references",
            tuple(kit.truth),
            settings,
            out_dir=out,
            sizes=sizes,
        )
        params = fit_scene(request)
    finally:
        engine.fit = fit
    log = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    for entry in log:
        values = {property_name(key): v if len(v) > 1 else v[0] for key, v in entry["params"].items()}
        clock.record(loop_started[0] - started + entry["seconds"], values)
    result = json.loads(params.read_text())
    return {
        "values": {property_name(key): v if len(v) > 1 else v[0] for key, v in result["params"].items()},
        "stopped": result.get("stopped", "-"),
        "seconds": time.perf_counter() - started,
    }


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


def run(kit: Kit, folder: Path, name: str, budget: float, repeat: int, conditions: dict, mi, dr) -> Outcome:
    """The run ``name`` on the kit in ``folder``, or its outcome stored there by an earlier
    run under the same ``conditions`` (the same committed FIT_CODE, machine and
    variant) and with the same budget and repeats."""
    stored = folder / f"outcome-{re.sub(r'[^a-z0-9]+', '-', name)}.json"
    key = conditions | {"budget": budget if name == "original" else None, "repeat": repeat}
    if stored.is_file() and not key["code"].endswith("+changes"):
        record = json.loads(stored.read_text())
        if record["conditions"] == key:
            return Outcome(**record["outcome"])
    for _ in range(repeat):
        clock = Clock(kit, budget)
        if name == "original":
            original_loop(kit, folder, clock, mi, dr)
            stopped = "target" if clock.reached else "budget"
            outcome = Outcome(clock.reached, clock.steps, clock.last, stopped, clock.elapsed())
        else:
            result = pipeline_fit(kit, folder, *CONFIGS[name], clock)
            outcome = Outcome(clock.reached, clock.steps, result["values"], result["stopped"], result["seconds"])
    stored.write_text(json.dumps({"conditions": key, "outcome": asdict(outcome)}, indent=1))
    return outcome


def summary_lines(outcomes: dict[tuple[str, str], list[tuple[Kit, Outcome, Outcome]]], budget: float) -> list[str]:
    """Per material and configuration: the share of kits whose result meets every
    target, the median time-to-target ratio against the original loop, and the median
    time the run took to its end."""
    lines = [
        "| material | run | kits | result within every target | reached the targets at some step "
        "| median ratio to the original | median seconds to the end |"
    ]
    lines.append("|---|---|---|---|---|---|---|")
    for (material, name), rows in outcomes.items():
        final_ok = sum(within(kit, result.final) for kit, result, _ in rows)
        reached = sum(result.reached is not None for _, result, _ in rows)
        ratios = [
            (original.reached or budget) / result.reached for _, result, original in rows if result.reached is not None
        ]
        median = f"{np.median(ratios):.1f}x" if ratios else "-"
        lines.append(
            f"| {material} | {name} | {len(rows)} | {final_ok} ({100 * final_ok / len(rows):.0f} %) | "
            f"{reached} | {median} | {np.median([result.seconds for _, result, _ in rows]):.0f} |"
        )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kits", type=int, default=20, help="kits per material (seeds first-seed ...)")
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--materials", nargs="*", default=["principled", "volumetric"])
    parser.add_argument("--configs", nargs="*", default=["defaults"])
    parser.add_argument("--budget", type=float, default=300.0, help="seconds the original loop may run per kit")
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--work", type=Path, help="keep each kit's scene and references here (default: a new folder)")
    parser.add_argument("--write", action="store_true", help="rewrite docs/benchmarks.md's section")
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="fit_speed_"))
    variant = mitsuba_variant.activate()
    import drjit as dr
    import mitsuba as mi

    version = code_version(*FIT_CODE, label="fitting code")
    conditions = {"code": version.partition(", ")[2], "machine": machine(), "variant": variant}
    print(f"variant {variant}, {version}")
    lines = [
        "| kit | material | scene | run | time to target | steps | stopped | seconds | errors of the result | ratio |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    print("\n".join(lines))
    outcomes: dict[tuple[str, str], list[tuple[Kit, Outcome, Outcome]]] = {}
    for material in args.materials:
        for seed in range(args.first_seed, args.first_seed + args.kits):
            kit = draw_kit(seed, material)
            folder = work / f"{material}-{seed}"
            folder.mkdir(parents=True, exist_ok=True)
            references(kit, folder, mi)
            original = run(kit, folder, "original", args.budget, args.repeat, conditions, mi, dr)
            for name in ["original", *args.configs]:
                outcome = (
                    original
                    if name == "original"
                    else run(kit, folder, name, args.budget, args.repeat, conditions, mi, dr)
                )
                if name != "original":
                    outcomes.setdefault((material, name), []).append((kit, outcome, original))
                reached = f"{outcome.reached:.1f} s" if outcome.reached is not None else "never"
                ratio = "-"
                if name != "original" and outcome.reached is not None:
                    ratio = f"{(original.reached or args.budget) / outcome.reached:.1f}x"
                    ratio = ratio if original.reached is not None else f">{ratio}"
                shown = ", ".join(f"{n} {e:.3f}" for n, e in errors(kit, outcome.final).items())
                lines.append(
                    f"| {seed} | {material} | {kit.describe()} | {name} | {reached} | {outcome.steps} | "
                    f"{outcome.stopped} | {outcome.seconds:.0f} | {shown} | {ratio} |"
                )
                print(lines[-1], flush=True)
    summary = summary_lines(outcomes, args.budget)
    print("\n".join(summary))
    if args.write:
        options = " ".join(o for o in sys.argv[1:] if o != "--write").replace(str(args.work), "DIR")
        intro = [
            "## Fitting speed",
            "",
            f"{machine()} Mitsuba variant {variant}; code: {version}. Command:",
            f"`.venv/bin/python -m bench.fit_speed {options}",
            "--write`. The kits, the targets and the runs: bench/fit_speed.py's docstring. A result within",
            "every target is what the fit returns; a ratio is the original loop's time to target over the",
            "run's (>: the original never got there within the budget).",
            "",
            *summary,
            "",
        ]
        write_section("fit-speed", intro + lines)


if __name__ == "__main__":
    main()
