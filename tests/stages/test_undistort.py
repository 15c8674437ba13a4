import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.camera.model import Intrinsics
from pipeline.formats.pinhole import read_photos
from pipeline.imaging.photo_io import read_photo, srgb_decode, srgb_encode, write_image

pytestmark = pytest.mark.slow


@pytest.fixture
def gradient() -> np.ndarray:
    """Linear RGB with distinct rows, columns and channels, 40x30."""
    y, x = np.mgrid[0:30, 0:40]
    return np.stack([x / 39, y / 29, 0.25 + 0 * x], axis=-1).astype(np.float32)


def _write_tiff16(path: Path, linear: np.ndarray) -> None:
    import OpenImageIO as oiio

    encoded = np.round(srgb_encode(linear) * 65535).astype(np.uint16)
    spec = oiio.ImageSpec(linear.shape[1], linear.shape[0], 3, oiio.UINT16)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(encoded) and out.close()


def test_every_format_reads_as_the_same_linear_radiance(gradient, tmp_path):
    write_image(tmp_path / "a.png", np.round(srgb_encode(gradient) * 255).astype(np.uint8))
    _write_tiff16(tmp_path / "a.tif", gradient)
    write_image(tmp_path / "a.exr", gradient)
    png, tiff, exr = (read_photo(tmp_path / f"a.{ext}") for ext in ("png", "tif", "exr"))
    assert (png.encoding, tiff.encoding, exr.encoding) == ("srgb", "srgb", "linear")
    assert (png.bits, tiff.bits, exr.bits) == (8, 16, 16)
    np.testing.assert_allclose(tiff.pixels, gradient, atol=1e-4)
    np.testing.assert_allclose(exr.pixels, gradient, atol=1e-3)  # half float
    np.testing.assert_allclose(png.pixels, gradient, atol=5e-3)  # 8-bit steps


def test_exif_orientation_is_applied(gradient, tmp_path):
    # Orientation 6: the camera was turned clockwise; the viewer rotates 90 degrees clockwise.
    write_image(tmp_path / "turned.tif", np.round(srgb_encode(gradient) * 255).astype(np.uint8), {"Orientation": 6})
    photo = read_photo(tmp_path / "turned.tif")
    assert photo.size == (30, 40)
    upright = np.rot90(gradient, k=-1)
    np.testing.assert_allclose(photo.pixels, upright, atol=5e-3)


def test_linear_copies_decode_the_srgb_copies(run_stages, tiny_capture, tmp_path):
    capture = tmp_path / "bird"
    shutil.copytree(tiny_capture, capture, ignore=shutil.ignore_patterns(".pipeline", "output"))
    outputs = run_stages(capture, "undistort")["undistort"]
    photos = read_photos(outputs["pinhole"])
    assert sorted(photos) == sorted(p.name for p in (capture / "images").glob("*.jpg"))
    for entry in photos.values():
        srgb, linear = read_photo(entry["srgb"]), read_photo(entry["linear"])
        assert srgb.size == linear.size == (96, 72)
        np.testing.assert_allclose(
            linear.pixels, srgb_decode(np.round(srgb_encode(linear.pixels) * 255) / 255), atol=2e-3
        )


def test_working_resolution_scales_the_camera(run_stages, tiny_capture, tmp_path):
    capture = tmp_path / "bird"
    shutil.copytree(tiny_capture, capture, ignore=shutil.ignore_patterns(".pipeline", "output"))
    outputs = run_stages(capture, "undistort", "undistort.max_size=48")["undistort"]
    listing = json.loads(outputs["pinhole"].read_text())
    source, target = (Intrinsics.from_json(listing["cameras"][0][k]) for k in ("source", "intrinsics"))
    assert (target.width, target.height) == (48, 36)
    assert target.fx == pytest.approx(source.fx / 2, rel=0.02)  # alpha=0 crops a little
    assert target.dist == [0.0] * 5
    for entry in read_photos(outputs["pinhole"]).values():
        assert read_photo(entry["linear"]).size == (48, 36)


def _copy_capture(tiny_capture, folder):
    shutil.copytree(tiny_capture, folder, ignore=shutil.ignore_patterns(".pipeline", "output"))
    return folder


def test_copies_of_one_photo_are_refused_with_the_fix(run_stages, tiny_capture, tmp_path):
    from pipeline.core.errors import PipelineError

    capture = _copy_capture(tiny_capture, tmp_path / "copies")
    photos = sorted((capture / "images").iterdir())
    for photo in photos[1:]:
        shutil.copy(photos[0], photo)
    with pytest.raises(PipelineError, match=r"holds 6 photo\(s\) but only 1 different one\(s\).*at least 3 photos"):
        run_stages(capture, "undistort")


def test_a_single_photo_is_refused_with_the_fix(run_stages, tiny_capture, tmp_path):
    from pipeline.core.errors import PipelineError

    capture = _copy_capture(tiny_capture, tmp_path / "single")
    for photo in sorted((capture / "images").iterdir())[1:]:
        photo.unlink()
    with pytest.raises(PipelineError, match=r"holds 1 photo\(s\).*at least 3 photos"):
        run_stages(capture, "undistort")


def test_an_unreadable_photo_is_named(run_stages, tiny_capture, tmp_path):
    from pipeline.core.errors import PipelineError

    capture = _copy_capture(tiny_capture, tmp_path / "unreadable")
    photo = sorted((capture / "images").iterdir())[2]
    photo.write_bytes(photo.read_bytes()[:200])  # a truncated download
    with pytest.raises(PipelineError, match=rf"{photo.name}.*remove or replace it"):
        run_stages(capture, "undistort")


def test_photos_whose_names_give_one_camera_id_are_refused_by_name(run_stages, tiny_capture, tmp_path):
    from pipeline.core.errors import PipelineError

    capture = _copy_capture(tiny_capture, tmp_path / "ids")
    photos = sorted((capture / "images").iterdir())
    photos[0].rename(capture / "images" / "a b.jpg")
    photos[1].rename(capture / "images" / "a_b.jpg")
    with pytest.raises(PipelineError, match=r"photos .*a b.jpg and .*a_b.jpg would get the same camera id.*rename one"):
        run_stages(capture, "undistort")


def test_files_that_are_not_photos_are_warned_about_and_left_out(run_stages, tiny_capture, tmp_path, caplog):
    capture = _copy_capture(tiny_capture, tmp_path / "psd")
    (capture / "images" / "IMG_0001.PSD").write_bytes(b"8BPS")
    outputs = run_stages(capture, "undistort")
    assert "IMG_0001.PSD is not a photo the pipeline reads" in caplog.text
    assert len(read_photos(outputs["undistort"]["pinhole"])) == 6


def test_raw_photos_give_the_linear_copies_their_jpegs_do(run_stages, tiny_capture, tmp_path):
    from tests.support.raw_photos import write_dng

    jpeg = _copy_capture(tiny_capture, tmp_path / "jpeg")
    raw = _copy_capture(tiny_capture, tmp_path / "raw")
    for photo in sorted((raw / "images").glob("*.jpg")):
        # RAW+JPEG shooting: the DNG beside its JPEG is the one read.
        write_dng(photo.with_suffix(".DNG"), read_photo(photo).pixels, neutral=(0.45, 1.0, 0.62))
    outputs = {name: run_stages(capture, "undistort")["undistort"] for name, capture in (("jpeg", jpeg), ("raw", raw))}
    from_jpeg, from_raw = (read_photos(outputs[name]["pinhole"]) for name in ("jpeg", "raw"))
    assert sorted(from_raw) == [name.replace(".jpg", ".DNG") for name in sorted(from_jpeg)]
    for name, entry in from_jpeg.items():
        expected = read_photo(entry["linear"]).pixels
        developed = read_photo(from_raw[name.replace(".jpg", ".DNG")]["linear"]).pixels
        # Demosaicing blurs edges a little; the colours (the white balance undone) are the same.
        np.testing.assert_allclose(developed.mean(axis=(0, 1)), expected.mean(axis=(0, 1)), rtol=0.02, atol=2e-3)
        assert np.median(np.abs(developed - expected)) < 0.01
