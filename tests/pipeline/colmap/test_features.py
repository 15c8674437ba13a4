"""Which photos of a turntable are matched: ring neighbours and look-alike outlines."""

from pathlib import Path

import cv2
import numpy as np

from pipeline.colmap.features import outline_neighbours, ring_pairs


def _outline(angle_deg: float, size: int = 96) -> np.ndarray:
    """A mask of a round body with a knob, turned in the image by ``angle_deg``: the
    nearer two angles, the more alike their outlines."""
    mask = np.zeros((size, size), np.uint8)
    centre = (size // 2, size // 2)
    cv2.circle(mask, centre, 22, 255, -1)
    knob = np.radians(angle_deg)
    cv2.circle(mask, (round(centre[0] + 26 * np.cos(knob)), round(centre[1] + 26 * np.sin(knob))), 12, 255, -1)
    return mask


def _masks(folder: Path, angles: list[float]) -> dict[str, Path]:
    paths = {}
    for index, angle in enumerate(angles):
        paths[f"view_{index:03d}.jpg"] = folder / f"view_{index:03d}.png"
        cv2.imwrite(str(paths[f"view_{index:03d}.jpg"]), _outline(angle))
    return paths


def _photos(masks: dict[str, Path]) -> dict[str, dict]:
    return {name: {"srgb": Path("/undistorted") / name.replace(".jpg", ".png"), "camera": 0} for name in masks}


def test_a_second_turn_is_matched_with_the_first_turns_photos_at_its_angles(tmp_path):
    # one turn in 30-degree steps, then a second partial turn 5 degrees on from the first
    first, second = [30.0 * i for i in range(12)], [5.0, 35.0, 65.0, 95.0]
    masks = _masks(tmp_path, first + second)
    pairs = set(ring_pairs(_photos(masks), masks, neighbours=2, alike=3))
    for k in range(4):
        assert tuple(sorted((f"view_{k:03d}.png", f"view_{12 + k:03d}.png"))) in pairs
    # the file-order ring is there too, wrapping round
    assert ("view_000.png", "view_015.png") in pairs and ("view_000.png", "view_001.png") in pairs


def test_one_turn_adds_no_pair_beyond_the_ring(tmp_path):
    masks = _masks(tmp_path, [30.0 * i for i in range(12)])
    ring = set(ring_pairs(_photos(masks), masks, neighbours=2, alike=0))
    assert set(ring_pairs(_photos(masks), masks, neighbours=2, alike=3)) == ring
    assert len(ring) == 24


def test_outline_neighbours_take_at_most_count_and_leave_out_the_excluded_pairs(tmp_path):
    # photo 4 is photo 0's angle again, and photos 5 and 6 near it: 4's neighbours in
    # file order (3 and 5) are 270 and 2 degrees away
    paths = list(_masks(tmp_path, [0.0, 90.0, 180.0, 270.0, 0.5, 2.0, 3.0]).values())
    assert (0, 4) in outline_neighbours(paths, 1, excluded=set())
    assert (0, 4) not in outline_neighbours(paths, 1, excluded={(0, 4)})
    assert len(outline_neighbours(paths, 1, excluded=set())) <= len(paths)
    assert outline_neighbours(paths, 0, excluded=set()) == set()
