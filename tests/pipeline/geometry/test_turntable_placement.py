"""Photos the features cannot place: by even steps, by their silhouette, or left out."""

import cv2
import numpy as np
import pytest

from pipeline.geometry.circular_motion import CircularSettings
from pipeline.geometry.turntable_placement import PlacementSettings, circular_poses
from tests.pipeline.geometry.test_circular_motion import START, _broken_ring
from tests.support.turntable_views import blob_mask, turntable_views

pytestmark = pytest.mark.slow  # each test solves a turntable

BIRDLIKE = [((0.0, 0.0, 0.045), 0.025), ((0.05, 0.0, 0.07), 0.02), ((-0.06, 0.015, 0.05), 0.012)]
"""Body, head and tail: an outline that changes as the table turns."""
BALL = [((0.0, 0.0, 0.045), 0.03)]
"""A ball on the axis: the same outline at every angle."""


def _masks(tmp_path, views, shape) -> dict:
    masks = {}
    for name in views.names:
        masks[name] = tmp_path / f"{name}.png"
        cv2.imwrite(str(masks[name]), blob_mask(views.poses[name], shape).astype(np.uint8) * 255)
    return masks


def _settings(even_steps: float = 0.0, coherence: bool = True) -> PlacementSettings:
    return PlacementSettings(
        CircularSettings(even_steps_deg=even_steps),
        True,
        silhouette_noise_factor=2.0,
        silhouette_ambiguity=2.0,
        silhouette_coherence=coherence,
    )


def _intrinsics(views) -> dict:
    return {name: START for name in views.names}


def _place(tmp_path, views, lonely: str, shape, even_steps: float = 0.0):
    masks = _masks(tmp_path, views, shape)
    matches = {pair: found for pair, found in views.matches.items() if lonely not in pair}
    return circular_poses(_settings(even_steps), views.names, _intrinsics(views), masks, views.keypoints, matches, {})


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


@pytest.mark.parametrize("coherence", [True, False])
def test_a_ring_broken_in_two_is_closed_by_the_arcs_silhouettes(tmp_path, coherence):
    """With the outlines fitted, the solver joins the arc to the ring and solves both
    with its features; without, the placement puts the arc where its silhouettes fit."""
    views = turntable_views()
    masks = _masks(tmp_path, views, BIRDLIKE)
    matches = _broken_ring(views, (5, 12))
    table, poses, solution, report = circular_poses(
        _settings(coherence=coherence), views.names, _intrinsics(views), masks, views.keypoints, matches, {}
    )
    arc = views.names[6:13]
    assert set(poses) == set(views.names)
    if coherence:
        # The arc's offset is its outlines': uncertain, and said so photo by photo.
        assert report["joined_groups"][0]["joined"] and report["pose_source"]["joined_by_outline"] == sorted(arc)
        assert report["pose_source"]["features"] == sorted(set(views.names) - set(arc))
        assert all(not report["photos"][name]["certain"] for name in arc)
        assert "7 by outline alone (uncertain)" in report["summary"]
    else:
        assert not report["joined_groups"] and report["pose_source"]["group_silhouette"] == sorted(arc)
    assert max(_angle_error_deg(table, views, name) for name in views.names) < 0.5
    # The arc's points are turned into the ring's frame: they project where they were seen.
    assert len(solution.points) == len(solution.tracks) and all(set(t) <= set(poses) for t in solution.tracks)


def test_a_photo_that_belongs_nowhere_is_left_out_not_stacked(tmp_path):
    """A stray photo (another object) whose keypoints two photos matched by chance."""
    views = turntable_views()
    masks = _masks(tmp_path, views, BIRDLIKE)
    stray = "view_999.jpg"
    rng = np.random.default_rng(3)
    keypoints = dict(views.keypoints, **{stray: rng.uniform(0, [START.width, START.height], (300, 2))})
    matches = dict(views.matches)
    for partner in views.names[3:5]:
        chosen = rng.choice(len(views.keypoints[partner]), 40, replace=False)
        matches[partner, stray] = {int(k): int(i) for i, k in enumerate(chosen)}
        matches[stray, partner] = {v: k for k, v in matches[partner, stray].items()}
    masks[stray] = tmp_path / "stray.png"
    cv2.imwrite(str(masks[stray]), (rng.uniform(size=(START.height, START.width)) > 0.7).astype(np.uint8) * 255)
    names = [*views.names, stray]
    intrinsics = {name: START for name in names}
    table, poses, _, report = circular_poses(_settings(), names, intrinsics, masks, keypoints, matches, {})
    assert stray not in poses and stray in report["unplaced"]
    assert set(poses) == set(views.names)
    assert max(_angle_error_deg(table, views, name) for name in views.names) < 0.3
