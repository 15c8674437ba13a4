"""Settings whose renders would pass Mitsuba's 2^32 samples are refused by name before
anything runs, instead of failing deep in a fit with Mitsuba's traceback."""

import pytest

from pipeline.cli.registry import registered_stages
from pipeline.core.config import load_config
from pipeline.core.errors import ConfigError
from pipeline.core.sections import schema
from pipeline.render.samples import MAX_SAMPLES, check_samples


def test_a_render_of_more_than_two_to_the_32_samples_is_refused_with_the_most_that_fits():
    check_samples(1000 * 1000, 4294, "scene.spp", "photos of 1000x1000 px")
    with pytest.raises(ConfigError, match=r"scene.spp = 4295 on photos of 1000x1000 px .*at most 4294\)"):
        check_samples(1000 * 1000, 4295, "scene.spp", "photos of 1000x1000 px")
    assert 4295 * 1000 * 1000 >= MAX_SAMPLES > 4294 * 1000 * 1000


@pytest.mark.parametrize(
    "override, message",
    [
        ("fit_material.spp=100000000", "fit_material.spp = 100000000 on films of up to fit_material.max_size"),
        ("fit_texture.bake_spp=20000", "fit_texture.bake_spp = 20000 on films of up to fit_texture.bake_max_size"),
        ("fit_geometry.material_spp=300000", "fit_geometry.material_spp = 300000 on films of up to"),
    ],
)
def test_a_fit_stages_samples_beyond_its_windows_are_a_config_error(tmp_path, override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(schema(registered_stages()), tmp_path, "standard", [override])
