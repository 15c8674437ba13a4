"""``pipeline fit``: the original tool's workflow, fitting parameters of any Mitsuba
scene to one reference image per sensor."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

from pipeline.cli.options import Arg
from pipeline.cli.registry import command
from pipeline.core.config import Range
from pipeline.core.errors import ConfigError
from pipeline.fit.engine import FitSettings


@dataclass(frozen=True)
class FitOptions:
    """Fit parameters of any Mitsuba scene to reference images (the original tool)."""

    scene: Annotated[str, Arg(positional=True)]
    """Mitsuba 3 scene XML, one sensor per reference image."""
    references: Annotated[str | None, Arg(metavar="DIR")] = None
    """One image per sensor, matched by sorted file name."""
    params: Annotated[tuple[str, ...], Arg(metavar="PATTERN")] = ()
    """Regular expressions selecting mi.traverse keys, e.g. 'bsdf.roughness'."""
    list: bool = False
    """List the scene's parameter keys and exit."""
    max_size: Annotated[int, Range(0, None)] = 64
    """Fit at films of at most this many pixels along the longer side, the references
    averaged down to them (0: at the films' own size). The written scene keeps its films."""
    coarse_to_fine: bool = True
    """After max_size, fit again at twice the pixels, and so on up to the films' own
    size, each level from the last one's values with half its learning rates, until
    nothing moves beyond its noise (--no-coarse-to-fine: max_size only)."""
    settings: FitSettings = field(default_factory=FitSettings)
    """The loop's settings."""
    lr: Annotated[float | None, Range(0.0, None, exclusive_lo=True)] = None
    """One learning rate for every parameter (default: per parameter, pipeline.render.materials)."""
    bound: Annotated[tuple[str, ...], Arg(repeat=True, metavar="NAME=LO:HI")] = ()
    """Bounds of a parameter, by property name or full key (repeatable)."""
    heldout: Annotated[tuple[str, ...], Arg(repeat=True, metavar="IMAGE")] = ()
    """A reference image (file name without its suffix) to hold out: not fitted to, but
    rendered every validate_every steps, and the fit keeps the state with the lowest error
    on the held-out images (repeatable)."""
    variant: Literal["auto", "cuda_ad_rgb", "llvm_ad_rgb"] = "auto"
    """Mitsuba variant (auto: cuda_ad_rgb if it works, else llvm_ad_rgb)."""
    out: str = "fit_out"
    """Folder for the fitted scene, params.json, log.jsonl, loss.png."""


def scene_fit_request(options: FitOptions):
    """The library's request for the fit ``options`` describe (`pipeline studio` fills
    the same options from its page)."""
    from pipeline.fit.scene_fit import FilmSizes, SceneFit

    return SceneFit(
        Path(options.scene),
        Path(options.references or ""),
        options.params,
        options.settings,
        options.bound,
        options.lr,
        Path(options.out),
        options.variant,
        FilmSizes(options.max_size, options.coarse_to_fine),
        options.heldout,
    )


@command("fit", FitOptions, "fit parameters of any Mitsuba scene to reference images (the original tool)")
def fit(options: FitOptions) -> int:
    from pipeline.fit.scene_fit import fit_scene, list_keys

    if options.list:
        print("\n".join(list_keys(Path(options.scene), options.variant)))
        return 0
    if not options.references or not options.params:
        raise ConfigError("pipeline fit needs --references DIR and --params PATTERN (or --list to see the keys)")
    params_json = fit_scene(scene_fit_request(options))
    print(params_json.read_text())
    return 0
