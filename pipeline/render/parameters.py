"""What a fit may change in a scene: a parameter's key, bounds and latent layout.

These describe scene parameters (pipeline.render.materials and pipeline.render.light
name theirs with them); pipeline.fit steps them (pipeline.fit.variables).
"""

from __future__ import annotations

from dataclasses import dataclass


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
    smoothness: float = 0.0
    """Weight of the neighbour-difference prior (textures only)."""
    smooth_logarithm: bool = False
    """The prior compares the logarithms of neighbours (a ``log`` parameter's latents), not
    their values: radiance, whose bright lobes are real."""
    mean_weights: tuple[float, ...] | None = None
    """Keep each channel's weighted mean of a texture's values at its start, with one
    weight per texel (row-major, summing to 1): only how the values are spread is fitted,
    not their level. For a light, whose scale and colour trade off exactly against a
    diffuse albedo's and are measured elsewhere (pipeline.render.light). ``log``
    parameters only."""
    layout: Layout | None = None
    """How the latent maps onto the scene's value when their shapes differ; None: the same."""


@dataclass(frozen=True)
class Layout:
    """A latent of ``shape`` taken from, and spread onto, a scene value of another shape:
    an environment map's data repeats its first and last columns for wrapping, and
    those copies must stay copies."""

    shape: tuple[int, ...]
    take: tuple[int, ...]
    """Flat index in the scene's value of each latent element (where it starts from)."""
    give: tuple[int, ...]
    """Flat index in the latent of each element of the scene's value."""
