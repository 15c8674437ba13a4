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
