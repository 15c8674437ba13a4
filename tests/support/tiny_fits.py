"""Stage settings small enough for a test: windows of 32-48 px, 4 spp, a few steps."""

TINY_FIT = (
    "fit_material.iterations=8",
    "fit_material.batch=2",
    "fit_material.spp=4",
    "fit_material.max_size=48",
    "fit_material.validate_every=4",
    "fit_material.validation_spp=8",
    "fit_material.loss=l2",
)

TINY_TEXTURE = (
    "fit_texture.levels=2",
    "fit_texture.max_resolution=32",
    "fit_texture.iterations=6",
    "fit_texture.spp=4",
    "fit_texture.max_size=48",
    "fit_texture.validate_every=3",
    "fit_texture.validation_spp=8",
    "fit_texture.loss=l2",
    "fit_texture.bake_max_size=96",
    "fit_texture.bake_spp=4",
)

TINY_GEOMETRY = (
    "fit_geometry.iterations=4",
    "fit_geometry.max_size=32",
    "fit_geometry.validate_every=4",
    "fit_geometry.validation_spp=8",
    "fit_geometry.spp=4",
    "fit_geometry.material_max_size=48",
    "fit_geometry.material_iterations=4",
    "fit_geometry.material_spp=4",
)
