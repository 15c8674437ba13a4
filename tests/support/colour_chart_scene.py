"""A ColorChecker 24 rendered by Mitsuba: the chart's reference reflectances on a
tilted card, lit by a warm directional light, seen by a camera whose channels mix
(a sensor's primaries are not sRGB's). The colour correction must undo both."""

from __future__ import annotations

import numpy as np

from pipeline.imaging.colour_chart import reference_linear

SENSOR_MIX = np.array([[0.82, 0.14, 0.04], [0.10, 0.80, 0.10], [0.04, 0.22, 0.74]])
"""Rows: what the camera's R, G, B record of linear sRGB's R, G, B."""
LIGHT = (1.0, 0.78, 0.5)
"""The light's colour (a warm, tungsten-like cast)."""


def chart_reflectance(patch: int = 40, gap: int = 10, border: int = 20) -> np.ndarray:
    """The chart as a linear reflectance image: 6 x 4 patches on a black card."""
    width, height = 2 * border + 6 * patch + 5 * gap, 2 * border + 4 * patch + 3 * gap
    card = np.full((height, width, 3), 0.03, np.float32)
    for i, colour in enumerate(reference_linear()):
        row, column = divmod(i, 6)
        y, x = border + row * (patch + gap), border + column * (patch + gap)
        card[y : y + patch, x : x + patch] = colour
    return card


def render_chart(width: int = 320, height: int = 240, spp: int = 16, upside_down: bool = False) -> np.ndarray:
    """Linear camera RGB of the lit chart, (height, width, 3)."""
    import mitsuba as mi

    from pipeline.render.mitsuba_variant import activate

    activate()
    card = chart_reflectance()
    aspect = card.shape[1] / card.shape[0]
    turn = mi.ScalarTransform4f.rotate([0, 0, 1], 180 if upside_down else 0)
    scene = mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "direct"},
            "sensor": {
                "type": "perspective",
                "fov": 45,
                "to_world": mi.ScalarTransform4f.look_at(origin=[0.25, -0.35, 2.4], target=[0, 0, 0], up=[0, 1, 0]),
                "film": {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"}},
                "sampler": {"type": "independent", "sample_count": spp},
            },
            "chart": {
                "type": "rectangle",
                "to_world": turn @ mi.ScalarTransform4f.scale([0.5 * aspect, 0.5, 1.0]),
                "bsdf": {
                    "type": "diffuse",
                    "reflectance": {
                        "type": "bitmap",
                        "bitmap": mi.Bitmap(np.flipud(card).copy(), pixel_format=mi.Bitmap.PixelFormat.RGB),
                        "raw": True,
                        "filter_type": "nearest",
                    },
                },
            },
            "light": {
                "type": "directional",
                "direction": [0.1, 0.2, -1.0],
                "irradiance": {"type": "rgb", "value": LIGHT},
            },
        }
    )
    linear = np.asarray(mi.render(scene, seed=1), dtype=np.float32)
    return (linear @ SENSOR_MIX.T).astype(np.float32)
