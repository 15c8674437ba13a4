"""Fitting scene parameters, or a mesh's shape, to photos: the entry points the fit
stages and `pipeline fit` call, on the one loop of pipeline.fit.loop.

``fit`` steps material parameters (pipeline.fit.variables.MaterialVariables:
plain values or textures, optionally a gain per photo: exposure, white balance) and reports their
best-held-out values; ``fit_shape`` steps a mesh's vertices (ShapeVariables) with
everything else frozen. Both leave the scenes in the best state.

Losses (pipeline.fit.settings.LoopSettings.loss): ``l2``, one render per view and
its squared error, whose gradient Mitsuba renders with independent samples and
so is unbiased; ``dual``, the dual-buffer estimator of Deng et al. 2022 from two
renders, mean((I1 - R)(I2 - R)), whose value too is unbiased by Monte Carlo
noise. The held-out error is always the dual estimator.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline import logger
from pipeline.core.errors import PipelineError
from pipeline.fit import loop
from pipeline.fit.loop import FitView
from pipeline.fit.settings import FitSettings, ShapeSettings
from pipeline.fit.variables import FitParameter, MaterialVariables, ShapeVariables, summarize


@dataclass
class FitResult:
    values: dict[str, list[float]]
    """Best-validation values (last values when nothing is held out); a texture's
    per-channel mean."""
    best_iteration: int
    validation_error: float | None
    stopped: str
    log: list[dict] = field(default_factory=list)
    photo_gains: dict[str, list[float]] = field(default_factory=dict)
    """Each training photo's RGB gain when exposure or white balance is fitted: the
    render times it matches the photo, as the scenes stand (their geometric mean: how
    much brighter the photos are than the scene renders, in each channel)."""
    start_validation_error: float | None = None
    """Validation error of the starting values."""
    textures: dict[str, np.ndarray] = field(default_factory=dict)
    """Best-validation arrays of texture parameters, (..., channels)."""
    skipped_gradients: int = 0
    """Non-finite gradient entries zeroed before a step."""
    averaged: bool = False
    """The values are the average of the last steps (pipeline.fit.loop.TailAverage)."""


@dataclass
class ShapeResult:
    positions: np.ndarray
    """(n, 3) best-validation vertex positions (last ones when nothing is held out)."""
    best_iteration: int
    validation_error: float | None
    start_validation_error: float | None
    log: list[dict] = field(default_factory=list)
    skipped_gradients: int = 0
    """Non-finite gradient entries zeroed before a step."""
    averaged: bool = False
    """The positions are the average of the last steps (pipeline.fit.loop.TailAverage)."""


def _with_pixels(views: list[FitView]) -> list[FitView]:
    """The views with at least one pixel that counts: an empty mask (or one eroded
    away) would divide its loss by a zero weight."""
    kept = []
    for view in views:
        if view.weight is None or np.any(view.weight > 0):
            kept.append(view)
        else:
            logger.warning("%s: no pixel of its mask counts, left out of fitting", view.name)
    return kept


def _traversed(views: list[FitView]) -> dict:
    import mitsuba as mi

    return {id(v.scene): mi.traverse(v.scene) for v in views}


def renders_medium(scene_values) -> bool:
    """Whether the scene ``scene_values`` traverses (mi.traverse) holds a participating
    medium (in a shape or about a sensor): FitSettings.resolved's condition."""
    import mitsuba as mi

    return any(isinstance(node, mi.Medium) for _, _, node, _ in scene_values.properties.values())


def fit(
    parameters: list[FitParameter],
    training: list[FitView],
    validation: list[FitView],
    settings: FitSettings,
    on_iteration=None,
    finish_on_interrupt: bool = False,
) -> FitResult:
    """Fit ``parameters`` to the training views; the scenes end in the best state.
    Settings left to the scene (None) are set for the training views' scenes
    (FitSettings.resolved). ``on_iteration`` sees each step's log entry and may return
    a reason to stop; ``finish_on_interrupt``: Ctrl-C ends the fit in its best state
    (loop.run)."""
    given = len(training)
    training, validation = _with_pixels(training), _with_pixels(validation)
    if given and not training:
        raise PipelineError(
            f"none of the {given} views to fit has a pixel of its mask left to compare (the masks empty, or "
            "eroded away: lower the stage's erode_px)"
        )
    if not training:
        raise PipelineError("no views to fit: every view is held out")
    traversed = _traversed(training + validation)
    settings = settings.resolved(any(renders_medium(traversed[id(v.scene)]) for v in training))
    gained = sorted(v.name for v in training) if settings.exposure or settings.white_balance else []
    variables = MaterialVariables(parameters, traversed, gained, 3 if settings.white_balance else 1, settings.whiten)
    variables.check_keys(training + validation)
    variables.register(settings.learning_rate_scale)
    result = loop.run(
        variables, training, validation, settings, on_iteration=on_iteration, finish_on_interrupt=finish_on_interrupt
    )
    textures = {n: v.astype(np.float32) for n, v in result.best.items() if v.ndim > 1}
    return FitResult(
        {n: summarize(v) for n, v in result.best.items()},
        result.best_iteration,
        result.best_error,
        result.stopped,
        result.log,
        variables.gains(),
        result.start_error,
        textures,
        result.skipped_gradients,
        result.averaged,
    )


def fit_shape(
    shape_id: str, training: list[FitView], validation: list[FitView], settings: ShapeSettings, integrator
) -> ShapeResult:
    """Vertex positions of the mesh ``shape_id`` in every view's scene, everything else
    frozen: Adam on LargeSteps' differential coordinates, L2 loss, rendered with
    ``integrator``. Only a projective integrator's gradients include silhouette
    edges; another one (``prbvolpath``) gives the interior terms alone: how the surface
    refracts, reflects and bounds the medium where it is seen."""
    import drjit as dr

    training, validation = _with_pixels(training), _with_pixels(validation)
    variables = ShapeVariables(shape_id, _traversed(training + validation), settings.step, settings.smoothing)
    with dr.scoped_set_flag(dr.JitFlag.SymbolicLoops, settings.symbolic_loops):
        result = loop.run(variables, training, validation, settings, integrator, label="shape fit")
    return ShapeResult(
        result.best["positions"],
        result.best_iteration,
        result.best_error,
        result.start_error,
        result.log,
        result.skipped_gradients,
        result.averaged,
    )


def heldout_error(validation: list[FitView], spp: int, integrator) -> float:
    """The held-out error of the views' scenes as they stand, rendered with
    ``integrator``: the dual estimator with the seeds a fit's validation uses, so it is
    comparable with the FitResult.validation_error of the same views at the same spp."""
    import drjit as dr
    import mitsuba as mi

    views = sorted(_with_pixels(validation), key=lambda v: v.name)  # in the order a fit validates them
    targets = {v.name: loop.Target.of(v, mi, dr) for v in views}
    return loop.validation_error(views, targets, spp, integrator, mi, dr)


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
        if not all(np.isfinite(result[name.strip()])):
            raise PipelineError(f"{where}: '{entry}' is not finite: give finite bounds (e.g. eta=1.3:1.6)")
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
        axis.semilogy(
            [e["iteration"] for e in validated],
            [max(e["validation_error"], 1e-12) for e in validated],
            "o-",
            label="validation error",
        )
    axis.set_xlabel("iteration")
    axis.legend()
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)


__all__ = [
    "FitParameter",
    "FitResult",
    "FitSettings",
    "FitView",
    "ShapeResult",
    "ShapeSettings",
    "fit",
    "fit_shape",
    "parse_bounds",
    "plot_loss",
    "renders_medium",
]
