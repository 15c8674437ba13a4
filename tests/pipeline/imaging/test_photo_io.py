import numpy as np
import pytest

from pipeline.imaging.photo_io import read_photo, write_image
from tests.support.toy_stages import run_python


@pytest.mark.parametrize("orientation", [1, 3, 6, 8])
def test_reduced_decoding_is_the_box_mean_of_the_full_photo(tmp_path, orientation):
    rng = np.random.default_rng(orientation)
    stored = rng.integers(0, 256, (96, 128, 3), dtype=np.uint8)
    path = write_image(tmp_path / "photo.png", stored, {"Orientation": orientation})
    full = read_photo(path).pixels
    reduced = read_photo(path, reduce=4).pixels
    height, width = full.shape[:2]
    assert reduced.shape == (height // 4, width // 4, 3)
    expected = full.reshape(height // 4, 4, width // 4, 4, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(reduced, expected, atol=1e-6)


MEASURE = """
import resource, sys
from pathlib import Path
from pipeline.imaging.photo_io import read_photo
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
photo = read_photo(Path(sys.argv[1]), reduce=8)
after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(photo.size[0], photo.size[1], (after - before) // 1024)
"""


def test_a_huge_photo_is_never_decoded_whole(tmp_path):
    # 9000x6000: 648 MB as float32 RGB, what a whole decode would hold at least once.
    gradient = np.linspace(0, 255, 9000, dtype=np.float32).astype(np.uint8)
    stored = np.broadcast_to(gradient[None, :, None], (6000, 9000, 3))
    path = write_image(tmp_path / "huge.jpg", np.ascontiguousarray(stored))
    del stored
    result = run_python(MEASURE.replace("sys.argv[1]", repr(str(path))))
    assert result.returncode == 0, result.stderr
    width, height, grown_mb = map(int, result.stdout.split())
    assert (width, height) == (1125, 750)
    assert grown_mb < 150, f"decoding grew the process by {grown_mb} MB"


@pytest.mark.parametrize("channels", [2, 4], ids=["grey+alpha", "rgb+alpha"])
def test_alpha_is_never_multiplied_into_the_colour(tmp_path, channels):
    import OpenImageIO as oiio

    from pipeline.core.errors import PipelineError

    colour = np.full((8, 8, channels), 200, np.uint8)
    for alpha, name in ((255, "opaque.png"), (128, "half.png")):
        colour[..., -1] = alpha
        spec = oiio.ImageSpec(8, 8, channels, oiio.UINT8)
        spec.alpha_channel = channels - 1
        out = oiio.ImageOutput.create(str(tmp_path / name))
        assert out.open(str(tmp_path / name), spec) and out.write_image(colour) and out.close()
    opaque = read_photo(tmp_path / "opaque.png").pixels
    assert opaque.shape == (8, 8, 3) and np.allclose(opaque, (200 / 255 + 0.055) ** 2.4 / 1.055**2.4, atol=1e-3)
    with pytest.raises(PipelineError, match=r"half.png is partly transparent .* save it as the photo's mask in masks/"):
        read_photo(tmp_path / "half.png")


def test_files_that_are_not_photos_are_listed(tmp_path):
    import os

    from pipeline.imaging.photo_io import unsupported_files

    for name in ("a.jpg", "b.HEIC", "c.dng", "e.psd", "f.CRW.xmp", ".DS_Store"):
        (tmp_path / name).write_bytes(b"x")
    os.mkfifo(tmp_path / "d.jpg")
    (tmp_path / "sub").mkdir()
    assert [p.name for p in unsupported_files(tmp_path)] == ["d.jpg", "e.psd", "f.CRW.xmp"]


def _patches(height=48, width=64):
    """Four flat patches of known linear sRGB colour."""
    colours = np.array([[0.2, 0.4, 0.6], [0.6, 0.3, 0.1], [0.05, 0.05, 0.05], [0.9, 0.8, 0.7]])
    pixels = np.empty((height, width, 3))
    for i, colour in enumerate(colours):
        pixels[(i // 2) * height // 2 : (i // 2 + 1) * height // 2, (i % 2) * width // 2 : (i % 2 + 1) * width // 2] = (
            colour
        )
    return pixels, colours


def _patch_means(pixels, margin):
    height, width = pixels.shape[:2]
    return np.array(
        [
            pixels[
                (i // 2) * height // 2 + margin : (i // 2 + 1) * height // 2 - margin,
                (i % 2) * width // 2 + margin : (i % 2 + 1) * width // 2 - margin,
            ].mean(axis=(0, 1))
            for i in range(4)
        ]
    )


@pytest.mark.parametrize("reduce", [1, 2, 3])
def test_a_raw_photo_develops_to_the_linear_colours_it_recorded(tmp_path, reduce):
    from pipeline.imaging.photo_io import read_metadata
    from tests.support.raw_photos import write_dng

    pixels, colours = _patches()
    path = write_dng(tmp_path / "IMG_0001.DNG", pixels, neutral=(0.5, 1.0, 0.7))
    photo = read_photo(path, reduce=reduce)
    assert photo.encoding == "linear" and photo.size == (64 // reduce, 48 // reduce)
    # No tone curve, no brightening, the as-shot white balance applied: the scene's values.
    np.testing.assert_allclose(_patch_means(photo.pixels, 4 // reduce + 1), colours, atol=0.004)
    metadata, size = read_metadata(path)
    assert size == (64, 48) and (metadata["Make"], metadata["Model"]) == ("TestMake", "TestModel")
    np.testing.assert_allclose(metadata["raw:WhiteBalance"], [2.0, 1.0, 1 / 0.7], rtol=1e-3)
    assert metadata["raw:BlackLevel"] == [256.0] * 4 and metadata["raw:WhiteLevel"] == 16383


def test_raw_and_jpeg_twins_are_one_photo_and_a_damaged_raw_is_named(tmp_path):
    from pipeline.core.errors import PipelineError
    from pipeline.imaging.photo_io import list_photos, unsupported_files
    from tests.support.raw_photos import write_dng

    pixels, _ = _patches()
    write_dng(tmp_path / "IMG_0001.DNG", pixels)
    write_image(tmp_path / "IMG_0001.JPG", np.zeros((48, 64, 3), np.uint8))
    write_image(tmp_path / "IMG_0002.JPG", np.zeros((48, 64, 3), np.uint8))
    assert [p.name for p in list_photos(tmp_path)] == ["IMG_0001.DNG", "IMG_0002.JPG"]
    assert unsupported_files(tmp_path) == []
    damaged = tmp_path / "IMG_0003.NEF"
    damaged.write_bytes((tmp_path / "IMG_0001.DNG").read_bytes()[:300])
    with pytest.raises(PipelineError, match="IMG_0003.NEF: cannot read this RAW file"):
        read_photo(damaged)


@pytest.mark.parametrize("primaries", ["srgb", "display-p3"])
def test_a_phone_heic_reads_as_the_linear_srgb_colours_it_shows(tmp_path, primaries):
    import pillow_heif
    from PIL import Image

    from pipeline.imaging.photo_io import SRGB_PRIMARIES, _rgb_to_xyz, read_metadata, srgb_encode

    pixels, colours = _patches()
    stored = pixels
    if primaries == "display-p3":  # the same colours as a phone stores them: P3 primaries, sRGB curve
        p3 = ((0.680, 0.320), (0.265, 0.690), (0.150, 0.060), (0.3127, 0.3290))
        stored = pixels @ np.linalg.solve(_rgb_to_xyz(p3), _rgb_to_xyz(SRGB_PRIMARIES)).T
    encoded = np.round(srgb_encode(stored) * 255).astype(np.uint8)
    exif = Image.Exif()
    exif[0x010F], exif[0x0110] = "PhoneMake", "PhoneModel"
    exif.get_ifd(0x8769)[0x920A] = 4.25  # FocalLength, in the Exif IFD
    heif = pillow_heif.from_bytes("RGB", (64, 48), encoded.tobytes())
    path = tmp_path / "IMG_0001.HEIC"
    heif.save(path, quality=-1, exif=exif.tobytes(), color_primaries=12 if primaries == "display-p3" else 1)
    photo = read_photo(path)
    assert photo.size == (64, 48) and photo.bits == 8
    np.testing.assert_allclose(_patch_means(photo.pixels, 4), colours, atol=0.01)
    metadata, size = read_metadata(path)
    assert size == (64, 48) and metadata["Make"] == "PhoneMake" and metadata["Exif:FocalLength"] == 4.25
