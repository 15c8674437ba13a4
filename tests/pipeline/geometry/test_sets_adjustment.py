"""Sets adjusted together: a set whose own circle is off is put right by the ring's points
that the matches across the sets share."""

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.camera.model import Intrinsics, rotation_angle_deg
from pipeline.geometry.circular_motion import CircularMotion
from pipeline.geometry.sets_adjustment import JoinedSet, _Tracks, adjust_sets
from pipeline.geometry.turntable import Turntable
from pipeline.geometry.turntable_sets import Join, Solved, project

CAMERA = Intrinsics(256, 192, 300.0, 300.0, 127.5, 95.5, [0.0, 0.0, 0.0, 0.0, 0.0])


def _circle(elevation_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """An axis (up in the photo, tilted towards the camera) and the unit offset ``p`` to it."""
    e = np.radians(elevation_deg)
    axis = np.array([0.0, -np.cos(e), np.sin(e)])
    p = np.array([0.0, 0.0, 1.0]) - axis * axis[2]
    return axis, p / np.linalg.norm(p)


def _solved(axis, p, angles: dict[str, float], points: np.ndarray, keypoints: dict) -> Solved:
    table = Turntable(axis, p, np.eye(3), np.zeros(3), angles)
    poses = {name: table.pose(angle) for name, angle in angles.items()}
    tracks = [{name: k for name in angles} for k in range(len(points))]
    solution = CircularMotion(
        axis, p, dict(angles), CAMERA, points, tracks, np.zeros(len(points), int), {}, {}, {}, {}, 0.2
    )
    return Solved(solution, poses)


def _two_sets():
    """A ring of 15 photos and a set of 12 from a camera moved up, the set as solved alone
    (its axis 3 degrees off) and joined 2 degrees turned; every photo sees every point;
    returns the ring, the set, the matches across, the keypoints and the true poses."""
    rng = np.random.default_rng(0)
    ring_axis, ring_p = _circle(20.0)
    world = ring_p + rng.normal(0.0, 0.08, (300, 3))  # the specimen, on the axis, in the ring's frame
    ring_angles = {f"ring_{i:02d}": a for i, a in enumerate(np.radians(np.arange(0, 360, 24.0)))}
    set_angles = {f"set_{i:02d}": a for i, a in enumerate(np.radians(np.arange(5, 360, 30.0)))}
    # The second set's camera stands 10 degrees higher, 1.1 times as far and 0.15 up the
    # axis, the table turned 23 degrees on; its frame is its first photo's.
    set_axis, set_p = _circle(30.0)
    upright = Rotation.align_vectors([ring_axis], [set_axis])[0].as_matrix()
    R = Rotation.from_rotvec(ring_axis * 0.4).as_matrix() @ upright
    true_join = Join(1.1, R, ring_p + 0.15 * ring_axis - 1.1 * R @ set_p, {})
    in_set = (world - true_join.t) @ true_join.R / true_join.scale
    set_table = Turntable(set_axis, set_p, np.eye(3), np.zeros(3), set_angles)
    truth = {name: Turntable(ring_axis, ring_p, np.eye(3), np.zeros(3), {}).pose(a) for name, a in ring_angles.items()}
    truth |= {name: true_join.pose(set_table.pose(a)) for name, a in set_angles.items()}
    keypoints = {
        name: project(CAMERA, pose, world) + rng.normal(0.0, 0.2, (len(world), 2)) for name, pose in truth.items()
    }
    ring = _solved(ring_axis, ring_p, ring_angles, world, keypoints)
    # The set as solved alone: its axis 3 degrees off, and joined 2 degrees turned.
    tilted = Rotation.from_rotvec([np.radians(3.0), 0, 0]).as_matrix() @ set_axis
    own = _solved(tilted, set_p - tilted * (set_p @ tilted), set_angles, in_set, keypoints)
    own.solution.points[:] = in_set
    joined = Join(1.1, Rotation.from_rotvec(ring_axis * np.radians(2.0)).as_matrix() @ R, true_join.t, {})
    across = {(a, b): {k: k for k in range(len(world))} for a in ring_angles for b in set_angles}
    return ring, own, joined, across, keypoints, truth


def test_a_set_whose_own_circle_is_off_is_put_right_by_the_rings_points():
    ring, own, joined, across, keypoints, truth = _two_sets()
    before = max(rotation_angle_deg(truth[n].R @ joined.pose(p).R.T) for n, p in own.poses.items())

    adjusted = adjust_sets(ring, [JoinedSet(own, joined, across, 100.0)], keypoints, {"f": True}, 3.0)

    errors = [rotation_angle_deg(truth[n].R @ adjusted.poses[n].R.T) for n in truth]
    assert before > 2.0
    assert max(errors) < 0.1, errors
    assert abs(adjusted.intrinsics.fx - 300.0) < 1.0
    assert adjusted.undetermined == [] and adjusted.report["matches_across_shared"] > 0
    assert adjusted.report["set_turn_std_deg"][0] < 0.05


def test_a_set_no_match_across_ties_is_left_undetermined():
    """The same capture with the join's limit at zero: no match across is shared, the
    set's turn is anyone's guess and its photos are not placed."""
    ring, own, joined, across, keypoints, _ = _two_sets()
    adjusted = adjust_sets(ring, [JoinedSet(own, joined, across, 0.0)], keypoints, {"f": True}, 3.0)
    assert adjusted.report["matches_across_shared"] == 0
    assert sorted(adjusted.undetermined) == sorted(own.poses)
    assert set(adjusted.poses) == set(ring.poses)


def test_a_keypoint_matched_into_two_tracks_is_observed_once():
    """A ring photo's untracked keypoint matched with two set photos' different points
    joins one of them (COLMAP refuses a keypoint in two points)."""
    ring, own, joined, _, keypoints, _ = _two_sets()
    for track in ring.solution.tracks:
        track.pop("ring_00", None)  # ring_00's keypoints are tracked by nothing
    tracks = _Tracks(ring, [JoinedSet(own, joined, {}, 1.0)])
    tracks.share(1, ("ring_00", 7), ("set_00", 7))
    tracks.share(1, ("ring_00", 7), ("set_01", 8))
    names = [*ring.poses, *own.poses]
    _, observations = tracks.problem(names, keypoints)
    seen = list(zip(observations.view.tolist(), observations.keypoint.tolist()))
    assert len(seen) == len(set(seen))
    assert seen.count((names.index("ring_00"), 7)) == 1
