"""Differentiable fitting of scene parameters to photos (Mitsuba 3, Dr.Jit, Adam).

Shared by the fit stages and ``pipeline fit``. The loop, per iteration:

1. draw ``batch`` views (a seeded permutation of the fitting views sorted by
   name, so the result does not depend on the order views are given in);
2. per view: set every scene parameter from its latent variable (the value, or
   its logarithm for positive quantities spanning decades), render, compute the
   loss on linear radiance over the view's weight mask, and backpropagate; the
   gradients of the batch add up in the latents;
3. one Adam step (``mi.ad.Adam``, one learning rate per parameter), then every
   latent is clamped to its bounds (box constraints);
4. every ``validate_every`` iterations, the held-out views are rendered with a
   fixed seed and their mean squared error recorded; the state with the lowest
   validation error is kept.

It stops at ``iterations``, when the time budget is spent, or when the mean
training loss over the last ``window`` iterations improved by less than
``tolerance`` (relative) on the window before; each view's loss counts relative
to its first value, so that a batch of bright views does not look like a setback.

Losses: ``l2``, mean((I - R)^2); ``dual``, the dual-buffer estimator of Deng et
al. 2022, mean((I1 - R)(I2 - R)) from two renders with independent seeds, whose
expectation is the squared error without the Monte Carlo variance that biases
plain L2 at low spp. Optional per-view exposure (a latent log-scale per fitting
view) absorbs exposure differences between photos.

Limitations: parameters must be plain values in ``mi.traverse`` (textures are
fitted by their own stage); the same key must exist in every view's scene.
"""

from __future__ import annotations

import time
from pathlib import Path
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from pipeline import logger
from pipeline.errors import PipelineError


@dataclass(frozen=True)
class FitParameter:
    """One scene parameter to fit."""

    name: str
    key: str
    """Key in ``mi.traverse`` of every view's scene."""
    lower: float
    upper: float
    log: bool = False
    learning_rate: float = 0.02


@dataclass
class FitView:
    """A view to fit or validate on."""

    name: str
    scene: Any
    """The loaded Mitsuba scene (views may share one)."""
    sensor: Any
    """The sensor to render (may be outside the scene: a crop window)."""
    reference: np.ndarray
    """(h, w, 3) linear radiance of the photo, the sensor's film size."""
    weight: np.ndarray | None = None
    """(h, w) pixel weights (the specimen's mask), or None for every pixel."""


@dataclass(frozen=True)
class FitSettings:
    """How the loop runs (the fit stages' config sections hold these fields too)."""

    iterations: int = 100
    batch: int = 2
    spp: int = 16
    loss: Literal["l2", "dual"] = "dual"
    learning_rate_scale: float = 1.0
    validate_every: int = 10
    validation_spp: int = 64
    tolerance: float = 1e-3
    window: int = 20
    time_budget_s: float = 0.0
    exposure: bool = False
    seed: int = 0


@dataclass
class FitResult:
    values: dict[str, list[float]]
    """Best-validation values (last values when nothing is held out)."""
    best_iteration: int
    validation_error: float | None
    stopped: str
    log: list[dict] = field(default_factory=list)
    exposures: dict[str, float] = field(default_factory=dict)


def _to_numpy(value) -> list[float]:
    return [float(v) for v in np.ravel(np.asarray(value))]


def parse_bounds(entries: tuple[str, ...] | list[str], where: str) -> dict[str, tuple[float, float]]:
    """Entries "name=lower:upper" (config or command line) as {name: (lower, upper)}."""
    result = {}
    for entry in entries:
        name, _, span = entry.partition("=")
        lower, _, upper = span.partition(":")
        try:
            result[name.strip()] = (float(lower), float(upper))
        except ValueError:
            raise PipelineError(f"{where}: '{entry}' is not name=lower:upper (e.g. eta=1.3:1.6)") from None
        if not result[name.strip()][0] < result[name.strip()][1]:
            raise PipelineError(f"{where}: '{entry}' has lower >= upper")
    return result


def plot_loss(log: list[dict], path: Path) -> None:
    """Training loss and validation error against iteration (matplotlib, no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(6, 3.5), dpi=100)
    axis.semilogy([e["iteration"] for e in log], [max(e["loss"], 1e-12) for e in log], label="training loss")
    validated = [e for e in log if "validation_error" in e]
    if validated:
        axis.semilogy([e["iteration"] for e in validated], [e["validation_error"] for e in validated], "o-",
                      label="validation MSE")  # fmt: skip
    axis.set_xlabel("iteration")
    axis.legend()
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)


class _Target:
    """A view's reference and pixel weights as Dr.Jit tensors, converted once rather
    than at every render."""

    def __init__(self, view: FitView, mi):
        self.reference = mi.TensorXf(view.reference.astype(np.float32))
        self.weight = None
        if view.weight is not None:
            self.weight = mi.TensorXf(np.repeat(view.weight[..., None], 3, axis=2).astype(np.float32))
            self.weight_sum = float(3 * view.weight.sum())

    def mean(self, values, dr):
        """Mean of a per-pixel tensor over the weights (all pixels without them)."""
        if self.weight is None:
            return dr.mean(values, axis=None)
        return dr.sum(values * self.weight, axis=None) / self.weight_sum

    def mse(self, image, dr):
        return self.mean(dr.square(image - self.reference), dr)


def fit(parameters: list[FitParameter], training: list[FitView], validation: list[FitView],
        settings: FitSettings, on_iteration=None) -> FitResult:  # fmt: skip
    """Run the loop; the scenes end in the best state."""
    import drjit as dr
    import mitsuba as mi

    if not training:
        raise PipelineError("no views to fit: every view is held out")
    training = sorted(training, key=lambda v: v.name)
    validation = sorted(validation, key=lambda v: v.name)
    scenes = {id(v.scene): v.scene for v in training + validation}
    targets = {v.name: _Target(v, mi) for v in training + validation}
    traversed = {key: mi.traverse(scene) for key, scene in scenes.items()}
    for parameter in parameters:
        missing = [v.name for v in training + validation if parameter.key not in traversed[id(v.scene)]]
        if missing:
            raise PipelineError(f"parameter {parameter.name}: key {parameter.key} is not in the scene of "
                                f"{', '.join(missing[:3])}")  # fmt: skip
    optimizer = mi.ad.Adam(lr=0.01)
    first = traversed[id(training[0].scene)]
    for parameter in parameters:
        value = first[parameter.key]
        latent = dr.log(value) if parameter.log else type(value)(value)
        optimizer[parameter.name] = latent
        optimizer.set_learning_rate({parameter.name: parameter.learning_rate * settings.learning_rate_scale})
    if settings.exposure:
        for view in training:
            optimizer[f"exposure:{view.name}"] = mi.Float(0.0)
            optimizer.set_learning_rate({f"exposure:{view.name}": 0.01 * settings.learning_rate_scale})

    def clamp() -> None:
        for parameter in parameters:
            lo, hi = (np.log(parameter.lower), np.log(parameter.upper)) if parameter.log else (parameter.lower, parameter.upper)
            optimizer[parameter.name] = dr.clip(optimizer[parameter.name], lo, hi)

    def apply(scene_key: int) -> None:
        params = traversed[scene_key]
        for parameter in parameters:
            latent = optimizer[parameter.name]
            params[parameter.key] = dr.exp(latent) if parameter.log else latent
        params.update()

    def current() -> dict[str, list[float]]:
        return {p.name: _to_numpy(np.exp(_to_numpy(optimizer[p.name])) if p.log else optimizer[p.name])
                for p in parameters}  # fmt: skip

    def validate(iteration: int) -> float:
        errors = []
        for index, view in enumerate(validation):
            with dr.suspend_grad():
                apply(id(view.scene))
                image = mi.render(view.scene, sensor=view.sensor, spp=settings.validation_spp, seed=index)
                errors.append(float(targets[view.name].mse(image, dr).array[0]))
        return float(np.mean(errors))

    clamp()
    rng = np.random.default_rng(settings.seed)
    order: list[int] = []
    started = time.perf_counter()
    best = {"values": current(), "iteration": 0, "error": validate(0) if validation else None}
    losses: list[float] = []
    first_loss: dict[str, float] = {}
    log: list[dict] = []
    stopped = "iterations"
    for iteration in range(1, settings.iterations + 1):
        total, relative = 0.0, 0.0
        for _ in range(min(settings.batch, len(training))):
            if not order:
                order = [int(i) for i in rng.permutation(len(training))]
            index = order.pop()
            view = training[index]
            apply(id(view.scene))
            seed = (iteration * len(training) + index) * 2
            image = mi.render(view.scene, traversed[id(view.scene)], sensor=view.sensor, spp=settings.spp, seed=seed)
            if settings.exposure:
                image = image * dr.exp(optimizer[f"exposure:{view.name}"])
            if settings.loss == "dual":
                second = mi.render(view.scene, traversed[id(view.scene)], sensor=view.sensor, spp=settings.spp,
                                   seed=seed + 1)  # fmt: skip
                if settings.exposure:
                    second = second * dr.exp(optimizer[f"exposure:{view.name}"])
                reference = targets[view.name].reference
                loss = targets[view.name].mean((image - reference) * (second - reference), dr)
            else:
                loss = targets[view.name].mse(image, dr)
            dr.backward(loss / settings.batch)
            value = float(loss.array[0])
            total += value
            # Views differ in brightness and size: the stopping rule compares each
            # view's loss with its first one.
            first_loss.setdefault(view.name, max(abs(value), 1e-12))
            relative += value / first_loss[view.name]
        optimizer.step()
        clamp()
        views_per_step = min(settings.batch, len(training))
        losses.append(relative / views_per_step)
        entry = {"iteration": iteration, "loss": total / views_per_step, "relative_loss": losses[-1],
                 "seconds": time.perf_counter() - started, "params": current()}  # fmt: skip
        if validation and (iteration % settings.validate_every == 0 or iteration == settings.iterations):
            entry["validation_error"] = validate(iteration)
            if entry["validation_error"] < best["error"]:
                best = {"values": entry["params"], "iteration": iteration, "error": entry["validation_error"]}
        elif not validation:
            best = {"values": entry["params"], "iteration": iteration, "error": None}
        log.append(entry)
        if on_iteration is not None:
            on_iteration(entry)
        window = settings.window
        if len(losses) >= 2 * window:
            previous, recent = np.mean(losses[-2 * window : -window]), np.mean(losses[-window:])
            if previous > 0 and (previous - recent) / previous < settings.tolerance:
                stopped = f"loss improved by less than {settings.tolerance:g} over {window} iterations"
                break
        if settings.time_budget_s and entry["seconds"] > settings.time_budget_s:
            stopped = f"time budget of {settings.time_budget_s:g} s spent"
            break
    # Leave the scenes in the best state.
    for parameter in parameters:
        value = np.asarray(best["values"][parameter.name])
        latent = np.log(value) if parameter.log else value
        optimizer[parameter.name] = type(optimizer[parameter.name])(*[float(v) for v in latent])
    for key in traversed:
        with dr.suspend_grad():
            apply(key)
    exposures = {v.name: float(np.exp(_to_numpy(optimizer[f"exposure:{v.name}"])[0])) for v in training} if settings.exposure else {}
    logger.info("fit stopped (%s) after %d iterations in %.0f s; best at iteration %d", stopped, len(log),
                time.perf_counter() - started, best["iteration"])  # fmt: skip
    return FitResult(best["values"], best["iteration"], best["error"], stopped, log, exposures)
