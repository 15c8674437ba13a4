"""Known intrinsics read from calibrate's JSON and OpenCV's FileStorage, fitted to the photos."""

import json

import cv2
import numpy as np
import pytest

from pipeline.camera.model import Intrinsics
from pipeline.core.errors import PipelineError
from pipeline.formats.known_intrinsics import fitted_to, read_known_intrinsics

CAMERA = Intrinsics(1280, 960, 1400.0, 1404.0, 650.5, 470.25, [-0.12, 0.03, 0.001, -0.002, 0.004])
SETTING = "calibrate.known_intrinsics"


def write_opencv(path, K, dist, width, height):
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    storage.write("image_width", width)
    storage.write("image_height", height)
    storage.write("camera_matrix", np.asarray(K, float))
    storage.write("distortion_coefficients", np.asarray(dist, float).reshape(-1, 1))
    storage.release()
    return path


def test_calibrates_own_intrinsics_json_reads_back_unchanged(tmp_path):
    path = tmp_path / "intrinsics.json"
    path.write_text(json.dumps(CAMERA.to_json()))
    assert read_known_intrinsics(path, SETTING) == CAMERA


def test_json_without_distortion_means_none(tmp_path):
    path = tmp_path / "k.json"
    path.write_text(json.dumps({"width": 640, "height": 480, "fx": 900, "fy": 900, "cx": 320, "cy": 240}))
    assert read_known_intrinsics(path, SETTING).dist == [0.0] * 5


@pytest.mark.parametrize("suffix", [".yml", ".xml"])
def test_opencv_calibration_files_are_read(tmp_path, suffix):
    path = write_opencv(tmp_path / f"camera{suffix}", CAMERA.K, CAMERA.dist, CAMERA.width, CAMERA.height)
    assert read_known_intrinsics(path, SETTING) == CAMERA


def test_four_coefficients_leave_k3_zero(tmp_path):
    path = write_opencv(tmp_path / "camera.yml", CAMERA.K, CAMERA.dist[:4], CAMERA.width, CAMERA.height)
    assert read_known_intrinsics(path, SETTING).dist == [*CAMERA.dist[:4], 0.0]


def test_rational_distortion_is_refused(tmp_path):
    path = write_opencv(tmp_path / "camera.yml", CAMERA.K, [*CAMERA.dist, 0.1, 0.0, 0.0], CAMERA.width, CAMERA.height)
    with pytest.raises(PipelineError, match="8 distortion coefficients"):
        read_known_intrinsics(path, SETTING)


@pytest.mark.parametrize(
    "content, message",
    [
        ({"width": 640, "height": 480, "fx": 900}, "lacks fy, cx, cy"),
        ({"width": 640, "height": 480, "fx": "wide", "fy": 900, "cx": 320, "cy": 240}, "not a number"),
        ({"width": 640, "height": 480, "fx": -900, "fy": 900, "cx": 320, "cy": 240}, "positive"),
        ([1, 2, 3], "lacks width"),
    ],
)
def test_a_bad_json_file_names_the_setting_and_what_is_wrong(tmp_path, content, message):
    path = tmp_path / "k.json"
    path.write_text(json.dumps(content))
    with pytest.raises(PipelineError, match=f"{SETTING}: .*{message}"):
        read_known_intrinsics(path, SETTING)


def test_a_missing_or_unknown_file_is_a_clear_error(tmp_path):
    with pytest.raises(PipelineError, match="is not a file"):
        read_known_intrinsics(tmp_path / "absent.json", SETTING)
    (tmp_path / "camera.txt").write_text("fx 900")
    with pytest.raises(PipelineError, match="neither .json nor an OpenCV file"):
        read_known_intrinsics(tmp_path / "camera.txt", SETTING)
    (tmp_path / "broken.yml").write_text("%YAML:1.0\nimage_width: 640\n")
    with pytest.raises(PipelineError, match="lacks camera_matrix"):
        read_known_intrinsics(tmp_path / "broken.yml", SETTING)


def test_a_calibration_at_twice_the_resolution_is_halved_for_the_photos(tmp_path):
    half = fitted_to(CAMERA, (640, 480), tmp_path / "k.json", SETTING)
    assert (half.width, half.height) == (640, 480)
    assert half.fx == pytest.approx(CAMERA.fx / 2) and half.fy == pytest.approx(CAMERA.fy / 2)
    # pixel centres stay pixel centres: x_half = (x + 0.5) / 2 - 0.5
    assert half.cx == pytest.approx((CAMERA.cx + 0.5) / 2 - 0.5)
    assert half.dist == CAMERA.dist
    assert fitted_to(CAMERA, (1280, 960), tmp_path / "k.json", SETTING) is CAMERA


@pytest.mark.parametrize("size", [(960, 1280), (1280, 720), (641, 480)])
def test_another_frame_is_refused(tmp_path, size):
    with pytest.raises(PipelineError, match=f"{SETTING}: .*is for 1280x960 images, but the photos are"):
        fitted_to(CAMERA, size, tmp_path / "k.json", SETTING)
