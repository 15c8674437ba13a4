"""``pipeline fit``: the original tool's workflow on any Mitsuba scene.

Given a scene XML with N sensors and a folder of N reference images (EXR as
linear radiance, 8-bit images as sRGB; matched to the sensors in the order the
scene declares them by the sorted file names; each the size of its sensor's
film), fit the ``mi.traverse`` parameters that ``--params`` selects with
pipeline.fit.engine (the same loop as the fit stages), and write the optimised
scene, params.json, log.jsonl and loss.png.

The scene is read as users write it (pipeline.render.user_scene: ``<ref>``s,
objects without ids, includes, ``<default>`` values, IOR names) and rendered
with the differentiable counterpart of its integrator (``path`` fits with
``prb``). A ``--params`` word names a property: it selects the keys that have it
as one of their dot-separated parts (``eta`` is not ``metallic``); a pattern
with a regular expression's characters is searched for in the keys. Bounds come
from pipeline.render.materials by the property's name (base_color, eta,
sigma_t, ...), else ``--bound`` must give them. Only plain values can be fitted
(a float or an RGB colour, not a bitmap).

The fit renders each sensor with its film reduced to ``max_size`` pixels along the
longer side and compares with the reference averaged down to the same pixels: a
plain value is one number for the whole image, and small films reach most targets
in a fraction of the time full ones take (docs/benchmarks.md, "Fitting speed").
``coarse_to_fine`` goes on from there at twice the pixels, and so on up to the films'
own size, each level starting from the last one's values with half its learning
rates and running until nothing moves beyond its noise (pipeline.fit.stopping; with
``step_halvings``, the last level then halves its steps, pipeline.fit.loop):
what only shows at full size (a small highlight's width) stays identifiable, and
the finer levels' smaller steps and lower noise let the values settle closer. The
written scene keeps its films.

``heldout`` names reference images that are not fitted to but rendered every
``validate_every`` steps: the fit then keeps the state with the lowest error on them
(pipeline.fit.loop) instead of its last. A watcher (``FitWatcher``: `pipeline
studio`) sees each level's views and each step, and may stop the fit, which then
ends in its best state and is written as any other.

params.json and log.jsonl are written first: a scene that cannot be written
back (a value given by a texture, say) keeps them and says what failed.
"""

from __future__ import annotations

import copy
import os
import re
import tempfile
import time
import xml.etree.ElementTree as ET
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Protocol

import numpy as np

from pipeline import logger
from pipeline.core import jsonio
from pipeline.core.errors import ConfigError, PipelineError
from pipeline.core.fsutil import atomic_write_text
from pipeline.core.interrupts import Interrupted, interruption, signal_name
from pipeline.core.lock import CaptureLock
from pipeline.fit import engine
from pipeline.fit.loop import INTERRUPTED
from pipeline.fit.outputs import write_fit_log
from pipeline.imaging.photo_io import list_photos, read_photo
from pipeline.render import materials, mitsuba_variant, scene_xml, user_scene
from pipeline.render.samples import check_samples

EXR_SUFFIXES = (".exr",)
LOCK_FILE = ".fit.lock"
"""In --out: held while a fit runs, so that two fits never mix their results in one folder."""
BUSY_HINT = "wait for that fit to end, or give this one another --out"
USER_STOP = "stopped by the user"
"""How a watcher's stop reason begins (``FitWatcher.step``): it ends every level."""


@dataclass(frozen=True)
class FilmSizes:
    """The film sizes a fit renders at."""

    max_size: int = 0
    """Pixels along a film's longer side at the first level (0: the films' own)."""
    coarse_to_fine: bool = False
    """Then twice as many, and so on, up to the films' own size."""

    def levels(self, longest: int) -> list[int]:
        """Each level's max_size for films whose longer side is ``longest`` (0: their own)."""
        if not self.max_size or self.max_size >= longest:
            return [0]
        if not self.coarse_to_fine:
            return [self.max_size]
        sizes = [self.max_size]
        while 2 * sizes[-1] < longest:
            sizes.append(2 * sizes[-1])
        return [*sizes, 0]


def property_name(key: str) -> str:
    """``specimen.interior_medium.sigma_t.value.value`` -> ``sigma_t``."""
    return [part for part in key.split(".") if part != "value"][-1]


def selects(pattern: str, key: str) -> bool:
    """Whether ``--params`` ``pattern`` selects ``key``: a plain word is a part of the
    key; anything else a regular expression searched for in it."""
    if re.fullmatch(r"\w+", pattern):
        return pattern in key.split(".")
    return re.search(pattern, key) is not None


def check_patterns(patterns: list[str]) -> None:
    for pattern in patterns:
        try:
            re.compile(pattern)
        except re.error as error:
            raise ConfigError(f"--params {pattern!r} is not a regular expression: {error}") from None


def _plain_value(params, key: str, tree) -> str | None:
    """Why ``key`` cannot be fitted (None: it can): only one float or colour written in
    the scene file ``tree`` can be fitted and written back."""
    import mitsuba as mi

    if not scene_xml.writable(tree, key):
        return "not a plain value in the scene file (a default Mitsuba adds?)"
    value = params[key]
    if not isinstance(value, (mi.Float, mi.Color3f)) or (isinstance(value, mi.Float) and len(value) != 1):
        return f"not a single float or colour ({type(value).__name__})"
    return None


def select_parameters(
    params, patterns: list[str], bounds: dict[str, tuple[float, float]], learning_rate: float | None, tree
) -> list[engine.FitParameter]:
    """The keys ``patterns`` select that hold one float or colour written in the scene
    file ``tree`` (so that the fit can be written back), with their bounds."""
    selected = []
    for key in params.keys():
        if not any(selects(pattern, key) for pattern in patterns):
            continue
        if (reason := _plain_value(params, key, tree)) is not None:
            logger.info("skipping %s: %s", key, reason)
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


def describe_parameters(scene_path: Path, variant: str) -> list[dict]:
    """Every differentiable key of the scene with its type, whether it can be fitted
    (and why not), its value and its default bounds (pipeline.render.materials; None:
    --bound must give them): `pipeline studio`'s parameter table."""
    mitsuba_variant.activate(variant)
    import mitsuba as mi

    tree = user_scene.normalised(scene_path)
    params = mi.traverse(_load(scene_path, tree))
    rows = []
    for key in params.keys():
        if params.flags(key) & int(mi.ParamFlags.NonDifferentiable):
            continue
        reason = _plain_value(params, key, tree)
        spec = materials.PARAMETERS.get(property_name(key))
        rows.append(
            {
                "key": key,
                "type": type(params[key]).__name__,
                "fittable": reason is None,
                "why_not": reason,
                "value": np.ravel(np.asarray(params[key])).tolist() if reason is None else None,
                "bounds": [spec.lower, spec.upper] if spec is not None else None,
            }
        )
    return rows


def set_values(scene_values, values: dict) -> None:
    """The fitted ``values`` (lists by key) into a traversed scene."""
    for key, value in values.items():
        kind = type(scene_values[key])
        scene_values[key] = kind(*value) if len(np.ravel(value)) > 1 else kind(float(np.ravel(value)[0]))
    scene_values.update()


def list_keys(scene_path: Path, variant: str) -> list[str]:
    mitsuba_variant.activate(variant)
    import mitsuba as mi

    params = mi.traverse(_load(scene_path, user_scene.normalised(scene_path)))
    return [f"{key}  {type(params[key]).__name__}" for key in params.keys()]


def _load(scene_path: Path, tree):
    import mitsuba as mi

    try:
        return mi.load_string(ET.tostring(tree.getroot(), encoding="unicode"))
    except RuntimeError as error:
        raise PipelineError(f"Mitsuba cannot load {scene_path}: {error}") from error


def _views(
    scene, scene_path: Path, references: Path, integrator, full_sizes: list[tuple[int, int]]
) -> list[engine.FitView]:
    """One view per sensor; each reference must be its sensor's film size in the scene
    file (``full_sizes``) and is averaged down to the film it is fitted at."""
    import cv2

    sensors = scene.sensors()
    files = list_photos(references) if references.is_dir() else []
    if len(files) != len(sensors):
        raise PipelineError(
            f"{references} holds {len(files)} reference images but {scene_path} has {len(sensors)} "
            "sensors: give one image per sensor (matched by sorted file name)"
        )
    if len(full_sizes) != len(sensors):
        raise PipelineError(f"{scene_path}: {len(sensors)} sensors load, but {len(full_sizes)} are declared at its top")
    views = []
    for index, (path, sensor, size) in enumerate(zip(files, sensors, full_sizes)):
        pixels = read_photo(path, "linear" if path.suffix.lower() in EXR_SUFFIXES else "srgb").pixels
        negative = int(np.count_nonzero((pixels < 0).any(axis=-1)))
        if negative:
            raise PipelineError(
                f"{path}: {negative} pixel(s) are negative, which no render (light is never negative) can match: "
                "clip them to 0 in the file"
            )
        if pixels.shape[:2] != size[::-1]:
            raise PipelineError(
                f"{path} is {pixels.shape[1]}x{pixels.shape[0]} but sensor {index} renders "
                f"{size[0]}x{size[1]}: resize it or fix the film"
            )
        fitted = tuple(int(v) for v in sensor.film().crop_size())
        if fitted != size:
            pixels = cv2.resize(pixels, fitted, interpolation=cv2.INTER_AREA)
        views.append(engine.FitView(path.stem, scene, sensor, pixels, integrator=integrator))
    return views


def _check_samples(views: list[engine.FitView], settings: engine.FitSettings) -> None:
    """Each render of the level within Mitsuba's samples per render (a film of a
    sensor at its level's size times the options' samples per pixel)."""
    largest = max(views, key=lambda view: int(np.prod(view.sensor.film().crop_size())))
    width, height = (int(v) for v in largest.sensor.film().crop_size())
    for option, spp in (
        ("--spp", settings.spp),
        ("--spp-grad", settings.spp_grad),
        ("--validation-spp", settings.validation_spp),
    ):
        if spp:
            check_samples(width * height, spp, option, f"{largest.name}'s film of {width}x{height} px")


def check_out_dir(out_dir: Path, scene_path: Path, references: Path) -> None:
    """Make ``out_dir`` and prove it writable before the fit, which may take long."""
    if out_dir.exists() and not out_dir.is_dir():
        raise ConfigError(f"--out {out_dir} is a file: name a folder")
    if (out_dir / scene_path.name).resolve() == scene_path.resolve():
        raise ConfigError(f"--out {out_dir} would overwrite the scene being fitted ({scene_path}): name another folder")
    if out_dir.resolve().is_relative_to(references.resolve()):
        raise ConfigError(
            f"--out {out_dir} is inside --references {references}: the fit's images would count as references "
            "next time; name another folder"
        )
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=out_dir).close()
    except OSError as error:
        raise ConfigError(
            f"--out {out_dir} cannot be written ({error.strerror}): name a folder you can write to"
        ) from error


@dataclass(frozen=True)
class SceneFit:
    """What `pipeline fit` and `pipeline studio` ask of a fit."""

    scene: Path
    """The Mitsuba scene file, one sensor per reference image."""
    references: Path
    """The folder of reference images, matched to the sensors by sorted file name."""
    patterns: tuple[str, ...]
    """``--params`` words or regular expressions selecting the keys to fit."""
    settings: engine.FitSettings = field(default_factory=engine.FitSettings)
    """The loop's settings."""
    bounds: tuple[str, ...] = ()
    """``NAME=LO:HI`` entries, by property name or full key."""
    learning_rate: float | None = None
    """One learning rate for every parameter (None: each parameter's own)."""
    out_dir: Path = Path("fit_out")
    """Where the fitted scene, params.json, log.jsonl and loss.png go."""
    variant: str = "auto"
    """The Mitsuba variant."""
    sizes: FilmSizes = field(default_factory=FilmSizes)
    """The film sizes the fit renders at."""
    heldout: tuple[str, ...] = ()
    """Reference images (by file name without its suffix) not fitted to but rendered
    every ``validate_every`` steps: the fit keeps the state with the lowest error on
    them instead of its last one."""


class FitWatcher(Protocol):
    """Follows a fit as it runs (`pipeline studio`); both calls come from the fit's thread."""

    def level_started(self, level: int, levels: list[int], views: list[engine.FitView]) -> None:
        """A level begins: its index, every level's max_size (0: full) and its views
        (training and held out), whose scenes render its current state."""

    def step(self, entry: dict) -> str | None:
        """One step's log entry; a reason to stop, or None to go on."""


def _split_heldout(views: list[engine.FitView], heldout: tuple[str, ...], references: Path):
    names = {view.name for view in views}
    unknown = sorted(set(heldout) - names)
    if unknown:
        raise ConfigError(
            f"--heldout {' '.join(unknown)}: no such image in {references} (its images: {', '.join(sorted(names))})"
        )
    training = [view for view in views if view.name not in heldout]
    if not training:
        raise ConfigError("--heldout names every reference image: leave at least one to fit to")
    return training, [view for view in views if view.name in heldout]


@dataclass
class _Fitted:
    """What the levels of a fit found, for writing."""

    levels: list[int]
    parameters: list[engine.FitParameter]
    start: dict[str, list[float]]
    settings: engine.FitSettings
    log: list[dict]
    result: engine.FitResult
    sensor_ids: list[str]
    seconds: float


def fit_scene(request: SceneFit, watcher: FitWatcher | None = None) -> Path:
    """Fit (at ``request.sizes``) and write the results into ``request.out_dir``;
    returns its params.json. --out is locked meanwhile; Ctrl-C or SIGTERM ends the fit
    in its best state so far, which is written and marked interrupted."""
    check_out_dir(request.out_dir, request.scene, request.references)
    check_patterns(list(request.patterns))
    mitsuba_variant.activate(request.variant)
    lock = CaptureLock(
        request.out_dir, "pipeline fit", wait=False, lock_file=request.out_dir / LOCK_FILE, busy_hint=BUSY_HINT
    )
    with lock:
        tree = user_scene.normalised(request.scene)
        fitted = _fit_levels(request, tree, watcher)
        params_json = _write_results(request, tree, fitted)
    if fitted.result.stopped.startswith(INTERRUPTED):
        logger.warning(
            '%s: the best state so far is written to %s (params.json: "interrupted": true)',
            fitted.result.stopped,
            request.out_dir,
        )
    return params_json


def _fit_levels(request: SceneFit, tree, watcher: FitWatcher | None) -> _Fitted:
    """The fit, level by level, of the scene file ``tree`` (user_scene.normalised)."""
    import mitsuba as mi

    scene_path, references = request.scene, request.references

    # 1. The films' sizes per level, the differentiable integrator and the bounds.
    full_sizes = user_scene.reduce_films(copy.deepcopy(tree), 0)
    integrator = user_scene.differentiable_integrator(tree)
    levels = request.sizes.levels(max((max(size) for size in full_sizes), default=0))
    bounds = engine.parse_bounds(list(request.bounds), "--bound")

    # 2. Each level: the scene loaded with its films reduced (the references averaged
    # down to them); the parameters chosen on the first, each later level starting from
    # the last one's values. Ctrl-C between two levels keeps the last level's result.
    started = time.perf_counter()
    parameters, start, log, result, first_step, sensor_ids = None, {}, [], None, 0.0, []
    settings = request.settings
    level = 0
    try:
        for level, max_size in enumerate(levels):
            reduced = copy.deepcopy(tree)
            user_scene.reduce_films(reduced, max_size)
            scene = _load(scene_path, reduced)
            scene_values = mi.traverse(scene)
            if parameters is None:
                parameters = select_parameters(
                    scene_values, list(request.patterns), bounds, request.learning_rate, tree
                )
                start = {p.key: np.ravel(np.asarray(scene_values[p.key])).tolist() for p in parameters}
                logger.info("fitting %s on %d views", ", ".join(p.key for p in parameters), len(full_sizes))
                medium = engine.renders_medium(scene_values)
                settings = request.settings.resolved(medium)
                if medium:
                    logger.info(
                        "the scene renders a participating medium: image memory %d, %d step halvings at the last level",
                        settings.image_memory,
                        settings.step_halvings,
                    )
            else:
                set_values(scene_values, result.values)
            views = _views(scene, scene_path, references, integrator, full_sizes)
            _check_samples(views, settings)
            training, heldout = _split_heldout(views, request.heldout, references)
            if len(levels) > 1:
                logger.info("level %d of %d: films of %s px", level + 1, len(levels), max_size or "their own")
            if watcher is not None:
                watcher.level_started(level, levels, views)
            # a later level's steps counted from the first level's first step, as one fit's
            first_step = first_step if level else time.perf_counter()
            offset = time.perf_counter() - first_step
            # Adam's steps keep a value jittering by about its learning rate: each finer level,
            # starting near the answer, steps half as far; only the last level, whose values
            # are the answer, halves its steps again when still (step_halvings)
            level_settings = replace(
                settings,
                learning_rate_scale=settings.learning_rate_scale / 2**level,
                step_halvings=settings.step_halvings if level == len(levels) - 1 else 0,
            )
            on_iteration = watcher.step if watcher else None
            result = engine.fit(
                parameters, training, heldout, level_settings, on_iteration=on_iteration, finish_on_interrupt=True
            )
            log += [entry | {"level": level, "seconds": offset + entry["seconds"]} for entry in result.log]
            sensor_ids = [view.sensor.id() for view in views]
            # Dr.Jit traces every live scene into the next level's kernels
            del scene, scene_values, views, training, heldout
            if result.stopped.startswith((USER_STOP, INTERRUPTED)):
                break  # the user's stop or Ctrl-C ends the fit, not only this level
    except (KeyboardInterrupt, Interrupted, RuntimeError) as error:
        signal_error = interruption(error)
        if signal_error is None or result is None:
            raise
        result = replace(result, stopped=f"{INTERRUPTED} ({signal_name(signal_error)}) before level {level + 1}")
    return _Fitted(levels, parameters, start, settings, log, result, sensor_ids, time.perf_counter() - started)


def _write_results(request: SceneFit, tree, fitted: _Fitted) -> Path:
    """params.json and log.jsonl first, then the scene with the values written in; each
    file written beside its place and renamed into it, so that a kill or a full disk
    leaves no half file."""
    scene_path, references, out_dir = request.scene, request.references, request.out_dir
    result, parameters, log = fitted.result, fitted.parameters, fitted.log
    params_json = out_dir / "params.json"
    summary = {
        "scene": str(scene_path),
        "references": dict(zip(fitted.sensor_ids, (str(path) for path in list_photos(references)))),
        "start": fitted.start,
        "params": result.values,
        "bounds": {p.key: [p.lower, p.upper] for p in parameters},
        "iterations": len(log),
        "levels": [size or "full" for size in fitted.levels],
        "final_loss": log[-1]["loss"] if log else None,
        "heldout": list(request.heldout),
        "best_iteration": result.best_iteration if request.heldout else None,
        "averaged": result.averaged,
        "heldout_error": result.validation_error,
        "stopped": result.stopped,
        "interrupted": result.stopped.startswith(INTERRUPTED),
        "seconds": fitted.seconds,
        "settings": asdict(fitted.settings),
    }
    out_scene = out_dir / scene_path.name
    user_scene.relative_filenames(tree, out_dir)
    with tempfile.TemporaryDirectory(dir=out_dir, prefix=".fit.tmp-") as folder:
        staging = Path(folder)
        atomic_write_text(params_json, jsonio.dumps(summary, indent=1))
        write_fit_log(staging, log)
        for written in sorted(staging.iterdir()):
            os.replace(written, out_dir / written.name)
        written_scene = staging.with_suffix(".xml")  # in out_dir, so that its relative file names hold
        try:
            scene_xml.write_values(tree, out_scene, result.values, written_scene)
            os.replace(written_scene, out_scene)
        except (PipelineError, OSError) as error:
            written_scene.unlink(missing_ok=True)
            raise PipelineError(
                f"the fit is in {params_json} and {out_dir / 'log.jsonl'}, but the fitted scene could not be "
                f"written: {error}"
            ) from error
    return params_json
