"""Renders past Mitsuba's 2^32 samples are refused by the setting that asks for them,
before they run, instead of failing deep in a fit with Mitsuba's traceback."""

import numpy as np
import pytest

from pipeline.cli import main
from pipeline.core.errors import ConfigError
from pipeline.render.samples import MAX_SAMPLES, check_samples
from tests.support.studio_kit import write_kit


def test_a_render_of_more_than_two_to_the_32_samples_is_refused_with_the_most_that_fits():
    check_samples(1000 * 1000, 4294, "scene.spp", "photos of 1000x1000 px")
    with pytest.raises(ConfigError, match=r"scene.spp = 4295 on photos of 1000x1000 px .*at most 4294\)"):
        check_samples(1000 * 1000, 4295, "scene.spp", "photos of 1000x1000 px")
    assert 4295 * 1000 * 1000 >= MAX_SAMPLES > 4294 * 1000 * 1000


def test_a_fits_samples_per_pixel_beyond_its_windows_are_refused_by_name_before_a_step(mi, tmp_path, capsys):
    from pipeline.fit import engine
    from pipeline.fit.engine import FitParameter, FitSettings, FitView

    scene_path, references = write_kit(tmp_path / "kit")
    assert (
        main(
            [
                "fit",
                str(scene_path),
                "--references",
                str(references),
                "--params",
                "roughness",
                "--validation-spp",
                "10000000",
                "--heldout",
                "1_side",
                "--out",
                str(tmp_path / "out"),
            ]
        )
        == 2
    )
    assert "--validation-spp = 10000000 on 0_front's film of 32x32 px" in capsys.readouterr().err
    scene = mi.load_file(str(scene_path))
    views = [FitView(f"v{i}", scene, sensor, np.zeros((32, 32, 3))) for i, sensor in enumerate(scene.sensors())]
    roughness = FitParameter("mat.roughness.value", "mat.roughness.value", 0.01, 1.0, False, 0.02)
    with pytest.raises(ConfigError, match=r"^spp = 5000000 on v0's window of 32x32 px \(fit\)"):
        engine.fit([roughness], views, [], FitSettings(spp=5_000_000, iterations=1))
