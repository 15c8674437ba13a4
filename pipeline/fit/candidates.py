"""Choosing by evidence: fits of competing models (a material model, a light model, a
path depth) kept as candidates and compared on held-out error.

The rule, the same for every choice: the simplest candidate (candidates are listed
simplest first) whose held-out error is within ``margin`` (relative) of the best
one's wins, so a richer model has to earn its place by more than the noise of the
held-out estimate. Where the candidates form a ladder (opaque, principled,
volumetric), the next rung is fitted only when the last one improved on the one
before by more than the margin (``improves``).

Limitations: the held-out error is measured on a few photos (fit_material's
``held_out``), so a margin below their noise chooses by chance; candidates are fitted
on the same budget, not to convergence.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np

from pipeline.fit.engine import FitResult
from pipeline.formats.scene_description import Integrator

Choice = Literal["light", "material", "depth"]


@dataclass
class Candidate:
    """One fit: a material model with a light (None: the light given) and an integrator."""

    model: str
    """The material model."""
    light: Any
    """pipeline.render.light's EstimatedLight (``model``, ``summary()``), or None."""
    integrator: Integrator
    """What the fit rendered with."""
    result: FitResult
    held: list[str]
    """The held-out photos its error was measured on. The fit's scenes are not kept:
    Dr.Jit traces every live BSDF and emitter into each render's kernels, so a
    candidate's scenes left alive would slow and recompile the next candidate's fit."""
    seconds: float

    def name(self, of: Choice) -> str:
        """What the candidate is, as a light or material model or a path depth."""
        if of == "material":
            return self.model
        if of == "depth":
            return f"max_depth {self.integrator.max_depth}"
        return self.light.model if self.light else "given"

    def level_in_light(self) -> Candidate:
        """The candidate with its photos' gains' geometric mean (per channel) moved into
        its estimated light: the gains' logarithms then average 0, so the scene renders
        at the level of the average photo, and each render times its photo's gain is
        what it was (every emitter's radiance scales a render exactly). As it is with
        the light given (its level is the user's: the gains keep theirs) or no gains."""
        gains = self.result.photo_gains
        if self.light is None or not gains:
            return self
        mean = np.exp(np.mean(np.log(np.asarray(list(gains.values()), np.float64)), axis=0))
        centred = {name: (np.asarray(gain) / mean).tolist() for name, gain in gains.items()}
        return replace(self, light=self.light.scaled(mean), result=replace(self.result, photo_gains=centred))

    def summary(self, of: Choice) -> dict:
        return {
            "model": self.name(of),
            "validation_mse": self.result.validation_error,
            "start_validation_mse": self.result.start_validation_error,
            "seconds": round(self.seconds, 1),
        }


def choose(candidates: list[Candidate], margin: float, of: Choice) -> tuple[Candidate, str]:
    """The simplest candidate (the first) whose held-out error is within ``margin``
    (relative) of the best one's, and why."""
    errors = [c.result.validation_error for c in candidates]
    if len(candidates) == 1 or any(e is None for e in errors):
        return candidates[-1], f"the only {of} candidate fitted" if len(candidates) == 1 else "no held-out photos"
    best = min(errors)
    for candidate, error in zip(candidates, errors):
        if error <= best * (1 + margin):
            return candidate, (
                f"{candidate.name(of)}: the simplest within {margin:.0%} of the best held-out error ({best:.4g})"
            )
    raise AssertionError("the best candidate is within any margin of itself")


def improves(richer: Candidate, simpler: Candidate, margin: float) -> bool:
    """Whether ``richer``'s held-out error is lower than ``simpler``'s by more than
    ``margin`` (relative): the condition to climb to the next rung of a ladder."""
    rich, simple = richer.result.validation_error, simpler.result.validation_error
    return rich is not None and simple is not None and rich < simple / (1 + margin)
