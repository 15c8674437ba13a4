"""The pipeline's stages, one module each, listed here in DAG order.

A module joins the pipeline by defining ``STAGE`` (see pipeline.core.stage) and being
added to ``STAGES``.
"""

from pipeline.core.stage import Stage
from stages import (
    calibrate,
    cleanup,
    colour,
    export,
    fit_geometry,
    fit_material,
    fit_texture,
    masks,
    mesh,
    scene,
    sfm,
    undistort,
    uv,
)

STAGES: tuple[Stage, ...] = (
    calibrate.STAGE,
    colour.STAGE,
    undistort.STAGE,
    masks.STAGE,
    sfm.STAGE,
    mesh.STAGE,
    cleanup.STAGE,
    uv.STAGE,
    scene.STAGE,
    fit_material.STAGE,
    fit_texture.STAGE,
    fit_geometry.STAGE,
    export.STAGE,
)
