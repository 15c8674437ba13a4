"""A turntable capture in two sets (tests/support/turntable_views.two_set_views): the
camera moved between them, the specimen turned over, matches across them that prove
nothing, a specimen whose outline is the same from every side."""

import logging

import numpy as np
import pytest

from pipeline.camera.model import Pose, rotation_angle_deg, similarity_umeyama
from pipeline.camera.self_calibration import SelfCalibrationSettings
from pipeline.geometry import turntable_sets
from pipeline.geometry.turntable_placement import PlacementSettings, RigSettings, circular_poses
from tests.pipeline.geometry.test_circular_motion import START
from tests.pipeline.geometry.test_turntable_placement import BALL, BIRDLIKE, _masks
from tests.support.turntable_views import two_set_views

pytestmark = pytest.mark.slow  # each test solves a turntable two or three times


def _place(tmp_path, views, shape=BIRDLIKE, matches=None):
    settings = PlacementSettings.of(RigSettings(), SelfCalibrationSettings(), True, 15, 6, True)
    masks = _masks(tmp_path, views, shape)
    intrinsics = {name: START for name in views.names}
    return circular_poses(settings, views.names, intrinsics, masks, views.keypoints, matches or views.matches, {})


def _rotation_errors_deg(poses: dict, views, aligned_on: str = "") -> dict[str, float]:
    """Each placed photo's rotation error after the similarity that best aligns the
    camera centres of the photos whose names start with ``aligned_on`` (the solution's
    frame and scale are its own)."""
    names = [n for n in views.names if n in poses]
    aligned = [n for n in names if n.startswith(aligned_on)]
    _, R, _ = similarity_umeyama(
        np.array([poses[n].center for n in aligned]), np.array([views.poses[n].center for n in aligned])
    )
    return {n: rotation_angle_deg(views.poses[n].R @ R @ poses[n].R.T) for n in names}


def test_a_second_set_from_a_camera_moved_up_is_found_solved_and_joined(tmp_path):
    """Posed freely on one circle's points, the second set's cameras stand 4 degrees
    higher: it is solved alone and joined by its matches with the first. One circle
    put both sets 2 degrees off; the sets each hold to the principal point's offset the
    solver keeps (0.7 degrees on these photos)."""
    views = two_set_views(elevation_change_deg=4.0, distance_ratio=1.05, restart_deg=10.0)
    _, poses, _, report = _place(tmp_path, views)
    assert set(poses) == set(views.names)
    (second,) = report["sets"]
    assert second["joined"] and sorted(second["photos"]) == sorted(n for n in views.names if n.startswith("set"))
    assert abs(second["elevation_change_deg"] - 4.0) < 0.5
    assert max(_rotation_errors_deg(poses, views).values()) < 1.0
    assert all(record["certain"] and record["set"] == (2 if name.startswith("set") else 1)
               for name, record in report["photos"].items())  # fmt: skip
    assert report["summary"].startswith("30 of 30 placed; 2 sets, 2 joined by")


def test_a_specimen_turned_over_between_the_sets_is_joined_by_its_features(tmp_path):
    views = two_set_views(turned_over=True, elevation_change_deg=0.0, distance_ratio=1.0)
    _, poses, _, report = _place(tmp_path, views)
    (second,) = report["sets"]
    assert second["joined"] and abs(second["specimen_axis_turned_deg"] - 180) < 2
    assert set(poses) == set(views.names)
    # The held principal point's 0.7 degrees, and the join's own error on 128 px photos.
    assert max(_rotation_errors_deg(poses, views).values()) < 1.5


def test_a_specimen_turned_over_on_a_patterned_table_is_joined_by_its_own_features(tmp_path):
    """The plate's features turn with the table, the specimen lies turned over on it,
    and the camera moved up: the matches of the plate across the sets tie them where
    the table lies, those on the specimen's outlines where the specimen lies. The join
    follows the specimen."""
    views = two_set_views(turned_over=True, patterned_table=True, elevation_change_deg=4.0, distance_ratio=1.05)
    _, poses, _, report = _place(tmp_path, views)
    (second,) = report["sets"]
    assert second["joined"] and abs(second["specimen_axis_turned_deg"] - 180) < 2
    assert max(_rotation_errors_deg(poses, views, aligned_on="view").values()) < 2.0  # the join target


def test_a_set_its_matches_do_not_tie_is_left_out_with_one_warning(tmp_path, caplog):
    """Matches across the sets that prove nothing (random keypoints): the second set is
    left out, named in one warning, never placed by its outlines."""
    views = two_set_views(elevation_change_deg=4.0)
    rng = np.random.default_rng(1)
    matches = dict(views.matches)
    for (a, b), found in views.matches.items():
        if a.startswith("view") and b.startswith("set"):
            matches[a, b] = {k: int(rng.integers(len(views.keypoints[b]))) for k in found}
            matches[b, a] = {v: k for k, v in matches[a, b].items()}
    with caplog.at_level(logging.WARNING, logger="pipeline"):
        _, poses, _, report = _place(tmp_path, views, matches=matches)
    second = [name for name in views.names if name.startswith("set")]
    assert not any(name in poses for name in second)
    assert all("left out" in report["unplaced"][name] for name in second)
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and "left out" in r.getMessage()]
    assert len(warned) == 1 and all(name in warned[0] for name in second)
    assert len(poses) == len(views.names) - len(second)


def test_sets_of_a_ball_no_feature_ties_are_not_joined_by_their_outlines(tmp_path):
    """No match across the sets, and a ball's outline is the same from every side: the
    second set has no angle its outline could prove, and is not placed on the first's
    circle."""
    views = two_set_views(elevation_change_deg=4.0, across=0)
    _, poses, _, report = _place(tmp_path, views, shape=BALL)
    assert not any(name.startswith("set") and name in poses for name in views.names)
    assert all(record["placed_by"] != "outline" for record in report["photos"].values())


def test_a_photo_of_another_set_is_a_stray_of_the_first_and_goes_where_its_matches_are():
    """Free elevations scattered by a tenth of a degree about 20, one photo at 27: it
    alone is a stray; it shares its matches with the second set's photos, and goes there."""
    rng = np.random.default_rng(0)
    cameras = {f"view_{i:03d}.jpg": (20 + 0.1 * rng.normal(), 1.0) for i in range(20)} | {"view_020.jpg": (27.0, 1.0)}
    assert turntable_sets.strays(cameras, 6.0) == ["view_020.jpg"]
    assert turntable_sets.strays({n: c for n, c in cameras.items() if n != "view_020.jpg"}, 6.0) == []
    matches = {("view_020.jpg", "set_000.jpg"): {0: 1, 2: 3}, ("view_020.jpg", "set_001.jpg"): {4: 5}}
    grown = turntable_sets.with_the_rest([["other_000.jpg"], ["set_000.jpg", "set_001.jpg"]], ["view_020.jpg"], matches)
    assert grown == [["other_000.jpg"], ["set_000.jpg", "set_001.jpg", "view_020.jpg"]]


def test_cameras_over_a_board_off_the_tables_centre_split_into_their_sets():
    """Board poses of two sets, 25 and 33 degrees up, circling an axis 3 cm off the
    board's centre: measured from the board's centre the elevations would wander with
    the turn; about the fitted axis each set's are one value, and they split."""
    poses = {}
    for prefix, elevation, distance in (("view", 25.0, 0.4), ("set", 33.0, 0.35)):
        for k, angle in enumerate(np.radians(np.arange(0, 360, 20))):
            e = np.radians(elevation)
            centre = np.array([0.03, -0.01, 0]) + distance * np.array(
                [np.cos(angle) * np.cos(e), np.sin(angle) * np.cos(e), np.sin(e)]
            )
            poses[f"{prefix}_{k:03d}.jpg"] = Pose.look_at(centre, [0.03, -0.01, 0.04])
    cameras = turntable_sets.over_the_board(poses)
    elevations = {prefix: [cameras[n][0] for n in poses if n.startswith(prefix)] for prefix in ("view", "set")}
    assert np.ptp(elevations["view"]) < 1e-6 and np.ptp(elevations["set"]) < 1e-6
    found = turntable_sets.split_by_camera(cameras, 6.0, 3)
    assert sorted(map(sorted, found)) == sorted([[n for n in poses if n.startswith(p)] for p in ("set", "view")])
