import numpy as np

from pipeline.camera.model import Intrinsics, Pose
from pipeline.geometry import turntable
from pipeline.geometry.turntable import Turntable, angle_from_silhouette, fit, fit_robust, splat

K = Intrinsics(160, 120, 200.0, 200.0, 79.5, 59.5)
NAMES = [f"view_{i:02d}.jpg" for i in range(16)]


def _truth(seed=0) -> tuple[Turntable, dict[str, float]]:
    rng = np.random.default_rng(seed)
    steps = 1 + 0.4 * rng.uniform(-1, 1, len(NAMES))  # a hand-turned table
    angles = np.concatenate([[0], np.cumsum(steps[:-1])]) * 2 * np.pi / steps.sum()
    axis = np.array([0.1, -0.05, 1.0])
    axis /= np.linalg.norm(axis)
    camera = Pose.look_at([0.4, 0.05, 0.2], [0.0, 0.0, 0.03], up=axis)
    model = Turntable(axis, np.array([0.01, -0.02, 0.0]), camera.R, camera.center, {})
    return model, dict(zip(NAMES, angles))


def test_fit_recovers_the_circle_and_the_uneven_angles():
    truth, angles = _truth()
    poses = {n: truth.pose(a) for n, a in angles.items()}
    model = fit(poses, NAMES)
    np.testing.assert_allclose(model.axis, truth.axis, atol=1e-9)
    steps = np.diff([model.angles[n] for n in NAMES])
    np.testing.assert_allclose(steps, np.diff([angles[n] for n in NAMES]), atol=1e-9)
    assert all(r < 1e-6 and c < 1e-6 for r, c in model.residuals(poses).values())
    for name in NAMES:
        np.testing.assert_allclose(model.pose(model.angles[name]).center, poses[name].center, atol=1e-9)


def test_fit_robust_drops_a_pose_off_the_circle():
    truth, angles = _truth(1)
    poses = {n: truth.pose(a) for n, a in angles.items()}
    wrong = poses[NAMES[5]]
    twist = turntable._turn(np.array([1.0, 0, 0]), np.radians(20))
    poses[NAMES[5]] = Pose(wrong.R @ twist, wrong.t)
    model, dropped = fit_robust(poses, NAMES)
    assert dropped == [NAMES[5]]
    assert max(r for r, _ in model.residuals({n: p for n, p in poses.items() if n != NAMES[5]}).values()) < 1e-6


def test_silhouette_places_a_photo_between_its_neighbours():
    truth, angles = _truth(2)
    rng = np.random.default_rng(0)
    # An asymmetric specimen: a box with a bump, as hull voxels.
    points = rng.uniform([-0.04, -0.02, 0], [0.04, 0.02, 0.05], (4000, 3))
    points = np.vstack([points, rng.uniform([0.02, 0.0, 0.05], [0.04, 0.02, 0.08], (800, 3))])
    missing = NAMES[7]
    model = fit({n: truth.pose(a) for n, a in angles.items() if n != missing}, NAMES)
    pose = truth.pose(angles[missing])
    depth = np.linalg.norm(model.c_fixed - points.mean(axis=0))
    mask = splat(points, int(np.ceil(0.5 * 0.004 * K.fx / depth)), pose, K, (K.height, K.width))
    lo, hi = turntable.bracket(model, NAMES, missing)
    angle, iou = angle_from_silhouette(model, lo, hi, points, 0.004, K, mask)
    assert iou > 0.95
    assert abs(np.degrees(angle - angles[missing])) < 0.5


def _project(points: np.ndarray, pose: Pose) -> np.ndarray:
    camera = points @ pose.R.T + pose.t
    return np.column_stack([K.fx * camera[:, 0] / camera[:, 2] + K.cx, K.fy * camera[:, 1] / camera[:, 2] + K.cy])


def test_matches_place_a_photo_and_a_false_pair_is_dropped():
    truth, angles = _truth(3)
    rng = np.random.default_rng(1)
    missing = NAMES[6]
    model = fit({n: truth.pose(a) for n, a in angles.items() if n != missing}, NAMES)
    # Features on a board-sized patch of table and on the specimen, spanning the frame.
    points = rng.uniform([-0.12, -0.12, 0], [0.12, 0.12, 0.06], (80, 3))
    pose = truth.pose(angles[missing])

    def seen_from(name: str) -> np.ndarray:
        return _project(points, truth.pose(angles[name])) + rng.normal(0, 0.3, (len(points), 2))

    seen = seen_from(missing)
    matches = [turntable.Matches(truth.pose(angles[n]), K, seen, seen_from(n)) for n in (NAMES[5], NAMES[7])]
    # A false pair: a quarter turn away, matched at random (a repetitive pattern).
    matches.append(
        turntable.Matches(
            truth.pose(angles[NAMES[10]]), K, seen, rng.uniform([0, 0], [K.width, K.height], (len(points), 2))
        )
    )
    lo, hi = turntable.bracket(model, NAMES, missing)
    angle, agreeing = turntable.angle_from_matches(model, lo, hi, K, matches)
    # 0.3 px of keypoint noise moves the angle by about 0.2 degrees (see its limitation).
    assert abs(np.degrees(angle - model.angle_of(pose))) < 0.3  # the fitted model counts from its own zero
    assert len(agreeing) == 2 and matches[2] not in agreeing
