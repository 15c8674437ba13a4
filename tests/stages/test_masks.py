import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.core.errors import PipelineError
from pipeline.imaging.segmentation import clean
from pipeline.synthetic.score import score_masks
from tests.support.hard_turntable import hard_turntable_options

pytestmark = pytest.mark.slow


def _copy(capture: Path, tmp_path: Path, *, plates: bool = True) -> Path:
    ignored = [".pipeline", "output"] + ([] if plates else ["background"])
    return Path(shutil.copytree(capture, tmp_path / capture.name, ignore=shutil.ignore_patterns(*ignored)))


def _ious(capture: Path, outputs: dict) -> list[float]:
    return list(
        score_masks(capture / "ground_truth", outputs["undistort"]["pinhole"], outputs["masks"]["masks_json"]).values()
    )


def test_segmentation_on_a_neutral_set_matches_the_truth(run_stages, mask_capture, tmp_path):
    capture = _copy(mask_capture, tmp_path, plates=False)
    outputs = run_stages(capture, "masks")
    assert json.loads(outputs["masks"]["masks_json"].read_text())["source"] == "segment"
    scores = _ious(capture, outputs)
    assert len(scores) == 6
    assert np.mean(scores) >= 0.95 and min(scores) >= 0.92, scores


def test_centre_prior_alone_is_worse_on_a_board(run_stages, mask_capture, tmp_path):
    """The board's black and white squares fool plain GrabCut: why neutral_backdrop exists."""
    capture = _copy(mask_capture, tmp_path, plates=False)
    scores = _ious(capture, run_stages(capture, "masks", "masks.segmenter=centre_prior"))
    assert np.mean(scores) < 0.9


def test_background_plates_give_masks(run_stages, mask_capture, tmp_path):
    capture = _copy(mask_capture, tmp_path)
    outputs = run_stages(capture, "masks")
    assert json.loads(outputs["masks"]["masks_json"].read_text())["source"] == "background"
    scores = _ious(capture, outputs)
    # Photo and plate carry independent Monte Carlo noise at 32 spp, well above a real
    # sensor's; the bundled samples (docs/benchmarks.md) are the accuracy reference.
    assert np.mean(scores) >= 0.93 and min(scores) >= 0.90, scores


def test_user_masks_win_and_are_undistorted_with_the_photos(run_stages, mask_capture, tmp_path):
    capture = _copy(mask_capture, tmp_path)
    shutil.copytree(capture / "ground_truth" / "masks", capture / "masks")
    outputs = run_stages(capture, "masks")
    assert json.loads(outputs["masks"]["masks_json"].read_text())["source"] == "user"
    assert min(_ious(capture, outputs)) > 0.99


@pytest.mark.parametrize("speck_filled", [True, False])
def test_an_opening_through_the_specimen_stays_open_and_a_speck_is_filled(
    run_stages, mask_capture, tmp_path, speck_filled
):
    """Twin of temple-ring, whose colonnade shows the backdrop between its columns (kept
    open at max_hole_fraction 0.01; the default fills every hole)."""
    import cv2

    capture = _copy(mask_capture, tmp_path)
    shutil.copytree(capture / "ground_truth" / "masks", capture / "masks")
    drawn = capture / "masks" / "view_000.png"
    mask = cv2.imread(str(drawn), cv2.IMREAD_GRAYSCALE)
    rows, cols = np.nonzero(mask > 127)
    cy, cx, side = int(rows.mean()), int(cols.mean()), int(0.25 * np.sqrt(len(rows)))
    mask[cy - side // 2 : cy + side // 2, cx - side // 2 : cx + side // 2] = 0  # 6 % of the silhouette
    mask[cy + side - 2 : cy + side + 2, cx - 2 : cx + 2] = 0  # a speck: 16 px
    cv2.imwrite(str(drawn), mask)
    outputs = run_stages(capture, "masks", f"masks.max_hole_fraction={0.01 if speck_filled else 0}")
    kept = cv2.imread(str(outputs["masks"]["masks_json"].parent / "masks" / "view_000.png"), cv2.IMREAD_GRAYSCALE)
    assert kept[cy, cx] == 0 and kept[cy + side, cx] == (255 if speck_filled else 0)


def test_a_missing_user_mask_is_named(run_stages, mask_capture, tmp_path):
    capture = _copy(mask_capture, tmp_path)
    shutil.copytree(capture / "ground_truth" / "masks", capture / "masks")
    (capture / "masks" / "view_002.png").unlink()
    with pytest.raises(PipelineError, match="no mask for view_002.jpg"):
        run_stages(capture, "masks")


def test_clean_keeps_the_specimen_fills_its_specks_and_keeps_its_openings():
    mask = np.zeros((60, 60), bool)
    mask[10:40, 10:40] = True
    mask[20:25, 20:25] = False  # an opening: 25 px, 2.8 % of the silhouette (a colonnade's gap)
    mask[32:34, 32:34] = False  # a speck taken for backdrop: 4 px, 0.4 %
    mask[50:52, 50:52] = True  # dust
    mask[5:8, 45:55] = True  # a part: 30 px, 3 % of the body
    cleaned = clean(mask, min_component_fraction=0.02, max_hole_fraction=0.01)
    assert cleaned[33, 33] and not cleaned[22, 22] and not cleaned[51, 51] and cleaned[6, 50]
    every_hole_open = clean(mask, min_component_fraction=0.05, max_hole_fraction=0.0)
    assert not every_hole_open[22, 22] and not every_hole_open[33, 33] and not every_hole_open[6, 50]
    assert clean(mask, min_component_fraction=0.02, max_hole_fraction=1.0)[22, 22]


def test_grayscale_photos_are_refused_under_the_colour_segmenter(run_stages, tiny_capture, tmp_path):
    import cv2

    capture = tmp_path / "grey"
    shutil.copytree(tiny_capture, capture, ignore=shutil.ignore_patterns(".pipeline", "output"))
    for photo in (capture / "images").iterdir():
        grey = cv2.cvtColor(cv2.imread(str(photo)), cv2.COLOR_BGR2GRAY)
        cv2.imwrite(str(photo), cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR))
    with pytest.raises(PipelineError, match=r"6 of 6 photos have no colour.*masks.segmenter = 'centre_prior'"):
        run_stages(capture, "masks")
    # The fix works (at twice the photos' size: GrabCut on grey photos converges slowly).
    masks = run_stages(capture, "masks", "masks.segmenter=centre_prior", "masks.working_size=192")["masks"]
    assert json.loads(masks["masks_json"].read_text())


def test_a_turntable_in_a_room_is_cut_from_the_set_its_photos_show_not_from_its_greyness(
    run_stages, synth_capture, caplog
):
    """The hard turntable's set: a dark dotted plate before a coloured room, and a board
    in capture.toml that was shot for calibration only. auto finds no board in the
    photos, learns the set's colours and the room that stays still (set_colours); the
    room's colours fool neutral_backdrop."""
    options = hard_turntable_options(
        views=6, width=96, height=72, spp=4, rings=(20.0,), backdrop="room", calibration_shots=2, seed=11
    )
    capture = synth_capture("room_turntable", **options)
    assert 'kind = "charuco"' in (capture / "capture.toml").read_text()
    small = ("masks.working_size=192",)  # twice the photos' size: GrabCut's time is per pixel
    outputs = run_stages(capture, "masks", *small)
    status = json.loads((outputs["masks"]["masks_json"].parent / "status.json").read_text())
    assert status["metrics"]["segmenter"] == "set_colours"
    assert "no photo in images/ shows the board" in caplog.text
    learned = _ious(capture, outputs)
    neutral = _ious(capture, run_stages(capture, "masks", *small, "masks.segmenter=neutral_backdrop"))
    # 96 px: a pixel of edge is much of a small silhouette's IoU.
    assert np.mean(learned) >= 0.75 and np.mean(learned) > np.mean(neutral) + 0.3, (learned, neutral)
