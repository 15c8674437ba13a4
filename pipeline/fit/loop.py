"""The one fitting loop (Mitsuba 3, Dr.Jit, Adam) behind every fit stage and `pipeline fit`.

Per step:

1. draw ``batch`` views (a seeded permutation of the training views sorted by
   name, so the result does not depend on the order views are given in);
2. per view: write the variables (pipeline.fit.variables) into its scene, render
   once (``l2``) or twice (``dual``), match the photo's gain to the render where
   photos have their own exposure, and backpropagate the loss on linear radiance
   over the view's weight mask; the batch's gradients add up. With ``image_memory``
   the l2 error is that of the render blended with the view's earlier estimate,
   carried to the current values by one more render of the values it stood for with
   the step's seed (Nicolet et al.'s recursive control variate, 2023);
3. non-finite gradient entries are zeroed (and counted: one would turn Adam's
   state into NaN for good); the variables' priors add their gradients; one Adam
   step; the variables are clamped to their bounds;
4. every ``validate_every`` steps the held-out views are rendered with fixed seeds
   and their error (the dual estimator: plain MSE would reward parameters that
   merely render with less noise) recorded; the state with the lowest one is kept
   and the variables end in it;
5. (``average``) the values join a running average that weighs the latest steps most
   (TailAverage: about the last half of the phase).

It stops at ``iterations``, when the time budget is spent, or when nothing moves
beyond its noise any more (pipeline.fit.stopping: no fitted value and not the
training loss trends over the second half of the fit so far) and the held-out error
has stopped falling (its latest render is not the best so far); each view's loss
counts relative to its first, so that a batch of bright views does not look like a
setback. With ``step_halvings``, the first such stillness (and the next ones, as
many times) halves every learning rate instead and the fit goes on: a phase of the
fit is its steps at one step size, and the trend test and the running average see
the current phase only.

At its stop, where the best held-out score came in the last half of the phase (the
fit settled about its best, not away from it), the average is rendered on the
held-out views and replaces the best state where its error is within the held-out
scores' own jitter of the best (jitter_of). Without held-out views it replaces the
last state where the fit stopped still or its steps were halved: a fit found still
once wanders about its optimum, and more steps only narrow the wander. Adam's fixed
steps keep a value jittering about its optimum, and with momentum the jitter is a
slow wander of several steps; the best of a few noisy held-out scores picks one
point of that wander, the average its centre.

What the loop costs, and why it is written this way (docs/benchmarks.md, "Fitting
speed"): render seeds are passed as opaque Dr.Jit variables, so the kernels
compiled for the first step serve every later one (a Python integer seed is baked
into the kernel as a literal: every step compiled its kernels again, most of a
step's time); one render per view suffices for an unbiased
gradient, since Mitsuba renders the adjoint with independent samples; the losses
are read from the device once per step, not once per view.

Long fits checkpoint (pipeline.fit.checkpoint) and resume; a progress bar shows
the step, the loss, the held-out error and the time left.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, fields, replace
from typing import Any, Callable

import numpy as np

from pipeline import logger
from pipeline.core import progress
from pipeline.core.errors import PipelineError
from pipeline.core.interrupts import Interrupted, interruption, signal_name
from pipeline.fit.checkpoint import next_checkpoint
from pipeline.fit.settings import LoopSettings
from pipeline.fit.stopping import still
from pipeline.render.samples import check_samples

INTERRUPTED = "interrupted"
"""How the reason begins when Ctrl-C or SIGTERM ended a loop that finishes on them."""


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
    integrator: Any = None
    """The integrator to render with; None: the scene's own (which must then be differentiable)."""
    heldout_gain: int = 0
    """Held out, the channels of the gain its render is matched to its photo by before
    its error is scored: 0, 1 (the photo's exposure is its own) or 3 (exposure and
    white balance: phones). Nothing fitted can know a held-out photo's exposure, and
    unmatched it would outweigh every other error."""
    heldout_gain_range: tuple[float, float] | None = None
    """The range the matched gain is held in: that of the training photos' fitted gains
    (a held-out photo's exposure is one the camera also chose for them). A free gain
    would forgive the fit's overall level, which only the training photos fix; None:
    the range of the gains being fitted alongside."""
    gain: np.ndarray | None = None
    """Held out, its photo's RGB gain when known beforehand (read off the table,
    pipeline.fit.exposure): its renders are scaled by it before they are scored (instead of
    ``heldout_gain``'s match) or written. None: not known."""


@dataclass
class LoopResult:
    best: dict[str, np.ndarray]
    """The variables' values at the best held-out error (the last ones without held-out views)."""
    best_iteration: int
    best_error: float | None
    start_error: float | None
    stopped: str
    log: list[dict] = field(default_factory=list)
    skipped_gradients: int = 0
    """Non-finite gradient entries zeroed before a step."""
    averaged: bool = False
    """``best`` is the running average of the last steps (TailAverage), not one step's values."""


def seed(value: int):
    """A render seed as an opaque Dr.Jit variable: the kernels do not change with it."""
    import drjit as dr
    import mitsuba as mi

    return dr.opaque(mi.UInt32, value)


@dataclass
class Target:
    """A view's reference and pixel weights as Dr.Jit values, converted once rather
    than at every render (every pixel weighs 1 without a mask). A dataclass: Dr.Jit
    traverses it, so a frozen step replays with each view's own (the weight sum is
    opaque for the same reason: a Python number would be baked into the recording)."""

    reference: Any
    weight: Any
    weight_sum: Any

    @staticmethod
    def of(view: FitView, mi, dr) -> Target:
        weight = view.weight if view.weight is not None else np.ones(view.reference.shape[:2], np.float32)
        return Target(
            mi.TensorXf(view.reference.astype(np.float32)),
            mi.TensorXf(np.repeat(weight[..., None], 3, axis=2).astype(np.float32)),
            dr.opaque(mi.Float, float(3 * weight.sum())),
        )

    def mean(self, values, dr):
        """Mean of a per-pixel tensor over the weights."""
        return dr.sum(values * self.weight, axis=None) / self.weight_sum

    def mse(self, image, dr):
        return self.mean(dr.square(image - self.reference), dr)

    def dual(self, image, second, dr):
        """Deng et al.'s dual-buffer estimator of the squared error of the expected image."""
        return self.mean((image - self.reference) * (second - self.reference), dr)

    def matched_gain(self, image, second, channels: int, dr, detached: bool = True):
        """matched_gain on the device: the gain (one, or one per colour channel)
        minimising the weighted error of the renders (``second`` is ``image`` for l2);
        ``detached``: without a gradient."""
        if detached:
            image, second = dr.detach(image), dr.detach(second)
        axis = (0, 1) if channels == 3 else None
        numerator = dr.sum(self.weight * self.reference * (image + second), axis=axis)
        denominator = 2 * dr.sum(self.weight * image * second, axis=axis)
        return dr.select(denominator > 0, numerator / denominator, 1.0)

    def view_error(self, view: FitView, index: int, spp: int, mi, dr, integrator=None, fitted_range=None) -> float:
        """The dual estimator's error of ``view`` (this target's) rendered with fixed
        seeds (2 * index and 2 * index + 1); ``integrator`` None renders with the view's;
        ``fitted_range``: the range of the training photos' gains as they stand."""
        integrator = integrator or view.integrator
        image = mi.render(view.scene, sensor=view.sensor, integrator=integrator, spp=spp, seed=seed(2 * index))
        second = mi.render(view.scene, sensor=view.sensor, integrator=integrator, spp=spp, seed=seed(2 * index + 1))
        if view.gain is not None:
            return scaled_dual(np.array(image), np.array(second), view, view.gain)
        if view.heldout_gain:
            gain_range = view.heldout_gain_range or fitted_range or (1 / 8, 8)
            return matched_dual(np.array(image), np.array(second), view, gain_range)
        return float(self.dual(image, second, dr).array[0])


def gain_range(gains: dict[str, list[float]]) -> tuple[float, float]:
    """The smallest and largest of the photos' fitted gains (every channel)."""
    values = np.asarray(list(gains.values()), np.float64)
    return float(values.min()), float(values.max())


def matched_gain(image, second, reference, weight, channels: int, gain_range=(-np.inf, np.inf)) -> np.ndarray:
    """The gain (one, or one per colour channel: the last axis) that minimises the
    weighted dual estimator's error sum(w (g I1 - R)(g I2 - R)), g = sum(w R (I1 + I2)) /
    (2 sum(w I1 I2)) (plain least squares when I1 is I2); 1 where the renders are black;
    held within ``gain_range``."""
    axes = tuple(range(image.ndim - 1)) if channels == 3 else None
    numerator = np.atleast_1d(np.sum(weight * reference * (image + second), axis=axes))
    denominator = np.atleast_1d(2 * np.sum(weight * image * second, axis=axes))
    return np.clip(np.divide(numerator, denominator, out=np.ones_like(numerator), where=denominator > 0), *gain_range)


def matched_dual(image: np.ndarray, second: np.ndarray, view: FitView, gain_range: tuple[float, float]) -> float:
    """The dual estimator's error of two renders of ``view`` after matched_gain (of
    view.heldout_gain channels, held within ``gain_range``)."""
    weight = np.ones(view.reference.shape[:2], np.float32) if view.weight is None else view.weight
    gain = matched_gain(image, second, view.reference, weight[..., None], view.heldout_gain, gain_range)
    return scaled_dual(image, second, view, gain)


def scaled_dual(image: np.ndarray, second: np.ndarray, view: FitView, gain) -> float:
    """The dual estimator's error of two renders of ``view`` scaled by ``gain``."""
    weight = np.ones(view.reference.shape[:2], np.float32) if view.weight is None else view.weight
    weight = weight[..., None]
    error = weight * (gain * image - view.reference) * (gain * second - view.reference)
    return float(np.sum(error) / (3 * np.sum(weight)))


LEVEL_PULL = 1e-2
"""Weight of each gained photo's squared log gain (the gain matched to its render, with
its gradient) beside its loss, which the matched gain makes blind to the renders'
overall level and colour: over the photos it pulls the level to where their gains
average 1 in logarithm, the average photo's, and keeps the albedo off the flat valley
along which Adam's noise would walk it (without it a phone capture's base colour
walked to its bound of 1). The gain is the rendered photo's own, so the pull has no delay."""


@dataclass
class ViewRender:
    """What one view's step renders. A dataclass: Dr.Jit traverses it, so a frozen step
    replays with each call's own scene parameters and seeds."""

    scene: Any
    params: Any
    """mi.traverse(scene), with the fitted values applied."""
    sensor: Any
    integrator: Any
    spp: int
    spp_grad: int
    """0: spp."""
    seeds: tuple
    """Two opaque render seeds (seed): the second render's for the dual loss."""


@dataclass
class ViewComparison:
    """How one view's renders are compared with its photo (a dataclass, as ViewRender)."""

    target: Target
    gain_channels: int
    """Channels of the gain matched to the renders before the loss (Target.matched_gain):
    1 or 3; 0: none."""
    dual: bool
    """The dual-buffer loss from two renders, else l2 from one."""
    share: Any
    """The weight the gradient is backpropagated with (an opaque 1 / batch)."""
    blend: bool = False
    """l2 on the image blended with the view's earlier ones (``image_memory``), its
    blend returned for the next step that draws the view."""
    carried: CarriedImage | None = None
    """The view's earlier estimate, where it has one (``blend``)."""


@dataclass
class CarriedImage:
    """A view's image estimate from the steps that drew it before (``image_memory``),
    with what view_loss needs to carry it to this step's values (a dataclass, as
    ViewRender)."""

    previous: Any
    """The view rendered at the values ``estimate`` stands for, with this step's seed
    and without a gradient: the control variate."""
    estimate: Any
    """The blended image the view's last step ended with."""
    keep: Any
    """The carried estimate's weight in the blend (an opaque Float), one minus the new
    render's."""


@dataclass
class ImageHistory:
    """What a view's next step carries its image from (``image_memory``)."""

    estimate: Any
    latents: dict[str, Any]
    """The variables (Variables.latents) the estimate stands for."""
    renders: int
    """Renders blended into it."""


def view_loss(render: ViewRender, comparison: ViewComparison):
    """One view's loss after the renders are multiplied by the gain matched to them
    (None returned for the gain when none is), its gradient backpropagated with the
    comparison's share; with ``blend``, the blended image as well (else None). What
    changes between calls is a Dr.Jit value or holds them, so that ``dr.freeze``
    replays it correctly."""
    import drjit as dr
    import mitsuba as mi

    r, target = render, comparison.target

    def rendered(seed_value):
        return mi.render(
            r.scene, r.params, sensor=r.sensor, integrator=r.integrator, spp=r.spp, spp_grad=r.spp_grad, seed=seed_value
        )

    image = rendered(r.seeds[0])
    second = rendered(r.seeds[1]) if comparison.dual else image
    blended = None
    if comparison.blend:
        # The carried estimate moved to this step's values by the same-seed difference
        # (Nicolet et al. 2023): unbiased, and nearly noise-free where the values moved
        # little, so the blend averages the noise of the renders before.
        blended = dr.detach(image)
        carried = comparison.carried
        if carried is not None:
            carried_blend = blended - carried.keep * (carried.previous - carried.estimate)
            # a pixel that once rendered NaN would stay NaN in every later blend
            blended = dr.select(dr.isfinite(carried_blend), carried_blend, blended)
    gain, pull = None, 0.0
    if comparison.gain_channels:
        # matched with its gradient for the level's pull (this photo's gain, fresh,
        # towards 1: LEVEL_PULL), detached where it scales the renders
        attached = target.matched_gain(image, second, comparison.gain_channels, dr, detached=False)
        gain = (
            dr.detach(attached)
            if blended is None
            else target.matched_gain(blended, blended, comparison.gain_channels, dr)
        )
        pull = LEVEL_PULL * dr.mean(dr.square(dr.log(attached)))
        image, second = image * gain, second * gain
    if blended is None:
        loss = target.dual(image, second, dr) if comparison.dual else target.mse(image, dr)
        dr.backward((loss + pull) * comparison.share)
        return loss, gain, None
    # l2's gradient, 2 (I - R) dI, with the blend's error for I - R: the derivative
    # (Mitsuba's adjoint pass, its own samples) is weighted by a residual of little noise.
    residual = (blended if gain is None else blended * gain) - target.reference
    loss = target.mean(dr.square(residual), dr)
    dr.backward((2 * target.mean(residual * image, dr) + pull) * comparison.share)
    return loss, gain, blended


def view_image(render: ViewRender):
    """One render of the view without a gradient, with the first of its seeds (as
    view_loss, frozen per view)."""
    import drjit as dr
    import mitsuba as mi

    r = render
    with dr.suspend_grad():
        return mi.render(r.scene, sensor=r.sensor, integrator=r.integrator, spp=r.spp, seed=r.seeds[0])


class _Batches:
    """Views to render per step: a seeded permutation of the views (sorted by name by
    the caller), drawn ``batch`` at a time, so results do not depend on the order
    views were given in; each draw carries its own render seed (even: a second,
    independent render uses seed + 1)."""

    def __init__(self, views: list[FitView], batch: int, seed_value: int):
        self.views, self.size = views, min(batch, len(views))
        self.rng = np.random.default_rng(seed_value)
        self.order: list[int] = []

    def draw(self, iteration: int) -> list[tuple[FitView, int]]:
        batch = []
        for _ in range(self.size):
            if not self.order:
                self.order = [int(i) for i in self.rng.permutation(len(self.views))]
            index = self.order.pop()
            batch.append((self.views[index], (iteration * len(self.views) + index) * 2))
        return batch


class _Loop:
    """One run of the loop: its views, variables, targets and state."""

    def __init__(self, variables, training, validation, settings: LoopSettings, integrator, label: str):
        import drjit as dr
        import mitsuba as mi

        self.dr, self.mi = dr, mi
        self.variables, self.settings, self.integrator, self.label = variables, settings, integrator, label
        self.training = sorted(training, key=lambda v: v.name)
        self.validation = sorted(validation, key=lambda v: v.name)
        self.targets = {v.name: Target.of(v, mi, dr) for v in self.training + self.validation}
        self.batches = _Batches(self.training, settings.batch, settings.seed)
        self.share = dr.opaque(mi.Float, 1.0 / self.batches.size)
        # Frozen functions per loop: their recordings belong to this loop's scenes.
        self.frozen: dict[tuple[int, Callable], Callable] = {}
        self.skipped = 0
        if settings.image_memory and settings.loss != "l2":
            raise PipelineError(
                f"image_memory {settings.image_memory} blends l2 renders only: set loss = l2, or image_memory = 0"
            )
        self.blend = settings.image_memory > 0
        self.histories: dict[str, ImageHistory] = {}
        self.values: dict[str, np.ndarray] | None = None
        """The last step's values, where the average took them (``average``)."""
        replays = settings.iterations * self.batches.size / max(len(self.training), 1)
        if settings.freeze and replays < settings.freeze_min_replays:
            logger.info(
                "%s: %d views replayed %.0f times each at most: traced, not frozen (freeze_min_replays %d)",
                label,
                len(self.training),
                replays,
                settings.freeze_min_replays,
            )
            self.settings = replace(settings, freeze=False)

    def replayed(self, view: FitView, function: Callable, *arguments):
        """``function(*arguments)``, frozen for this view: one recording per function
        and view's sensor. Dr.Jit 1.5's dr.freeze keys a recording on the sensor object
        and on its values (measured: two sensors of identical settings, or one sensor
        whose parameters were updated between calls, each record anew), and a film size
        or crop offset is a literal in the kernels; one function for every view would
        record again at nearly every call."""
        if not self.settings.freeze:
            return function(*arguments)
        key = (id(view.sensor), function)
        if key not in self.frozen:
            self.frozen[key] = self.dr.freeze(function)
        try:
            return self.frozen[key](*arguments)
        except RuntimeError as error:
            # Dr.Jit 1.5 now and then refuses to replay a recording whose registry of
            # Mitsuba objects it miscounts ("assign_with_registry(): The number of
            # registry entries (132) did not match ... (132)!", seen once in a fit_geometry
            # material pass); it fails before running anything, so the step is traced.
            if "registry" not in str(error):
                raise
            logger.warning("%s: Dr.Jit could not replay a recording (%s); going on without freezing", self.label, error)
            self.settings = replace(self.settings, freeze=False)
            return function(*arguments)

    def view_render(self, view: FitView, render_seed: int) -> ViewRender:
        """What the view's renders at ``render_seed`` take, the values as they stand in its scene."""
        return ViewRender(
            view.scene,
            self.variables.traversed[id(view.scene)],
            view.sensor,
            self.integrator or view.integrator,
            self.settings.spp,
            self.settings.spp_grad,
            (seed(render_seed), seed(render_seed + 1)),
        )

    def step(self, iteration: int) -> list[tuple[str, Any, Any]]:
        """One step's renders, losses and backpropagation: each view's name, loss and
        matched gain (None where none is), still on the device."""
        losses = []
        for view, render_seed in self.batches.draw(iteration):
            carried = self.carried_image(view, render_seed) if self.blend else None
            self.variables.apply(id(view.scene))
            latents = self.variables.latents() if self.blend else None
            comparison = ViewComparison(
                self.targets[view.name],
                self.variables.gain_channels_of(view.name),
                self.settings.loss == "dual",
                self.share,
                self.blend,
                carried,
            )
            loss, gain, blended = self.replayed(view, view_loss, self.view_render(view, render_seed), comparison)
            if blended is not None:
                renders = self.histories[view.name].renders if view.name in self.histories else 0
                self.histories[view.name] = ImageHistory(blended, latents, renders + 1)
            losses.append((view.name, loss, gain))
        return losses

    def carried_image(self, view: FitView, render_seed: int) -> CarriedImage | None:
        """The view's last estimate and its values rendered again with this step's
        seed (``image_memory``); None before the view's first step."""
        history = self.histories.get(view.name)
        if history is None:
            return None
        dr, mi = self.dr, self.mi
        with dr.suspend_grad():
            self.variables.apply(id(view.scene), history.latents)
        previous = self.replayed(view, view_image, self.view_render(view, render_seed))
        # the running mean until the memory is full, then an exponential one
        new_weight = max(1.0 / (history.renders + 1), 1.0 / self.settings.image_memory)
        return CarriedImage(previous, history.estimate, dr.opaque(mi.Float, 1.0 - new_weight))

    def drop_non_finite_gradients(self, iteration: int) -> None:
        """Zero NaN or infinite gradient entries (counted, with a warning) before the
        step: a degenerate configuration causes them (Mitsuba's dielectric at eta = 1)."""
        dr, optimizer = self.dr, self.variables.optimizer
        for key in optimizer.keys():
            value = optimizer[key]
            gradient = dr.grad(value)
            finite = dr.isfinite(gradient)
            if not dr.all(finite, axis=None):
                self.skipped += int(np.count_nonzero(~np.isfinite(np.array(gradient))))
                dr.set_grad(value, dr.select(finite, gradient, 0))
                logger.warning("%s, step %d: non-finite gradient of %s dropped", self.label, iteration, key)

    def match_gains(self) -> None:
        """Each gained training view's gain matched again, to two renders of the state
        the scenes stand in (the one the fit returns). A gain matched during the fit is
        that of the state the step that last drew its view rendered, up to
        ``len(training) / batch`` steps before; early in a fit over many photos those
        states differ more than the photos' exposures do (docs/decisions.md, "Photos and
        exposure")."""
        dr, mi, spp = self.dr, self.mi, self.settings.spp
        with dr.suspend_grad():
            for index, view in enumerate(self.training):
                channels = self.variables.gain_channels_of(view.name)
                if not channels:
                    continue
                integrator = self.integrator or view.integrator
                image, second = (
                    mi.render(view.scene, sensor=view.sensor, integrator=integrator, spp=spp, seed=seed(s))
                    for s in (2 * index, 2 * index + 1)
                )
                gain = self.targets[view.name].matched_gain(image, second, channels, dr)
                self.variables.record_gain(view.name, np.ravel(np.array(gain, np.float64)))

    def train(self, iteration: int, state: LoopState, started: float) -> dict:
        """One step: renders, backpropagation, Adam, the bounds; its log entry."""
        variables = self.variables
        step_losses = self.step(iteration)
        variables.add_priors()
        self.drop_non_finite_gradients(iteration)
        variables.whiten_gradients()
        variables.optimizer.step()
        variables.clamp()
        # One read of the device per step: the batch's losses and gains together.
        self.dr.eval([(loss, gain) for _, loss, gain in step_losses])
        values = [float(loss.array[0]) for _, loss, _ in step_losses]
        for name, _, gain in step_losses:
            if gain is not None:
                variables.record_gain(name, np.ravel(np.array(gain, np.float64)))
        relative = 0.0
        for (name, _, _), value in zip(step_losses, values):
            # Views differ in brightness and size: the stopping rule compares each
            # view's loss with its first one.
            state.first_loss.setdefault(name, max(abs(value), 1e-12))
            relative += value / state.first_loss[name]
        state.relative_losses.append(relative / len(values))
        entry = {
            "iteration": iteration,
            "loss": float(np.mean(values)),
            "relative_loss": state.relative_losses[-1],
            "seconds": time.perf_counter() - started,
        }
        if self.settings.step_halvings:
            entry["halvings"] = state.halvings
        values = variables.snapshot() if self.settings.average else None
        if values is not None:
            state.average.add(values)
        self.values = values
        summary = variables.summary(values)
        if summary is not None:
            entry["params"] = summary
        return entry

    def finish(self, best: BestState) -> None:
        """The scenes in the best state, and the training views' gains matched to it."""
        self.variables.restore(best.values)
        with self.dr.suspend_grad():
            for scene_key in self.variables.traversed:
                self.variables.apply(scene_key)
        self.match_gains()

    def validate(self) -> float:
        with self.dr.suspend_grad():
            for scene_key in {id(view.scene) for view in self.validation}:
                self.variables.apply(scene_key)
        spp = self.settings.validation_spp
        fitted = self.variables.gains()
        fitted_range = gain_range(fitted) if fitted else None
        return validation_error(self.validation, self.targets, spp, self.integrator, self.mi, self.dr, fitted_range)


def validation_error(
    views: list[FitView], targets: dict[str, Target], spp: int, integrator, mi, dr, fitted_range=None
) -> float:
    """The mean of the views' held-out errors (the i-th view with seeds 2i and 2i + 1),
    their scenes as they stand; ``integrator`` None renders each with its own;
    ``fitted_range``: the range of the gains fitted alongside (Target.view_error)."""
    with dr.suspend_grad():
        errors = [targets[v.name].view_error(v, i, spp, mi, dr, integrator, fitted_range) for i, v in enumerate(views)]
    return float(np.mean(errors))


@dataclass
class TailAverage:
    """A running average of the fitted values that weighs step i of t by about
    (i / t)^POWER (polynomial-decay averaging, Shamir and Zhang 2013): most of its
    weight on the last half of the steps, however long the fit, in one copy of the
    values. Values are averaged as the variables give them (pipeline.fit.variables:
    snapshot), inside their bounds, so the average is too."""

    values: dict[str, np.ndarray] = field(default_factory=dict)
    count: int = 0

    POWER = 3
    """94 % of the weight on the last half of the steps; a uniform average of the whole
    fit would keep the start's values, one of its last steps the jitter."""

    def add(self, values: dict[str, np.ndarray]) -> None:
        self.count += 1
        rate = (self.POWER + 1) / (self.count + self.POWER)
        for name, value in values.items():
            kept = self.values.setdefault(name, np.array(value, np.float64))
            kept += rate * (value - kept)


@dataclass
class BestState:
    """The state the loop returns to: the variables' values at the lowest held-out error."""

    values: dict[str, np.ndarray]
    iteration: int
    error: float | None
    """Its held-out error (None without held-out views: then the last state)."""
    averaged: bool = False
    """The values are the running average's (TailAverage), not one step's."""


@dataclass
class LoopState:
    """What the loop carries from step to step, and what its checkpoint saves."""

    start_error: float | None
    """The held-out error before the first step."""
    iteration: int = 0
    seconds: float = 0.0
    """Time spent over this and earlier (resumed) runs."""
    relative_losses: list[float] = field(default_factory=list)
    """Each step's mean of its views' losses, each relative to that view's first."""
    first_loss: dict[str, float] = field(default_factory=dict)
    log: list[dict] = field(default_factory=list)
    stopped: str | None = None
    gain_estimates: dict[str, list] = field(default_factory=dict)
    """The gains matched to each view so far (pipeline.fit.variables)."""
    average: TailAverage = field(default_factory=TailAverage)
    """The running average of the values over the current phase (``average``);
    checkpointed as arrays."""
    halvings: int = 0
    """Times the learning rates were halved (``step_halvings``)."""
    phase_start: int = 0
    """Index in ``log`` of the first step at the current learning rates."""

    @property
    def phase(self) -> list[dict]:
        """The log's steps at the current learning rates."""
        return self.log[self.phase_start :]

    RECORD_KEYS = {"relative_losses": "losses"}
    """Names in the checkpoint's record that differ from the field's."""

    def record(self, best: BestState) -> dict:
        """The checkpoint's JSON record."""
        record = {self.RECORD_KEYS.get(f.name, f.name): getattr(self, f.name) for f in fields(self)}
        del record["average"]
        return record | {
            "best_iteration": best.iteration,
            "best_error": best.error,
            "best_averaged": best.averaged,
            "averaged": self.average.count,
        }

    def arrays(self, best: BestState) -> dict[str, np.ndarray]:
        """The checkpoint's arrays: the best values and the running average."""
        return {f"best/{n}": v for n, v in best.values.items()} | {
            f"average/{n}": v for n, v in self.average.values.items()
        }

    @staticmethod
    def resumed(record: dict, arrays: dict[str, np.ndarray]) -> tuple[LoopState, BestState]:
        names = {LoopState.RECORD_KEYS.get(f.name, f.name): f.name for f in fields(LoopState)}
        state = LoopState(**{names[key]: value for key, value in record.items() if key in names and key != "average"})
        state.average = TailAverage(_prefixed(arrays, "average/"), record.get("averaged", 0))
        best = BestState(_prefixed(arrays, "best/"), record["best_iteration"], record["best_error"])
        best.averaged = record.get("best_averaged", False)
        return state, best


def _prefixed(arrays: dict[str, np.ndarray], prefix: str) -> dict[str, np.ndarray]:
    return {name[len(prefix) :]: array for name, array in arrays.items() if name.startswith(prefix)}


def run(
    variables,
    training: list[FitView],
    validation: list[FitView],
    settings: LoopSettings,
    integrator=None,
    on_iteration: Callable[[dict], str | None] | None = None,
    label: str = "fit",
    finish_on_interrupt: bool = False,
) -> LoopResult:
    """Fit ``variables`` (pipeline.fit.variables, registered in their optimiser) to the
    training views; the scenes end in the best state. ``integrator`` overrides the
    views' own; ``on_iteration`` sees each step's log entry and may return a reason to
    stop (a user's Stop in the studio): the loop then ends as it would at its own stop,
    in the best state. With ``finish_on_interrupt`` (`pipeline fit`, which has no
    checkpoint to resume from), Ctrl-C or SIGTERM during the steps ends the loop the
    same way, stopped ``INTERRUPTED``; a stage's loop lets it through to the runner,
    whose checkpoint keeps the steps."""
    if not training:
        raise PipelineError("no views to fit: every view is held out")
    _check_samples(training, validation, settings, label)
    loop = _Loop(variables, training, validation, settings, integrator, label)
    checkpoint = next_checkpoint()
    state, best = _start(loop, checkpoint)
    started = time.perf_counter() - state.seconds

    def save(why: str | None) -> None:
        state.seconds, state.stopped = time.perf_counter() - started, why
        state.gain_estimates = variables.gain_estimates
        arrays = state.arrays(best) | variables.optimiser_arrays()
        checkpoint.save(variables.optimizer, arrays, state.record(best))

    def steps(advance) -> None:
        nonlocal best
        for iteration in range(state.iteration + 1, last + 1):
            entry = loop.train(iteration, state, started)
            if loop.validation and (iteration % settings.validate_every == 0 or iteration == settings.iterations):
                entry["validation_error"] = loop.validate()
                if entry["validation_error"] < best.error:
                    best = BestState(variables.snapshot(), iteration, entry["validation_error"])
            elif not loop.validation:
                # the step's snapshot where the average took one: read the device once
                best = BestState(loop.values if loop.values is not None else variables.snapshot(), iteration, None)
            state.log.append(entry)
            state.iteration = iteration
            advance(_status(entry, state.log, best))
            if checkpoint is not None:
                checkpoint.log_step(entry)
            asked = on_iteration(entry) if on_iteration is not None else None
            state.stopped = asked or _stop_reason(settings, state.phase, entry, best)
            if state.stopped and not asked and state.halvings < settings.step_halvings and not _spent(settings, entry):
                _halve_steps(variables.optimizer, label, state)
                state.stopped = None
            if state.stopped:
                return
            if checkpoint is not None and checkpoint.due():
                save(None)

    last = settings.iterations if state.stopped is None else state.iteration
    with progress.steps(last - state.iteration, label) as advance:
        try:
            steps(advance)
        except (KeyboardInterrupt, Interrupted, RuntimeError) as error:
            signal_error = interruption(error)
            if signal_error is None or not finish_on_interrupt:
                raise
            state.stopped = f"{INTERRUPTED} ({signal_name(signal_error)}) after step {state.iteration}"
            logger.warning("%s %s; it ends in its best state so far", label, state.stopped)
    state.stopped = state.stopped or "iterations"
    state.stopped = state.stopped or "iterations"
    best = _averaged(loop, state, best)
    if checkpoint is not None:
        state.iteration = len(state.log)
        save(state.stopped)
    loop.finish(best)
    logger.info(
        "%s stopped (%s) after %d steps in %.0f s; ends in %s (held-out error %s -> %s)",
        label,
        state.stopped,
        len(state.log),
        time.perf_counter() - started,
        "the average of the last steps" if best.averaged else f"step {best.iteration}",
        _number(state.start_error),
        _number(best.error),
    )
    return LoopResult(
        best.values,
        best.iteration,
        best.error,
        state.start_error,
        state.stopped,
        state.log,
        loop.skipped,
        best.averaged,
    )


def _check_samples(training: list[FitView], validation: list[FitView], settings: LoopSettings, label: str) -> None:
    """Each render the loop will make within Mitsuba's samples per render, named by the
    setting that asks for it (the views' windows are known only now)."""
    for views, asked in ((training, ("spp", "spp_grad")), (validation, ("validation_spp",))):
        if not views:
            continue
        largest = max(views, key=lambda view: int(np.prod(view.sensor.film().crop_size())))
        width, height = (int(v) for v in largest.sensor.film().crop_size())
        for name in asked:
            if getattr(settings, name):
                film = f"{largest.name}'s window of {width}x{height} px ({label})"
                check_samples(width * height, getattr(settings, name), name, film)


def _start(loop: _Loop, checkpoint) -> tuple[LoopState, BestState]:
    """A fresh state, or the checkpoint's (its views' draws replayed, so that each
    later step draws the views it would have)."""
    variables = loop.variables
    resumed = checkpoint.restore(variables.optimizer) if checkpoint is not None else None
    if resumed is None:
        start_error = loop.validate() if loop.validation else None
        return LoopState(start_error), BestState(variables.snapshot(), 0, start_error)
    state, best = LoopState.resumed(resumed.record, resumed.arrays)
    variables.restore_optimiser_arrays(resumed.arrays)
    _scale_learning_rates(variables.optimizer, 0.5**state.halvings)
    for name, gain in state.gain_estimates.items():
        variables.record_gain(name, np.asarray(gain))
    for iteration in range(1, state.iteration + 1):
        loop.batches.draw(iteration)
    return state, best


def _averaged(loop: _Loop, state: LoopState, best: BestState) -> BestState:
    """The running average as the best state where the best step is among those it
    weighs most (the last half of the phase) and it scores on the held-out views within
    their jitter of that step (jitter_of), or, without held-out views, where the values
    wander about a still point rather than drift: the fit stopped still (nothing
    trended over about the steps the average weighs) or was found still before this
    phase's step halving (``step_halvings``); else ``best``."""
    settings, average, phase = loop.settings, state.average, state.phase
    if not average.count or best.averaged:
        return best
    if not loop.validation:
        if not state.halvings and still(phase, settings.window, settings.still_threshold) is None:
            return best
        return BestState(average.values, state.iteration, None, averaged=True)
    tail = phase[len(phase) // 2 :]
    if not tail or best.iteration < tail[0]["iteration"]:
        return best  # the fit moved away from its best: its average is of worse states
    loop.variables.restore(average.values)
    error = loop.validate()
    jitter = jitter_of([e["validation_error"] for e in tail if "validation_error" in e])
    logger.info(
        "%s: held-out error of the last steps' average %.4g, of the best step %.4g (jitter %.2g)",
        loop.label,
        error,
        best.error,
        jitter,
    )
    if error <= best.error + jitter:
        return BestState(average.values, state.iteration, error, averaged=True)
    return best


def jitter_of(errors: list[float]) -> float:
    """How much held-out errors scored in turn (the last half of a fit's) move from one
    score to the next beyond a steady trend: the standard deviation from their second
    differences (x[i+1] - 2 x[i] + x[i-1] has variance 6 sigma^2 for independent
    scores, and a straight fall adds nothing); 0 for fewer than three. The held-out
    renders have fixed seeds, so this is the values' jitter as the held-out views see
    it. The best of several such scores leads the average by up to this much by the
    draw alone: where the average is within it, the best step's lead is no evidence
    (the one-standard-error rule of model selection)."""
    if len(errors) < 3:
        return 0.0
    return float(np.sqrt(np.mean(np.square(np.diff(errors, 2))) / 6))


def _stop_reason(settings: LoopSettings, phase: list[dict], entry: dict, best: BestState) -> str | None:
    # Still, but not while the held-out error keeps falling: its latest render the best
    # so far says the values are still on their way below the training loss's noise.
    validated = [e["iteration"] for e in phase if "validation_error" in e]
    falling = bool(validated) and best.iteration == validated[-1]
    if not falling and (reason := still(phase, settings.window, settings.still_threshold)) is not None:
        return reason
    if _spent(settings, entry):
        return f"time budget of {settings.time_budget_s:g} s spent"
    return None


def _spent(settings: LoopSettings, entry: dict) -> bool:
    return bool(settings.time_budget_s) and entry["seconds"] > settings.time_budget_s


def _halve_steps(optimizer, label: str, state: LoopState) -> None:
    """Every learning rate halved, and a new phase begun: the trend test and the running
    average start again from the next step."""
    _scale_learning_rates(optimizer, 0.5)
    state.halvings += 1
    state.phase_start = len(state.log)
    state.average = TailAverage()
    logger.info("%s: still at step %d; learning rates halved (%d times so far)", label, state.iteration, state.halvings)


def _scale_learning_rates(optimizer, factor: float) -> None:
    """Each parameter's learning rate (the optimiser's own where it has none) times ``factor``."""
    if factor == 1:
        return
    for key in list(optimizer.keys()):
        rate = optimizer.state[key][2]
        optimizer.set_learning_rate({key: (optimizer.lr if rate is None else rate) * factor})


def _number(value: float | None) -> str:
    return "-" if value is None else f"{value:.4g}"


def _status(entry: dict, log: list[dict], best: BestState) -> str:
    """The progress line's: this step's loss, the last held-out error and the best."""
    validation = next((e["validation_error"] for e in reversed(log) if "validation_error" in e), None)
    heldout = f", held-out {_number(validation)} (best {_number(best.error)})" if validation is not None else ""
    return f"loss {entry['loss']:.4g}{heldout}"
