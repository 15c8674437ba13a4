"""Mitsuba's limit on one render: at most 2^32 Monte Carlo samples (pixels times samples
per pixel); past it ``mi.render`` raises deep inside a fit. Settings whose product could
pass it are checked here, by name, before the render: in a section's validation where
the film's size is a setting too, else where the film is known."""

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


def check_window_samples(section: str, settings, pairs: tuple[tuple[str, str], ...]) -> None:
    """For a config section: each (samples-per-pixel field, film-size field) pair of
    ``settings`` within the limit at the largest square film the size allows."""
    for spp_field, size_field in pairs:
        size = getattr(settings, size_field)
        spp = getattr(settings, spp_field)
        if size and spp:
            check_samples(
                size * size, spp, f"{section}.{spp_field}", f"films of up to {section}.{size_field} = {size} px"
            )
