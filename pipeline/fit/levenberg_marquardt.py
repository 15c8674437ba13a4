"""Levenberg-Marquardt steps for a handful of plain values, with Jacobians by forward mode.

The loop (pipeline.fit.loop) steps a fit's variables with Adam unless
``FitSettings.optimizer`` is ``levenberg_marquardt``. Each step then, for every view of
the batch:

1. renders the view at the current values (seed s) and matches the photo's gain to it
   where photos have their own exposure (detached, as Adam's loss does): the residual
   r = w (g I - R) over the view's pixel weights w;
2. renders it once more per latent channel (seed s + 1, independent of the residual's
   samples, so that the products J^T r are unbiased) and propagates that channel's unit
   tangent forward through the render (``dr.forward``): one column g dI/dtheta of the
   Jacobian J per pass;
3. adds J^T W J and J^T W r, each view weighted as the loss weighs it.

The step solves (J^T W J + lambda diag(J^T W J)) delta = -J^T W r in the latents (the
logarithm of values spanning decades), clamps to the bounds, and renders the batch
again at the new values with the very seeds of step 1 (common random numbers: the
comparison sees the change of the values, not that of the samples). A lower loss keeps
the step and divides lambda by ``DAMPING_DOWN``; a higher one rejects it and multiplies
lambda by ``DAMPING_UP``. Far from the answer lambda falls and the steps are Gauss-Newton's;
where the Monte Carlo noise outweighs what is left to gain, steps are rejected, lambda
grows and the steps shrink towards gradient steps of vanishing length (the damping
averages the noise away that Adam's fixed step would keep walking on), and once lambda
reaches the top of ``DAMPING_RANGE`` the fit stops: no step lowers the loss beyond its
noise.

One step costs (2 + channels) renders per view (a base colour and three scalars: 8),
against Adam's render and backward pass; the few steps it needs far from the answer are
what it buys (docs/benchmarks.md, "Fitting speed").

Limitations: plain values only (a texture's thousands of texels would need as many
passes: those are Adam's); only what Mitsuba 3.9 differentiates forward: not through a
medium (``prbvolpath`` refuses forward mode), and not the principled BSDF's ``specular``
(its derived index of refraction loses the tangent): a fit of either stops with an error
that says so; no dual-buffer loss (the residual is l2's); no dr.freeze; a resumed fit
restarts lambda at ``damping``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.core.errors import PipelineError

DAMPING_DOWN = 3.0
"""lambda is divided by this after a kept step."""
DAMPING_UP = 4.0
"""lambda is multiplied by this after a rejected step."""
DAMPING_RANGE = (1e-6, 1e4)
"""lambda is held within these; at the upper one a step is a ten-thousandth of Gauss-Newton's
and the fit has settled (``settled``)."""


class LevenbergMarquardt:
    """The damped Gauss-Newton steps of one fit (see the module docstring)."""

    def __init__(self, variables, damping: float):
        self.variables, self.damping = variables, damping
        self.channels = variables.latent_channels()
        self.checked = False
        """Whether the first view's Jacobian has shown every column to be nonzero."""

    def settled(self) -> str | None:
        """Why the fit may stop (lambda at its upper bound), or None."""
        if self.damping < DAMPING_RANGE[1]:
            return None
        return f"Levenberg-Marquardt's damping reached {DAMPING_RANGE[1]:g}: no step lowers the loss beyond its noise"

    def step(self, loop, iteration: int) -> list[tuple[str, float, Any]]:
        """One step on the batch ``loop`` draws for ``iteration``: each view's name, loss
        at the values the step started from, and matched gain (None where none is)."""
        dr = loop.dr
        batch = loop.batches.draw(iteration)
        normal, gradient, losses = np.zeros((len(self.channels),) * 2), np.zeros(len(self.channels)), []
        for view, render_seed in batch:
            residual, gain, loss = self._residual(loop, view, render_seed)
            columns = self._jacobian(loop, view, render_seed + 1, gain)
            target = loop.targets[view.name]
            weight = np.array(target.weight, np.float64).ravel() / float(target.weight_sum.array[0])
            normal += columns.T @ (weight[:, None] * columns)
            gradient += columns.T @ (weight * residual)
            losses.append((view.name, loss, gain))
        start = self.variables.latents()
        solved = self._solve(normal, gradient)
        if solved is None:
            self.damping = min(self.damping * DAMPING_UP, DAMPING_RANGE[1])
            return losses
        self.variables.set_latents(start + solved)
        with dr.suspend_grad():
            trial = sum(self._residual(loop, view, render_seed)[2] for view, render_seed in batch)
        if trial < sum(loss for _, loss, _ in losses):
            self.damping = max(self.damping / DAMPING_DOWN, DAMPING_RANGE[0])
        else:
            self.variables.set_latents(start)
            self.damping = min(self.damping * DAMPING_UP, DAMPING_RANGE[1])
        return losses

    def _solve(self, normal: np.ndarray, gradient: np.ndarray) -> np.ndarray | None:
        """The damped step, or None where the system has no finite solution."""
        damped = normal + self.damping * np.diag(np.maximum(np.diag(normal), 1e-12 * max(np.trace(normal), 1e-30)))
        if not (np.all(np.isfinite(damped)) and np.all(np.isfinite(gradient))):
            return None
        try:
            step = np.linalg.solve(damped, -gradient)
        except np.linalg.LinAlgError:
            return None
        return step if np.all(np.isfinite(step)) else None

    @staticmethod
    def _integrator(loop, view):
        """The loop's integrator, else the view's, else its scene's own."""
        return loop.integrator or view.integrator or view.scene.integrator()

    def _render(self, loop, view, render_seed: int):
        from pipeline.fit.loop import seed

        params = self.variables.traversed[id(view.scene)]
        return loop.mi.render(
            view.scene,
            params,
            sensor=view.sensor,
            integrator=self._integrator(loop, view),
            spp=loop.settings.spp,
            seed=seed(render_seed),
        )

    def _residual(self, loop, view, render_seed: int) -> tuple[np.ndarray, Any, float]:
        """The view's weighted residual's values (flat), its matched gain (None without
        one) and its loss, at the variables' current values."""
        dr = loop.dr
        with dr.suspend_grad():
            self.variables.apply(id(view.scene))
            image = self._render(loop, view, render_seed)
            target = loop.targets[view.name]
            gain = None
            if channels := self.variables.gain_channels_of(view.name):
                gain = target.matched_gain(image, image, channels, dr)
                image = image * gain
            difference = image - target.reference
            loss = target.mse(image, dr)
            dr.eval(difference, loss, gain)
        return np.array(difference, np.float64).ravel(), gain, float(loss.array[0])

    def _jacobian(self, loop, view, render_seed: int, gain) -> np.ndarray:
        """(pixels x channels) the render's derivative with respect to each latent channel,
        times the view's gain. The tangent starts at the scene's value (d value / d latent:
        the value itself for a logarithm, else 1): Mitsuba's forward pass through a render
        takes only tangents of the scene's own parameters."""
        dr = loop.dr
        # by name: Mitsuba registers the plugin's class from a module of its own
        if type(self._integrator(loop, view)).__name__ == "PRBVolpathIntegrator":
            raise PipelineError("prbvolpath renders no forward-mode derivatives: fit this scene with optimizer = adam")
        with dr.suspend_grad():
            self.variables.apply(id(view.scene))
        params = self.variables.traversed[id(view.scene)]
        parameters = {p.name: p for p in self.variables.parameters}
        columns = []
        for name, channel in self.channels:
            parameter = parameters[name]
            value = params[parameter.key]
            leaf = type(value)(dr.detach(value))
            dr.enable_grad(leaf)
            params[parameter.key] = leaf
            params.update()
            image = self._render(loop, view, render_seed)
            tangent = [0.0] * len(np.ravel(np.array(value)))
            tangent[channel] = float(np.ravel(np.array(value))[channel]) if parameter.log else 1.0
            dr.set_grad(leaf, type(leaf)(*tangent))
            dr.enqueue(dr.ADMode.Forward, leaf)
            dr.traverse(dr.ADMode.Forward)
            derivative = dr.grad(image) if gain is None else dr.grad(image) * gain
            columns.append(np.array(derivative, np.float64).ravel())
            if not self.checked and not np.any(columns[-1]):
                raise PipelineError(
                    f"{parameter.key}: Mitsuba gives no forward-mode derivative of it (a value the BSDF derives "
                    "others from when its parameters change): fit it with optimizer = adam"
                )
            params[parameter.key] = dr.detach(leaf)
            params.update()
        self.checked = True
        return np.stack(columns, axis=1)


__all__ = ["LevenbergMarquardt"]
