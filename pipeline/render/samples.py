"""Mitsuba's limit on one render: at most 2^32 Monte Carlo samples (pixels times samples
per pixel); past it ``mi.render`` raises deep inside a fit. Settings whose product could
pass it are checked here, by name, once the films are known and before they render."""

from __future__ import annotations

from pipeline.core.errors import ConfigError

MAX_SAMPLES = 2**32
"""Samples one render may take (Mitsuba 3: "exceeds 2^32 ... use fewer samples per pixel")."""


def check_samples(pixels: int, spp: int, setting: str, film: str) -> None:
    """Refuse ``spp`` samples per pixel (the setting named ``setting``) on ``pixels``
    pixels (the film ``film`` describes) when Mitsuba cannot render them at once."""
    if pixels * spp >= MAX_SAMPLES:
        raise ConfigError(
            f"{setting} = {spp} on {film} asks one render for {pixels * spp:.3g} samples, over Mitsuba's "
            f"2^32 = {MAX_SAMPLES:.3g}: lower {setting} (at most {(MAX_SAMPLES - 1) // pixels})"
        )
