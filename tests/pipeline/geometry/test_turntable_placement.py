"""Photos the features cannot place: by even steps, by their silhouette, or left out."""

import cv2
import numpy as np
import pytest

from pipeline.geometry.circular_motion import CircularSettings
from pipeline.geometry.turntable_placement import PlacementSettings, circular_poses
from tests.pipeline.geometry.test_circular_motion import START
from tests.support.turntable_views import blob_mask, turntable_views

pytestmark = pytest.mark.slow  # each test solves a turntable

BIRDLIKE = [((0.0, 0.0, 0.045), 0.025), ((0.05, 0.0, 0.07), 0.02), ((-0.06, 0.015, 0.05), 0.012)]
"""Body, head and tail: an outline that changes as the table turns."""
BALL = [((0.0, 0.0, 0.045), 0.03)]
"""A ball on the axis: the same outline at every angle."""


def _place(tmp_path, views, lonely: str, shape, even_steps: float = 0.0):
    masks = {}
    for name in views.names:
        masks[name] = tmp_path / f"{name}.png"
        cv2.imwrite(str(masks[name]), blob_mask(views.poses[name], shape).astype(np.uint8) * 255)
    matches = {pair: found for pair, found in views.matches.items() if lonely not in pair}
    settings = PlacementSettings(
        CircularSettings(in_file_order=True, even_steps_deg=even_steps),
        True,
        max_silhouette_error_px=1.5,
        silhouette_ambiguity=2.0,
    )
    intrinsics = {name: START for name in views.names}
    return circular_poses(settings, views.names, intrinsics, masks, views.keypoints, matches, {})


def _angle_error_deg(table, views, name: str) -> float:
    """The error of ``name``'s angle, counted from the first photo's."""
    first = views.names[0]
    estimate = table.angles[name] - table.angles[first]
    truth = views.angles[views.names.index(name)] - views.angles[0]
    return float(np.degrees(abs(np.angle(np.exp(1j * (estimate - truth))))))


def test_a_photo_without_features_is_placed_by_its_silhouette(tmp_path):
    views = turntable_views()
    lonely = views.names[7]
    table, _, _, report = _place(tmp_path, views, lonely, BIRDLIKE)
    assert report["pose_source"]["silhouette"] == [lonely]
    assert report["silhouette"][lonely]["error_px"] < 1.0
    assert _angle_error_deg(table, views, lonely) < 0.5


def test_an_outline_that_never_changes_leaves_the_photo_out_not_stacked(tmp_path):
    views = turntable_views()
    lonely = views.names[7]
    _, poses, _, report = _place(tmp_path, views, lonely, BALL)
    assert lonely not in poses and "ambiguous" in report["unplaced"][lonely]
    assert report["pose_source"]["silhouette"] == []


def test_even_steps_place_a_photo_of_a_timed_table(tmp_path):
    views = turntable_views(jitter=0.0)
    lonely = views.names[7]
    table, _, _, report = _place(tmp_path, views, lonely, BALL, even_steps=0.2)
    assert report["pose_source"]["even_steps"] == [lonely]
    assert _angle_error_deg(table, views, lonely) < 0.2
