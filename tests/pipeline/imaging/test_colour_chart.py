import numpy as np
import pytest

from pipeline.imaging.colour_chart import delta_e, exposure, find_chart, fit_correction, patch_means, reference_linear
from tests.support.colour_chart_scene import render_chart


@pytest.mark.parametrize("upside_down", [False, True], ids=["upright", "upside-down"])
def test_a_rendered_chart_gives_the_matrix_that_restores_its_reflectances(upside_down):
    photo = render_chart(upside_down=upside_down)
    photo += np.random.default_rng(0).normal(0.0, 0.001, photo.shape).astype(np.float32)  # sensor noise
    corners = find_chart(photo)
    assert corners is not None and corners.shape == (24, 4, 2)
    correction = fit_correction(patch_means(photo, corners))
    # The warm light and the sensor's mixing: far off before, even after the best exposure.
    assert correction.delta_e_before > 5
    assert correction.delta_e_after < 1.0 and correction.used == 24
    # Every patch, corrected, within a just-noticeable difference of its reflectance.
    # (The detector reads the chart's own order, whichever way up it is.)
    corrected = patch_means(correction.apply(photo), corners)
    assert delta_e(corrected, reference_linear()).max() < 2.0


def test_no_chart_is_found_where_there_is_none():
    rng = np.random.default_rng(1)
    assert find_chart(rng.uniform(0, 1, (240, 320, 3)).astype(np.float32)) is None
    assert find_chart(np.full((240, 320, 3), 0.18, np.float32)) is None


def test_clipped_patches_are_left_out_of_the_fit():
    measured = reference_linear() * 0.5
    measured[18] = [1.0, 1.0, 1.0]  # the white patch clipped
    correction = fit_correction(measured)
    assert correction.used == 23
    np.testing.assert_allclose(correction.matrix, 2 * np.eye(3), atol=1e-9)


def test_exposure_from_exif():
    assert exposure({"ExposureTime": 0.01, "Exif:ISOSpeedRatings": 200, "FNumber": 4.0}) == pytest.approx(0.125)
    assert exposure({"ExposureTime": 0.01, "FNumber": 4.0}) is None
