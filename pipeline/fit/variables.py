"""What a fit changes: the variables the loop (pipeline.fit.loop) steps with Adam.

Both kinds share one protocol: they hold their latents in the loop's optimiser
(``mi.ad.Adam``), write them into every view's scene (``apply``), keep them
inside their bounds after each step (``clamp``), add their priors' gradients
(``add_priors``), and give (``snapshot``) and take back (``restore``) their values
as NumPy arrays, which the loop keeps as the best state and checkpoints. They say
how a view's render is matched to its photo (``gain_channels_of``) and keep the gains
matched (``gain_estimates``).

=================  ===========================================================  ==========================
kind               latents                                                      bounds, priors
=================  ===========================================================  ==========================
MaterialVariables  one per FitParameter: the value, or its logarithm for        box per parameter;
                   positive quantities spanning decades; plain values, or a     smoothness on textures
                   texture's data tensor; optionally a gain per view (exposure,
                   or exposure and white balance: one per channel), not a
                   latent: matched in closed form at every render
ShapeVariables     a mesh's vertices as LargeSteps' differential coordinates    none (the Laplacian
                   (Nicolet et al. 2021, seams welded)                          spreads each step)
=================  ===========================================================  ==========================

Limitations: the same key must exist in every view's scene; a texture's
resolution is fixed during one fit (coarse to fine is the caller's loop).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.core.errors import PipelineError
from pipeline.render.parameters import FitParameter


def summarize(value: np.ndarray) -> list[float]:
    """A plain value as a list; a texture as its per-channel mean."""
    if value.ndim > 1:
        value = value.reshape(-1, value.shape[-1]).mean(axis=0)
    return [float(v) for v in np.ravel(value)]


def _channels(texture: np.ndarray) -> np.ndarray:
    """A texture (..., channels) as (texels, channels)."""
    return texture.reshape(-1, texture.shape[-1])


def neighbour_pairs(shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices (i, j) of every pair of texels adjacent along a spatial axis,
    channel by channel, of a C-ordered array of ``shape`` (spatial..., channels)."""
    index = np.arange(int(np.prod(shape))).reshape(shape)
    first, second = [], []
    for axis in range(len(shape) - 1):
        count = shape[axis] - 1
        first.append(np.take(index, range(count), axis=axis).ravel())
        second.append(np.take(index, range(1, count + 1), axis=axis).ravel())
    return np.concatenate(first), np.concatenate(second)


class GradientWhitening:
    """Gradients of a few plain values decorrelated by the inverse square root of their
    running second-moment matrix: full-matrix Adam's preconditioner, fed to the
    diagonal Adam that steps them.

    In units of each value's learning rate, a Monte Carlo gradient's noise near the
    optimum is about J^T Sigma J, the Gauss-Newton curvature weighted by the render
    noise. Where two values trade off along a diagonal valley (a transmission against
    the base colour it dims), the steep direction's noise fills both coordinates, and
    Adam's per-coordinate steps move along the valley by its signal over that noise:
    the fit stops still short of the answer. Whitened, each direction is stepped by its
    own signal over its own noise. Adam then sees gradients of about unit spread in
    every coordinate, so its steps keep their size, one learning rate at most.

    Limitations: the plain values only (a texture's texels are too many for a matrix);
    one eigendecomposition of a matrix of their channels per step, on the host."""

    BETA = 0.99
    """Decay of the second moment: a memory of about a hundred steps, shorter than Adam's
    own (0.999), so that the first steps' large gradients, along the steep directions,
    do not set the directions' scales for the whole fit."""
    FLOOR = 1e-6
    """Eigenvalues below this fraction of the largest are raised to it: a direction no
    gradient has shown yet is not amplified without bound."""

    def __init__(self, moment: np.ndarray | None = None, count: int = 0):
        self.moment, self.count = moment, count

    def whiten(self, gradient: np.ndarray) -> np.ndarray:
        """``gradient`` (in units of the learning rates) decorrelated; the moment updated."""
        outer = np.outer(gradient, gradient)
        self.moment = (
            (1 - self.BETA) * outer if self.moment is None else self.BETA * self.moment + (1 - self.BETA) * outer
        )
        self.count += 1
        values, vectors = np.linalg.eigh(self.moment / (1 - self.BETA**self.count))
        floor = max(values.max(), np.finfo(float).tiny) * self.FLOOR
        return vectors @ ((vectors.T @ gradient) / np.sqrt(np.maximum(values, floor)))


class MaterialVariables:
    """Scene parameters (plain values or textures), in log space where they span decades,
    and optionally a gain per training view: one (its exposure) or one per colour channel
    (exposure and white balance).

    A view's gain is not stepped by Adam: it is matched in closed form to each render of
    the view (the least-squares gain, pipeline.fit.loop.Target.matched_gain) and its
    gradient detached, which is exact for the loss minimised over the gain (variable
    projection). A latent gain would get a gradient only on the steps that draw its
    photo, a few in a fit over many photos, and stay near where it started
    (docs/decisions.md, "Photos and exposure"). The loss is thereby blind to the overall level
    and colour of the renders, which the gains trade off exactly with the light and the
    albedo; each rendered photo's own gain pulls them towards 1 (pipeline.fit.loop.LEVEL_PULL),
    so the level and colour settle at the average photo's. The gains are those of the
    scenes as they stand (render times gain matches the photo); fit_material moves
    what is left of their geometric mean into an estimated light. An earlier pull
    through the gains' mean acted on gains matched up to ``len(training) / batch``
    steps before, and Adam's steps of fixed size turned that delay into a limit cycle
    of the level and colour (docs/decisions.md, "Photos and exposure")."""

    def __init__(
        self,
        parameters: list[FitParameter],
        traversed: dict[int, Any],
        gain_views: list[str],
        gain_channels: int = 1,
        whiten: bool = False,
    ):
        import drjit as dr
        import mitsuba as mi

        self.parameters, self.traversed, self.dr, self.mi = parameters, traversed, dr, mi
        self.gain_views, self.gain_channels = gain_views, gain_channels
        self.gain_estimates: dict[str, list[float]] = {}
        """Each gained view's latest matched gain."""
        self.optimizer = mi.ad.Adam(lr=0.01)
        self.whitening = GradientWhitening() if whiten else None

    def register(self, learning_rate_scale: float) -> None:
        """The latents in the optimiser, from the first scene's values."""
        dr, optimizer = self.dr, self.optimizer
        first = next(iter(self.traversed.values()))
        self.start_means, self.mean_weights = {}, {}
        for parameter in self.parameters:
            value = first[parameter.key]
            if parameter.layout is not None:
                taken = np.ravel(np.array(value, dtype=np.float32))[list(parameter.layout.take)]
                value = self.mi.TensorXf(taken.reshape(parameter.layout.shape))
            latent = dr.log(value) if parameter.log else type(value)(value)
            # A start value read from a scene file is a literal, which Dr.Jit would bake
            # into the first renders' kernels (compiled anew for every start value).
            dr.make_opaque(latent)
            optimizer[parameter.name] = latent
            optimizer.set_learning_rate({parameter.name: parameter.learning_rate * learning_rate_scale})
            if parameter.mean_weights is not None:
                weights = np.asarray(parameter.mean_weights)
                self.start_means[parameter.name] = weights @ _channels(np.exp(np.array(latent, np.float64)))
                self.mean_weights[parameter.name] = self.mi.Float(np.repeat(weights, latent.shape[-1]))
        self.gives = {
            p.name: self.mi.UInt32(np.array(p.layout.give, np.uint32)) for p in self.parameters if p.layout is not None
        }
        self.textured = {p.name for p in self.parameters if dr.is_tensor_v(optimizer[p.name])}
        self.rates = {p.name: p.learning_rate * learning_rate_scale for p in self.parameters}
        self.priors = []
        for parameter in self.parameters:
            if parameter.smoothness > 0 and parameter.name in self.textured:
                first_index, second_index = neighbour_pairs(tuple(optimizer[parameter.name].shape))
                self.priors.append((parameter, self.mi.UInt32(first_index), self.mi.UInt32(second_index)))
        self.clamp()

    def check_keys(self, views) -> None:
        """Every parameter's key in every view's scene, or a PipelineError naming the views."""
        for parameter in self.parameters:
            missing = [v.name for v in views if parameter.key not in self.traversed[id(v.scene)]]
            if missing:
                raise PipelineError(
                    f"parameter {parameter.name}: key {parameter.key} is not in the scene of {', '.join(missing[:3])}"
                )

    def clamp(self) -> None:
        for parameter in self.parameters:
            lo, hi = (parameter.lower, parameter.upper)
            if parameter.log:
                lo, hi = np.log(lo), np.log(hi)
            self.optimizer[parameter.name] = self.dr.clip(self.optimizer[parameter.name], lo, hi)

    def latents(self) -> dict[str, Any]:
        """The optimiser's values as they stand, detached: ``apply`` renders them again
        after later steps (a Dr.Jit value is not changed by the steps that replace it)."""
        return {p.name: self.dr.detach(self.optimizer[p.name]) for p in self.parameters}

    def apply(self, scene_key: int, latents: dict[str, Any] | None = None) -> None:
        """Write the values into one scene: the optimiser's, or ``latents`` (from ``latents()``)."""
        dr, params = self.dr, self.traversed[scene_key]
        for parameter in self.parameters:
            latent = self.optimizer[parameter.name] if latents is None else latents[parameter.name]
            if parameter.mean_weights is not None:
                latent = self._channel_mean_fixed(parameter.name, latent)
            if parameter.log:
                # exp of a float32 log-bound can land a hair outside the bound; clip
                # the value, but pass the gradient straight through (a clip's gradient
                # is zero there, which would pin the parameter to its bound for good)
                value = dr.exp(latent)
                latent = value + dr.detach(dr.clip(value, parameter.lower, parameter.upper) - value)
            if parameter.layout is not None:
                spread = dr.gather(self.mi.Float, latent.array, self.gives[parameter.name])
                latent = type(params[parameter.key])(spread, params[parameter.key].shape)
            params[parameter.key] = latent
        params.update()

    def _channel_mean_fixed(self, name: str, latent):
        """``latent`` (log values, channels last) shifted so that each channel's weighted
        mean of the values is its start's."""
        dr, mi = self.dr, self.mi
        start = self.start_means[name]
        channel = dr.arange(mi.UInt32, dr.width(latent.array)) % len(start)
        sums = dr.zeros(mi.Float, len(start))
        dr.scatter_reduce(dr.ReduceOp.Add, sums, dr.exp(latent.array) * self.mean_weights[name], channel)
        shift = dr.log(mi.Float(start.astype(np.float32)) / sums)
        return type(latent)(latent.array + dr.gather(mi.Float, shift, channel), latent.shape)

    def gain_channels_of(self, view_name: str) -> int:
        """The channels of the gain a training view's render is matched to its photo by
        at each render (0: none)."""
        return self.gain_channels if view_name in self.gain_views else 0

    def record_gain(self, view_name: str, gain: np.ndarray) -> None:
        """The gain just matched to ``view_name``'s render (a gained view's)."""
        self.gain_estimates[view_name] = np.broadcast_to(gain, self.gain_channels).astype(float).tolist()

    def whiten_gradients(self) -> None:
        """The plain values' gradients decorrelated (GradientWhitening) before Adam's
        step, when there are two channels or more; textures keep theirs."""
        if self.whitening is None:
            return
        dr = self.dr
        plain = [p.name for p in self.parameters if p.name not in self.textured]
        gradients = [np.ravel(np.array(dr.grad(self.optimizer[name]), np.float64)) for name in plain]
        if sum(len(g) for g in gradients) < 2:
            return
        rates = np.concatenate([np.full(len(g), self.rates[name]) for name, g in zip(plain, gradients)])
        whitened = self.whitening.whiten(np.concatenate(gradients) * rates)
        start = 0
        for name, gradient in zip(plain, gradients):
            value = self.optimizer[name]
            part = type(value)(*[float(v) for v in whitened[start : start + len(gradient)]])
            # A literal would be baked into the step's kernels, compiled anew every step.
            dr.make_opaque(part)
            dr.set_grad(value, part)
            start += len(gradient)

    def optimiser_arrays(self) -> dict[str, np.ndarray]:
        """What a checkpoint needs beside Adam's state to resume the steps: the
        whitening's moment."""
        if self.whitening is None or self.whitening.moment is None:
            return {}
        return {"whitening/moment": self.whitening.moment, "whitening/count": np.array(self.whitening.count)}

    def restore_optimiser_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        if self.whitening is not None and "whitening/moment" in arrays:
            self.whitening = GradientWhitening(arrays["whitening/moment"], int(arrays["whitening/count"]))

    def add_priors(self) -> None:
        dr = self.dr
        for parameter, first_index, second_index in self.priors:
            texels = self.optimizer[parameter.name].array
            if parameter.log and not parameter.smooth_logarithm:
                texels = dr.exp(texels)
            difference = dr.gather(self.mi.Float, texels, first_index) - dr.gather(self.mi.Float, texels, second_index)
            dr.backward(parameter.smoothness * dr.mean(dr.square(difference)))

    def snapshot(self) -> dict[str, np.ndarray]:
        """Values as arrays: a texture (..., channels), else flat."""
        arrays = {p.name: np.array(self.optimizer[p.name], dtype=np.float64) for p in self.parameters}
        for parameter in self.parameters:
            if parameter.mean_weights is not None:
                start, latent = self.start_means[parameter.name], arrays[parameter.name]
                mean = np.asarray(parameter.mean_weights) @ _channels(np.exp(latent))
                arrays[parameter.name] = latent + np.log(start / mean)
        arrays = {n: a if n in self.textured else np.ravel(a) for n, a in arrays.items()}
        return {
            p.name: np.clip(np.exp(arrays[p.name]), p.lower, p.upper) if p.log else arrays[p.name]
            for p in self.parameters
        }

    def summary(self, values: dict[str, np.ndarray] | None = None) -> dict[str, list[float]]:
        """Each parameter's value for the log (``values``, a snapshot just taken, or the
        current ones): a texture's per-channel mean."""
        return {name: summarize(value) for name, value in (values or self.snapshot()).items()}

    def restore(self, values: dict[str, np.ndarray]) -> None:
        for parameter in self.parameters:
            value = values[parameter.name]
            latent = (np.log(value) if parameter.log else value).astype(np.float32)
            kind = type(self.optimizer[parameter.name])
            self.optimizer[parameter.name] = kind(latent) if value.ndim > 1 else kind(*[float(v) for v in latent])

    def gains(self) -> dict[str, list[float]]:
        """Each view's RGB gain (render times gain matches the photo); for a view never
        drawn, the geometric mean of the others' (1 before any)."""
        matched = np.asarray(list(self.gain_estimates.values())) if self.gain_estimates else np.ones((1, 1))
        mean = np.exp(np.mean(np.log(matched), axis=0))
        return {
            name: np.broadcast_to(np.asarray(self.gain_estimates.get(name, mean)), 3).tolist()
            for name in self.gain_views
        }


class ShapeVariables:
    """A mesh's vertex positions in every view's scene, as LargeSteps' differential
    coordinates stepped by a uniform Adam."""

    def __init__(self, shape_id: str, traversed: dict[int, Any], step: float, smoothing: float):
        import drjit as dr
        import mitsuba as mi

        self.dr, self.traversed = dr, traversed
        self.key = f"{shape_id}.vertex_positions"
        first = next(iter(traversed.values()))
        self.steps = mi.ad.LargeSteps(first[self.key], first[f"{shape_id}.faces"], smoothing)
        self.optimizer = mi.ad.Adam(lr=step, uniform=True)
        self.optimizer["u"] = self.steps.to_differential(first[self.key])
        self.mi = mi
        self.gain_estimates: dict[str, list[float]] = {}

    def clamp(self) -> None:
        pass

    def latents(self) -> dict[str, Any]:
        """The differential coordinates as they stand, detached (MaterialVariables.latents)."""
        return {"u": self.dr.detach(self.optimizer["u"])}

    def apply(self, scene_key: int, latents: dict[str, Any] | None = None) -> None:
        """Write the positions into one scene: the optimiser's, or ``latents``'."""
        coordinates = self.optimizer["u"] if latents is None else latents["u"]
        self.traversed[scene_key][self.key] = self.dr.ravel(self.steps.from_differential(coordinates))
        self.traversed[scene_key].update()

    def gain_channels_of(self, view_name: str) -> int:
        """No gains: a shape fit renders the photos as the material fit saw them."""
        return 0

    def record_gain(self, view_name: str, gain: np.ndarray) -> None:
        raise AssertionError("a shape fit matches no gains")

    def whiten_gradients(self) -> None:
        """None: LargeSteps' coordinates are the shape's preconditioning."""

    def optimiser_arrays(self) -> dict[str, np.ndarray]:
        return {}

    def restore_optimiser_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        pass

    def add_priors(self) -> None:
        pass

    def summary(self, values: dict[str, np.ndarray] | None = None) -> None:
        """Nothing per step for the log: reading every vertex would cost a device sync."""
        return None

    def gains(self) -> dict[str, list[float]]:
        """No photo gains: a shape fit renders the photos as the material fit saw them."""
        return {}

    def snapshot(self) -> dict[str, np.ndarray]:
        with self.dr.suspend_grad():
            positions = self.steps.from_differential(self.optimizer["u"])
            return {"positions": np.array(positions, dtype=np.float32).reshape(-1, 3)}

    def restore(self, values: dict[str, np.ndarray]) -> None:
        self.optimizer["u"] = self.steps.to_differential(self.mi.Float(values["positions"].ravel()))
