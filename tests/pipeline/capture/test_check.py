import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import skimage.data

from pipeline.capture.check import check_capture, verified_count
from pipeline.cli import main
from pipeline.core.config import load_config
from pipeline.core.sections import schema
from stages import STAGES
from tests.support.real_captures import SHARED_CAPTURES

pytestmark = pytest.mark.slow
POROUS_CUBE = SHARED_CAPTURES / "porous-cube"


def _config(capture: Path):
    return load_config(schema(STAGES), capture)


def _flagged(problems, check: str) -> dict[str, str]:
    return {p.file.removeprefix("images/"): p.severity for p in problems if p.check == check}


@pytest.fixture
def spoilt(orbit_capture, tmp_path) -> Path:
    """The orbit with four planted problems."""
    capture = Path(shutil.copytree(orbit_capture, tmp_path / "orbit"))
    images = capture / "images"
    photo = cv2.imread(str(images / "view_003.jpg"))
    cv2.imwrite(str(images / "view_003.jpg"), cv2.GaussianBlur(photo, (0, 0), 2.5))
    photo = cv2.imread(str(images / "view_007.jpg")).astype(np.float32)
    cv2.imwrite(str(images / "view_007.jpg"), np.clip(photo * 2.5, 0, 255).astype(np.uint8))
    shutil.copy(images / "view_009.jpg", images / "view_009b.jpg")
    stray = cv2.resize(skimage.data.astronaut()[..., ::-1], (192, 144), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(images / "view_100.jpg"), stray)
    return capture


def test_a_clean_capture_has_no_errors(orbit_capture):
    problems = check_capture(orbit_capture, _config(orbit_capture))
    assert [p for p in problems if p.severity == "error"] == []
    assert not _flagged(problems, "blur") and not _flagged(problems, "duplicates") and not _flagged(problems, "strays")


def test_planted_problems_are_flagged_by_name(spoilt):
    problems = check_capture(spoilt, _config(spoilt))
    assert _flagged(problems, "blur") == {"view_003.jpg": "warning"}
    assert "view_007.jpg" in _flagged(problems, "exposure")
    assert _flagged(problems, "duplicates") == {"view_009b.jpg": "warning"}
    assert _flagged(problems, "strays") == {"view_100.jpg": "error"}


def test_check_exits_1_on_errors_and_prints_one_line_per_problem(spoilt, capsys):
    assert main(["check", str(spoilt)]) == 1
    out = capsys.readouterr().out
    assert "error   images/view_100.jpg: shares only" in out
    assert main(["check", str(spoilt), "--json"]) == 1
    report = json.loads(capsys.readouterr().out)
    assert report["errors"] >= 1 and {"severity", "check", "file", "message", "advice"} <= set(report["problems"][0])


def test_a_missing_specimen_is_an_error(orbit_capture, tmp_path):
    capture = Path(shutil.copytree(orbit_capture, tmp_path / "orbit"))
    plate = np.full((144, 192, 3), 128, np.uint8)
    cv2.imwrite(str(capture / "images" / "view_005.jpg"), plate)
    masks = _flagged(check_capture(capture, _config(capture), features=False), "masks")
    assert masks == {"view_005.jpg": "error"}


@pytest.mark.real_data
@pytest.mark.skipif(not POROUS_CUBE.is_dir(), reason="../shared/captures/porous-cube is not here")
def test_the_room_shot_in_the_porous_cube_capture_is_flagged(tmp_path):
    capture = tmp_path / "porous-cube"
    capture.mkdir()
    (capture / "images").symlink_to(POROUS_CUBE / "images")
    problems = check_capture(capture, _config(capture))
    assert _flagged(problems, "strays") == {"20221109_144453775_iOS.jpg": "error"}


def test_degenerate_matches_count_as_none_instead_of_failing_the_check():
    """Matches on two repeated spots (a few table dots of a small turntable photo) make
    OpenCV's USAC assert `!model.empty()`; the pair then shares no verified match."""

    repeated = np.float32([[20, 30], [28, 70]] * 9)
    scattered = np.random.default_rng(2).random((18, 2)).astype(np.float32)
    with pytest.raises(cv2.error):
        cv2.findFundamentalMat(repeated, scattered, cv2.USAC_MAGSAC, 1.5, 0.999)
    assert verified_count(repeated, scattered) == 0
    rng = np.random.default_rng(0)
    points = rng.random((40, 2)).astype(np.float32) * 200
    assert verified_count(points, points + np.float32([5, 0])) >= 30  # a plain translation: all consistent


def test_photos_cut_out_on_white_are_neither_overexposed_nor_duplicates(synth_capture):
    """White around the specimen is clipped and alike in every photo: what matters is
    the specimen, which is neither."""
    capture = synth_capture(
        "white_turntable",
        views=8,
        width=128,
        height=96,
        spp=4,
        calibration_shots=0,
        rig="turntable",
        rings=(25.0,),
        table="dots",
        backdrop="white",
        seed=2,
    )
    problems = check_capture(capture, _config(capture), features=False)
    assert not _flagged(problems, "exposure") and not _flagged(problems, "duplicates"), problems


def test_files_that_are_not_photos_are_listed_as_warnings(orbit_capture, tmp_path):
    capture = Path(shutil.copytree(orbit_capture, tmp_path / "orbit"))
    for name in ("IMG_0001.HEIC", "IMG_0002.PSD", "IMG_0003.DNG", "IMG_0003.xmp"):
        (capture / "images" / name).write_bytes(b"x")
    problems = check_capture(capture, _config(capture), features=False)
    assert _flagged(problems, "unsupported") == {"IMG_0002.PSD": "warning", "IMG_0003.xmp": "warning"}
    # RAW and HEIC are read: damaged ones are named as unreadable.
    assert _flagged(problems, "readable") == {"IMG_0001.HEIC": "error", "IMG_0003.DNG": "error"}


def test_a_large_set_is_checked_on_evenly_spread_masks_and_its_unread_files_counted(
    orbit_capture, tmp_path, monkeypatch
):
    from pipeline.capture import check

    capture = Path(shutil.copytree(orbit_capture, tmp_path / "orbit"))
    for index in range(12):
        (capture / "images" / f"notes_{index:02d}.txt").write_text("x")
    segmented = []
    monkeypatch.setattr(check, "MASK_CHECK_PHOTOS", 4)
    real_segment = check.segment
    monkeypatch.setattr(check, "segment", lambda srgb, *args: segmented.append(1) or real_segment(srgb, *args))
    problems = check_capture(capture, _config(capture), features=False)
    photos = len(check.list_photos(capture / "images"))
    assert len(segmented) == 4
    assert any(p.severity == "note" and f"masks segmented for 4 of {photos} photos" in p.message for p in problems)
    unsupported = [p for p in problems if p.check == "unsupported"]
    assert len(unsupported) == check.UNREAD_NAMED + 1 and "7 more files are not photos" in unsupported[-1].message


def test_duplicates_and_match_pairs_scale_with_the_photo_count():
    """3,000 thumbnails: the planted near-duplicate is found by block products, and the
    stray check's pairs grow with the count (neighbours and look-alikes), not its square."""
    from pipeline.capture.check import DUPLICATE_CORRELATION, STRAY_NEIGHBOURS, _correlated_pairs, candidate_pairs

    rng = np.random.default_rng(0)
    rows = rng.normal(size=(3_000, 1024))
    rows[2321] = rows[12] + rng.normal(scale=0.01, size=1024)
    rows = (rows - rows.mean(axis=1, keepdims=True)) / rows.std(axis=1, keepdims=True)
    assert [(i, j) for i, j, _ in _correlated_pairs(rows, DUPLICATE_CORRELATION)] == [(12, 2321)]
    pairs = candidate_pairs([None] * 3_000, rows / 32)
    assert len(pairs) <= 3_000 * 2 * STRAY_NEIGHBOURS and (12, 2321) in pairs and (0, 1) in pairs
    assert len(candidate_pairs([None] * 20, rows[:20] / 32)) == 190  # a usual capture: every pair
