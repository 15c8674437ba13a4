"""``pipeline fit``: the original tool's workflow on any Mitsuba scene.

Given a scene XML with N sensors and a folder of N reference images (EXR as
linear radiance, 8-bit images as sRGB; matched to the sensors in the order the
scene declares them by the sorted file names; each the size of its sensor's
film), fit the ``mi.traverse`` parameters whose keys match the given regular
expressions with pipeline.fit.engine (the same loop as the fit stages), and write
the optimised scene, params.json, log.jsonl and loss.png.

Bounds come from pipeline.render.materials by the property's name (base_color, eta,
sigma_t, ...; the last part of the key that is not "value"), else ``--bound``
must give them. Only plain values can be fitted (a float or an RGB colour, not
a bitmap).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

from pipeline import logger
from pipeline.core.errors import PipelineError
from pipeline.fit import engine
from pipeline.imaging.photo_io import list_photos, read_photo
from pipeline.render import materials, mitsuba_variant, scene_xml

EXR_SUFFIXES = (".exr",)


def property_name(key: str) -> str:
    """``specimen.interior_medium.sigma_t.value.value`` -> ``sigma_t``."""
    return [part for part in key.split(".") if part != "value"][-1]


def select_parameters(
    params, patterns: list[str], bounds: dict[str, tuple[float, float]], learning_rate: float | None
) -> list[engine.FitParameter]:
    import mitsuba as mi

    selected = []
    for key in params.keys():
        if not any(re.search(pattern, key) for pattern in patterns):
            continue
        value = params[key]
        if not isinstance(value, (mi.Float, mi.Color3f)) or (isinstance(value, mi.Float) and len(value) != 1):
            logger.info("skipping %s: not a single float or colour (%s)", key, type(value).__name__)
            continue
        name = property_name(key)
        spec = materials.PARAMETERS.get(name)
        span = bounds.get(key, bounds.get(name))
        if span is None and spec is None:
            raise PipelineError(f"no default bounds for {key}: give them with --bound {name}=LOWER:UPPER")
        lower, upper = span if span is not None else (spec.lower, spec.upper)
        log = spec.log if spec is not None else False
        rate = learning_rate if learning_rate is not None else (spec.learning_rate if spec is not None else 0.02)
        selected.append(engine.FitParameter(key, key, lower, upper, log, rate))
    if not selected:
        raise PipelineError(
            f"no fittable parameter matches {' '.join(patterns)}; `pipeline fit SCENE --list` shows the scene's keys"
        )
    return selected


def list_keys(scene_path: Path, variant: str) -> list[str]:
    mitsuba_variant.activate(variant)
    import mitsuba as mi

    params = mi.traverse(_load(scene_path))
    return [f"{key}  {type(params[key]).__name__}" for key in params.keys()]


def _load(scene_path: Path):
    import mitsuba as mi

    if not scene_path.is_file():
        raise PipelineError(f"{scene_path} does not exist")
    try:
        return mi.load_file(str(scene_path))
    except RuntimeError as error:
        raise PipelineError(f"Mitsuba cannot load {scene_path}: {error}") from error


def fit_scene(
    scene_path: Path,
    references: Path,
    patterns: list[str],
    settings: engine.FitSettings,
    bound_entries: list[str],
    learning_rate: float | None,
    out_dir: Path,
    variant: str = "auto",
) -> Path:
    """Fit and write the results into ``out_dir``; returns its params.json."""
    mitsuba_variant.activate(variant)
    import mitsuba as mi

    scene = _load(scene_path)
    sensors = scene.sensors()
    files = list_photos(references) if references.is_dir() else []
    if len(files) != len(sensors):
        raise PipelineError(
            f"{references} holds {len(files)} reference images but {scene_path} has {len(sensors)} "
            "sensors: give one image per sensor (matched by sorted file name)"
        )
    views = []
    for index, (path, sensor) in enumerate(zip(files, sensors)):
        size = tuple(int(v) for v in sensor.film().crop_size())
        pixels = read_photo(path, "linear" if path.suffix.lower() in EXR_SUFFIXES else "srgb").pixels
        if pixels.shape[:2] != size[::-1]:
            raise PipelineError(
                f"{path} is {pixels.shape[1]}x{pixels.shape[0]} but sensor {index} renders "
                f"{size[0]}x{size[1]}: resize it or fix the film"
            )
        views.append(engine.FitView(path.stem, scene, sensor, pixels))
    parameters = select_parameters(
        mi.traverse(scene), patterns, engine.parse_bounds(bound_entries, "--bound"), learning_rate
    )
    logger.info("fitting %s on %d views", ", ".join(p.key for p in parameters), len(views))
    result = engine.fit(parameters, views, [], settings)

    out_dir.mkdir(parents=True, exist_ok=True)
    scene_xml.set_values(scene_path, result.values, out_dir / scene_path.name)
    with (out_dir / "log.jsonl").open("w") as log:
        for entry in result.log:
            log.write(json.dumps(entry) + "\n")
    engine.plot_loss(result.log, out_dir / "loss.png")
    params_json = out_dir / "params.json"
    params_json.write_text(
        json.dumps(
            {
                "scene": str(scene_path),
                "params": result.values,
                "bounds": {p.key: [p.lower, p.upper] for p in parameters},
                "iterations": len(result.log),
                "final_loss": result.log[-1]["loss"] if result.log else None,
                "stopped": result.stopped,
            },
            indent=1,
        )
    )
    return params_json
