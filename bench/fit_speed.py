"""Time to target of `pipeline fit` against the original tool's loop, in one run.

    .venv/bin/python -m bench.fit_speed [--materials principled volumetric] [--budget 900]
                                        [--configs NAME ...] [--repeat 2] [--write]

The kit, built like the original tool's synthetic test scenes: a blob (a sphere with
low-frequency bumps, 1280 faces) on a grey floor, one square area light and a
constant environment, four views at 256x256 around it, written as a scene file the
usual way (the material declared once, used through ``<ref>``; the render
integrator, path or volpath), references rendered from it at 1024 spp. Two
materials: Disney principled (base_color, roughness, spec_trans, eta) and a rough
dielectric with a homogeneous medium (alpha, eta, albedo, sigma_t). Every fit
starts from the same values.

The targets are the issue's: colour within 0.03 (every channel), roughness, alpha,
spec_trans and eta within 0.05, sigma_t within 15 %. A run's time to target is the
first moment (wall clock from the call, scene loading and kernel compilation
included) at which every parameter is within its target. A run that does not get
there says "never" and how far it got.

Runs:

- ``original``: the original tool's loop. Per view: render twice at 8 spp, the dual
  loss, backward, an Adam step (lr 0.03 for every parameter, no log space), clamp;
  its parameters are read after every step (the reading is not timed); it stops at
  the target or after ``--budget`` seconds.
- `pipeline fit` (pipeline.fit.scene_fit.fit_scene) with named settings
  (``CONFIGS``; ``defaults`` are the command's), the parameters named by property
  (``--params base_color roughness ...``); it runs to its own stopping rule and
  its log says when it met the targets.

Each run is repeated (``--repeat``, default 2) and the last is reported: every run
then finds Dr.Jit's kernels compiled, so the ratio is the loops' own cost; the
first run's time (cold for whichever compiled first) is in its own column. The
machine's variant is Mitsuba's automatic choice (cuda_ad_rgb where a GPU works).
``--write`` puts the table into docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import machine, write_section
from pipeline.cli.fit import FitOptions
from pipeline.fit import engine
from pipeline.render import mitsuba_variant
from pipeline.render.user_scene import DIFFERENTIABLE

TARGETS = {"base_color": 0.03, "albedo": 0.03, "roughness": 0.05, "alpha": 0.05, "spec_trans": 0.05, "eta": 0.05}
"""Absolute error targets; sigma_t's is relative (SIGMA_T_TARGET)."""
SIGMA_T_TARGET = 0.15

TRUTH = {
    "principled": {"base_color": [0.72, 0.46, 0.22], "roughness": 0.35, "spec_trans": 0.45, "eta": 1.45},
    "volumetric": {"alpha": 0.12, "eta": 1.40, "albedo": [0.90, 0.72, 0.50], "sigma_t": 40.0},
}
START = {
    "principled": {"base_color": [0.5, 0.5, 0.5], "roughness": 0.5, "spec_trans": 0.3, "eta": 1.3},
    "volumetric": {"alpha": 0.3, "eta": 1.25, "albedo": [0.6, 0.6, 0.6], "sigma_t": 15.0},
}
BOUNDS = {
    "base_color": (0.0, 1.0),
    "albedo": (0.001, 0.999),
    "roughness": (0.01, 1.0),
    "alpha": (0.01, 1.0),
    "spec_trans": (0.0, 1.0),
    "eta": (1.001, 2.5),
    "sigma_t": (1.0, 500.0),
}
INTEGRATORS = {"principled": ("path", 8), "volumetric": ("volpath", 16)}
VIEWS = 4
SIZE = 256

DEFAULT_MAX_SIZE = FitOptions.__dataclass_fields__["max_size"].default

CONFIGS = {
    "defaults": (engine.FitSettings(), DEFAULT_MAX_SIZE),
    "defaults, not frozen": (engine.FitSettings(freeze=False), DEFAULT_MAX_SIZE),
    "defaults at 256 px": (engine.FitSettings(), 0),
    "previous defaults": (engine.FitSettings(spp=16, batch=2, learning_rate_scale=1.0, freeze=False), 0),
}
"""`pipeline fit`'s settings to compare with the original loop: the loop's settings and
``--max-size``. ``defaults`` are those `pipeline fit` runs with when given no option
(64 px, spp 4, batch 4, learning rates x2, frozen steps); ``previous defaults`` are
the loop's before the fitting-speed work (full size, spp 16, batch 2) with its
integer seeds replaced by opaque ones."""


def blob_file(folder: Path) -> Path:
    """The blob as a PLY: a sphere of radius 0.1 with low-frequency bumps, on z = 0."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    v = sphere.vertices
    bumps = 1 + 0.12 * np.sin(3 * v[:, 0] + 1) * np.cos(2 * v[:, 1]) + 0.08 * np.sin(4 * v[:, 2])
    vertices = 0.1 * v * bumps[:, None]
    vertices[:, 2] -= vertices[:, 2].min()
    path = folder / "blob.ply"
    trimesh.Trimesh(vertices, sphere.faces).export(path)
    return path


def _numbers(value) -> str:
    return ", ".join(f"{v:g}" for v in np.ravel(value))


def kit_xml(kind: str, values: dict, folder: Path) -> Path:
    """The kit as a scene file, written the usual way (a BSDF and a medium declared once
    and used through ``<ref>``; the render integrator), with ``values``."""
    integrator, depth = INTEGRATORS[kind]
    if kind == "principled":
        material = (
            '<bsdf type="principled" id="blob_bsdf">'
            f'<rgb name="base_color" value="{_numbers(values["base_color"])}"/>'
            f'<float name="roughness" value="{values["roughness"]:g}"/>'
            f'<float name="spec_trans" value="{values["spec_trans"]:g}"/>'
            f'<float name="eta" value="{values["eta"]:g}"/></bsdf>'
        )
        uses = '<ref id="blob_bsdf"/>'
    else:
        material = (
            f'<bsdf type="roughdielectric" id="blob_bsdf"><float name="alpha" value="{values["alpha"]:g}"/>'
            f'<float name="int_ior" value="{values["eta"]:g}"/></bsdf>'
            f'<medium type="homogeneous" id="blob_medium"><rgb name="albedo" value="{_numbers(values["albedo"])}"/>'
            f'<float name="sigma_t" value="{values["sigma_t"]:g}"/></medium>'
        )
        uses = '<ref id="blob_bsdf"/><ref name="interior" id="blob_medium"/>'
    sensors = []
    for i, azimuth in enumerate(np.radians(np.arange(VIEWS) * 360 / VIEWS + 20)):
        origin = f"{0.5 * math.cos(azimuth):.6f}, {0.5 * math.sin(azimuth):.6f}, 0.3"
        sensors.append(
            f'<sensor type="perspective" id="view_{i}"><float name="fov" value="30"/>'
            f'<transform name="to_world"><lookat origin="{origin}" target="0, 0, 0.09" up="0, 0, 1"/></transform>'
            f'<film type="hdrfilm"><integer name="width" value="{SIZE}"/><integer name="height" value="{SIZE}"/>'
            '<string name="pixel_format" value="rgb"/></film>'
            '<sampler type="independent"><integer name="sample_count" value="8"/></sampler></sensor>'
        )
    scene = f"""<scene version="3.0.0">
<integrator type="{integrator}" id="integrator"><integer name="max_depth" value="{depth}"/></integrator>
{material}
<shape type="ply" id="blob"><string name="filename" value="{blob_file(folder)}"/>
<boolean name="face_normals" value="false"/>{uses}</shape>
<shape type="rectangle" id="floor"><bsdf type="diffuse" id="floor_bsdf"><rgb name="reflectance" value="0.5"/></bsdf></shape>
<shape type="rectangle" id="light"><transform name="to_world"><scale x="0.15" y="0.15"/>
<lookat origin="0.4, -0.3, 0.6" target="0, 0, 0.1" up="0, 0, 1"/></transform>
<emitter type="area" id="light_emitter"><rgb name="radiance" value="15"/></emitter></shape>
<emitter type="constant" id="environment"><rgb name="radiance" value="0.3"/></emitter>
{chr(10).join(sensors)}
</scene>
"""
    path = folder / f"{kind}.xml"
    path.write_text(scene)
    return path


def references(kind: str, folder: Path, mi) -> Path:
    """The truth's renders at 1024 spp, one EXR per sensor, in ``folder``/references."""
    scene = mi.load_file(str(kit_xml(kind, TRUTH[kind], folder)))
    out = folder / "references"
    out.mkdir(exist_ok=True)
    for i in range(VIEWS):
        mi.Bitmap(mi.render(scene, sensor=i, spp=1024, seed=100 + i)).write(str(out / f"view_{i}.exr"))
    return out


def errors(kind: str, values: dict) -> dict[str, float]:
    """Each parameter's error: the largest channel's absolute one; sigma_t's relative."""
    result = {}
    for name, truth in TRUTH[kind].items():
        difference = np.abs(np.ravel(values[name]) - np.ravel(truth))
        result[name] = float(difference.max() / (np.ravel(truth)[0] if name == "sigma_t" else 1.0))
    return result


def within(kind: str, values: dict) -> bool:
    return all(e <= (SIGMA_T_TARGET if n == "sigma_t" else TARGETS[n]) for n, e in errors(kind, values).items())


class Clock:
    """When the parameters first met every target; the parameters are read outside the timing."""

    def __init__(self, kind: str, budget: float):
        self.kind, self.budget = kind, budget
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
        if self.reached is None and within(self.kind, values):
            self.reached = seconds

    def check(self, values: dict) -> bool:
        """True when the run should stop (target met or budget spent)."""
        now = self.elapsed()
        pause = time.perf_counter()
        self.steps += 1
        self.last = values
        if self.reached is None and within(self.kind, values):
            self.reached = now
        self.paused += time.perf_counter() - pause
        return self.reached is not None or now > self.budget


def original_loop(kind: str, folder: Path, clock: Clock, mi, dr) -> None:
    """The original tool's loop: per view, two renders at 8 spp, the dual loss, backward,
    an Adam step at lr 0.03, clamp; on the scene loaded as the tool loaded it (with its
    differentiable integrator) and the references at full size."""
    from pipeline.fit.scene_fit import property_name

    render_integrator, depth = INTEGRATORS[kind]
    scene = mi.load_file(str(kit_xml(kind, START[kind], folder)))
    integrator = mi.load_dict({"type": DIFFERENTIABLE[render_integrator], "max_depth": depth})
    params = mi.traverse(scene)
    keys = {
        property_name(key): key
        for key in params.keys()
        if key.startswith("blob_") and property_name(key) in TRUTH[kind]
    }
    optimizer = mi.ad.Adam(lr=0.03)
    for key in keys.values():
        optimizer[key] = params[key]
    params.update(optimizer)
    targets = [mi.TensorXf(mi.Bitmap(str(folder / "references" / f"view_{i}.exr"))) for i in range(VIEWS)]
    iteration = 0
    while True:
        for view in range(VIEWS):
            seed = 2 * (iteration * VIEWS + view)
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


def pipeline_fit(kind: str, folder: Path, settings: engine.FitSettings, max_size: int, clock: Clock) -> None:
    """`pipeline fit` (pipeline.fit.scene_fit.fit_scene, what the command calls) on the
    kit's file, the parameters named by property as a user names them; it runs to its own
    stopping rule. Its log's parameters after each step are checked against the targets;
    the time before the loop (loading the scene and the references) counts."""
    from pipeline.fit.scene_fit import fit_scene, property_name

    out = folder / "fit_out"
    loop_started = []
    fit = engine.fit

    def timed_fit(*args, **kwargs):
        loop_started.append(time.perf_counter())
        return fit(*args, **kwargs)

    engine.fit = timed_fit
    started = time.perf_counter()
    fit_scene(
        kit_xml(kind, START[kind], folder),
        folder / "references",
        list(TRUTH[kind]),
        settings,
        [],
        None,
        out,
        "auto",
        max_size,
    )
    engine.fit = fit
    log = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    for entry in log:
        values = {property_name(key): v if len(v) > 1 else v[0] for key, v in entry["params"].items()}
        clock.record(loop_started[0] - started + entry["seconds"], values)


def run(kind: str, folder: Path, name: str, budget: float, repeat: int, mi, dr) -> dict:
    clocks = []
    for _ in range(repeat):
        clock = Clock(kind, budget)
        if name == "original":
            original_loop(kind, folder, clock, mi, dr)
        else:
            pipeline_fit(kind, folder, *CONFIGS[name], clock)
        clocks.append(clock)
    return {"first": clocks[0], "last": clocks[-1]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--materials", nargs="*", default=["principled", "volumetric"])
    parser.add_argument("--configs", nargs="*", default=list(CONFIGS))
    parser.add_argument("--budget", type=float, default=300.0)
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--write", action="store_true", help="rewrite docs/benchmarks.md's section")
    args = parser.parse_args()
    variant = mitsuba_variant.activate()
    import drjit as dr
    import mitsuba as mi

    print(f"variant {variant}")
    lines = [
        "| material | run | time to target | steps | first run | errors at the end | ratio to the original |",
        "|---|---|---|---|---|---|---|",
    ]
    print("\n".join(lines))
    for kind in args.materials:
        folder = Path(tempfile.mkdtemp(prefix=f"fit_speed_{kind}_"))
        references(kind, folder, mi)
        baseline = None
        for name in ["original", *args.configs]:
            result = run(kind, folder, name, args.budget, args.repeat, mi, dr)
            last, first = result["last"], result["first"]
            reached = f"{last.reached:.1f} s" if last.reached is not None else f"never ({args.budget:.0f} s)"
            first_time = f"{first.reached:.1f} s" if first.reached is not None else "never"
            if name == "original":
                baseline = last.reached
            ratio = f"{baseline / last.reached:.2f}x" if baseline is not None and last.reached is not None else "-"
            shown = ", ".join(f"{n} {e:.3f}" for n, e in errors(kind, last.last).items())
            lines.append(f"| {kind} | {name} | {reached} | {last.steps} | {first_time} | {shown} | {ratio} |")
            print(lines[-1], flush=True)
    if args.write:
        options = sys.argv[1:]
        command = " ".join([".venv/bin/python -m bench.fit_speed", *(o for o in options if o != "--write")])
        intro = [
            "## Fitting speed",
            "",
            f"{machine()} Mitsuba variant {variant}. Command: `{command} --write`. The kit, the",
            "targets and the runs: bench/fit_speed.py's docstring (each run repeated, the last reported;",
            "the first run's time in its own column).",
            "",
        ]
        write_section("fit-speed", intro + lines)


if __name__ == "__main__":
    main()
