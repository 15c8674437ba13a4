"""pipeline.fit.levenberg_marquardt through engine.fit (optimizer = levenberg_marquardt)
on test_engine's tiny scene: a sphere under a sky and a softbox, three 40x30 sensors."""

import xml.etree.ElementTree as ET

import numpy as np
import pytest

from pipeline.core.errors import PipelineError
from pipeline.fit import engine
from tests.pipeline.fit.test_engine import PARAMETERS, TRUTH, _scene_file, _views, references  # noqa: F401

pytestmark = pytest.mark.slow
SETTINGS = engine.FitSettings(optimizer="levenberg_marquardt", iterations=12, batch=3, spp=8, still_threshold=0.0)


def test_steps_reach_the_truth_in_a_few_iterations_within_bounds(mi, references, tmp_path):  # noqa: F811
    """From the middle of the ranges, a dozen damped Gauss-Newton steps bring every
    value near the truth (Adam at the same spp needs about 40 to halve the errors:
    test_engine), and every logged value stays inside its bounds."""
    start = {"base_color": [0.5, 0.5, 0.5], "roughness": [0.7]}
    views = _views(mi, _scene_file(tmp_path, start["base_color"], start["roughness"]), references / "references")
    result = engine.fit(PARAMETERS, views, [], SETTINGS)
    np.testing.assert_allclose(result.values["base_color"], TRUTH["base_color"], atol=0.03)
    np.testing.assert_allclose(result.values["roughness"], TRUTH["roughness"], atol=0.05)
    for entry in result.log:
        assert all(0.0 <= v <= 1.0 for v in entry["params"]["base_color"])
        assert 0.001 <= entry["params"]["roughness"][0] <= 1.0
        assert entry["damping"] > 0


def test_at_the_truth_the_damping_rises_until_the_fit_stops(mi, references, tmp_path):  # noqa: F811
    """Started at the truth, no step beats the noise: steps are rejected, lambda grows
    and the fit stops by itself, long before its iterations, still at the truth."""
    views = _views(mi, _scene_file(tmp_path, TRUTH["base_color"], TRUTH["roughness"]), references / "references")
    settings = engine.FitSettings(optimizer="levenberg_marquardt", iterations=200, batch=3, spp=4, still_threshold=0.0)
    result = engine.fit(PARAMETERS, views, [], settings)
    assert "damping reached" in result.stopped and len(result.log) < 200
    np.testing.assert_allclose(result.values["base_color"], TRUTH["base_color"], atol=0.03)
    np.testing.assert_allclose(result.values["roughness"], TRUTH["roughness"], atol=0.05)


def test_a_value_mitsuba_does_not_differentiate_forward_is_refused(mi, references, tmp_path):  # noqa: F811
    """The principled BSDF's specular derives its index of refraction when the
    parameters change, which loses the forward tangent: an error that names it and
    says to use Adam, not a fit that never moves it."""
    path = _scene_file(tmp_path, [0.5, 0.5, 0.5], [0.7])
    tree = ET.parse(path)
    ET.SubElement(tree.find(".//bsdf"), "float", {"name": "specular", "value": "0.5"})
    tree.write(path)
    specular = engine.FitParameter("specular", "specimen.bsdf.specular", 0.0, 1.0, learning_rate=0.05)
    with pytest.raises(PipelineError, match="specimen.bsdf.specular.*optimizer = adam"):
        engine.fit([specular], _views(mi, path, references / "references"), [], SETTINGS)


def test_a_medium_is_refused(mi, tmp_path):
    """prbvolpath renders no forward-mode derivatives: an error naming Adam."""
    from pipeline.fit import stability
    from pipeline.render import materials

    scene = mi.load_file(str(stability.sphere_scene(tmp_path, "volumetric", 16, 4)))
    reference = np.zeros((12, 16, 3), np.float32)
    views = [engine.FitView(f"view{i}", scene, s, reference) for i, s in enumerate(scene.sensors())]
    with pytest.raises(PipelineError, match="no forward-mode derivatives.*optimizer = adam"):
        engine.fit(materials.fit_parameters("volumetric"), views, [], SETTINGS)
