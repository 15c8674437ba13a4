import cv2
import numpy as np

from pipeline.geometry import silhouette_coherence, silhouette_tangency
from pipeline.geometry.turntable import Turntable
from tests.support.turntable_views import CAMERA, blob_mask, pose_at, scaled

LENS = scaled(4)
"""512 px photos: the specimen's outline some 70 px across."""

SPHERES = [((0.0, 0.0, 0.03), 0.03), ((0.025, 0.01, 0.06), 0.018), ((-0.02, -0.015, 0.015), 0.015)]
"""A lumpy specimen: its outline changes shape as the table turns."""


def _motion():
    """The turntable as the circular-motion solver sees it: the camera fixed at the
    origin, the axis (world z) and a point on it in the camera's frame."""
    axis = CAMERA.R @ np.array([0.0, 0.0, 1.0])
    point = CAMERA.t - axis * (axis @ CAMERA.t)
    return axis, point


def _normalised(hulls: list[np.ndarray]) -> np.ndarray:
    padded = silhouette_tangency.padded(hulls)
    return (padded - [LENS.cx, LENS.cy]) / LENS.fx


def test_a_pair_s_turn_gives_the_tangency_of_its_two_poses_and_errors_are_signed():
    """The circular motion's shortcut (a pair's relative pose from its turn alone) against
    the relative pose of the two photos' own poses on the turntable."""
    rng = np.random.default_rng(0)
    axis, point = _motion()
    angles = np.sort(rng.uniform(0, 2 * np.pi, 10))
    hulls = []
    for _ in angles:
        cloud = (rng.normal(size=(40, 2)) * [0.05, 0.08]).astype(np.float32)
        hulls.append(cv2.convexHull(cloud.reshape(-1, 1, 2)).reshape(-1, 2).astype(float))
    padded = silhouette_tangency.padded(hulls)
    pairs = silhouette_coherence.choose_pairs(angles)
    turns = angles[pairs[:, 1]] - angles[pairs[:, 0]]
    residuals = silhouette_coherence.tangency_residuals(axis, point, turns, padded, pairs, 100.0)
    table = Turntable(axis, point, np.eye(3), np.zeros(3), {})
    poses = [table.pose(a) for a in angles]
    R = np.array([poses[b].R @ poses[a].R.T for a, b in pairs])
    t = np.array([poses[b].t - R_ab @ poses[a].t for (a, b), R_ab in zip(pairs, R)])
    own, valid = silhouette_tangency.tangency_errors(R, t, padded[pairs[:, 0]], padded[pairs[:, 1]])
    assert valid.sum() > len(pairs) // 2
    np.testing.assert_allclose(residuals, own * 100.0, atol=1e-9)
    # Random outlines do not agree: some tangents miss, some cut.
    assert np.any(residuals > 0) and np.any(residuals < 0)


def test_a_tangent_that_misses_is_positive_and_one_that_cuts_is_negative():
    """Two photos 60 degrees apart at the true motion: a's tangents carried to b touch b's
    outline; shrunk about its centre, b's outline is missed, grown, it is cut."""
    axis, point = _motion()
    hull_a, hull_b = (silhouette_tangency.outline(blob_mask(pose_at(a), SPHERES, LENS)) for a in (0.0, np.pi / 3))
    normalised = _normalised([hull_a, hull_b])
    centre = normalised[1].mean(axis=0)
    for scale, sign in ((0.9, 1.0), (1.1, -1.0)):
        outlines = np.stack([normalised[0], centre + scale * (normalised[1] - centre)])
        found = silhouette_coherence.tangency_residuals(
            axis, point, np.array([np.pi / 3]), outlines, np.array([[0, 1]]), LENS.fx
        )
        assert np.all(sign * found[0, :2] > 1.0)  # pixels


def test_the_true_motion_makes_the_outlines_agree_and_a_wrong_turn_does_not():
    axis, point = _motion()
    angles = np.radians(np.arange(0, 360, 20.0))
    hulls = [silhouette_tangency.outline(blob_mask(pose_at(a), SPHERES, LENS)) for a in angles]
    normalised = _normalised(hulls)
    pairs = silhouette_coherence.choose_pairs(angles)
    assert len(pairs) >= len(angles) * silhouette_coherence.PARTNERS // 2

    def sigma(turn_error_deg: float) -> float:
        turns = angles[pairs[:, 1]] - angles[pairs[:, 0]] + np.radians(turn_error_deg)
        found = silhouette_coherence.tangency_residuals(axis, point, turns, normalised, pairs, LENS.fx)
        return silhouette_coherence.robust_sigma(found)

    # Rasterised masks (and a lens distortion the outlines keep): a fraction of a pixel.
    assert sigma(0.0) < 0.5
    assert sigma(3.0) > 3 * sigma(0.0)


def test_choose_pairs_skips_turns_that_give_no_tangents():
    angles = np.radians([0.0, 5.0, 60.0, 120.0, 178.0])
    pairs = silhouette_coherence.choose_pairs(angles)
    turns = np.degrees(np.abs(np.angle(np.exp(1j * (angles[pairs[:, 1]] - angles[pairs[:, 0]])))))
    assert np.all((turns > silhouette_coherence.MIN_TURN_DEG) & (turns < silhouette_coherence.MAX_TURN_DEG))
    assert (0, 1) not in map(tuple, pairs) and (0, 4) not in map(tuple, pairs)
    assert len({tuple(p) for p in pairs}) == len(pairs)


def test_the_weighting_is_quadratic_near_zero_and_bounded_far_out():
    small = silhouette_coherence.weighted(np.array([0.1, -0.1]), sigma=1.0, feature_sigma=0.5)
    np.testing.assert_allclose(small, [0.05, -0.05], rtol=1e-3)
    far = silhouette_coherence.weighted(np.array([100.0, 1000.0]), sigma=1.0, feature_sigma=0.5)
    assert far[1] < 2 * far[0]  # a bad mask's tangent pulls little harder the worse it is
