"""All sets of a turntable capture adjusted together: one camera, a circle per set, each
set's place on the specimen, and the points the matches across sets share.

Each set was solved alone and joined to the ring by a similarity
(pipeline.geometry.turntable_sets). A set solved alone has only its own photos to fix
its circle: a set of a few short arcs fixes its axis poorly, and the join then places
a circle that is itself off. Adjusted together, a set's cameras see the ring's points
through the matches across the sets, which hold its circle as well as its place.

The model (parameters of the bundle adjuster, pipeline.geometry.bundle):

===================  =====================================================================
global, shared       focal length, principal point, radial k1 (the ring's: free where
                     the ring's self-calibration freed them, the principal point held)
global, per set      the set's circle in its own frame: axis direction (two) and the angle
                     of the camera's offset from it (pipeline.geometry.circular_motion.Model)
global, per set > 1  the similarity from the ring's frame into the set's: a rotation
                     (three, applied after the join's), a translation (three), log scale
per photo            its angle about its set's axis; each set's first photo holds its own
per point            its position in the ring's frame
===================  =====================================================================

Observations: each set's own tracks, and each match across sets that the join explains
(its reprojection within the join's inlier limit): a match between two tracked
keypoints makes their points one, a match with one tracked keypoint adds the other as
an observation of that point. Outliers (beyond ``outlier_px`` or four robust standard
deviations) are dropped and the problem solved again, at most three times.

Limitations: the principal point stays where the ring held it; a set's uncertainty
about its turn on the ring's axis is what the matches across say at the residuals'
noise, not what a wrong set of matches would say; forward differences (one projection
per global parameter) make each iteration cost about 4 + 10 x sets projections.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.camera.model import Intrinsics, Pose
from pipeline.geometry import silhouette_coherence, silhouette_tangency
from pipeline.geometry.bundle import Observations, Prior, Problem, adjust, keep_inliers, noise_px
from pipeline.geometry.circular_motion import CX, CY, FOCAL, K1, Coherence, Model
from pipeline.geometry.turntable_sets import Join, Solved, project

SHARED = ("f", "cx", "cy", "k1")
"""The shared intrinsics, first in the global vector."""
CIRCLE, SIMILARITY = 3, 7
"""Global parameters per set's circle, and per set's similarity (sets after the first)."""
MAX_ROUNDS = 3
"""Solves with outliers dropped between them."""
MAX_SET_TURN_STD_DEG = 1.0
"""A set whose turn on the ring's axis the adjustment leaves more uncertain than this
(one standard deviation) is not placed: twice that is the most a join may be off."""


@dataclass(frozen=True)
class JoinedSet:
    """A set solved alone, its join to the ring, and its matches with the ring's photos
    (ring photo, set photo) that may be shared (on the specimen)."""

    own: Solved
    join: Join
    matches: dict[tuple[str, str], dict[int, int]]
    limit_px: float
    """The join's inlier limit: matches across reprojecting within it are shared."""


@dataclass
class Adjusted:
    """The sets adjusted together, in the ring's frame."""

    intrinsics: Intrinsics
    axis: np.ndarray
    point: np.ndarray
    angles: dict[str, float]
    """Every photo's angle in its own set (the ring's photos: on the ring)."""
    poses: dict[str, Pose]
    """Every photo adjusted, the ring's and the sets'."""
    angle_std_deg: dict[str, float]
    """One standard deviation of each photo's angle; a set's photos' include the set's
    turn on the ring's axis."""
    undetermined: list[str]
    """Photos whose angle the adjustment leaves undetermined (their observations all
    dropped as outliers, or too few), or whose set's turn it leaves uncertain by more
    than ``MAX_SET_TURN_STD_DEG``: not in ``poses``."""
    points: np.ndarray
    tracks: list[dict[str, int]]
    report: dict


class _Layout:
    """Where each set's parameters lie in the global vector, the photos in the order of
    the view parameters (the ring's, then each set's) and each photo's set."""

    def __init__(self, ring: Solved, sets: list[JoinedSet]):
        self.models = [Model(ring.solution.axis)] + [Model(s.own.solution.axis) for s in sets]
        self.rotations = [s.join.R.T for s in sets]
        """Each set's join rotation (ring frame into the set's), before the adjusted one."""
        self.circles = [slice(4 + CIRCLE * k, 4 + CIRCLE * (k + 1)) for k in range(len(self.models))]
        start = 4 + CIRCLE * len(self.models)
        self.similarities = [slice(start + SIMILARITY * k, start + SIMILARITY * (k + 1)) for k in range(len(sets))]
        self.size = start + SIMILARITY * len(sets)
        self.members = [list(ring.poses)] + [list(s.own.poses) for s in sets]
        self.names = [name for members in self.members for name in members]
        self.set_of_view = np.array([k for k, members in enumerate(self.members) for _ in members])

    def own_parameters(self, g: np.ndarray, k: int) -> np.ndarray:
        """Set k's parameters in circular_motion.Model's layout."""
        own = np.zeros(7)
        own[:3] = g[self.circles[k]]
        own[[FOCAL, CX, CY, K1]] = g[:4]
        return own

    def _similarity(self, g: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, float]:
        """Set k's (k >= 1) rotation, translation and scale: set points are scale R (X - t)."""
        x = g[self.similarities[k - 1]]
        return Rotation.from_rotvec(x[:3]).as_matrix() @ self.rotations[k - 1], x[3:6], float(np.exp(x[6]))

    def into_set(self, g: np.ndarray, k: int, points: np.ndarray) -> np.ndarray:
        """Ring-frame ``points`` in set k's frame (k >= 1)."""
        R, t, scale = self._similarity(g, k)
        return scale * (points - t) @ R.T

    def pose(self, g: np.ndarray, k: int, angle: float) -> Pose:
        """A photo of set k at ``angle``, in the ring's frame."""
        axis, p = self.models[k].axis_and_point(self.own_parameters(g, k))
        turn = Rotation.from_rotvec(axis * angle).as_matrix()
        if k == 0:
            return Pose(turn, p - turn @ p)
        R, t, scale = self._similarity(g, k)
        # camera = turn (scale R (X - t) - p) + p, divided by scale (a camera sees rays).
        return Pose(turn @ R, (p - turn @ p) / scale - turn @ R @ t)

    def initial(self, ring: Solved, sets: list[JoinedSet]) -> tuple[np.ndarray, np.ndarray]:
        """The global parameters and the angles (n, 1) as the sets were solved and joined."""
        g = np.zeros(self.size)
        intrinsics = ring.solution.intrinsics
        g[:4] = intrinsics.fx, intrinsics.cx, intrinsics.cy, intrinsics.dist[0] if intrinsics.dist else 0.0
        solved = [ring] + [s.own for s in sets]
        for k, model in enumerate(self.models):
            u = model.axis_and_point(np.zeros(7))[1]
            v = np.cross(model.axis0, u)
            point = solved[k].solution.point
            g[self.circles[k].start + 2] = np.arctan2(point @ v, point @ u)
        for k, joined in enumerate(sets):
            # Ring to set: (X - t) R^T / scale: the join's translation, and the log of 1 / scale.
            g[self.similarities[k]] = np.concatenate([np.zeros(3), joined.join.t, [-np.log(joined.join.scale)]])
        angles = [solved[k].solution.angles[name] for k, members in enumerate(self.members) for name in members]
        return g, np.array(angles)[:, None]


class _Tracks:
    """Every set's tracks as points of one problem: the ring's first, then each set's in
    the ring's frame; matches across sets merge points (union-find) or add observations."""

    def __init__(self, ring: Solved, sets: list[JoinedSet]):
        self.positions: list[np.ndarray] = []
        self.observed: list[dict[str, int]] = []
        self.index: list[dict[tuple[str, int], int]] = []
        """Per set, (photo, keypoint) -> point."""
        for k, solved in enumerate([ring] + [s.own for s in sets]):
            kept = np.flatnonzero(solved.solution.point_groups == 0)
            points = solved.solution.points[kept]
            self.positions += list(sets[k - 1].join.points(points) if k else points)
            index = {}
            for point in kept:
                track = {n: key for n, key in solved.solution.tracks[point].items() if n in solved.poses}
                index |= {(n, key): len(self.observed) for n, key in track.items()}
                self.observed.append(track)
            self.index.append(index)
        self.parent = list(range(len(self.positions)))

    def root(self, point: int) -> int:
        while self.parent[point] != point:
            self.parent[point] = self.parent[self.parent[point]]
            point = self.parent[point]
        return point

    def share(self, k: int, ring_photo: tuple[str, int], set_photo: tuple[str, int]) -> None:
        """A match across sets (ring photo and keypoint, set k's photo and keypoint)."""
        ring_point, set_point = self.index[0].get(ring_photo), self.index[k].get(set_photo)
        if ring_point is not None and set_point is not None:
            a, b = self.root(ring_point), self.root(set_point)
            if a != b:
                self.parent[b] = a
                self.observed[a] |= {n: key for n, key in self.observed[b].items() if n not in self.observed[a]}
        elif ring_point is not None:
            self.observed[self.root(ring_point)].setdefault(set_photo[0], set_photo[1])
        elif set_point is not None:
            self.observed[self.root(set_point)].setdefault(ring_photo[0], ring_photo[1])

    def problem(self, names: list[str], keypoints: dict[str, np.ndarray]) -> tuple[np.ndarray, Observations]:
        """The points (one per merged track seen twice) and their observations."""
        view_of = {name: i for i, name in enumerate(names)}
        roots = [p for p in range(len(self.positions)) if self.root(p) == p and len(self.observed[p]) >= 2]
        # A keypoint matched into two tracks (two matches across) is one point's: the first's.
        used: set[tuple[str, int]] = set()
        seen = []
        for number, p in enumerate(roots):
            for name, key in self.observed[p].items():
                if (name, key) not in used:
                    used.add((name, key))
                    seen.append((view_of[name], number, key))
        views, points, keys = (np.array([row[column] for row in seen], int) for column in range(3))
        pixels = np.array([keypoints[names[view]][key] for view, _, key in seen], float).reshape(-1, 2)
        observations = Observations(views, points, pixels, keys)
        positions = np.array([self.positions[p] for p in roots]).reshape(-1, 3)
        observations, positions = keep_inliers(observations, positions, np.ones(len(views), bool))
        return positions, observations  # the points still seen twice


class _Projection:
    """The joint model's pixels: each observation through its own set's circle."""

    def __init__(self, layout: _Layout):
        self.layout = layout

    def __call__(self, g: np.ndarray, views: np.ndarray, points: np.ndarray, obs: Observations) -> np.ndarray:
        pixels = np.zeros((len(obs.view), 2))
        of_set = self.layout.set_of_view[obs.view]
        for k, model in enumerate(self.layout.models):
            rows = np.flatnonzero(of_set == k)
            if not len(rows):
                continue
            seen = points[obs.point[rows]]
            if k:
                seen = self.layout.into_set(g, k, seen)
            own = Observations(obs.view[rows], np.arange(len(rows)), obs.pixels[rows])
            pixels[rows] = model.project(self.layout.own_parameters(g, k), views, seen, own)
        return pixels


def _share_across(tracks: _Tracks, ring: Solved, sets: list[JoinedSet], keypoints: dict[str, np.ndarray]) -> int:
    """Merges the tracks along the matches across sets that the joins explain (each
    tracked side reprojecting within the join's limit); returns how many."""
    shared = 0
    for k, joined in enumerate(sets, start=1):
        set_poses = {name: joined.join.pose(pose) for name, pose in joined.own.poses.items()}

        def error(pose: Pose, point: int | None, pixel: np.ndarray) -> float:
            if point is None:
                return 0.0
            seen = project(ring.solution.intrinsics, pose, tracks.positions[point][None])[0]
            return float(np.linalg.norm(seen - pixel))

        for (a, b), found in sorted(joined.matches.items()):
            if a not in ring.poses or b not in set_poses:
                continue
            for ka, kb in found.items():
                ring_point, set_point = tracks.index[0].get((a, ka)), tracks.index[k].get((b, kb))
                if ring_point is None and set_point is None:
                    continue
                in_set = error(set_poses[b], ring_point, keypoints[b][kb])
                if max(in_set, error(ring.poses[a], set_point, keypoints[a][ka])) < joined.limit_px:
                    tracks.share(k, (a, ka), (b, kb))
                    shared += 1
    return shared


def _coherences(layout: _Layout, outlines: dict[str, np.ndarray], g, angles, feature_sigma: float) -> list[Prior]:
    """Each set's silhouette coherence at the current state: pairs of its own photos'
    outlines, as the set was solved alone (pipeline.geometry.circular_motion.Coherence)."""
    priors = []
    for k, model in enumerate(layout.models):
        views = np.array([i for i, n in enumerate(layout.names) if layout.set_of_view[i] == k and n in outlines], int)
        if len(views) < 2:
            continue
        padded = silhouette_tangency.padded([outlines[layout.names[i]] for i in views])
        coherence = Coherence(
            model,
            silhouette_coherence.Outlines(padded, views),
            g,
            angles[:, 0],
            feature_sigma,
            lambda g, k=k: layout.own_parameters(g, k),
        )
        if coherence.usable:
            priors.append(coherence.prior)
    return priors


def adjust_sets(
    ring: Solved,
    sets: list[JoinedSet],
    keypoints: dict[str, np.ndarray],
    free_intrinsics: dict[str, bool],
    outlier_px: float,
    outlines: dict[str, np.ndarray] | None = None,
) -> Adjusted:
    """The ring and its joined ``sets`` adjusted together (see the module's table);
    ``free_intrinsics``: which of f and k1 the ring's own solve adjusted; ``outlines``:
    the convex outlines (pixels) of the photos whose silhouette coherence each set's
    own solve fitted, fitted here too."""
    # 1. One problem: the parameters, the tracks merged along the matches across sets.
    layout = _Layout(ring, sets)
    g, angles = layout.initial(ring, sets)
    tracks = _Tracks(ring, sets)
    shared = _share_across(tracks, ring, sets, keypoints)
    points, observations = tracks.problem(layout.names, keypoints)
    free_global = np.ones(layout.size, bool)
    # The principal point stays held: sets at one elevation (a specimen turned over)
    # say nothing more of it than one circle does, and freed it wandered 10 px on such a
    # synthetic capture.
    free_global[:4] = [free_intrinsics.get("f", False), False, False, free_intrinsics.get("k1", False)]
    free_views = np.ones((len(layout.names), 1), bool)
    for members in layout.members:
        free_views[layout.names.index(members[0]), 0] = False  # each set's angles hold its first photo's
    steps = np.concatenate([[1e-4, 1e-4, 1e-4, 1e-7], np.full(layout.size - 4, 1e-6)])
    # 2. Solved, the outliers dropped, solved again.
    for _ in range(MAX_ROUNDS):
        problem = Problem(_Projection(layout), observations, free_global, free_views, steps, np.array([1e-7]), 1e-7)
        if outlines:
            sigma = noise_px(problem.project, g, angles, points, observations)
            problem.priors = _coherences(layout, outlines, g, angles, sigma)
        result = adjust(problem, g, angles, points)
        g, angles, points = result.global_params, result.view_params, result.points
        inliers = result.errors_px <= max(outlier_px, 4 * result.sigma_px)
        if inliers.all():
            break
        observations, points = keep_inliers(observations, points, inliers)
    # 3. The poses, their uncertainties and the tracks.
    return _adjusted(layout, ring.solution.intrinsics, problem, result, shared)


def _adjusted(layout: _Layout, start: Intrinsics, problem: Problem, result, shared: int) -> Adjusted:
    """The solution in records; each set's turn on the ring's axis (from the covariance
    of its similarity's rotation) added to its photos' angle uncertainty."""
    g, angles, observations, names = result.global_params, result.view_params[:, 0], problem.observations, layout.names
    free = list(np.flatnonzero(problem.free_global))
    std = np.zeros(len(names))
    std[np.flatnonzero(problem.free_views[:, 0])] = np.sqrt(np.maximum(np.diag(result.covariance)[len(free) :], 0))
    axis, p = layout.models[0].axis_and_point(layout.own_parameters(g, 0))
    set_turn_std = []
    for similarity in layout.similarities:
        rotation = [free.index(i) for i in range(similarity.start, similarity.start + 3)]
        block = result.covariance[np.ix_(rotation, rotation)]
        set_turn_std.append(float(np.degrees(np.sqrt(max(axis @ block @ axis, 0.0)))))
    turn_std = np.array([0.0] + set_turn_std)[layout.set_of_view]
    intrinsics_std = {
        name: float(np.sqrt(result.covariance[free.index(i), free.index(i)])) if i in free else None
        for name, i in zip(SHARED, range(4))
    }
    angle_std = {name: float(np.hypot(np.degrees(s), t)) for name, s, t in zip(names, std, turn_std)}
    seen = np.bincount(observations.view, minlength=len(names))
    loose = np.array([False] + [not std <= MAX_SET_TURN_STD_DEG for std in set_turn_std])[layout.set_of_view]
    undetermined = [n for i, n in enumerate(names) if loose[i] or not np.isfinite(angle_std[n]) or not seen[i]]
    tracks: list[dict[str, int]] = [{} for _ in range(len(result.points))]
    for view, point, key in zip(observations.view, observations.point, observations.keypoint):
        tracks[point][names[view]] = int(key)
    return Adjusted(
        intrinsics=Intrinsics(start.width, start.height, g[0], g[0], g[1], g[2], [float(g[3]), 0, 0, 0, 0]),
        axis=axis,
        point=p,
        angles={name: float(a) for name, a in zip(names, angles)},
        poses={
            name: layout.pose(g, int(k), float(a))
            for name, k, a in zip(names, layout.set_of_view, angles)
            if name not in undetermined
        },
        angle_std_deg=angle_std,
        undetermined=undetermined,
        points=result.points,
        tracks=tracks,
        report={
            "observations": int(len(observations.view)),
            "matches_across_shared": shared,
            "reprojection_px_median": round(float(np.median(result.errors_px)), 3) if len(result.errors_px) else None,
            "set_turn_std_deg": [round(s, 4) for s in set_turn_std],
            "intrinsics": {
                name: {"value": float(g[i]), "std": intrinsics_std[name], "adjusted": intrinsics_std[name] is not None}
                for i, name in enumerate(SHARED)
            },
            "iterations": result.iterations,
        },
    )
