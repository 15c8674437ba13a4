"""Sets of a turntable capture joined by their features: a user shoots a turn, moves the
tripod up or down for a second ring, or turns the specimen over and shoots another
turn. Each set is its own circular motion (the camera's height, tilt and distance
from the axis are its own; a re-placed specimen stands on the table in a new pose),
and its place relative to the first set is known only where features prove it.

1. **Which photos are sets.** Where the camera moved: each photo posed freely (PnP)
   on the points of the one circle fitted to all (``free_cameras``), its elevation
   over the circle's plane; the photos split where those elevations form groups
   (``split_by_camera``), a photo not posed freely going with the group it shares
   the most matches with (``with_the_rest``). And a group of photos the
   circular-motion solver left apart from the ring (pipeline.geometry.circular_motion,
   ``_join_groups``), whose photos share strong pairs of verified matches with the
   ring's that one circle does not explain, is another set. (A group no such pair
   ties to the ring is an arc of the ring that matching left apart: its outlines
   place it, marked uncertain.) Ring matching retrieves the pairs across sets by
   their descriptors on the specimen (pipeline.colmap.features,
   ``descriptor_neighbours``): their outlines differ.
2. **Each set alone**: its photos' circular motion solved at the ring's intrinsics
   (held: one camera), its own axis, camera offset, angles and points.
3. **The join**: the similarity (rotation, translation, scale: each set's unit is its
   own camera's distance from the axis) taking the set's points into the ring's
   frame. Drawn by RANSAC from triples of points that matches across the sets tie
   together, only matches whose keypoints lie on the specimen's masks in both photos
   (a specimen turned over on a patterned table no longer turns with the table, whose
   matches would join the table, not the specimen), then refined on the reprojection errors of every such match's
   observations (a set's point in the ring's photo, a ring's point in the set's
   photo). Its inliers lie within ``join_noise_factor`` times the larger median
   reprojection error of the two sets' own features: a noise level measured on the
   photos, not a number of pixels. The set is joined when at least
   ``min_observations`` inlier observations from at least two photo pairs fit (one
   false pair cannot join a set), and ``CHANCE_FACTOR`` times as many as the same
   estimation finds with the matches across the sets shuffled (a similarity chosen
   from hundreds of draws and refined explains a few dozen of thousands of random
   observations); else it is left out, with the reason.
4. **The report**: per set its photos, the pairs and inliers, the residual, the
   uncertainty of its turn about the ring's axis (from the refinement's covariance),
   and how the camera moved: the change of its elevation over the table, its distance
   from the axis, and how far the specimen's axis turned (a specimen turned over).

The joined sets are then adjusted together (pipeline.geometry.sets_adjustment).

Limitations: a join is drawn on each set's circle as solved alone: a set whose own
circle is too far off for its matches across to fit one similarity within the noise is
left out, not solved together. Outlines never join a set. A specimen
turned over on a patterned table with the camera where it stood is not found: the
table's features put both sets on one circle and the specimen's matches across them,
which disagree with it, are set aside as pairs one turn does not explain (their
epipolar agreement alone does not tell the sets apart: a circle's own neighbouring
pairs disagree about as often).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from pipeline.camera.model import Intrinsics, Pose, similarity_umeyama
from pipeline.geometry.circular_motion import CircularMotion
from pipeline.geometry.turntable import Turntable

CHANCE_FACTOR = 3
"""A join must explain this many times the observations the same estimation explains
with the matches across the sets shuffled (random matches were joined by 26 of 4,000
observations, at least 15 and from 20 pairs of photos)."""
JOIN_TRIALS = 500
"""RANSAC draws of three tied points: with half of them right, the chance that none of
500 draws is all right is 1e-29."""


@dataclass(frozen=True)
class Solved:
    """A circular motion solved, and its placed photos' poses in its frame."""

    solution: CircularMotion
    poses: dict[str, Pose]


@dataclass
class Join:
    """A set joined to the ring: ring-frame points are ``scale * R @ set points + t``."""

    scale: float
    R: np.ndarray
    t: np.ndarray
    report: dict

    def pose(self, own: Pose) -> Pose:
        """A set photo's pose (in the set's frame) in the ring's frame."""
        R = own.R @ self.R.T
        return Pose(R, self.scale * own.t - R @ self.t)

    def points(self, own: np.ndarray) -> np.ndarray:
        return self.scale * own @ self.R.T + self.t


@dataclass
class _Tied:
    """What matches across the sets tie: pairs of points (ring's, set's), and the
    observations of each side's points in the other side's photos."""

    ring_points: np.ndarray
    set_points: np.ndarray
    in_ring_photos: list[tuple[str, np.ndarray, int, tuple[str, str]]]
    """(ring photo, pixel, set point index, the pair of photos whose match it is)."""
    in_set_photos: list[tuple[str, np.ndarray, int, tuple[str, str]]]
    """(set photo, pixel, ring point index, the pair of photos whose match it is)."""


def _track_index(solution: CircularMotion) -> dict[tuple[str, int], int]:
    """(photo, keypoint) -> point index of the solution's tracks."""
    return {(name, k): point for point, track in enumerate(solution.tracks) for name, k in track.items()}


def _tie(
    ring_side: Solved,
    set_side: Solved,
    keypoints: dict[str, np.ndarray],
    matches: dict[tuple[str, str], dict[int, int]],
) -> _Tied:
    ring, own = ring_side.solution, set_side.solution
    ring_index, own_index = _track_index(ring), _track_index(own)
    ring_points, set_points, in_ring, in_set = [], [], [], []
    seen: set[tuple[int, int]] = set()
    for (a, b), found in sorted(matches.items()):
        if a not in ring_side.poses or b not in set_side.poses:
            continue
        for ka, kb in found.items():
            ring_point, set_point = ring_index.get((a, ka)), own_index.get((b, kb))
            if set_point is not None:
                in_ring.append((a, keypoints[a][ka], set_point, (a, b)))
            if ring_point is not None:
                in_set.append((b, keypoints[b][kb], ring_point, (a, b)))
            if ring_point is not None and set_point is not None and (ring_point, set_point) not in seen:
                seen.add((ring_point, set_point))
                ring_points.append(ring.points[ring_point])
                set_points.append(own.points[set_point])
    return _Tied(np.array(ring_points).reshape(-1, 3), np.array(set_points).reshape(-1, 3), in_ring, in_set)


def project(intrinsics: Intrinsics, pose: Pose, points: np.ndarray) -> np.ndarray:
    """Pixels of ``points`` (n, 3) in a photo at ``pose``, with the radial term k1 the
    circular-motion solver fits (the photos' pixels carry what undistort left)."""
    camera = points @ pose.R.T + pose.t
    z = np.maximum(camera[:, 2], 1e-9)
    x, y = camera[:, 0] / z, camera[:, 1] / z
    radial = 1 + intrinsics.dist[0] * (x * x + y * y)
    return np.column_stack([intrinsics.fx * x * radial + intrinsics.cx, intrinsics.fy * y * radial + intrinsics.cy])


class _Residuals:
    """Reprojection errors of the tied observations under a similarity (rotation vector,
    translation, log scale): a set point in a ring photo, a ring point in a set photo."""

    def __init__(self, tied: _Tied, ring: Solved, own: Solved):
        self.intrinsics = ring.solution.intrinsics
        self.ring_side = _Side(tied.in_ring_photos, ring.poses, own.solution.points)
        self.set_side = _Side(tied.in_set_photos, own.poses, ring.solution.points)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return np.concatenate([self.errors(x, self.ring_side), self.errors(x, self.set_side)]).ravel()

    def errors(self, x: np.ndarray, side: "_Side") -> np.ndarray:
        if not len(side.pixels):
            return np.zeros((0, 2))
        R, t, scale = Rotation.from_rotvec(x[:3]).as_matrix(), x[3:6], np.exp(x[6])
        if side is self.ring_side:  # set points into the ring's frame
            moved = scale * side.points @ R.T + t
        else:  # ring points into the set's frame
            moved = (side.points - t) @ R / scale
        out = np.zeros_like(side.pixels)
        for name, rows in side.rows.items():
            out[rows] = project(self.intrinsics, side.poses[name], moved[rows]) - side.pixels[rows]
        return out

    def inliers(self, x: np.ndarray, limit_px: float) -> tuple[np.ndarray, np.ndarray]:
        """Which observations of each side reproject within ``limit_px``."""
        return tuple(
            np.linalg.norm(self.errors(x, side), axis=1) < limit_px for side in (self.ring_side, self.set_side)
        )


class _Side:
    """Observations of one side's photos of the other side's points."""

    def __init__(self, observed: list[tuple], poses: dict[str, Pose], points: np.ndarray):
        self.poses = poses
        self.names = [name for name, *_ in observed]
        self.pairs = [pair for *_, pair in observed]
        self.pixels = np.array([pixel for _, pixel, *_ in observed]).reshape(-1, 2)
        self.points = points[[point for _, _, point, _ in observed]].reshape(-1, 3)
        self.rows: dict[str, np.ndarray] = {}
        for row, name in enumerate(self.names):
            self.rows.setdefault(name, []).append(row)
        self.rows = {name: np.array(rows) for name, rows in self.rows.items()}


def _parameters(scale: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return np.concatenate([Rotation.from_matrix(R).as_rotvec(), t, [np.log(scale)]])


@dataclass
class _Estimate:
    """A join drawn and refined on one set of tied observations."""

    x: np.ndarray
    """Rotation vector, translation, log scale."""
    inliers: int
    photo_pairs: int
    errors: np.ndarray
    """(inliers, 2) reprojection errors of the inlier observations."""
    residual: object
    """The inliers' residual function of ``x`` (for the covariance)."""


def _estimate(residuals: "_Residuals", tied: _Tied, limit_px: float, noise_px: float) -> _Estimate | None:
    """RANSAC over triples of tied points, scored by the observations each draw explains,
    then least squares on the best draw's inliers (twice, recounting them)."""
    rng = np.random.default_rng(0)
    best, best_count = None, -1
    for _ in range(JOIN_TRIALS):
        sample = rng.choice(len(tied.ring_points), 3, replace=False)
        source, target = tied.set_points[sample], tied.ring_points[sample]
        if np.linalg.matrix_rank(source - source.mean(0), tol=1e-9) < 2:
            continue
        scale, R, t = similarity_umeyama(source, target)
        if not np.isfinite(scale) or scale <= 0:
            continue
        x = _parameters(scale, R, t)
        count = sum(int(inside.sum()) for inside in residuals.inliers(x, limit_px))
        if count > best_count:
            best, best_count = x, count
    if best is None:
        return None
    x = best
    for _ in range(2):
        ring_in, set_in = residuals.inliers(x, limit_px)
        if not (ring_in.sum() + set_in.sum()):
            break
        x = least_squares(_InlierResiduals(residuals, ring_in, set_in), x, loss="soft_l1", f_scale=noise_px).x
    ring_in, set_in = residuals.inliers(x, limit_px)
    pairs = {pair for pair, inside in zip(residuals.ring_side.pairs, ring_in) if inside}
    pairs |= {pair for pair, inside in zip(residuals.set_side.pairs, set_in) if inside}
    inlier_residuals = _InlierResiduals(residuals, ring_in, set_in)
    return _Estimate(
        x, int(ring_in.sum() + set_in.sum()), len(pairs), inlier_residuals(x).reshape(-1, 2), inlier_residuals
    )


class _InlierResiduals:
    def __init__(self, residuals: "_Residuals", ring_in: np.ndarray, set_in: np.ndarray):
        self.residuals, self.ring_in, self.set_in = residuals, ring_in, set_in

    def __call__(self, x: np.ndarray) -> np.ndarray:
        r = self.residuals
        return np.concatenate([r.errors(x, r.ring_side)[self.ring_in], r.errors(x, r.set_side)[self.set_in]]).ravel()


def _shuffled(matches: dict[tuple[str, str], dict[int, int]], ring: set[str], rng) -> dict:
    """The matches across the sets with each pair's partners shuffled: what the same
    photos, points and geometry give by chance."""
    shuffled = {}
    for (a, b), found in matches.items():
        if a in ring and b not in ring and found:
            keys, values = list(found), rng.permutation(list(found.values()))
            shuffled[a, b] = dict(zip(keys, (int(v) for v in values)))
    return shuffled


def join(
    ring: Solved,
    own: Solved,
    keypoints: dict[str, np.ndarray],
    matches: dict[tuple[str, str], dict[int, int]],
    min_observations: int,
    noise_factor: float,
    axis: np.ndarray,
) -> tuple[Join | None, dict]:
    """Steps 3-4 for one set: its join to the ring (None when features do not prove
    one) and its report. ``axis``: the turntable's axis in the ring's frame."""
    tied = _tie(ring, own, keypoints, matches)
    noise_px = max(ring.solution.reprojection_px, own.solution.reprojection_px, 0.1)
    limit_px = noise_factor * noise_px
    report: dict = {
        "tied_points": len(tied.ring_points),
        "observations_across": len(tied.in_ring_photos) + len(tied.in_set_photos),
        "noise_px": round(noise_px, 3),
        "inlier_limit_px": round(limit_px, 3),
    }
    found = _estimate(_Residuals(tied, ring, own), tied, limit_px, noise_px) if len(tied.ring_points) >= 3 else None
    if found is None:
        report["decision"] = f"{len(tied.ring_points)} points tied across the sets by matches, none in general place"
        return None, report
    # The same estimation on the matches shuffled within each pair: how many
    # observations a join explains by chance, selected as it was from many draws.
    null = _tie(ring, own, keypoints, _shuffled(matches, set(ring.poses), np.random.default_rng(1)))
    chance = _estimate(_Residuals(null, ring, own), null, limit_px, noise_px) if len(null.ring_points) >= 3 else None
    by_chance = chance.inliers if chance is not None else 0
    report["inliers"] = found.inliers
    report["inliers_by_chance"] = by_chance
    report["photo_pairs"] = found.photo_pairs
    report["residual_px_median"] = (
        round(float(np.median(np.linalg.norm(found.errors, axis=1))), 3) if found.inliers else None
    )
    needed = max(min_observations, CHANCE_FACTOR * by_chance)
    if found.inliers < needed or found.photo_pairs < 2:
        report["decision"] = (
            f"{found.inliers} observations across the sets fit one join within {limit_px:.2f} px, from "
            f"{found.photo_pairs} pairs of photos ({by_chance} with the matches shuffled); a join needs {needed} "
            "from at least two pairs"
        )
        return None, report
    x = found.x
    R, t, scale = Rotation.from_rotvec(x[:3]).as_matrix(), x[3:6], float(np.exp(x[6]))
    joined = Join(scale, R, t, report)
    report["angle_std_deg"] = _turn_std_deg(x, found.residual, axis, found.errors)
    report.update(_camera_moves(ring, own, joined, axis))
    report["decision"] = (
        f"joined by {found.inliers} observations of {found.photo_pairs} pairs of photos within {limit_px:.2f} px "
        f"({by_chance} with the matches shuffled)"
    )
    return joined, report


def _turn_std_deg(x: np.ndarray, residual, axis: np.ndarray, errors: np.ndarray) -> float:
    """One standard deviation of the join's turn about the table's axis (degrees), from
    the refinement's covariance at the inliers' own noise."""
    step = 1e-6
    base = residual(x)
    J = np.column_stack([(residual(x + step * e) - base) / step for e in np.eye(len(x))])
    sigma = float(np.sqrt(np.mean(errors**2))) if len(errors) else 1.0
    covariance = np.linalg.pinv(J.T @ J) * sigma**2
    return float(np.degrees(np.sqrt(max(axis @ covariance[:3, :3] @ axis, 0.0))))


def _camera_moves(ring: Solved, own: Solved, joined: Join, axis: np.ndarray) -> dict:
    """How the set's camera stands to the table against the ring's: its elevation over
    the table and its distance from the axis (medians over the photos), and how far the
    set's own axis lies from the ring's (a specimen re-placed or turned over)."""

    def elevation_and_distance(poses: list[Pose]) -> tuple[float, float]:
        elevations, distances = [], []
        for pose in poses:
            along = float((pose.center - ring.solution.point) @ axis)
            radial = np.linalg.norm(pose.center - ring.solution.point - along * axis)
            forward = pose.R[2]
            elevations.append(np.degrees(np.arcsin(np.clip(-forward @ axis, -1, 1))))
            distances.append(radial)
        return float(np.median(elevations)), float(np.median(distances))

    ring_elevation, ring_distance = elevation_and_distance(list(ring.poses.values()))
    set_elevation, set_distance = elevation_and_distance([joined.pose(p) for p in own.poses.values()])
    own_axis = joined.R @ own.solution.axis
    # Each set's axis points the way its table turned: a specimen turned over turns it by 180.
    tilt = float(np.degrees(np.arccos(np.clip(own_axis @ axis, -1, 1))))
    return {
        # The axis' sign follows the turning sense, not up: the change's size is reported.
        "elevation_change_deg": round(abs(set_elevation - ring_elevation), 2),
        "distance_ratio": round(set_distance / ring_distance, 4) if ring_distance else None,
        "specimen_axis_turned_deg": round(tilt, 2),
    }


def free_cameras(solution: CircularMotion, keypoints: dict[str, np.ndarray], matches) -> dict[str, tuple[float, float]]:
    """Each placed photo's camera posed freely on the solution's points (PnP with RANSAC
    through its matches to photos whose keypoints the tracks hold, started at its
    circle pose): its elevation over the circle's plane (degrees) and its distance from
    the axis (in the circle's unit). One circle fitted to two sets shot from different
    heights puts both between them; posed freely, each set's photos sit at their own."""
    K = solution.intrinsics
    camera = np.array([[K.fx, 0, K.cx], [0, K.fy, K.cy], [0, 0, 1.0]])
    distortion = np.array([K.dist[0], 0, 0, 0, 0], float)
    tracked = _track_index(solution)
    table = Turntable(solution.axis, solution.point, np.eye(3), np.zeros(3), solution.angles)
    found = {}
    for name, pose in ((n, table.pose(a)) for n, a in solution.angles.items()):
        objects, pixels = [], []
        for (a, b), pairs in matches.items():
            if a != name:
                continue
            for mine, theirs in pairs.items():
                point = tracked.get((b, theirs))
                if point is not None:
                    objects.append(solution.points[point])
                    pixels.append(keypoints[name][mine])
        if len(objects) < 6:
            continue
        rvec = cv2.Rodrigues(pose.R)[0]
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            np.array(objects, float), np.array(pixels, float), camera, distortion, rvec, pose.t.reshape(3, 1).copy(),
            useExtrinsicGuess=True, reprojectionError=max(2.0, 4 * solution.reprojection_px), iterationsCount=200,
        )  # fmt: skip
        if not ok or inliers is None or len(inliers) < 6:
            continue
        centre = -cv2.Rodrigues(rvec)[0].T @ tvec.ravel() - solution.point
        along = float(centre @ solution.axis)
        radial = float(np.linalg.norm(centre - along * solution.axis))
        found[name] = (float(np.degrees(np.arctan2(along, radial))), radial)
    return found


def over_the_board(board_poses: dict[str, Pose]) -> dict[str, tuple[float, float]]:
    """Each photo's camera over the board on the table, from its board pose: its
    elevation over the board's plane (degrees) and its distance from the table's axis
    (metres), as ``free_cameras`` gives them. The axis is the board's normal through the
    centre of the circle fitted to the cameras' centres in the board's plane (Kasa's
    algebraic fit: the board need not lie at the table's centre; the sets' circles about
    one axis share that centre)."""
    names = list(board_poses)
    centres = np.array([board_poses[name].center for name in names])
    x, y = centres[:, 0], centres[:, 1]
    (d, e, _), *_ = np.linalg.lstsq(np.column_stack([x, y, np.ones(len(x))]), -(x * x + y * y), rcond=None)
    radial = np.hypot(x + d / 2, y + e / 2)
    elevation = np.degrees(np.arctan2(centres[:, 2], radial))
    return {name: (float(a), float(r)) for name, a, r in zip(names, elevation, radial)}


def split_by_camera(cameras: dict[str, tuple[float, float]], separation: float, min_photos: int) -> list[list[str]]:
    """The photos in groups whose free cameras stand at different elevations:
    recursively, the split of the sorted elevations into two groups with the least
    squares within them (Otsu's) is kept where their medians lie ``separation`` robust
    standard deviations apart (each group's median absolute deviation, pooled by size,
    at least ``MIN_ELEVATION_SPREAD_DEG``) and each holds ``min_photos``. One set's
    photos scatter about one elevation: the best split of one unimodal scatter lies
    about three deviations apart. (A camera moved only nearer or farther changes its
    elevation too; the distances from the axis split a single set's photos where they
    cluster by chance, and are not used.)"""
    names = sorted(cameras, key=lambda n: cameras[n][0])
    elevations = np.array([cameras[n][0] for n in names])
    cuts = range(min_photos, len(names) - min_photos + 1)
    if not cuts:
        return [names]
    # The cut is Otsu's (the least squares within the two groups); the test is robust.
    cut = min(cuts, key=lambda c: float(np.var(elevations[:c]) * c + np.var(elevations[c:]) * (len(names) - c)))
    low, high = elevations[:cut], elevations[cut:]
    spread = np.sqrt((len(low) * _robust_std(low) ** 2 + len(high) * _robust_std(high) ** 2) / len(names))
    if (np.median(high) - np.median(low)) / max(spread, MIN_ELEVATION_SPREAD_DEG) < separation:
        return [names]
    return [
        *split_by_camera({n: cameras[n] for n in names[:cut]}, separation, min_photos),
        *split_by_camera({n: cameras[n] for n in names[cut:]}, separation, min_photos),
    ]


def strays(cameras: dict[str, tuple[float, float]], separation: float) -> list[str]:
    """The photos whose free camera (``free_cameras``) stands more than ``separation``
    robust standard deviations (at least MIN_ELEVATION_SPREAD_DEG) from the median
    elevation of all: in a set solved alone, photos of another set."""
    if len(cameras) < 3:
        return []
    elevations = np.array([elevation for elevation, _ in cameras.values()])
    spread = max(_robust_std(elevations), MIN_ELEVATION_SPREAD_DEG)
    far = np.abs(elevations - np.median(elevations)) > separation * spread
    return [name for name, stray in zip(cameras, far) if stray]


def with_the_rest(found_sets: list[list[str]], names: list[str], matches) -> list[list[str]]:
    """``found_sets`` with each of ``names`` in none of them (a photo not posed freely)
    added to the set it shares the most matches with (the first where it shares none):
    a photo of a moved camera's set must not be solved on the first set's circle."""
    member = {name: k for k, found in enumerate(found_sets) for name in found}
    grown = [list(found) for found in found_sets]
    for name in names:
        if name in member:
            continue
        shared = np.zeros(len(found_sets))
        for (a, b), found in matches.items():
            if a == name and b in member:
                shared[member[b]] += len(found)
        grown[int(np.argmax(shared))].append(name)
    return grown


MIN_ELEVATION_SPREAD_DEG = 0.05
"""The least scatter of one set's free elevations: a few photos that agree by chance
must not make a tiny gap look wide."""


def _robust_std(values: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(values - np.median(values))))
