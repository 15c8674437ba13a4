"""Circular motion from feature matches: a still camera and an object turning about
one axis (a turntable), or a camera carried round a still object on one circle (a
ring gantry). Every photo is one angle; the axis, the camera's place relative to it
and the intrinsics are shared.

In the camera's frame the axis is the line through ``p`` with direction ``a``
(unit vectors, ``p`` perpendicular to ``a``; the camera's distance from the axis is
the unit of length). A point ``X`` of the object (in the frame of the photo at angle
0) is seen in photo i at ``Rot(a, angle_i) (X - p) + p``: the photo's pose is
``R_i = Rot(a, angle_i)``, ``t_i = p - R_i p``, a ``Turntable`` with ``R_fixed = I``
and ``c_fixed = 0``.

The solver:

1. **The axis**: the direction (in the camera's frame) under which every matched
   pair's verified matches are best explained by one turn each (truncated Sampson
   distances, a grid over the half sphere refined twice), the camera facing the
   axis. A pair's own essential matrix is not used: a few dozen matches between
   photos a few degrees apart fix one angle well but a full rotation poorly (on a
   synthetic turntable their relative rotations were 3 degrees off, their average
   axis 16 degrees).
2. **Each pair's turn** under that axis (a 1-degree grid, then 0.05 degrees). Steps
   2-4 run first with the strong pairs: ``min_observations`` inliers of one turn.
   Where those leave photos out of the ring (a small or plain specimen's pairs share
   a dozen matches) and outlines are given, they run again with weak pairs too:
   pairs one turn explains better than chance (a binomial test,
   ``pair_significance``), and pairs two-view verification found no geometry for (a
   dozen matches fail five degrees of freedom) where one turn explains them. A weak
   pair's turn is a few degrees off where a strong pair's is one or two, and enough
   of them can pull the ring into another solution the features fit about as well,
   so the extended ring is kept only where it joins more photos and the outlines
   agree with it about as well as with the strong ring (``extension_verdict``;
   sfm.json ``weak_pairs``).
3. **Angles**: synchronised over the graph of pairs (the leading eigenvector of the
   pairs' unit phasors, then robust least squares), so any matched pair counts and
   the photos need not be in order (a restarted or second turn is no exception).
   The largest connected set of photos is the ring; each other connected set (a
   ring broken by a gap in matching) is a group whose angles are known up to one
   offset.
4. **Bundle adjustment** of the model (pipeline.geometry.bundle): axis, ``p``, one
   angle per photo, focal length, radial distortion when the photos constrain it
   (``self_calibrate``; the principal point is held, see ``_self_calibration``),
   and the feature tracks' points, with Cauchy's loss; observations off by more
   than ``outlier_px`` are dropped and it is solved again. Every group's angles
   share the axis, offset and intrinsics; each group holds one of its angles fixed.
   An optional prior makes the ring's steps between photos in file order even (a
   timed turntable). Where the photos' outlines are given, their silhouette
   coherence (pipeline.geometry.silhouette_coherence: the epipolar tangency errors
   of pairs of the ring's photos) is fitted with the features, each in its own
   measured noise, re-measured until it settles: features on a plain or glossy
   specimen are shading that stays with the light, and the outlines decide what
   they leave loose. A group is then put where its outlines agree best with the
   ring's and solved with it, and stays joined where no other offset fits its
   outlines nearly as well and the outlines agree with the joined ring about as
   well as with the ring alone (``_join_groups``; a group left apart is placed by
   the sfm stage from its silhouettes, pipeline.geometry.turntable_placement).
5. **Which photos it placed**: no threshold in degrees or pixels, since what a photo's
   angle can be known to depends on the photos' size and noise. A photo is placed
   when it has ``min_observations`` inlier observations (``weak_min_observations``
   in the extended ring) and its residuals are no
   worse than the other photos' (a one-sided sign test against the pooled median, at
   ``misfit_significance`` over the photos, and a median more than ``misfit_ratio``
   times the pooled one), and its angle is determined at all. Its angle's uncertainty
   (one standard deviation, from the bundle adjustment's covariance) is reported, not
   judged: a small photo's angle is uncertain by more than a large one's, and still the
   best the photos say. The sfm stage tries the other photos' board pose or silhouette.

Limitations: one camera setting; a group no silhouette can place is left out; the
axis must not point at the camera (a camera looking straight down the axis sees
only a rotation of the image).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, NamedTuple

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial.transform import Rotation
from scipy.stats import binom

from pipeline import logger
from pipeline.camera.model import Intrinsics, Pose
from pipeline.camera.self_calibration import corner_radius, frame_coverage, radial_shift_px
from pipeline.geometry import silhouette_coherence, silhouette_tangency
from pipeline.geometry.bundle import Observations, Prior, Problem, adjust, keep_inliers, noise_px

GLOBAL_NAMES = ("axis_a", "axis_b", "psi", "f", "cx", "cy", "k1")
"""The model's global parameters: two for the axis direction (a tangent-plane offset
from its initial estimate), the angle of ``p`` about the axis, focal length,
principal point, radial distortion."""
FOCAL, CX, CY, K1 = 3, 4, 5, 6
PAIR_MIN_MATCHES = 6
"""Pairs with fewer matches are not tested: where a third of a pair's matches fit any turn
by chance (a small specimen), all five of five fitting one turn is not significant at the
default ``pair_significance`` ((1/3) ** 5 = 4e-3)."""
KNOWN_TURN_STD_DEG = 0.1
"""How closely the bundle adjustment holds the turns between photos with known poses (a
board's, from its many corners) to what those poses say."""


@dataclass(frozen=True)
class CircularSettings:
    """How the circular-motion solver places photos (the sfm stage's settings)."""

    min_observations: int = 15
    """Inlier observations a photo needs to be placed by its features, and a pair of
    photos to count, in the ring of strong pairs (step 3)."""
    weak_min_observations: int = 6
    """... and a photo in the ring extended by weak pairs: a photo there has one unknown,
    its angle, where a free pose has six, and whether its few observations fit is the
    misfit test's and the reported uncertainty's to say."""
    pair_significance: float = 1e-3
    """In the extended ring, a matched pair counts when one turn explains more of its
    matches than chance would at this level (a one-sided binomial test against the share
    its matches fit at the turns it does not have) and at least half of them: a pair of photos of a small or
    plain specimen shares a dozen matches, which one turn about a known axis tests as
    surely as hundreds test five degrees of freedom. A pair with under half the inliers
    of the capture's median pair counts only where one of its photos has fewer than two
    stronger pairs (the seams of a small specimen's turn): elsewhere such pairs are
    mostly highlights, which pull the angles off."""
    misfit_significance: float = 1e-3
    """A photo whose residuals exceed the pooled median more often than chance allows at
    this level (a one-sided sign test, divided among the photos) fits the circle worse
    than the others ..."""
    misfit_ratio: float = 2.5
    """... and is left out when its median residual is also this many times the pooled one:
    with hundreds of observations a slight excess is significant and harmless (a specimen
    that shifted on the table part-way fits the circle somewhat worse, its angles no
    worse), while a photo turned in the image plane or from another camera fits many
    times worse. The ring extended by weak pairs is kept only where its outlines' tangency
    noise is at most this many times the strong pairs' ring's (``extension_verdict``)."""
    silhouette_ambiguity: float = 2.0
    """A group of photos the features leave apart from the ring is joined to it by the
    outlines (step 4) only where its outlines fit one offset this many times better than
    any other local minimum of their error more than 5 degrees away (the slope of the
    best offset's own valley is no rival)."""
    outlier_px: float = 3.0
    """Observations farther than this from their reprojection (or 4 robust standard
    deviations, whichever is larger) are dropped between solves."""
    refine_focal: bool = True
    """Adjust the focal length (False when a board calibrated it)."""
    self_calibrate: bool = True
    """Adjust the radial distortion when the photos constrain it (the principal point is
    held: see ``_self_calibration``)."""
    max_calibration_std_px: float = 1.0
    """Distortion is adjusted only when its standard deviation, as a displacement in pixels
    at the frame's corner, is below this."""
    min_frame_coverage: float = 0.4
    """Self-calibration needs observations in at least this fraction of a 6x6 grid over
    the frame: distortion and principal point show only towards the edges."""
    even_steps_deg: float = 0.0
    """Above 0: a prior that consecutive photos in file order are one equal step apart,
    with this standard deviation (degrees): a turntable turned by a timer."""


@dataclass
class CircularMotion:
    """The solution: the axis in the camera's frame, the camera's offset from it, an
    angle per placed photo, the intrinsics, and the triangulated tracks."""

    axis: np.ndarray
    point: np.ndarray
    angles: dict[str, float]
    intrinsics: Intrinsics
    points: np.ndarray
    """(M, 3) track points in the frame of the photo at angle 0 (a group's: of its own
    first photo, see ``place_group``)."""
    tracks: list[dict[str, int]]
    """Per point: photo name -> keypoint index of its inlier observations."""
    point_groups: np.ndarray
    """(M,) the group of each point's photos: 0 for the ring, k for ``groups[k - 1]``."""
    angle_std_deg: dict[str, float]
    """One standard deviation of each placed or grouped photo's angle (degrees; a group's
    relative to its own fixed photo)."""
    observations: dict[str, int]
    """Inlier observations per photo (placed or not)."""
    partners: dict[str, int]
    """Per placed or grouped photo, how many photos of its ring or group trusted pairs of
    matches join it to: a photo one pair alone placed cannot be checked against another."""
    calibration: dict
    """Self-calibration: per parameter its value, standard deviation and whether adjusted."""
    reprojection_px: float
    """Median reprojection error of the inlier observations."""
    unplaced: dict[str, str] = field(default_factory=dict)
    """Photos the features could not place, with the reason."""
    groups: list[dict[str, float]] = field(default_factory=list)
    """Photos the features tie to each other but not to the ring: per group, each photo's
    angle relative to the group's first (radians); the group as a whole is still to place."""
    silhouette_coherence: dict = field(default_factory=dict)
    """Where outlines were fitted too: the pairs compared and the standard deviations of
    their tangency errors and of the features' reprojection errors at the solution (pixels)."""
    weak_pairs: dict = field(default_factory=dict)
    """Where the strong pairs left photos out of the ring and weak pairs were tried: the
    photos in each ring, its tangency noise, and which ring was kept and why."""
    joined_groups: list[dict] = field(default_factory=list)
    """Per group of photos the features left apart from the ring, where outlines were
    fitted: its photos, the offset its outlines gave, the tangency noise before and after
    joining, and whether it was joined and why."""


def place_group(solution: "CircularMotion", offsets: dict[int, float]) -> tuple[np.ndarray, list[dict[str, int]]]:
    """The solution's points and tracks with each placed group's (``offsets``: group
    number, 1 for ``groups[0]``, -> the angle its first photo was placed at) turned into
    the ring's frame, and the points of groups not placed dropped."""
    keep = (solution.point_groups == 0) | np.isin(solution.point_groups, list(offsets))
    points = solution.points.copy()
    for group, offset in offsets.items():
        own = solution.point_groups == group
        points[own] = axis_rotation(solution.axis, np.full(int(own.sum()), -offset), points[own] - solution.point)
        points[own] += solution.point
    return points[keep], [track for track, kept in zip(solution.tracks, keep) if kept]


def axis_rotation(axis: np.ndarray, angles: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Rodrigues: ``vectors`` (m, 3) turned about the unit ``axis`` by ``angles`` (m,)."""
    c, s = np.cos(angles)[:, None], np.sin(angles)[:, None]
    return vectors * c + np.cross(axis, vectors) * s + axis * (vectors @ axis)[:, None] * (1 - c)


class Model:
    """The circular camera model's projection, parameterised for the bundle adjuster."""

    def __init__(self, axis0: np.ndarray):
        self.axis0 = axis0 / np.linalg.norm(axis0)
        helper = np.array([1.0, 0, 0]) if abs(self.axis0[0]) < 0.9 else np.array([0, 1.0, 0])
        self.e1 = np.cross(self.axis0, helper)
        self.e1 /= np.linalg.norm(self.e1)
        self.e2 = np.cross(self.axis0, self.e1)

    def axis_and_point(self, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        axis = self.axis0 + g[0] * self.e1 + g[1] * self.e2
        axis /= np.linalg.norm(axis)
        u = self.e1 - (self.e1 @ axis) * axis
        u /= np.linalg.norm(u)
        v = np.cross(axis, u)
        return axis, np.cos(g[2]) * u + np.sin(g[2]) * v

    def camera_points(self, g: np.ndarray, angles: np.ndarray, points: np.ndarray) -> np.ndarray:
        axis, p = self.axis_and_point(g)
        return axis_rotation(axis, angles, points - p) + p

    def project(self, g: np.ndarray, views: np.ndarray, points: np.ndarray, obs: Observations) -> np.ndarray:
        camera = self.camera_points(g, views[obs.view, 0], points[obs.point])
        z = np.maximum(camera[:, 2], 1e-6)
        x, y = camera[:, 0] / z, camera[:, 1] / z
        radial = 1 + g[K1] * (x * x + y * y)
        return np.column_stack([g[FOCAL] * x * radial + g[CX], g[FOCAL] * y * radial + g[CY]])

    def jacobians(
        self, g: np.ndarray, views: np.ndarray, points: np.ndarray, obs: Observations
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``project``'s pixels (m, 2) and their derivatives by the global parameters
        (m, 2, 7), the angle (m, 2, 1) and the point (m, 2, 3), in closed form but for
        the axis and ``p`` by the first three global parameters (central differences of
        ``axis_and_point``, a function of three numbers). Vectors throughout, no 3x3
        matrix per observation: numpy's products of many tiny matrices are slow."""
        axis, p = self.axis_and_point(g)
        angles, relative = views[obs.view, 0], points[obs.point] - p
        turned = axis_rotation(axis, angles, relative)
        camera = turned + p
        z = np.maximum(camera[:, 2], 1e-6)
        x, y = camera[:, 0] / z, camera[:, 1] / z
        r2 = x * x + y * y
        radial = 1 + g[K1] * r2
        pixels = np.column_stack([g[FOCAL] * x * radial + g[CX], g[FOCAL] * y * radial + g[CY]])
        # Pixels by the camera point: the distortion's 2x2 times the perspective
        # division's 2x3 (nothing by depth where ``project`` clamps it).
        by_x = g[FOCAL] * np.column_stack([radial + 2 * g[K1] * x * x, 2 * g[K1] * x * y])  # (m, 2)
        by_y = g[FOCAL] * np.column_stack([2 * g[K1] * x * y, radial + 2 * g[K1] * y * y])
        in_front = camera[:, 2] > 1e-6
        x_by_camera = np.column_stack([1 / z, np.zeros_like(z), -x / z * in_front])  # (m, 3)
        y_by_camera = np.column_stack([np.zeros_like(z), 1 / z, -y / z * in_front])
        by_camera = by_x[:, :, None] * x_by_camera[:, None, :] + by_y[:, :, None] * y_by_camera[:, None, :]

        # By the point: the camera point moves by R dX, so each pixel row's gradient is
        # R^T of its gradient in the camera frame (the turn undone).
        J_point = np.stack([axis_rotation(axis, -angles, by_camera[:, row]) for row in range(2)], 1)
        J_view = np.einsum("mij,mj->mi", by_camera, np.cross(axis, turned))[:, :, None]
        # By the axis and p, along central differences of axis_and_point (columns of
        # d_axis and d_p): Rodrigues' formula R w = c w + s (a x w) + (1 - c) a (a . w)
        # differentiated by the axis a as a free vector, and the camera point R w + p
        # (w = X - p) by p; each pixel row's gradient b dotted with them, as products
        # with the three columns.
        d_axis, d_p = np.zeros((3, 3)), np.zeros((3, 3))
        for index in range(3):
            ahead, behind = g.copy(), g.copy()
            ahead[index] += 1e-6
            behind[index] -= 1e-6
            (axis_ahead, p_ahead), (axis_behind, p_behind) = self.axis_and_point(ahead), self.axis_and_point(behind)
            d_axis[:, index], d_p[:, index] = (axis_ahead - axis_behind) / 2e-6, (p_ahead - p_behind) / 2e-6
        c, s = np.cos(angles)[:, None], np.sin(angles)[:, None]
        dot = (relative @ axis)[:, None]
        J_global = np.zeros((len(z), 2, len(g)))
        for row in range(2):
            b = by_camera[:, row]
            b_axis = (b @ axis)[:, None]
            J_global[:, row, :3] = (
                s * (np.cross(relative, b) @ d_axis)  # b . (d x w) = d . (w x b)
                + (1 - c) * (dot * (b @ d_axis) + b_axis * (relative @ d_axis))
                + (1 - c) * (b @ d_p - b_axis * (axis @ d_p))  # (I - R) d_p: its cosine and axis terms
                - s * (b @ np.cross(axis, d_p.T).T)  # and its sine term
            )
        J_global[:, 0, FOCAL], J_global[:, 1, FOCAL] = x * radial, y * radial
        J_global[:, 0, CX] = J_global[:, 1, CY] = 1.0
        J_global[:, 0, K1], J_global[:, 1, K1] = g[FOCAL] * x * r2, g[FOCAL] * y * r2
        return pixels, J_global, J_view, J_point

    def undistorted_rays(self, g: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        """Normalised image coordinates of ``pixels`` (distortion removed by fixed-point iteration)."""
        distorted = (pixels - g[[CX, CY]]) / g[FOCAL]
        undistorted = distorted.copy()
        for _ in range(10):
            undistorted = distorted / (1 + g[K1] * np.sum(undistorted**2, axis=1))[:, None]
        return undistorted


# --- 1-3. the axis, each pair's turn and the angles ---------------------------------------


@dataclass
class PairRays:
    """A matched photo pair (file indices ``i`` < ``j``) as normalised camera rays (k, 3), z = 1."""

    i: int
    j: int
    rays_i: np.ndarray
    rays_j: np.ndarray


def essentials(axis: np.ndarray, point: np.ndarray, turns: np.ndarray) -> np.ndarray:
    """(G, 3, 3) essential matrices of the model between photos ``turns`` apart:
    ``R = Rot(axis, turn)``, ``t = (I - R) p``."""
    # No turn has no epipolar geometry (E = 0 explains anything): the least turn is kept.
    turns = np.where(np.abs(turns) < 1e-4, np.where(turns < 0, -1e-4, 1e-4), turns)
    R = Rotation.from_rotvec(np.outer(turns, axis)).as_matrix()
    return silhouette_tangency.cross_matrices(point - R @ point) @ R


def sampson_sq(E: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """(G, N) squared Sampson distances of rays ``x1`` -> ``x2`` (N, 3) under each of ``E`` (G, 3, 3)."""
    # Matrix products over all G at once: the algebraic error x2^T E x1 as the rays'
    # outer products against E's nine entries, the gradient's four terms one row or
    # column of every E each. The axis search evaluates dozens of turns for hundreds
    # of axes.
    G = len(E)
    algebraic = (x2[:, :, None] * x1[:, None, :]).reshape(-1, 9) @ E.reshape(G, 9).T  # (N, G)
    denominator = np.zeros_like(algebraic)
    for row in range(2):
        denominator += (x1 @ E[:, row, :].T) ** 2  # (E x1)_row
        denominator += (x2 @ E[:, :, row].T) ** 2  # (E^T x2)_row
    return (algebraic**2 / np.maximum(denominator, 1e-300)).T


def facing_point(axis: np.ndarray) -> np.ndarray:
    """The camera's offset ``p`` from an axis it looks at: the optical axis with its
    component along the axis removed (the specimen, on the axis, is in view)."""
    forward = np.array([0.0, 0.0, 1.0])
    p = forward - (forward @ axis) * axis
    return p / np.linalg.norm(p)


def pair_turns(
    axis: np.ndarray, pairs: list[PairRays], turns: np.ndarray, threshold: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each pair's turn among ``turns`` under the model with ``axis`` (the camera
    facing it), by the truncated sum of squared Sampson distances (``threshold`` in
    normalised units). Returns the best turn, its cost and its inlier count per pair,
    and the median inlier count over all ``turns`` (what its matches fit by chance,
    when the turns span far more than the pair's own)."""
    x1, x2 = np.vstack([p.rays_i for p in pairs]), np.vstack([p.rays_j for p in pairs])
    sizes = [len(p.rays_i) for p in pairs]
    starts = np.cumsum([0] + sizes)[:-1]
    distances = sampson_sq(essentials(axis, facing_point(axis), turns), x1, x2)
    costs = np.add.reduceat(np.minimum(distances, threshold**2), starts, axis=1)
    counts = np.add.reduceat((distances < threshold**2).astype(int), starts, axis=1)
    best = np.argmin(costs, axis=0)
    columns = np.arange(len(pairs))
    return turns[best], costs[best, columns], counts[best, columns], np.median(counts, axis=0)


def _axis_from(elevation: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Axis directions in the camera's frame: ``roll`` turns the axis' image away from
    the image's vertical, ``elevation`` tilts it towards the camera (an upright camera
    looking down at a turntable from elevation e sees the axis at elevation e)."""
    return np.stack([np.cos(elevation) * np.sin(roll), -np.cos(elevation) * np.cos(roll), -np.sin(elevation)], -1)


def search_axis(pairs: list[PairRays], threshold: float) -> np.ndarray:
    """The axis (camera frame) under which the pairs' matches are best explained by one
    turn each: a grid over the half sphere of directions (every 15 degrees), refined
    twice around the best (3 and 0.75 degrees). Unlike averaging the pairs' own relative
    rotations, it needs no pair to determine a rotation on its own: a few dozen matches
    between photos a few degrees apart fix one angle well but three poorly."""
    coarse_turns = np.radians(np.arange(-60, 61, 2.0))
    # A sample is enough to rank axes: at most 30 matches of each of at most 120 pairs.
    rng = np.random.default_rng(0)
    sample = []
    for pair in pairs[:: max(1, len(pairs) // 120)]:
        keep = np.sort(rng.permutation(len(pair.rays_i))[:30])
        sample.append(PairRays(pair.i, pair.j, pair.rays_i[keep], pair.rays_j[keep]))
    best_cost, best = np.inf, (0.0, 0.0)
    for step, span in ((15.0, None), (3.0, 15.0), (0.75, 3.0)):
        if span is None:
            elevations, rolls = np.arange(-75, 76, step), np.arange(0, 180, step)
        else:
            elevations = np.arange(best[0] - span, best[0] + span + step / 2, step)
            rolls = np.arange(best[1] - span, best[1] + span + step / 2, step)
        for elevation in elevations:
            for roll in rolls:
                axis = _axis_from(np.radians(elevation), np.radians(roll))
                cost = float(np.sum(pair_turns(axis, sample, coarse_turns, threshold)[1]))
                if cost < best_cost:
                    best_cost, best = cost, (float(elevation), float(roll))
    return _axis_from(*np.radians(best))


def consistent_pairs(
    n: int, pairs: np.ndarray, turns: np.ndarray, weights: np.ndarray, tolerance: float, trials: int = 200
) -> np.ndarray:
    """Which pairs agree on one set of angles (boolean per pair). Angles from random
    spanning trees of the pair graph (heavier pairs more likely drawn; the chain of
    pairs of consecutive photos, a turntable's order, is tried first), each pair's
    turn compared with the angles' difference; the tree that the most weight agrees
    with (within ``tolerance``) wins. A pair a repeated pattern joined with a plausible
    but wrong turn (a board seen from opposite sides matches itself as if barely
    turned) disagrees with the rest and is left out."""
    rng = np.random.default_rng(0)
    best, best_score = np.zeros(len(pairs), bool), -1.0
    chain = np.where(pairs[:, 1] - pairs[:, 0] == 1, 0.0, np.inf)
    for trial in range(trials):
        keys = chain if trial == 0 else -np.log(rng.uniform(1e-12, 1, len(pairs))) / weights
        tree = _spanning_tree(n, pairs, np.argsort(keys, kind="stable"))
        angles = _tree_angles(n, pairs[tree], turns[tree])
        residuals = np.angle(np.exp(1j * (angles[pairs[:, 1]] - angles[pairs[:, 0]] - turns)))
        agree = np.isfinite(residuals) & (np.abs(residuals) < tolerance)
        score = float(weights[agree].sum())
        if score > best_score:
            best, best_score = agree, score
    return best


def _spanning_tree(n: int, pairs: np.ndarray, edge_order: np.ndarray) -> np.ndarray:
    """Indices of a spanning forest's pairs, taken in ``edge_order`` (Kruskal)."""
    parent = list(range(n))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    tree = []
    for k in edge_order:
        a, b = root(int(pairs[k, 0])), root(int(pairs[k, 1]))
        if a != b:
            parent[a] = b
            tree.append(int(k))
    return np.array(tree, int)


def _tree_angles(n: int, pairs: np.ndarray, turns: np.ndarray) -> np.ndarray:
    """Angles along a spanning forest, each tree's from its own first photo (nan for
    photos in no pair)."""
    neighbours: dict[int, list[tuple[int, float]]] = {}
    for (i, j), turn in zip(pairs, turns):
        neighbours.setdefault(int(i), []).append((int(j), float(turn)))
        neighbours.setdefault(int(j), []).append((int(i), -float(turn)))
    angles = np.full(n, np.nan)
    for start in neighbours:
        if np.isfinite(angles[start]):
            continue
        angles[start], stack = 0.0, [start]
        while stack:
            i = stack.pop()
            for j, turn in neighbours[i]:
                if not np.isfinite(angles[j]):
                    angles[j] = angles[i] + turn
                    stack.append(j)
    return angles


def synchronise_angles(n: int, pairs: np.ndarray, turns: np.ndarray, weights: np.ndarray, reference: int) -> np.ndarray:
    """Angles (n,) with angle[reference] = 0 that best explain ``turns[k]`` = angle[j] -
    angle[i] for ``pairs[k]`` = (i, j), modulo 2 pi: the leading eigenvector of the
    pairs' phasors, then iteratively reweighted least squares on the unwrapped
    differences (Cauchy weights, scale 1 degree)."""
    H = np.zeros((n, n), complex)
    H[pairs[:, 0], pairs[:, 1]] = weights * np.exp(-1j * turns)
    H[pairs[:, 1], pairs[:, 0]] = weights * np.exp(1j * turns)
    H += np.diag(np.full(n, weights.max()))
    vector = np.linalg.eigh(H)[1][:, -1]
    angles = np.angle(vector * np.conj(vector[reference]) / max(abs(vector[reference]), 1e-300))
    # Unwrapped differences against the spectral solution, then least squares.
    wraps = np.round((angles[pairs[:, 1]] - angles[pairs[:, 0]] - turns) / (2 * np.pi))
    targets = turns + 2 * np.pi * wraps
    A = np.zeros((len(pairs), n))
    A[np.arange(len(pairs)), pairs[:, 1]] = 1
    A[np.arange(len(pairs)), pairs[:, 0]] = -1
    free = np.arange(n) != reference
    robust = np.ones(len(pairs))
    for _ in range(10):
        w = np.sqrt(weights * robust)
        solution = np.linalg.lstsq(A[:, free] * w[:, None], targets * w, rcond=None)[0]
        angles = np.zeros(n)
        angles[free] = solution
        residuals = A @ angles - targets
        robust = 1 / (1 + (residuals / np.radians(1.0)) ** 2)
    return angles


# --- 4. tracks and triangulation ----------------------------------------------------------


def build_tracks(
    order: list[str], keypoints: dict[str, np.ndarray], matches: dict[tuple[str, str], dict[int, int]]
) -> list[dict[str, int]]:
    """Feature tracks: connected keypoints over all verified matches; a track holding
    two keypoints of one photo (a repeated pattern joined it) is dropped."""
    offsets = np.cumsum([0] + [len(keypoints[n]) for n in order])
    index = {name: i for i, name in enumerate(order)}
    rows, cols = [], []
    for (a, b), pairs in matches.items():
        if index[a] < index[b] and pairs:
            mine, theirs = np.array(list(pairs.items())).T
            rows.append(offsets[index[a]] + mine)
            cols.append(offsets[index[b]] + theirs)
    if not rows:
        return []
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(offsets[-1], offsets[-1]))
    _, labels = connected_components(graph, directed=False)
    used = np.unique(np.concatenate([rows, cols]))
    photo_of = np.searchsorted(offsets, used, side="right") - 1
    tracks: dict[int, dict[str, int]] = {}
    conflicted = set()
    for node, photo in zip(used, photo_of):
        track = tracks.setdefault(int(labels[node]), {})
        name = order[photo]
        if name in track:
            conflicted.add(int(labels[node]))
        track[name] = int(node - offsets[photo])
    return [t for label, t in sorted(tracks.items()) if label not in conflicted and len(t) >= 2]


def triangulate(rays: list[np.ndarray], rotations: list[np.ndarray], translations: list[np.ndarray]) -> np.ndarray:
    """Linear (DLT) triangulation of one track from normalised rays and poses."""
    rows = []
    for (x, y), R, t in zip(rays, rotations, translations):
        P = np.hstack([R, t[:, None]])
        rows += [x * P[2] - P[0], y * P[2] - P[1]]
    X = np.linalg.svd(np.array(rows))[2][-1]
    return X[:3] / X[3] if abs(X[3]) > 1e-12 else np.full(3, np.nan)


# --- the solver ----------------------------------------------------------------------------


class _Solver:
    """State shared by the solver's steps: photos, keypoints, the model and its parameters."""

    def __init__(self, settings: CircularSettings, order: list[str], intrinsics: Intrinsics, keypoints, weak: bool):
        self.settings = settings
        self.weak = weak
        """Weak pairs are admitted (the extended ring, step 3)."""
        self.min_observations = settings.weak_min_observations if weak else settings.min_observations
        """Inlier observations a photo needs to be placed by its features."""
        self.min_pair_matches = PAIR_MIN_MATCHES if weak else settings.min_observations
        """Matches a pair needs to be tested."""
        self.order = order
        self.index = {name: i for i, name in enumerate(order)}
        self.keypoints = keypoints
        self.start = intrinsics
        self.g = np.zeros(len(GLOBAL_NAMES))
        self.g[[FOCAL, CX, CY]] = intrinsics.fx, intrinsics.cx, intrinsics.cy
        self.g[K1] = intrinsics.dist[0] if intrinsics.dist else 0.0
        self.model: Model | None = None
        self.angles = np.zeros(len(order))
        self.placed = np.zeros(len(order), bool)
        """Photos in the bundle adjustment: the ring's and the groups'."""
        self.group = np.full(len(order), -1)
        """0 for the ring, 1, 2, ... for groups the features do not tie to it, -1 for none."""
        self.trusted_pairs: set[tuple[str, str]] = set()
        """Feature pairs the model explains with turns the other pairs agree with."""
        self.known_rotations: dict[int, np.ndarray] = {}
        """World-to-camera rotations of photos with known poses (a board's), by index."""
        self.outlines: silhouette_coherence.Outlines | None = None
        """The photos' outlines (pixels), when their silhouette coherence is fitted."""
        self.coherence: dict = {}
        """The last solve's silhouette coherence: pairs, tangency and feature noise (pixels)."""

    def K(self) -> np.ndarray:
        return np.array([[self.g[FOCAL], 0, self.g[CX]], [0, self.g[FOCAL], self.g[CY]], [0, 0, 1.0]])

    def pose(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        return self.pose_at(self.angles[i])

    def pose_at(self, angle: float) -> tuple[np.ndarray, np.ndarray]:
        axis, p = self.model.axis_and_point(self.g)
        R = Rotation.from_rotvec(axis * angle).as_matrix()
        return R, p - R @ p


def _pair_rays(solver: _Solver, matches) -> list[PairRays]:
    """The pairs with ``min_observations`` matches (``PAIR_MIN_MATCHES`` in the extended
    ring), as rays."""
    model = Model(np.array([0.0, -1.0, 0.0]))
    pairs = []
    for (a, b), matched in sorted(matches.items()):
        i, j = solver.index[a], solver.index[b]
        if i < j and len(matched) >= solver.min_pair_matches:
            mine, theirs = np.array(list(matched.items())).T
            rays = [model.undistorted_rays(solver.g, solver.keypoints[n][k]) for n, k in ((a, mine), (b, theirs))]
            pairs.append(PairRays(i, j, *[np.column_stack([r, np.ones(len(r))]) for r in rays]))
    return pairs


def _known_turns(solver: _Solver, known: dict[str, Pose]) -> tuple[np.ndarray, list[np.ndarray]]:
    """Pairs (i < j) of photos with known poses (a board's) and their relative rotations."""
    names = sorted((n for n in known if n in solver.index), key=solver.index.get)
    pairs, rotations = [], []
    for a, name_a in enumerate(names):
        for name_b in names[a + 1 :]:
            pairs.append((solver.index[name_a], solver.index[name_b]))
            rotations.append(known[name_b].R @ known[name_a].R.T)
    return np.array(pairs, int).reshape(-1, 2), rotations


def _turns_of_pairs(
    solver: _Solver, axis: np.ndarray, pairs: list[PairRays], threshold: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each pair's turn about ``axis`` (a 1-degree grid, then 0.05 degrees), its inlier
    count, and whether the turn explains the pair: ``CircularSettings.min_observations``
    inliers in the ring of strong pairs, ``pair_significance`` in the extended ring."""
    turns, _, inliers, chance = pair_turns(axis, pairs, np.radians(np.arange(-90, 90, 1.0)), threshold)
    for k, pair in enumerate(pairs):
        fine = turns[k] + np.radians(np.arange(-1, 1.01, 0.05))
        found, _, count, _ = pair_turns(axis, [pair], fine, threshold)
        turns[k], inliers[k] = found[0], count[0]
    sizes = np.array([len(p.rays_i) for p in pairs])
    if not solver.weak:
        return turns, inliers, (inliers >= solver.min_observations) & (inliers >= 0.5 * sizes)
    # At least one match fits by chance: a pair whose matches fit no other turn at all
    # is not thereby certain.
    chance_share = np.maximum(chance, 1) / sizes
    significant = binom.sf(inliers - 1, sizes, chance_share) < solver.settings.pair_significance
    explained = significant & (inliers >= 0.5 * sizes)
    typical = float(np.median(inliers[explained])) if explained.any() else 0.0
    strong = explained & (inliers >= 0.5 * typical)
    index = np.array([(p.i, p.j) for p in pairs]).reshape(-1, 2)
    strong_pairs = np.bincount(index[strong].ravel(), minlength=len(solver.order))
    needed = np.any(strong_pairs[index] < 2, axis=1)
    return turns, inliers, strong | (explained & needed)


def _explained_by_one_turn(
    solver: _Solver, verified: list[PairRays], candidates: dict[tuple[str, str], dict[int, int]]
) -> dict[tuple[str, str], dict[int, int]]:
    """The inlier matches of each candidate pair (matches two-view verification left
    without a geometry) that one turn about the solver's axis explains, judged by
    ``_turns_of_pairs`` among the ``verified`` pairs; a pair it does not explain is left out."""
    pairs = _pair_rays(solver, candidates)
    if not pairs:
        return {}
    axis = solver.model.axis_and_point(solver.g)[0]
    threshold = 2.0 / solver.g[FOCAL]
    turns, _, explained = _turns_of_pairs(solver, axis, verified + pairs, threshold)
    turns, explained = turns[len(verified) :], explained[len(verified) :]
    found = {}
    for pair, turn in ((pair, turn) for pair, turn, kept in zip(pairs, turns, explained) if kept):
        E = essentials(axis, facing_point(axis), np.array([turn]))
        inlier = sampson_sq(E, pair.rays_i, pair.rays_j)[0] < threshold**2
        a, b = solver.order[pair.i], solver.order[pair.j]
        kept = [(k, m) for (k, m), keep in zip(candidates[a, b].items(), inlier) if keep]
        found[a, b] = dict(kept)
        found[b, a] = {m: k for k, m in kept}
    logger.info(
        "circular motion: %d of %d pairs without a verified geometry explained by one turn", len(found) // 2, len(pairs)
    )
    return found


def _initial_axis_and_angles(
    solver: _Solver, pairs: list[PairRays], known: dict[str, Pose], axis: np.ndarray | None
) -> None:
    """Steps 1-3: the axis (searched unless given), each pair's turn, the angles of the
    photos in the largest connected component of pairs the model explains, and the
    camera's offset. Known poses (a board's) give exact relative rotations: the axis
    is theirs when they turn, and each of their pairs counts as much as all feature
    pairs together."""
    n = len(solver.order)
    threshold = 2.0 / solver.g[FOCAL]
    known_pairs, known_rotations = _known_turns(solver, known)
    rotvecs = np.array([Rotation.from_matrix(R).as_rotvec() for R in known_rotations]).reshape(-1, 3)
    if np.any(np.linalg.norm(rotvecs, axis=1) > np.radians(5)):
        axis = np.linalg.svd(rotvecs, full_matrices=False)[2][0]
    elif axis is None:
        axis = search_axis(pairs, threshold)
    turns, inliers, explained = _turns_of_pairs(solver, axis, pairs, threshold)
    # A pair whose matches the model does not explain, or whose turn disagrees with the
    # other pairs' (a repeated pattern joined it), is left out.
    index = np.vstack([np.array([(p.i, p.j) for p in pairs]).reshape(-1, 2), known_pairs])
    turns = np.concatenate([turns, rotvecs @ axis])
    weights = np.concatenate([inliers, np.full(len(known_pairs), max(inliers.sum(), 1))]).astype(float)
    consistent = np.concatenate([explained, np.ones(len(known_pairs), bool)])
    agree = consistent_pairs(n, index[consistent], turns[consistent], weights[consistent], np.radians(3))
    consistent[np.flatnonzero(consistent)[~agree]] = False
    # The table turns one way: turns between photos close in file order are mostly
    # positive (weighted by the pairs' matches; the turn back across the first photo
    # counted the other way).
    near = consistent & (index[:, 1] - index[:, 0] < n / 2)
    across = consistent & ~near
    if np.sum(weights[near] * np.sign(turns[near])) - np.sum(weights[across] * np.sign(turns[across])) < 0:
        axis, turns = -axis, -turns
    graph = coo_matrix((np.ones(int(consistent.sum())), tuple(index[consistent].T)), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    linked = np.bincount(labels[index[consistent].ravel()], minlength=labels.max() + 1)
    solver.placed[:] = False
    solver.group[:] = -1
    # The ring is the largest set of linked photos, the groups the other sets (largest first).
    for group, label in enumerate(label for label in np.argsort(-linked, kind="stable") if linked[label]):
        members = np.flatnonzero(labels == label)
        keep = consistent & (labels[index[:, 0]] == label)
        local = -np.ones(n, int)
        local[members] = np.arange(len(members))
        solver.angles[members] = synchronise_angles(len(members), local[index[keep]], turns[keep], weights[keep], 0)
        solver.placed[members] = True
        solver.group[members] = group
    solver.trusted_pairs = {
        (solver.order[i], solver.order[j]) for i, j in index[: len(pairs)][consistent[: len(pairs)]]
    }
    solver.model = Model(axis)
    p = facing_point(axis)
    u = solver.model.axis_and_point(np.zeros(3))[1]  # the offset at psi = 0
    v = np.cross(axis, u)
    solver.g[2] = np.arctan2(p @ v, p @ u)
    logger.info(
        "circular motion: %d photo pairs by features (%d not explained by one turn or disagreeing), %d by known "
        "poses; %d photos in the largest ring, %d in %d groups apart from it",
        len(pairs),
        int((~consistent[: len(pairs)]).sum()),
        len(known_pairs),
        int(np.sum(solver.group == 0)),
        int(np.sum(solver.group > 0)),
        int(solver.group.max()),
    )


def _tracks_to_problem(solver: _Solver, tracks: list[dict[str, int]]) -> tuple[np.ndarray, Observations]:
    """Triangulated points of the tracks among placed photos, and their observations."""
    placed = {solver.order[i] for i in np.flatnonzero(solver.placed)}
    poses = {i: solver.pose(i) for i in np.flatnonzero(solver.placed)}
    points, views, point_ids, pixels, keypoint_ids = [], [], [], [], []
    for track in tracks:
        members = {n: k for n, k in track.items() if n in placed}
        if len(members) < 2:
            continue
        names = sorted(members, key=solver.index.get)
        observed = np.array([solver.keypoints[n][members[n]] for n in names])
        rays = solver.model.undistorted_rays(solver.g, observed)
        Rs = [poses[solver.index[n]][0] for n in names]
        ts = [poses[solver.index[n]][1] for n in names]
        X = triangulate(list(rays), Rs, ts)
        if not np.all(np.isfinite(X)) or any((R @ X + t)[2] <= 0 for R, t in zip(Rs, ts)):
            continue
        for name, pixel in zip(names, observed):
            views.append(solver.index[name])
            point_ids.append(len(points))
            pixels.append(pixel)
            keypoint_ids.append(members[name])
        points.append(X)
    observations = Observations(
        np.array(views, int), np.array(point_ids, int), np.array(pixels).reshape(-1, 2), np.array(keypoint_ids, int)
    )
    return np.array(points).reshape(-1, 3), observations


class Coherence:
    """The silhouette coherence term of one solve: some photos' outlines, the pairs
    compared (chosen at the angles the solve starts from) and the tangency errors'
    standard deviation there, against the features' ``feature_sigma``. ``own`` maps
    the problem's global parameters to this circle's (``Model``'s layout): the
    identity for one circle, one set's for sets adjusted together
    (pipeline.geometry.sets_adjustment)."""

    def __init__(
        self,
        model: Model,
        outlines: silhouette_coherence.Outlines,
        g: np.ndarray,
        angles: np.ndarray,
        feature_sigma: float,
        own: Callable[[np.ndarray], np.ndarray] = lambda g: g,
    ):
        self.model, self.own = model, own
        self.views, self.pixels = outlines.views, outlines.pixels
        self.pairs = silhouette_coherence.choose_pairs(angles[self.views])
        self.feature_sigma = feature_sigma
        self._undistorted: tuple[tuple, np.ndarray | None] = ((), None)
        """The intrinsics the outlines were last undistorted with, and their rays."""
        self.sigma = silhouette_coherence.robust_sigma(self.residuals(g, angles[:, None]))

    def residuals(self, g: np.ndarray, views: np.ndarray, turn_step: float = 0.0) -> np.ndarray:
        """(P, 4) tangency errors (pixels) of the pairs at the global parameters and
        angles, every pair's turn increased by ``turn_step``."""
        g = self.own(g)
        axis, p = self.model.axis_and_point(g)
        intrinsics = tuple(g[[FOCAL, CX, CY, K1]])
        if intrinsics != self._undistorted[0]:
            # The bundle adjuster differentiates by the axis and the angles with the
            # intrinsics unchanged: the outlines' rays are undistorted once for those.
            rays = self.model.undistorted_rays(g, self.pixels.reshape(-1, 2)).reshape(self.pixels.shape)
            self._undistorted = (intrinsics, rays)
        normalised = self._undistorted[1]
        angles = views[self.views, 0]
        turns = angles[self.pairs[:, 1]] - angles[self.pairs[:, 0]] + turn_step
        return silhouette_coherence.tangency_residuals(axis, p, turns, normalised, self.pairs, g[FOCAL])

    def weighted(self, g: np.ndarray, views: np.ndarray, turn_step: float = 0.0) -> np.ndarray:
        return silhouette_coherence.weighted(self.residuals(g, views, turn_step), self.sigma, self.feature_sigma)

    def view_jacobian(self, g: np.ndarray, views: np.ndarray) -> np.ndarray:
        """(4P, n, 1) derivatives by the angles: a pair's residuals depend on its turn alone,
        so one evaluation with every turn moved gives them all."""
        step = 1e-7
        by_turn = (self.weighted(g, views, step) - self.weighted(g, views)) / step
        J = np.zeros((*by_turn.shape, *views.shape))
        rows = np.arange(len(self.pairs))
        J[rows, :, self.views[self.pairs[:, 1]], 0] = by_turn
        J[rows, :, self.views[self.pairs[:, 0]], 0] = -by_turn
        return J.reshape(-1, *views.shape)

    @property
    def prior(self) -> Prior:
        return Prior(lambda g, views: self.weighted(g, views).ravel(), self.view_jacobian)

    @property
    def usable(self) -> bool:
        return len(self.pairs) > 0 and np.isfinite(self.sigma) and self.sigma > 0


def _problem(
    solver: _Solver, observations: Observations, free_global: np.ndarray, coherence: Coherence | None = None
) -> Problem:
    free_views = solver.placed[:, None].copy()
    for group in np.unique(solver.group[solver.placed]):
        # Each group's angles are known up to one offset: its first photo holds it.
        free_views[int(np.flatnonzero(solver.placed & (solver.group == group))[0]), 0] = False
    placed = np.flatnonzero(solver.placed & (solver.group == 0))
    priors = []
    if solver.settings.even_steps_deg > 0:
        sigma = np.radians(solver.settings.even_steps_deg)

        def even_steps(g: np.ndarray, views: np.ndarray) -> np.ndarray:
            turns = np.angle(np.exp(1j * np.diff(views[placed, 0])))
            steps = turns / np.diff(placed)
            return (steps - np.sum(turns) / (placed[-1] - placed[0])) / sigma

        priors.append(Prior(even_steps))
    known = [(i, R) for i, R in solver.known_rotations.items() if solver.placed[i]]
    if len(known) >= 2:
        # Known poses (a board's) hold their photos' turns: a group of photos no feature
        # track ties to the rest keeps its place.
        reference, R_reference = known[0]
        rotvecs = np.array([Rotation.from_matrix(R @ R_reference.T).as_rotvec() for _, R in known[1:]])
        others = np.array([i for i, _ in known[1:]])
        sigma = np.radians(KNOWN_TURN_STD_DEG)

        def known_turns(g: np.ndarray, views: np.ndarray) -> np.ndarray:
            axis = solver.model.axis_and_point(g)[0]
            difference = views[others, 0] - views[reference, 0] - rotvecs @ axis
            return np.angle(np.exp(1j * difference)) / sigma

        priors.append(Prior(known_turns))
    if coherence is not None:
        priors.append(coherence.prior)
    return Problem(
        project=solver.model.project,
        jacobians=solver.model.jacobians,
        observations=observations,
        free_global=free_global,
        free_views=free_views,
        global_steps=np.array([1e-6, 1e-6, 1e-6, 1e-4, 1e-4, 1e-4, 1e-7]),
        view_steps=np.array([1e-7]),
        point_step=1e-7,
        priors=priors,
    )


def _solve(solver: _Solver, tracks, free_global: np.ndarray):
    """Bundle adjustment of the placed photos, outliers dropped and solved again."""
    points, observations = _tracks_to_problem(solver, tracks)
    feature_sigma = _feature_sigma(solver, observations, points)
    solver.coherence = {}
    for attempt in range(4):
        coherence = _coherence(solver, feature_sigma)
        problem = _problem(solver, observations, free_global, coherence)
        result = adjust(problem, solver.g, solver.angles[:, None], points)
        solver.g, solver.angles, points = result.global_params, result.view_params[:, 0], result.points
        limit = max(solver.settings.outlier_px, 4 * result.sigma_px)
        inliers = result.errors_px <= limit
        # The two noises were measured where the solve started; solved again until
        # the features' and the outlines' noise at the solution agree with them.
        settled = coherence is None or _settled(solver, coherence, result.sigma_px)
        if (inliers.all() and settled) or attempt == 3:
            break
        feature_sigma = result.sigma_px
        if inliers.all():
            continue
        observations, points = keep_inliers(observations, points, inliers)
    return result, problem, points, observations


def _feature_sigma(solver: _Solver, observations: Observations, points: np.ndarray) -> float:
    """The features' reprojection noise at the solver's state."""
    return noise_px(solver.model.project, solver.g, solver.angles[:, None], points, observations)


def _coherence(solver: _Solver, feature_sigma: float) -> Coherence | None:
    """The silhouette coherence term at the solver's state, None without outlines or pairs."""
    if solver.outlines is None:
        return None
    ring = np.flatnonzero((solver.placed & (solver.group == 0))[solver.outlines.views])
    outlines = silhouette_coherence.Outlines(solver.outlines.pixels[ring], solver.outlines.views[ring])
    coherence = Coherence(solver.model, outlines, solver.g, solver.angles, feature_sigma)
    return coherence if coherence.usable else None


def _settled(solver: _Solver, coherence: Coherence, feature_sigma: float) -> bool:
    """Whether both noises at the solution are within a fifth of those the solve weighted
    by, and records them (sfm.json)."""
    sigma = silhouette_coherence.robust_sigma(coherence.residuals(solver.g, solver.angles[:, None]))
    solver.coherence = {
        "pairs": len(coherence.pairs),
        "tangency_sigma_px": round(sigma, 3),
        "feature_sigma_px": round(feature_sigma, 3),
    }
    return abs(sigma / coherence.sigma - 1) < 0.2 and abs(feature_sigma / coherence.feature_sigma - 1) < 0.2


def _angle_std_deg(solver: _Solver, problem: Problem, covariance: np.ndarray) -> np.ndarray:
    n_global = int(problem.free_global.sum())
    std = np.zeros(len(solver.order))
    free_rows = np.flatnonzero(problem.free_views[:, 0])
    std[free_rows] = np.degrees(np.sqrt(np.maximum(np.diag(covariance)[n_global:], 0)))
    return std


def _self_calibration(solver: _Solver, tracks, base_free: np.ndarray, observations: Observations):
    """Whether the photos constrain k1: solved with it free too, kept free only when its
    standard deviation, as a displacement in pixels at the frame's corner, is below the
    limit. The principal point is never adjusted: a single circular motion gives two
    constraints on the image of the absolute conic, enough for the focal length with
    the principal point known, not for all three; freed, the principal point follows
    second-order effects (a lens' higher terms, blob centres under perspective) and on
    a synthetic turntable landed 15 px off with a standard deviation of 0.13 px.
    Returns (free mask, report); the solver's state is left as it was."""
    report: dict = {
        "frame_coverage": round(frame_coverage(observations.pixels, solver.start.width, solver.start.height), 3),
        "principal_point": "held: a single circular motion does not determine it",
    }
    if not solver.settings.self_calibrate:
        report["skipped"] = (
            "the camera was calibrated (the board or calibrate.known_intrinsics), or sfm.self_calibrate is off"
        )
        return base_free, report
    if report["frame_coverage"] < solver.settings.min_frame_coverage:
        report["skipped"] = (
            f"observations cover {report['frame_coverage']:.0%} of the frame "
            f"(< {solver.settings.min_frame_coverage:.0%}): principal point and distortion are not constrained"
        )
        return base_free, report
    saved = solver.g.copy(), solver.angles.copy()
    trial = base_free.copy()
    trial[K1] = True
    result, problem, *_ = _solve(solver, tracks, trial)
    std = _global_std(problem, result.covariance)
    radius = corner_radius(solver.start.width, solver.start.height, *solver.g[[FOCAL, CX, CY]])
    displacement = radial_shift_px(std[K1], solver.g[FOCAL], radius)
    report["tried"] = {"k1": float(solver.g[K1]), "std_px": round(displacement, 3)}
    solver.g, solver.angles = saved
    limit = solver.settings.max_calibration_std_px
    free = base_free.copy()
    free[K1] = displacement <= limit
    if not free[K1]:
        report["held_k1"] = f"its standard deviation moves points by {displacement:.2f} px (> {limit})"
    return free, report


def _global_std(problem: Problem, covariance: np.ndarray) -> np.ndarray:
    """Standard deviation of each global parameter (0 for fixed ones)."""
    std = np.zeros(len(problem.free_global))
    free = np.flatnonzero(problem.free_global)
    std[free] = np.sqrt(np.maximum(np.diag(covariance)[: len(free)], 0))
    return std


def _solve_placing(solver: _Solver, tracks, free: np.ndarray, unplaced: dict[str, str]):
    """``_solve``, then the photos that fail step 5's tests left unplaced and solved
    again, until every photo left passes."""
    while True:
        result, problem, points, observations = _solve(solver, tracks, free)
        counts = np.bincount(observations.view, minlength=len(solver.order))
        std = _angle_std_deg(solver, problem, result.covariance)
        reasons = _placement_failures(solver, result.errors_px, observations, counts, std)
        if not reasons or np.sum(solver.placed & (solver.group == 0)) - len(reasons) < 3:
            return result, problem, points, observations, counts, std
        for i, reason in reasons.items():
            unplaced[solver.order[i]] = reason
            logger.info("%s: %s", solver.order[i], reason)
            solver.placed[i] = False
        for group in np.unique(solver.group[solver.placed]):
            members = np.flatnonzero(solver.placed & (solver.group == group))
            if group > 0 and len(members) < 2:
                for i in members:
                    unplaced[solver.order[i]] = "the one photo left of a group of photos not matched into the ring"
                    solver.placed[i] = False


def _placement_failures(
    solver: _Solver, errors_px: np.ndarray, observations: Observations, counts: np.ndarray, std: np.ndarray
) -> dict[int, str]:
    """Step 5: why each placed photo that fails a test is not placed, by index."""
    settings = solver.settings
    placed = np.flatnonzero(solver.placed)
    pooled = float(np.median(errors_px)) if len(errors_px) else 0.0
    reasons = {}
    for i in placed:
        own = errors_px[observations.view == i]
        median = float(np.median(own)) if len(own) else 0.0
        exceed = int(np.sum(own > pooled))
        significance = float(binom.sf(exceed - 1, len(own), 0.5)) if len(own) else 1.0
        if counts[i] < solver.min_observations:
            reasons[i] = f"{counts[i]} inlier observations (needs {solver.min_observations})"
        elif not np.isfinite(std[i]):
            reasons[i] = "its features leave its angle undetermined (the bundle adjustment's covariance)"
        elif significance < settings.misfit_significance / len(placed) and median > settings.misfit_ratio * pooled:
            reasons[i] = (
                f"its observations fit the circle to {median:.2f} px against the photos' {pooled:.2f} px (sign test "
                f"p = {significance:.1e}): not the same camera on the circle"
            )
    return reasons


def _partners(solver: _Solver) -> dict[str, int]:
    placed = {solver.order[i] for i in np.flatnonzero(solver.placed)}
    partners: dict[str, set[str]] = {name: set() for name in placed}
    for a, b in solver.trusted_pairs:
        if a in placed and b in placed and solver.group[solver.index[a]] == solver.group[solver.index[b]]:
            partners[a].add(b)
            partners[b].add(a)
    return {name: len(found) for name, found in partners.items()}


class _Ring(NamedTuple):
    """Steps 1-4's state: the solver, its trusted tracks, their inlier observations, the
    photos left out with the reason, and the global parameters adjusted."""

    solver: _Solver
    tracks: list[dict[str, int]]
    observations: Observations
    unplaced: dict[str, str]
    free: np.ndarray


def _ring(
    settings: CircularSettings,
    order: list[str],
    intrinsics: Intrinsics,
    keypoints: dict[str, np.ndarray],
    matches: dict[tuple[str, str], dict[int, int]],
    known: dict[str, Pose],
    outlines: dict[str, np.ndarray] | None,
    unverified: dict[tuple[str, str], dict[int, int]] | None,
    weak: bool,
) -> _Ring:
    """Steps 1-4 with the strong pairs, or with the weak pairs too (``weak``)."""
    solver = _Solver(settings, order, intrinsics, keypoints, weak)
    solver.known_rotations = {solver.index[n]: pose.R for n, pose in known.items() if n in solver.index}
    if outlines:
        solver.outlines = silhouette_coherence.Outlines.of({solver.index[n]: hull for n, hull in outlines.items()})
    free = np.zeros(len(GLOBAL_NAMES), bool)
    free[:3] = True
    free[FOCAL] = settings.refine_focal
    axis = None
    # Twice when the focal length moved: a wrong one scales every turn, and a ring whose
    # turns do not add up to a full one breaks where the fewest pairs bridge (a prior
    # 28 % too long made 20 steps of 18 degrees add up to 410 and cut a photo off).
    for _ in range(2):
        focal = solver.g[FOCAL]
        pairs = _pair_rays(solver, matches)
        if len(pairs) < 2:
            raise ValueError(f"only {len(pairs)} photo pairs share {solver.min_pair_matches} verified matches")
        _initial_axis_and_angles(solver, pairs, known, axis)
        if unverified:
            # Once, with the axis the verified pairs give: a pair's one turn is a far
            # stronger model than the five degrees of freedom verification fitted.
            found = _explained_by_one_turn(solver, pairs, unverified)
            unverified = None
            if found:
                matches = matches | found
                pairs = _pair_rays(solver, matches)
                _initial_axis_and_angles(solver, pairs, known, solver.model.axis_and_point(solver.g)[0])
        if np.sum(solver.group == 0) < 3:
            raise ValueError("fewer than three photos are connected by consistent matches")
        unplaced = {n: "not matched into the ring of the other photos" for n, p in zip(order, solver.placed) if not p}
        # 4. Bundle adjustment with the focal length, then self-calibration; tracks only
        # through the pairs step 3 trusted (one false pair corrupts every track it joins).
        trusted = {pair: found for pair, found in matches.items() if pair in solver.trusted_pairs}
        tracks = build_tracks(order, keypoints, trusted)
        *_, observations, _, _ = _solve_placing(solver, tracks, free, unplaced)
        if abs(solver.g[FOCAL] / focal - 1) < 0.02:
            break
        axis = solver.model.axis_and_point(solver.g)[0]
    return _Ring(solver, tracks, observations, unplaced, free)


def _in_ring(solver: _Solver) -> np.ndarray:
    """Which photos the features placed in the ring."""
    return solver.placed & (solver.group == 0)


def extension_verdict(
    ring_sizes: tuple[int, int], tangency_sigma_px: tuple[float | None, float | None], ratio: float
) -> dict:
    """Whether the ring extended by weak pairs is kept, from the photos in each ring
    (strong pairs', extended) and the standard deviation of each ring's outline tangency
    errors: it must join more photos, and its outlines must agree with its angles about
    as well as the strong ring's do (their noise at most ``ratio`` times). Weak pairs' turns
    are a few degrees off where strong pairs' are one or two, and enough of them can
    pull the whole ring into another solution that fits the features about as well;
    the outlines then disagree by many times their own noise."""
    strong, extended = tangency_sigma_px
    verdict: dict = {"ring_photos": {"strong_pairs": ring_sizes[0], "with_weak_pairs": ring_sizes[1]}}
    if strong is not None and extended is not None:
        verdict["tangency_sigma_px"] = {"strong_pairs": strong, "with_weak_pairs": extended}
    kept = False
    if ring_sizes[1] <= ring_sizes[0]:
        why = f"weak pairs join {ring_sizes[1]} photos in the ring, the strong pairs {ring_sizes[0]}"
    elif strong is None or extended is None:
        why = "the outlines could not judge the ring extended by weak pairs"
    elif extended > ratio * strong:
        why = (
            f"the outlines disagree with the ring extended by weak pairs by {extended:.2f} px against "
            f"{strong:.2f} px with the strong pairs alone (more than {ratio} times)"
        )
    else:
        why, kept = f"weak pairs join {ring_sizes[1]} photos in the ring, the strong pairs {ring_sizes[0]}", True
    verdict["kept"] = kept
    verdict["decision"] = f"{why}: kept the {'weak' if kept else 'strong'} pairs' ring"
    return verdict


GROUP_OUTLINES = 8
"""Outlines of a group compared at each candidate offset (twice as many of the ring's):
more cost time and add little."""


def _spread(indices: np.ndarray, count: int) -> np.ndarray:
    return indices[:: max(1, len(indices) // count)]


def _outline_offset(solver: _Solver, members: np.ndarray) -> silhouette_tangency.Placement | None:
    """Where a group's outlines agree best with the ring's: the angle of its first photo,
    searched over the whole turn at the ring's axis and intrinsics."""
    hulls = dict(zip(solver.outlines.views.tolist(), solver.outlines.pixels))

    def rays(i: int) -> np.ndarray:
        return solver.model.undistorted_rays(solver.g, hulls[i])

    base = solver.angles[members[0]]
    group = [(rays(i), solver.angles[i] - base) for i in _spread(members, GROUP_OUTLINES) if i in hulls]
    ring = np.array([i for i in np.flatnonzero(_in_ring(solver)) if i in hulls], int)
    partners = [(rays(i), solver.pose(i)) for i in _spread(ring, 2 * GROUP_OUTLINES)]
    if not group or not partners:
        return None
    candidates = np.radians(np.arange(0.0, 360.0, 0.5))
    return silhouette_tangency.place(group, solver.pose_at, partners, candidates, solver.g[FOCAL])


def matched_pairs(
    matches: dict[tuple[str, str], dict[int, int]], first: set[str], second: set[str], min_matches: int
) -> int:
    """How many pairs of a photo of ``first`` and one of ``second`` share ``min_matches``
    verified matches."""
    return sum(1 for (a, b), found in matches.items() if a in first and b in second and len(found) >= min_matches)


def _join_groups(
    solver: _Solver,
    tracks,
    free: np.ndarray,
    unplaced: dict[str, str],
    observations: Observations,
    matches: dict[tuple[str, str], dict[int, int]],
) -> tuple[list[dict], Observations]:
    """Step 4 for the groups, where outlines are fitted: each group (largest first) is put
    at the offset where its outlines agree best with the ring's and the ring is solved
    again with the group's features and every outline. A turn whose features are
    shading breaks the ring where the specimen shows its plainest sides, and each arc
    fixes the axis and focal length poorly; joined, they fix them as a full turn does.
    The group stays apart (for the placement's silhouettes) where another offset, a
    distinct minimum of the outlines' error more than 5 degrees away, fits within
    ``silhouette_ambiguity`` times as well (the slope of the best offset's own valley
    is no rival), or where the joined ring's tangency noise is more than
    ``misfit_ratio`` times the ring's alone, as a wrong offset or a wrong mask makes
    it. A group that strong pairs of matches tie to the ring's photos, pairs one circle
    does not explain (step 3 set them aside), is another set: the camera moved or the
    specimen was re-placed between them, and no one offset on this circle is right.
    It is left for pipeline.geometry.turntable_sets to join by those matches, never
    by outlines. Returns a report per group and the inlier observations of the ring
    as it stands."""
    reports: list[dict] = []
    if solver.outlines is None:
        return reports, observations
    for group in np.unique(solver.group[solver.placed & (solver.group > 0)]):
        members = np.flatnonzero(solver.placed & (solver.group == group))
        if not len(members):  # an earlier group's joined solve left all its photos out
            continue
        before = solver.coherence.get("tangency_sigma_px")
        report: dict = {"photos": [solver.order[i] for i in members]}
        reports.append(report)
        ring_names = {solver.order[i] for i in np.flatnonzero(_in_ring(solver))}
        crossing = matched_pairs(matches, ring_names, set(report["photos"]), solver.settings.min_observations)
        if crossing:
            report["joined"] = False
            report["decision"] = (
                f"another set: {crossing} pairs of matches with the ring that one circle does not explain; "
                "joined by its features or left out"
            )
            continue
        placement = _outline_offset(solver, members) if before is not None else None
        if placement is None:
            why = (
                "no outline of the ring constrains the group"
                if before is not None
                else "the ring's outlines were not fitted"
            )
            report["joined"], report["decision"] = False, why
            continue
        rival = placement.rivals[0][1] if placement.rivals else None
        report["offset_deg"] = round(float(np.degrees(placement.angle)), 3)
        report["outline_error_px"] = {"best": round(placement.error_px, 3), "rival": rival and round(rival, 3)}
        if rival is not None and rival < solver.settings.silhouette_ambiguity * placement.error_px:
            report["joined"] = False
            report["decision"] = (
                f"ambiguous: another offset fits its outlines almost as well ({rival:.2f} px against "
                f"{placement.error_px:.2f} px)"
            )
            continue
        saved = (
            solver.g.copy(),
            solver.angles.copy(),
            solver.placed.copy(),
            solver.group.copy(),
            dict(solver.coherence),
            dict(unplaced),
        )
        ring_before = int(np.sum(_in_ring(solver)))
        solver.angles[members] += placement.angle - solver.angles[members[0]]
        solver.group[members] = 0
        *_, joined_observations, _, _ = _solve_placing(solver, tracks, free, unplaced)
        after = solver.coherence.get("tangency_sigma_px")
        report["tangency_sigma_px"] = {"ring": before, "joined": after}
        ring_after = int(np.sum(_in_ring(solver)))
        if after is None or after > solver.settings.misfit_ratio * before:
            why = f"the joined ring's outlines disagree by {after} px against {before:.2f} px for the ring alone"
        elif ring_after <= ring_before:
            why = f"the joined ring holds {ring_after} photos, the ring alone {ring_before}"
        else:
            report["joined"], report["decision"] = (
                True,
                f"joined: {ring_after} photos in the ring (before {ring_before})",
            )
            logger.info("circular motion: a group of %d photos %s", len(members), report["decision"])
            observations = joined_observations
            continue
        report["joined"], report["decision"] = False, why
        logger.info("circular motion: a group of %d photos stays apart: %s", len(members), why)
        solver.g, solver.angles, solver.placed, solver.group, solver.coherence, restored = saved
        unplaced.clear()
        unplaced.update(restored)
    return reports, observations


def solve(
    settings: CircularSettings,
    order: list[str],
    intrinsics: Intrinsics,
    keypoints: dict[str, np.ndarray],
    matches: dict[tuple[str, str], dict[int, int]],
    known: dict[str, Pose] | None = None,
    outlines: dict[str, np.ndarray] | None = None,
    unverified: dict[tuple[str, str], dict[int, int]] | None = None,
) -> CircularMotion:
    """Circular motion of the photos ``order`` (one camera, initial ``intrinsics``)
    from their keypoints and verified matches, ``known`` poses of some of them (a
    board's, in any one frame) for the start, the convex ``outlines`` (pixels) of
    the photos whose silhouette coherence is fitted too, and ``unverified`` matches of
    pairs two-view verification found no geometry for (a < b), kept where one turn
    about the axis the verified pairs give explains them; ValueError when fewer than
    three photos are connected by consistent matches."""
    # 1-4 with the strong pairs; where they leave photos out and the outlines can judge
    # the result, again with the weak pairs too (step 3).
    ring = _ring(settings, order, intrinsics, keypoints, matches, known or {}, outlines, None, weak=False)
    weak_pairs: dict = {}
    if outlines and not np.all(_in_ring(ring.solver)):
        extended = _ring(settings, order, intrinsics, keypoints, matches, known or {}, outlines, unverified, weak=True)
        weak_pairs = extension_verdict(
            tuple(int(np.sum(_in_ring(r.solver))) for r in (ring, extended)),
            tuple(r.solver.coherence.get("tangency_sigma_px") for r in (ring, extended)),
            settings.misfit_ratio,
        )
        logger.info("circular motion: %s", weak_pairs["decision"])
        if weak_pairs["kept"]:
            ring = extended
    solver, tracks, observations, unplaced, free = ring
    joined_groups, observations = _join_groups(solver, tracks, free, unplaced, observations, matches)
    free, calibration = _self_calibration(solver, tracks, free, observations)
    result, problem, points, observations, counts, std = _solve_placing(solver, tracks, free, unplaced)
    # Tracks from the inlier observations (outliers were dropped from tracks, not from
    # the keypoint graph); the solution's points are in the inliers' order.
    kept: list[dict[str, int]] = [{} for _ in range(len(points))]
    point_groups = np.zeros(len(points), int)
    for view, point, keypoint in zip(observations.view, observations.point, observations.keypoint):
        kept[point][order[view]] = int(keypoint)
        point_groups[point] = solver.group[view]
    # 5. The solution: the ring's angles unwrapped in file order, the groups' relative to their first photo.
    global_std = _global_std(problem, result.covariance)
    calibration["values"] = {
        name: {"value": float(solver.g[i]), "std": float(global_std[i]) if free[i] else None, "adjusted": bool(free[i])}
        for name, i in (("f", FOCAL), ("cx", CX), ("cy", CY), ("k1", K1))
    }
    axis, p = solver.model.axis_and_point(solver.g)
    ring = np.flatnonzero(solver.placed & (solver.group == 0))
    groups = []
    renumbered = np.zeros(len(points), int)
    for group in np.unique(solver.group[solver.placed & (solver.group > 0)]):
        members = np.flatnonzero(solver.placed & (solver.group == group))
        base = solver.angles[members[0]]
        groups.append(
            {order[i]: float(a) for i, a in zip(members, np.angle(np.exp(1j * (solver.angles[members] - base))))}
        )
        # The group's points in the frame of its first photo at angle 0, as its relative angles say.
        own = point_groups == group
        points[own] = axis_rotation(axis, np.full(int(own.sum()), base), points[own] - p) + p
        renumbered[own] = len(groups)
    g = solver.g
    return CircularMotion(
        axis=axis,
        point=p,
        angles={order[i]: float(a) for i, a in zip(ring, np.unwrap(solver.angles[ring]))},
        intrinsics=Intrinsics(
            intrinsics.width, intrinsics.height, g[FOCAL], g[FOCAL], g[CX], g[CY], [float(g[K1]), 0, 0, 0, 0]
        ),
        points=points,
        tracks=kept,
        point_groups=renumbered,
        angle_std_deg={order[i]: float(std[i]) for i in np.flatnonzero(solver.placed)},
        observations={n: int(counts[solver.index[n]]) for n in order},
        partners=_partners(solver),
        calibration=calibration,
        reprojection_px=float(np.median(result.errors_px)) if len(result.errors_px) else 0.0,
        unplaced={n: reason for n, reason in unplaced.items() if not any(n in group for group in groups)},
        groups=groups,
        silhouette_coherence=solver.coherence,
        weak_pairs=weak_pairs,
        joined_groups=joined_groups,
    )
