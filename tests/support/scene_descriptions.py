"""A scene.json record for library tests that need only some of its fields."""

from __future__ import annotations

from pipeline.formats.scene_description import Integrator, LightStart, SceneDescription


def scene_description(**fields) -> SceneDescription:
    """A principled scene without views, ground or board, with ``fields`` in their place."""
    integrator = Integrator(type="path", max_depth=8, differentiable="prb")
    defaults = dict(
        model="principled",
        integrator=integrator,
        light_frame="world",
        near_clip=0.01,
        board_print=None,
        ground=None,
        parameters={},
        views={},
        model_choice=["principled"],
        integrators={"principled": integrator},
        light=LightStart(model="given"),
    )
    return SceneDescription(**(defaults | fields))
