import json
import shutil

import numpy as np
import pytest

from pipeline.formats.pinhole import read_photos
from pipeline.imaging.photo_io import read_photo, write_image
from tests.support.colour_chart_scene import render_chart

pytestmark = pytest.mark.slow


@pytest.fixture
def chart_capture(tiny_capture, tmp_path):
    """The tiny capture with a rendered ColorChecker shot among its board shots."""
    capture = tmp_path / "chart"
    shutil.copytree(tiny_capture, capture, ignore=shutil.ignore_patterns(".pipeline", "output"))
    write_image(capture / "calibration" / "zz_chart.exr", render_chart())
    return capture


def test_a_chart_shot_corrects_every_photo(run_stages, chart_capture):
    corrected = run_stages(chart_capture, "undistort")
    record = json.loads(corrected["colour"]["colour"].read_text())
    assert record["shot"] == "zz_chart.exr" and record["correction"]["delta_e_after"] < 1.0
    assert record["correction"]["delta_e_before"] > 5
    matrix = np.asarray(record["correction"]["matrix"])
    plain = run_stages(chart_capture, "undistort", "colour.chart=none")
    assert json.loads(plain["colour"]["colour"].read_text())["correction"] is None
    # Undistortion is linear: the corrected copies are the matrix times the plain ones
    # (up to half-float rounding and the clip at 0).
    for name, entry in read_photos(corrected["undistort"]["pinhole"]).items():
        with_chart = read_photo(entry["linear"]).pixels
        without = read_photo(read_photos(plain["undistort"]["pinhole"])[name]["linear"]).pixels
        np.testing.assert_allclose(with_chart, np.maximum(without @ matrix.T, 0), rtol=2e-3, atol=2e-3)


def test_board_shots_alone_give_no_correction(run_stages, tiny_capture, tmp_path):
    capture = shutil.copytree(tiny_capture, tmp_path / "plain", ignore=shutil.ignore_patterns(".pipeline", "output"))
    record = json.loads(run_stages(capture, "colour")["colour"]["colour"].read_text())
    # (A board's squares can look like a chart to the detector; no matrix fits them.)
    assert record["correction"] is None and record["reason"].startswith("no ColorChecker 24 in the 3 calibration/")
