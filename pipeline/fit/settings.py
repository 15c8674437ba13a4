"""The fitting loop's settings: what every fit shares (``LoopSettings``), and what a
material fit (``FitSettings``) and a shape fit (``ShapeSettings``) add. The fit
stages' config sections and `pipeline fit`'s options hold these fields."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Annotated, Literal

from pipeline.core.config import Range


@dataclass(frozen=True)
class LoopSettings:
    """How the loop runs."""

    iterations: Annotated[int, Range(1, None)] = 100
    """Most steps."""
    batch: Annotated[int, Range(1, None)] = 2
    """Views rendered per step; their gradients add up before the step."""
    spp: Annotated[int, Range(1, None)] = 16
    """Samples per pixel of each training render."""
    spp_grad: Annotated[int, Range(0, None)] = 0
    """Samples per pixel of the pass that renders the gradient (mi.render's
    ``spp_grad``); 0: ``spp``. Near the optimum most of the gradient's noise for a value
    the image is smooth in (a colour, a medium's) is the image's noise times the
    derivative, and an image sample costs less than a gradient sample: more samples in
    the image than in the gradient lower the noise per second there
    (bench/studies/gradient_samples.py)."""
    loss: Literal["l2", "dual"] = "l2"
    """l2: one render per view and its squared error; Mitsuba renders the gradient with
    independent samples, so it is that of the expected image's error, unbiased by Monte
    Carlo noise. dual: Deng et al.'s dual-buffer estimator from two renders (an unbiased
    loss value too, at twice the cost per view)."""
    image_memory: Annotated[int, Range(0, None)] = 0
    """Carry each view's image from the steps that drew it before (``loss`` l2): Nicolet et
    al.'s recursive control variate (2023). The view is rendered again at the values
    its last estimate stood for, with the new render's seed; their difference, which
    the shared samples keep nearly free of noise where the values moved little, carries
    the old estimate to the new values, and the new render weighs at least 1 /
    ``image_memory`` in the blend. The derivative (Mitsuba's adjoint pass) is weighted
    by the blend's error rather than the render's: near the answer a render's error is
    mostly its noise, and that noise times the derivative's own is most of a medium's
    gradient noise. One more render (no gradient) per view and step. The estimates
    start afresh at each level of a coarse-to-fine fit and after a resume. 0: off;
    each step's render alone."""
    validate_every: Annotated[int, Range(1, None)] = 10
    """Steps between renders of the held-out views."""
    validation_spp: Annotated[int, Range(1, None)] = 64
    """Samples per pixel of the held-out renders."""
    still_threshold: Annotated[float, Range(0.0, None)] = 2.0
    """Stop when no fitted value and not the loss trends, over the second half of the fit
    so far, by more than this many standard errors of its step-to-step noise
    (pipeline.fit.stopping); 0: never stop early (run ``iterations``)."""
    window: Annotated[int, Range(4, None)] = 40
    """Fewest steps the trend test looks at (and before which the fit does not stop
    early): a drift a few times the noise shows over about this many steps."""
    step_halvings: Annotated[int, Range(0, None)] = 0
    """Times the fit, found still, halves every learning rate and fits on before it
    stops: Adam's constant step keeps a value wandering about its optimum by about the
    step (along a flat valley, far), and each halving narrows the wander. The trend
    test and the running average (``average``) start again at each halving, so each
    step size runs at least ``window`` steps."""
    time_budget_s: Annotated[float, Range(0.0, None)] = 0.0
    """Stop after this many seconds of fitting; 0 for no limit."""
    average: bool = True
    """Keep a running average of the values over about the last half of the steps and
    end in it where the best single step came in that half and it scores on the held-out
    views within their own jitter of that step (without them: where the fit stopped
    still; pipeline.fit.loop)."""
    seed: int = 0
    """Seed of the batch order and the renders."""
    freeze: bool = True
    """Record each view's render, loss and backpropagation once (``dr.freeze``) and
    replay it on later steps instead of tracing it again: half the time of a step at
    64 px on a CPU (docs/benchmarks.md, "Fitting speed"), when a recording is replayed
    often enough to pay for itself (``freeze_min_replays``)."""
    freeze_min_replays: Annotated[int, Range(0, None)] = 30
    """Freeze only when each recording (one per view) would be replayed at least this
    many times on average (iterations x batch / training views): a recording
    costs about as much as tracing the step tens of times."""


@dataclass(frozen=True)
class FitSettings(LoopSettings):
    """How a fit of material parameters (plain values or textures) runs. The defaults
    are `pipeline fit`'s, measured on bench/fit_speed.py's suite of kits; the fit
    stages' presets set their own."""

    iterations: Annotated[int, Range(1, None)] = 400
    """Most steps (per level of a coarse-to-fine fit): a cap the trend stop
    (``still_threshold``) ends a fit before, unless the values keep drifting."""
    spp: Annotated[int, Range(1, None)] = 4
    """Samples per pixel of each training render."""
    batch: Annotated[int, Range(1, None)] = 4
    """Views rendered per step; their gradients add up before the step."""
    learning_rate_scale: Annotated[float, Range(0.0, None, exclusive_lo=True)] = 2.0
    """Multiplies every parameter's learning rate (pipeline.render.materials)."""
    whiten: bool = True
    """Decorrelate the plain values' gradients before Adam's step
    (pipeline.fit.variables.GradientWhitening), so that values that trade off along a
    diagonal valley follow it."""
    image_memory: Annotated[int | None, Range(0, None)] = None
    """Carry each view's image from the steps that drew it before, the new render
    weighing at least 1 / this (loss l2; LoopSettings.image_memory); 0: off. Unset
    (None): 10 (``MEDIUM_IMAGE_MEMORY``) where the scene renders a participating medium
    and the loss is l2, else off (``resolved``)."""
    step_halvings: Annotated[int | None, Range(0, None)] = None
    """Times the fit, found still, halves every learning rate and fits on before it
    stops (LoopSettings.step_halvings). Unset (None): 2 (``MEDIUM_STEP_HALVINGS``) where
    the unset image memory is on (a medium), else 0 (``resolved``)."""
    exposure: bool = False
    """Fit one exposure scale per photo (photos shot with automatic exposure)."""
    white_balance: bool = False
    """Fit one gain per colour channel per photo (automatic white balance, as phones
    shoot): exposure and white balance at once."""

    def resolved(self, renders_medium: bool) -> FitSettings:
        """These settings with the fields left to the scene (None) set for it: the image
        memory and halved steps where it renders a medium and the loss is one the memory
        blends (l2)."""
        medium = renders_medium and self.loss == "l2"
        image_memory = MEDIUM_IMAGE_MEMORY if medium else 0
        step_halvings = MEDIUM_STEP_HALVINGS if medium else 0
        return replace(
            self,
            image_memory=image_memory if self.image_memory is None else self.image_memory,
            step_halvings=step_halvings if self.step_halvings is None else self.step_halvings,
        )


MEDIUM_IMAGE_MEMORY = 10
"""`pipeline fit`'s image memory where the scene renders a participating medium: a
medium's gradient is mostly its render's noise times the derivative's own, which the
memory's blend lowers; with halved steps (``MEDIUM_STEP_HALVINGS``) the suite's
volumetric kits end within every target more often, for a longer wait
(docs/decisions.md, "The fitting loop's stop and schedule"). Without a medium it is
not measured to help, and it costs a render per view and step."""
MEDIUM_STEP_HALVINGS = 2
"""`pipeline fit`'s step halvings at the last level where the scene renders a
participating medium (with ``MEDIUM_IMAGE_MEMORY``): the memory lowers the gradient's
noise, and the halved steps let a value's wander about its optimum narrow with it."""


@dataclass(frozen=True)
class ShapeSettings(LoopSettings):
    """How a fit of a mesh's vertices runs (the loss is always l2)."""

    iterations: Annotated[int, Range(1, None)] = 40
    """Most steps."""
    spp: Annotated[int, Range(1, None)] = 8
    """Samples per pixel of each training render."""
    validation_spp: Annotated[int, Range(1, None)] = 32
    """Samples per pixel of the held-out renders."""
    still_threshold: Annotated[float, Range(0.0, None)] = 0.0
    """Stop when nothing trends beyond its noise (pipeline.fit.stopping); 0: never stop
    early (run ``iterations``)."""
    step: Annotated[float, Range(0.0, None, exclusive_lo=True)] = 1e-3
    """Adam step (uniform) on the differential coordinates, in world units."""
    smoothing: Annotated[float, Range(0.0, None)] = 20.0
    """LargeSteps' lambda: how far a vertex's gradient spreads over the surface."""
    freeze: bool = False
    """Replay recorded renders (``dr.freeze``): not measured on shape fits, whose
    vertices change the scene's geometry every step."""
    average: bool = False
    """Average the vertex positions of the last steps (pipeline.fit.loop.TailAverage):
    not measured on shape fits, and reading every vertex at every step costs a device
    sync."""
    symbolic_loops: bool = True
    """False renders with evaluated loops: Dr.Jit 1.5's LLVM backend cannot compile
    ``prbvolpath``'s symbolic loop once vertex positions carry gradients ("module could
    not be verified"); evaluated loops compile and give finite gradients."""
