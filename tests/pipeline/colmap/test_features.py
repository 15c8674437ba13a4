"""Which photos of a turntable are matched: ring neighbours and look-alike outlines."""

from pathlib import Path

import cv2
import numpy as np
import pycolmap

from pipeline.colmap.features import descriptor_neighbours, outline_neighbours, ring_pairs


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


def _database(path: Path, descriptors: list[np.ndarray], keypoints: list[np.ndarray]) -> Path:
    """A COLMAP database of photos view_000.png... with the given features (keypoints
    as x, y and an affine shape of their scale)."""
    camera = pycolmap.Camera.create_from_model_name(1, "SIMPLE_RADIAL", 100.0, 96, 96)
    with pycolmap.Database.open(path) as db:
        camera_id = db.write_camera(camera)
        for index, (found, where) in enumerate(zip(descriptors, keypoints)):
            image_id = db.write_image(pycolmap.Image(name=f"view_{index:03d}.png", camera_id=camera_id))
            shapes = np.column_stack(
                [where[:, :2], where[:, 2], np.zeros(len(where)), np.zeros(len(where)), where[:, 2]]
            )
            db.write_keypoints(image_id, shapes.astype(np.float32))
            db.write_descriptors(image_id, pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT, found))
    return path


def test_descriptor_neighbours_find_the_photos_that_share_features_on_the_specimen(tmp_path):
    """Photos 0 and 3 share the specimen's features (another set, the same side); photos
    1 and 2 share only features off the specimen (the table). Retrieval pairs 0 with 3,
    not 1 with 2, and leaves out a pair already matched."""
    rng = np.random.default_rng(0)
    shared_on, shared_off = rng.integers(0, 255, (40, 128)), rng.integers(0, 255, (40, 128))
    own = [rng.integers(0, 255, (40, 128)) for _ in range(4)]
    on, off = (
        np.column_stack([rng.uniform(30, 60, (40, 2)), np.full(40, 2.0)]),
        np.column_stack([rng.uniform(70, 90, (40, 2)), np.full(40, 2.0)]),
    )
    descriptors = [np.vstack([shared_on if i in (0, 3) else own[i], shared_off if i in (1, 2) else own[(i + 1) % 4]])
                   for i in range(4)]  # fmt: skip
    database = _database(
        tmp_path / "database.db", [d.astype(np.uint8) for d in descriptors], [np.vstack([on, off])] * 4
    )
    mask = np.zeros((96, 96), np.uint8)
    mask[25:65, 25:65] = 255
    cv2.imwrite(str(tmp_path / "mask.png"), mask)
    masks = {f"view_{i:03d}.png": tmp_path / "mask.png" for i in range(4)}
    assert descriptor_neighbours(database, 1, set(), masks) == {("view_000.png", "view_003.png")}
    assert ("view_000.png", "view_003.png") not in descriptor_neighbours(
        database, 1, {("view_000.png", "view_003.png")}, masks
    )
    # Without masks every feature counts: the table's pair is found too.
    assert ("view_001.png", "view_002.png") in descriptor_neighbours(database, 1, set(), {})
