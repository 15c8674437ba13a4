import cv2
import numpy as np
import pytest

from pipeline.camera.model import Intrinsics
from pipeline.geometry import circular_motion
from pipeline.geometry.bundle import Observations
from pipeline.geometry.circular_motion import CircularSettings, synchronise_angles
from pipeline.geometry.silhouette_tangency import outline
from tests.support.turntable_views import (
    CAMERA,
    SPECIMEN,
    K,
    blob_mask,
    scaled,
    shaded_turntable_views,
    turntable_views,
)

pytestmark = pytest.mark.slow  # each solve takes a few seconds

# The photos' size and COLMAP's focal length prior: no principal point, no distortion known.
START = Intrinsics(K.width, K.height, 1.2 * K.width, 1.2 * K.width, (K.width - 1) / 2, (K.height - 1) / 2)


def _angle_errors_deg(solution, views) -> np.ndarray:
    """Each placed photo's angle error, their mean offset removed (the angles' gauge)."""
    names = [n for n in views.names if n in solution.angles]
    estimate = np.array([solution.angles[n] for n in names])
    truth = np.array([a for n, a in zip(views.names, views.angles) if n in solution.angles])
    difference = np.angle(np.exp(1j * (estimate - truth)))
    return np.degrees(np.abs(np.angle(np.exp(1j * (difference - np.angle(np.mean(np.exp(1j * difference))))))))


@pytest.fixture(scope="module")
def views():
    return turntable_views()


@pytest.fixture(scope="module")
def solution(views):
    settings = CircularSettings()
    return circular_motion.solve(settings, views.names, START, views.keypoints, views.matches)


def test_the_models_jacobians_are_its_projections_central_differences():
    """The closed-form derivatives the bundle adjustment steps by, against central
    differences of the projection, for a tilted axis, distortion and points about it."""
    rng = np.random.default_rng(0)
    model = circular_motion.Model(np.array([0.1, -0.9, -0.4]))
    g = np.array([0.02, -0.01, 0.3, 900.0, 320.0, 240.0, -0.08])
    axis, p = model.axis_and_point(g)
    views, points = rng.uniform(-3, 3, (6, 1)), p + rng.normal(0, 0.2, (40, 3))
    view, point = np.meshgrid(np.arange(6), np.arange(40), indexing="ij")
    obs = Observations(view.ravel(), point.ravel(), np.zeros((240, 2)))
    pixels, J_global, J_view, J_point = model.jacobians(g, views, points, obs)
    np.testing.assert_allclose(pixels, model.project(g, views, points, obs), atol=1e-6)

    def central(moved_ahead, moved_behind, step):
        return (model.project(*moved_ahead, obs) - model.project(*moved_behind, obs)) / (2 * step)

    for index, step in enumerate([1e-6, 1e-6, 1e-6, 1e-3, 1e-3, 1e-3, 1e-6]):
        ahead, behind = g.copy(), g.copy()
        ahead[index] += step
        behind[index] -= step
        expected = central((ahead, views, points), (behind, views, points), step)
        np.testing.assert_allclose(J_global[:, :, index], expected, rtol=1e-5, atol=1e-4 * np.abs(expected).max())
    expected = central((g, views + 1e-6, points), (g, views - 1e-6, points), 1e-6)
    np.testing.assert_allclose(J_view[:, :, 0], expected, rtol=1e-5, atol=1e-4 * np.abs(expected).max())
    for j in range(3):
        ahead, behind = points.copy(), points.copy()
        ahead[:, j] += 1e-6
        behind[:, j] -= 1e-6
        expected = central((g, views, ahead), (g, views, behind), 1e-6)
        np.testing.assert_allclose(J_point[:, :, j], expected, rtol=1e-5, atol=1e-4 * np.abs(expected).max())


def test_the_solver_recovers_uneven_angles_axis_focal_length_and_distortion(views, solution):
    assert set(solution.angles) == set(views.names) and not solution.unplaced
    assert _angle_errors_deg(solution, views).max() < 0.3
    true_axis = CAMERA.R @ np.array([0.0, 0.0, 1.0])  # world z in the camera's frame
    assert np.degrees(np.arccos(abs(solution.axis @ true_axis))) < 1.0
    assert abs(solution.intrinsics.fx / K.fx - 1) < 0.02  # from a prior 28 % off
    assert abs(solution.intrinsics.dist[0] - K.dist[0]) < 0.02
    calibration = solution.calibration
    assert calibration["values"]["k1"]["adjusted"] and calibration["values"]["k1"]["std"] < 0.01
    # A single circular motion does not determine the principal point: it stays where it was.
    assert not calibration["values"]["cx"]["adjusted"] and solution.intrinsics.cx == START.cx
    # Angles increase in file order: the table turns one way.
    steps = np.diff([solution.angles[n] for n in views.names])
    assert np.all(steps > 0)


def test_a_photo_without_matches_is_left_unplaced_not_stacked(views):
    lonely = views.names[7]
    matches = {pair: found for pair, found in views.matches.items() if lonely not in pair}
    found = circular_motion.solve(CircularSettings(), views.names, START, views.keypoints, matches)
    assert lonely not in found.angles and lonely in found.unplaced
    assert _angle_errors_deg(found, views).max() < 0.3


def test_false_pairs_of_a_symmetric_pattern_are_left_out(views):
    """Photos half a turn apart matched as if barely turned (a board's squares look the same
    from the other side): the pairs disagree with the ring and change nothing."""
    matches = dict(views.matches)
    n = len(views.names)
    for i in range(0, n, 2):
        a, b = views.names[i], views.names[(i + n // 2) % n]
        near = views.matches[views.names[i], views.names[i + 1]]
        matches[a, b] = {u: v % len(views.keypoints[b]) for u, v in near.items()}
        matches[b, a] = {v: u for u, v in matches[a, b].items()}
    found = circular_motion.solve(CircularSettings(), views.names, START, views.keypoints, matches)
    assert _angle_errors_deg(found, views).max() < 0.3


def test_synchronised_angles_wrap_round_a_full_turn():
    truth = np.radians(np.arange(0, 360, 30.0))
    pairs = np.array([(i, (i + k) % 12) for i in range(12) for k in (1, 2)])
    turns = np.angle(np.exp(1j * (truth[pairs[:, 1]] - truth[pairs[:, 0]])))
    angles = synchronise_angles(12, pairs, turns, np.ones(len(pairs)), 0)
    np.testing.assert_allclose(np.angle(np.exp(1j * (angles - truth))), 0, atol=1e-9)


def test_small_noisy_photos_in_alternating_steps_are_all_placed_with_their_uncertainty():
    """256 px photos, steps alternating short and long, keypoints 2 px off: every photo's
    angle is uncertain by about half a degree, and each consistent one is placed with it
    (a fixed limit of 0.5 degrees refused most of them)."""
    lens = scaled(2)
    views = turntable_views(views=40, points=700, jitter=0.1, alternation=2.0, noise_px=2.0, intrinsics=lens)
    start = Intrinsics(lens.width, lens.height, 1.2 * lens.width, 1.2 * lens.width, 127.5, 95.5)
    found = circular_motion.solve(CircularSettings(), views.names, start, views.keypoints, views.matches)
    assert set(found.angles) == set(views.names)
    std = np.array([found.angle_std_deg[n] for n in views.names])
    assert np.median(std) > 0.5
    errors = _angle_errors_deg(found, views)
    assert errors.max() < 1.5 and np.median(errors) < 0.6


def _broken_ring(views, gaps: tuple[int, int]):
    """The views' matches without any pair across the two gaps (after photos gaps[0] and
    gaps[1]): the ring falls into two arcs no feature ties together."""
    low, high = gaps

    def side(name: str) -> bool:
        return low < views.names.index(name) <= high

    return {pair: found for pair, found in views.matches.items() if side(pair[0]) == side(pair[1])}


def test_a_ring_broken_in_two_keeps_the_smaller_arc_as_a_group(views):
    matches = _broken_ring(views, (5, 12))
    found = circular_motion.solve(CircularSettings(), views.names, START, views.keypoints, matches)
    arc = views.names[6:13]
    assert len(found.groups) == 1 and sorted(found.groups[0]) == sorted(arc)
    assert set(found.angles) == set(views.names) - set(arc) and not found.unplaced
    truth = dict(zip(views.names, views.angles))
    relative = np.array([found.groups[0][n] - (truth[n] - truth[arc[0]]) for n in arc])
    assert np.degrees(np.abs(np.angle(np.exp(1j * relative)))).max() < 0.3
    assert set(found.point_groups.tolist()) == {0, 1}


def test_a_ring_broken_in_two_is_joined_by_its_outlines(views):
    """No feature pair crosses the two gaps: the arc's outlines agree with the ring's at
    one offset, and the ring solved with both halves' features and every outline holds
    every photo at its angle."""
    found = circular_motion.solve(
        CircularSettings(), views.names, START, views.keypoints, _broken_ring(views, (5, 12)), outlines=_outlines(views)
    )
    (joined,) = found.joined_groups
    assert joined["joined"] and sorted(joined["photos"]) == sorted(views.names[6:13])
    assert set(found.angles) == set(views.names) and not found.groups
    assert _angle_errors_deg(found, views).max() < 0.3


def _outlines(views, photos_where: "callable" = lambda index: False, shifted: "callable" = lambda index: False) -> dict:
    """The specimen's outline in each photo (pixels); dilated by 2 px where ``photos_where``
    holds for the photo's index (a mask that takes in a shadow), 10 px lower where
    ``shifted`` holds."""
    found = {}
    for i, name in enumerate(views.names):
        mask = blob_mask(views.poses[name], SPECIMEN, views.intrinsics)
        if photos_where(i):
            mask = cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        if shifted(i):
            mask = np.roll(mask, 10, axis=0)
        found[name] = outline(mask)
    return found


def test_outlines_correct_angles_that_shading_features_pull_off():
    """A plain specimen: nearly a third of its features are shading that slides with the
    light. The features alone pull the angles off; fitted with the outlines, much less."""
    lens = scaled(2)
    views = shaded_turntable_views(shading=0.3, seed=1, intrinsics=lens)
    start = Intrinsics(lens.width, lens.height, 1.2 * lens.width, 1.2 * lens.width, 127.5, 95.5)
    alone = _angle_errors_deg(
        circular_motion.solve(CircularSettings(), views.names, start, views.keypoints, views.matches), views
    )
    found = circular_motion.solve(
        CircularSettings(), views.names, start, views.keypoints, views.matches, outlines=_outlines(views)
    )
    errors = _angle_errors_deg(found, views)
    assert set(found.angles) == set(views.names)
    assert np.median(alone) > 0.6 and alone.max() > 1.5
    assert np.median(errors) < 0.5 * np.median(alone) and errors.max() < 1.4
    coherence = found.silhouette_coherence
    assert coherence["pairs"] >= len(views.names) and coherence["tangency_sigma_px"] < 0.5


def test_outlines_leave_angles_that_true_features_pin_down(views, solution):
    """Textured features and masks 2 px too wide in every second photo: the angles stay
    where the features alone put them."""
    found = circular_motion.solve(
        CircularSettings(),
        views.names,
        START,
        views.keypoints,
        views.matches,
        outlines=_outlines(views, lambda i: i % 2),
    )
    assert _angle_errors_deg(found, views).max() < 0.3
    assert np.abs(_angle_errors_deg(found, views) - _angle_errors_deg(solution, views)).max() < 0.05


def test_a_small_specimen_s_pairs_of_a_dozen_matches_place_the_photos_fifteen_leave_out():
    """Few features: neighbours share 6-25 matches, a tenth of them wrong. 15 inliers per
    pair and per photo leave photos out of the ring; one turn about the axis explains a
    dozen matches beyond chance, a photo's one angle needs no more, and the outlines
    agree with the ring the weak pairs extend."""
    views = turntable_views(points=80)
    found = circular_motion.solve(
        CircularSettings(), views.names, START, views.keypoints, views.matches, outlines=_outlines(views)
    )
    verdict = found.weak_pairs
    assert verdict["kept"] and verdict["ring_photos"]["strong_pairs"] < verdict["ring_photos"]["with_weak_pairs"]
    # A photo whose pairs leave it too few inliers is left out, with the count, not stacked.
    assert len(found.angles) >= len(views.names) - 1 and not found.groups
    assert all("inlier observations" in reason for reason in found.unplaced.values())
    errors = _angle_errors_deg(found, views)
    assert np.median(errors) < 0.5 and errors.max() < 1.0


def _solve_broken_ring_with_unverified_pairs(views, outlines: dict):
    """The ring broken after photos 5 and 12, its pairs across the gaps given only as
    matches without a verified geometry."""
    verified = _broken_ring(views, (5, 12))
    unverified = {(a, b): found for (a, b), found in views.matches.items() if (a, b) not in verified and a < b}
    return circular_motion.solve(
        CircularSettings(), views.names, START, views.keypoints, verified, outlines=outlines, unverified=unverified
    )


def test_matches_verification_found_no_geometry_for_close_a_broken_ring(views):
    """The pairs across two gaps come only as matches without a verified geometry: one
    turn each explains them, and the two arcs are one ring again."""
    found = _solve_broken_ring_with_unverified_pairs(views, _outlines(views))
    assert found.weak_pairs["kept"] and found.weak_pairs["ring_photos"] == {"strong_pairs": 13, "with_weak_pairs": 20}
    assert set(found.angles) == set(views.names) and not found.groups
    assert _angle_errors_deg(found, views).max() < 0.3


def test_a_ring_extended_by_weak_pairs_that_its_outlines_disagree_with_is_refused(views):
    """The same broken ring, the arc's masks 10 px too low: however well its features
    fit, the extended ring's outlines disagree far more than the strong ring's (whatever
    put it off, weak pairs or masks), so the strong ring and its group stand."""
    found = _solve_broken_ring_with_unverified_pairs(views, _outlines(views, shifted=lambda i: 5 < i <= 12))
    assert not found.weak_pairs["kept"] and "disagree" in found.weak_pairs["decision"]
    # Nor is the arc joined by its outlines, which disagree with the ring's at every offset.
    (joined,) = found.joined_groups
    assert not joined["joined"]
    assert len(found.groups) == 1 and sorted(found.groups[0]) == sorted(views.names[6:13])


def test_the_extended_ring_is_kept_only_where_it_joins_more_photos_and_its_outlines_agree():
    verdict = circular_motion.extension_verdict
    assert verdict((30, 50), (0.3, 0.7), 2.5)["kept"]
    assert not verdict((30, 50), (0.3, 0.8), 2.5)["kept"]  # 2.7 times the strong ring's noise
    assert not verdict((50, 50), (0.3, 0.3), 2.5)["kept"]  # joins no more photos
    refused = verdict((30, 50), (None, 0.3), 2.5)
    assert not refused["kept"] and "could not judge" in refused["decision"]
