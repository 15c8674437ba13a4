import json
import shutil
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

from pipeline.camera.board import BoardDetector, homography_residual_px, straightness_px
from pipeline.camera.model import Intrinsics, ideal_pinhole, undistort
from pipeline.core.errors import PipelineError
from pipeline.core.sections import BoardSection
from pipeline.formats.cameras import read_cameras
from pipeline.imaging.photo_io import gray_uint8, read_photo, write_image
from stages.calibrate import Config, calibrate_from_board, exif_focal_px

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def calibrated(run_stages, calibration_capture: Path) -> dict:
    outputs = run_stages(calibration_capture, "calibrate")["calibrate"]
    return json.loads(outputs["calibration"].read_text())["groups"][0]


def test_board_calibration_recovers_the_focal_length(calibrated, calibration_capture):
    truth, _ = read_cameras(calibration_capture / "ground_truth" / "cameras.json")
    estimate = Intrinsics.from_json(calibrated["intrinsics"])
    assert calibrated["source"] == "board" and calibrated["shots_used"] >= 6
    assert estimate.fx == pytest.approx(truth.fx, rel=0.01)
    assert estimate.fy == pytest.approx(truth.fy, rel=0.01)
    assert calibrated["rms_px"] < 0.5
    assert set(calibrated["shots"]) | set(calibrated["dropped"]) == {f"board_{i:02d}.jpg" for i in range(10)}


def test_a_rerun_gives_the_same_intrinsics_to_the_last_digit(run_stages, calibrated, calibration_capture):
    """Threaded OpenCV calibration varied the intrinsics in the 11th digit between runs."""
    first = json.dumps(calibrated, sort_keys=True)
    rerun = run_stages(calibration_capture, "calibrate", force=("calibrate",))["calibrate"]
    assert json.dumps(json.loads(rerun["calibration"].read_text())["groups"][0], sort_keys=True) == first


def test_undistorted_board_corners_are_straight(calibrated, calibration_capture):
    board = BoardSection()
    detector = BoardDetector(board, min_corners=12)
    source = Intrinsics.from_json(calibrated["intrinsics"])
    target = ideal_pinhole(source, alpha=0.0, max_size=0)
    distorted, straightened = [], []
    for shot in sorted((calibration_capture / "calibration").glob("*.jpg")):
        linear = read_photo(shot).pixels
        before, after = (
            detector.detect(gray_uint8(linear)),
            detector.detect(gray_uint8(undistort(linear, source, target))),
        )
        if before is None or after is None:
            continue
        distorted.append(homography_residual_px(before))
        straightened.append((straightness_px(after, board), homography_residual_px(after)))
    assert len(straightened) >= 5
    assert max(line for line, _ in straightened) < 0.5, straightened
    assert max(plane for _, plane in straightened) < 0.5, straightened
    assert max(distorted) > 0.5, "on the raw shots this check must fail, or it proves nothing"


def test_a_bad_shot_is_dropped_and_named(calibration_capture):
    detector = BoardDetector(BoardSection(), min_corners=8)
    detections = {}
    for shot in sorted((calibration_capture / "calibration").glob("*.jpg")):
        if (found := detector.detect(gray_uint8(read_photo(shot).pixels))) is not None:
            detections[shot.name] = found
    victim = sorted(detections)[2]
    rng = np.random.default_rng(0)
    detections[victim].image_points = detections[victim].image_points + rng.normal(
        0, 3.0, detections[victim].image_points.shape
    )
    result = calibrate_from_board(detections, (320, 240), Config())
    assert list(result.dropped) == [victim]
    assert "RMS" in result.dropped[victim]
    assert victim not in result.shot_rms_px
    assert result.rms_px < 0.5


def test_without_usable_board_shots_exif_gives_the_focal_length(run_stages, tiny_capture, tmp_path):
    capture = tmp_path / "bird"
    shutil.copytree(tiny_capture, capture, ignore=shutil.ignore_patterns(".pipeline", "output"))
    outputs = run_stages(capture, "calibrate")["calibrate"]
    group = json.loads(outputs["calibration"].read_text())["groups"][0]
    truth, _ = read_cameras(capture / "ground_truth" / "cameras.json")
    assert group["source"] == "exif" and group["refine_in_sfm"]
    assert group["intrinsics"]["fx"] == pytest.approx(truth.fx, rel=1e-3)
    assert (
        json.loads((capture / "output" / "stages" / "calibrate" / "intrinsics.json").read_text()) == group["intrinsics"]
    )


def zoom_in(capture: Path, *names: str) -> None:
    """Rewrite the photos' EXIF as if shot at twice the focal length (another camera setting)."""
    for name in names:
        photo = read_photo(capture / "images" / name)
        zoomed = {k: v for k, v in photo.metadata.items() if k.startswith(("Exif:", "Make", "Model"))}
        zoomed["Exif:FocalLength"] = 2 * float(photo.metadata["Exif:FocalLength"])
        buf = oiio.ImageBuf(str(capture / "images" / name))
        write_image(capture / "images" / name, buf.get_pixels(oiio.UINT8), zoomed)


def test_each_zoom_setting_gets_its_own_intrinsics(run_stages, tiny_capture, tmp_path):
    capture = tmp_path / "bird"
    shutil.copytree(tiny_capture, capture, ignore=shutil.ignore_patterns(".pipeline", "output"))
    zoom_in(capture, "view_004.jpg", "view_005.jpg")
    outputs = run_stages(capture, "calibrate")["calibrate"]
    groups = json.loads(outputs["calibration"].read_text())["groups"]
    assert [len(g["images"]) for g in groups] == [4, 2]
    assert groups[1]["images"] == ["view_004.jpg", "view_005.jpg"]
    assert groups[1]["intrinsics"]["fx"] == pytest.approx(2 * groups[0]["intrinsics"]["fx"], rel=1e-3)


def test_known_intrinsics_replace_board_and_exif_and_are_held(run_stages, tiny_capture, tmp_path, caplog):
    """A lab calibration of the same camera at twice the photos' resolution: halved,
    used for every photo and marked as not to be refined; the board shots go unused."""
    capture = Path(
        shutil.copytree(tiny_capture, tmp_path / "bird", ignore=shutil.ignore_patterns(".pipeline", "output"))
    )
    truth, _ = read_cameras(capture / "ground_truth" / "cameras.json")
    # Twice the resolution: pixel centres at 2 x + 0.5.
    lab = Intrinsics(
        2 * truth.width,
        2 * truth.height,
        2 * truth.fx,
        2 * truth.fy,
        2 * truth.cx + 0.5,
        2 * truth.cy + 0.5,
        truth.dist,
    )
    (capture / "lab.json").write_text(json.dumps(lab.to_json()))
    outputs = run_stages(capture, "calibrate", "calibrate.known_intrinsics='lab.json'")["calibrate"]
    (group,) = json.loads(outputs["calibration"].read_text())["groups"]
    assert group["source"] == "known" and not group["refine_in_sfm"]
    assert group["images"] == sorted(p.name for p in (capture / "images").iterdir())
    given = Intrinsics.from_json(group["intrinsics"])
    for key in ("width", "height", "fx", "fy", "cx", "cy"):
        assert getattr(given, key) == pytest.approx(getattr(truth, key), abs=1e-9), key
    assert "board shots not used" in caplog.text


def test_known_intrinsics_for_photos_of_two_camera_settings_are_refused(run_stages, tiny_capture, tmp_path):
    capture = Path(
        shutil.copytree(tiny_capture, tmp_path / "bird", ignore=shutil.ignore_patterns(".pipeline", "output"))
    )
    truth, _ = read_cameras(capture / "ground_truth" / "cameras.json")
    (capture / "lab.json").write_text(json.dumps(truth.to_json()))
    zoom_in(capture, "view_004.jpg")
    with pytest.raises(
        PipelineError, match="calibrate.known_intrinsics gives one camera, but images/ holds photos of 2"
    ):
        run_stages(capture, "calibrate", "calibrate.known_intrinsics='lab.json'")


def test_a_capture_without_photos_is_a_clear_error(run_stages, tmp_path):
    (tmp_path / "images").mkdir()
    with pytest.raises(PipelineError, match="images.*has no photos"):
        run_stages(tmp_path, "calibrate")


@pytest.mark.parametrize(
    "metadata, expected, how",
    [
        (
            {"Exif:FocalLength": 4.0, "Exif:FocalPlaneXResolution": 100.0, "Exif:FocalPlaneResolutionUnit": 4},
            400.0,
            "focal-plane",
        ),
        ({"Exif:FocalLength": 4.0}, 4.0 * 1000 / 8.0, "sensor_width_mm"),
        ({"Exif:FocalLengthIn35mmFilm": 43.27}, float(np.hypot(1000, 750)), "35 mm"),
    ],
)
def test_exif_focal_length_paths(metadata, expected, how):
    focal, description = exif_focal_px(metadata, (1000, 750), sensor_width_mm=8.0)
    assert focal == pytest.approx(expected) and how in description


def test_no_exif_means_no_exif_focal_length():
    assert exif_focal_px({}, (1000, 750), sensor_width_mm=0.0) is None
