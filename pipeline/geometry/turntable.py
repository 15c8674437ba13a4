"""The turntable model: a fixed camera and an object turning about one axis.

In the object's frame (the frame SfM reconstructs) the camera then moves on a
circle: photo i, taken after the table turned by ``angle[i]``, has the pose

    R_i = R_fixed @ Rot(axis, angle_i),     c_i = Rot(axis, angle_i)^T (c_fixed - o) + o

with ``o`` a point on the axis. The model has 6 + 2 + 2 degrees of freedom plus
one angle per photo, against 6 per photo for free poses, so a photo SfM could not
register needs only its angle: from the board when it is seen (the board turns
with the object), else from its feature matches with posed photos (epipolar
geometry), else from the silhouette; searched between the angles of its
neighbours in file order (a turntable only turns one way; steps may be uneven).

Limitations: the camera and the table must not move between photos, and the
photos must be named in the order they were taken. A photo whose neighbours are
both unregistered gets the wider bracket of the nearest registered ones; a
symmetric specimen with no board leaves its angle ambiguous within that bracket.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.camera.model import Intrinsics, Pose, project, rotation_angle_deg


def _turn(axis: np.ndarray, angle: float) -> np.ndarray:
    return Rotation.from_rotvec(axis * angle).as_matrix()


def _chordal_mean(rotations: list[np.ndarray]) -> np.ndarray:
    U, _, Vt = np.linalg.svd(np.sum(rotations, axis=0))
    return U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt


@dataclass
class Turntable:
    axis: np.ndarray
    """Unit vector; the table turns by +angle about it from one photo to the next."""
    point: np.ndarray
    """A point on the axis."""
    R_fixed: np.ndarray
    c_fixed: np.ndarray
    angles: dict[str, float]
    """Angle of each photo the model was fitted to, radians, increasing in file order."""

    def pose(self, angle: float) -> Pose:
        turn = _turn(self.axis, angle)
        R = self.R_fixed @ turn
        centre = turn.T @ (self.c_fixed - self.point) + self.point
        return Pose(R, -R @ centre)

    @property
    def radius(self) -> float:
        offset = self.c_fixed - self.point
        return float(np.linalg.norm(offset - self.axis * (offset @ self.axis)))

    def angle_of(self, pose: Pose) -> float:
        """The angle whose model rotation is nearest to ``pose``'s."""
        rotvec = Rotation.from_matrix(self.R_fixed.T @ pose.R).as_rotvec()
        return float(rotvec @ self.axis)

    def residuals_at(self, pose: Pose, angle: float) -> tuple[float, float]:
        """Rotation difference (degrees) and centre distance (fraction of the radius)
        between ``pose`` and the model's pose at ``angle``."""
        model = self.pose(angle)
        return rotation_angle_deg(model.R @ pose.R.T), float(np.linalg.norm(model.center - pose.center) / self.radius)

    def residuals(self, poses: dict[str, Pose]) -> dict[str, tuple[float, float]]:
        """``residuals_at`` for each photo the model was fitted to, at its angle."""
        return {name: self.residuals_at(pose, self.angles[name]) for name, pose in poses.items()}


def fit(poses: dict[str, Pose], order: list[str]) -> Turntable:
    """The turntable that best explains registered poses; ``order`` lists every photo
    in capture order (registered or not)."""
    names = [n for n in order if n in poses]
    if len(names) < 3:
        raise ValueError("a turntable needs at least three registered photos")
    reference = poses[names[0]].R
    rotvecs = np.array([Rotation.from_matrix(reference.T @ poses[n].R).as_rotvec() for n in names])
    # Relative rotations all turn about the axis: it is their dominant direction.
    axis = np.linalg.svd(rotvecs, full_matrices=False)[2][0]
    angles = np.unwrap(rotvecs @ axis)
    if np.sum(np.diff(angles)) < 0:
        axis, angles = -axis, -angles
    R_fixed = _chordal_mean([poses[n].R @ _turn(axis, a).T for n, a in zip(names, angles)])
    # Re-measure angles against the averaged camera, then solve the centres linearly:
    # c_i = T_i^T c_fixed + (I - T_i^T) o.
    angles = np.unwrap([Rotation.from_matrix(R_fixed.T @ poses[n].R).as_rotvec() @ axis for n in names])
    turns = [_turn(axis, a) for a in angles]
    A = np.vstack([np.hstack([T.T, np.eye(3) - T.T]) for T in turns])
    b = np.concatenate([poses[n].center for n in names])
    solution = np.linalg.lstsq(A, b, rcond=None)[0]
    c_fixed, point = solution[:3], solution[3:]
    # Only the axis' position is defined; put `point` level with the camera.
    point = point + axis * ((c_fixed - point) @ axis)
    return Turntable(axis, point, R_fixed, c_fixed, dict(zip(names, map(float, angles))))


def fit_robust(poses: dict[str, Pose], order: list[str], tolerance_deg: float = 1.0) -> tuple[Turntable, list[str]]:
    """``fit`` after dropping, worst first, photos whose pose disagrees with the model
    by more than max(3 x the median rotation residual, ``tolerance_deg``): SfM
    sometimes registers a photo of a repetitive set at a wrong pose. Returns the
    model and the photos dropped."""
    kept = dict(poses)
    while True:
        model = fit(kept, order)
        residuals = {n: r for n, (r, _) in model.residuals(kept).items()}
        worst = max(residuals, key=residuals.get)
        limit = max(3 * float(np.median(list(residuals.values()))), tolerance_deg)
        if residuals[worst] <= limit or len(kept) <= 3:
            return model, sorted(set(poses) - set(kept))
        del kept[worst]


def bracket(model: Turntable, order: list[str], name: str) -> tuple[float, float]:
    """Angles between which an unplaced photo must lie: those of the nearest placed
    photos before and after it in file order (wrapping round once)."""
    placed = [n for n in order if n in model.angles]
    index = order.index(name)
    before = [n for n in order[:index] if n in model.angles]
    after = [n for n in order[index + 1 :] if n in model.angles]
    lo = model.angles[before[-1]] if before else model.angles[placed[-1]] - 2 * np.pi
    hi = model.angles[after[0]] if after else model.angles[placed[0]] + 2 * np.pi
    return lo, hi


@dataclass(eq=False)
class Matches:
    """Keypoints of an unposed photo matched to those of a posed one (pixels)."""

    pose: Pose
    """The posed photo's pose."""
    intrinsics: Intrinsics
    """The posed photo's camera."""
    points: np.ndarray
    """(n, 2) keypoints in the unposed photo."""
    partner_points: np.ndarray
    """(n, 2) the matching keypoints in the posed photo."""


def _sampson_px(model: Turntable, angles: np.ndarray, intrinsics: Intrinsics, matches: Matches) -> np.ndarray:
    """(angles, n) Sampson distances of the matches for the photo at each angle."""
    x = np.column_stack([matches.points, np.ones(len(matches.points))])
    x_partner = np.column_stack([matches.partner_points, np.ones(len(matches.points))])
    K_inv = np.linalg.inv(intrinsics.K)
    K_partner_inv = np.linalg.inv(matches.intrinsics.K)
    distances = []
    for angle in angles:
        pose = model.pose(angle)
        R = matches.pose.R @ pose.R.T
        t = matches.pose.t - R @ pose.t
        t_cross = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
        F = K_partner_inv.T @ t_cross @ R @ K_inv
        Fx, Ftx = x @ F.T, x_partner @ F
        algebraic = np.sum(x_partner * Fx, axis=1)
        denominator = Fx[:, 0] ** 2 + Fx[:, 1] ** 2 + Ftx[:, 0] ** 2 + Ftx[:, 1] ** 2
        distances.append(np.abs(algebraic) / np.sqrt(np.maximum(denominator, 1e-300)))
    return np.array(distances)


def angle_from_matches(
    model: Turntable, lo: float, hi: float, intrinsics: Intrinsics, matches: list[Matches], threshold_px: float = 2.0
) -> tuple[float, list[Matches]]:
    """The angle in [lo, hi] at which the photo's feature matches with posed photos
    best obey their epipolar geometry, and the partners that agree with it (most of
    their matches within ``threshold_px``). A planar set that defeats SfM's pose
    estimation still gives correct correspondences, and one unknown needs few. A
    repetitive set also gives false pairs (a checkerboard a quarter turn away):
    partners that disagree are dropped and the angle is searched again.

    The cost is the mean truncated squared Sampson distance (outliers count
    ``threshold_px``), searched on a grid of 1/4 degree and then 1/64 degree.

    Limitation: for cameras on one circle the turn moves image points mostly along
    the epipolar lines, so the angle is weakly determined: with matches spread over
    the whole frame, 0.3 px of keypoint noise moves it by about 0.2 degrees."""

    def cost(angles: np.ndarray, partners: list[Matches]) -> np.ndarray:
        distances = np.hstack([_sampson_px(model, angles, intrinsics, m) for m in partners])
        return np.mean(np.minimum(distances, threshold_px) ** 2, axis=1)

    coarse_step, fine_step = np.radians(0.25), np.radians(1 / 64)
    partners = list(matches)
    while True:
        coarse = np.arange(lo, hi + coarse_step / 2, coarse_step)
        angle = float(coarse[int(np.argmin(cost(coarse, partners)))])
        fine = np.clip(np.arange(angle - coarse_step, angle + coarse_step + fine_step / 2, fine_step), lo, hi)
        angle = float(fine[int(np.argmin(cost(fine, partners)))])
        agreeing = [
            m
            for m in partners
            if np.mean(_sampson_px(model, np.array([angle]), intrinsics, m)[0] < threshold_px) >= 0.5
        ]
        if len(agreeing) == len(partners) or not agreeing:
            return angle, agreeing
        partners = agreeing


def splat(points: np.ndarray, radius_px: int, pose: Pose, intrinsics: Intrinsics, shape: tuple[int, int]) -> np.ndarray:
    """The silhouette of hull points seen from ``pose``: each a disc of ``radius_px``."""
    pixels, depth = project(points, intrinsics, pose)
    u, v = np.round(pixels[depth > 1e-6]).astype(int).T
    h, w = shape
    keep = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    rendered = np.zeros((h, w), np.uint8)
    rendered[v[keep], u[keep]] = 1
    if radius_px > 0:
        rendered = cv2.dilate(rendered, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1,) * 2))
    return rendered.astype(bool)


def splat_radius(voxel: float, intrinsics: Intrinsics, depth: float) -> int:
    """Pixels of half a voxel at ``depth``: hull points splatted this wide leave no gaps."""
    return max(int(np.ceil(0.5 * voxel * intrinsics.fx / depth)), 0)


def silhouette_iou(points: np.ndarray, radius_px: int, pose: Pose, intrinsics: Intrinsics, mask: np.ndarray) -> float:
    """IoU of ``mask`` with the splatted projection of hull points seen from ``pose``."""
    rendered = splat(points, radius_px, pose, intrinsics, mask.shape)
    union = np.count_nonzero(rendered | mask)
    return np.count_nonzero(rendered & mask) / union if union else 0.0


def angle_from_silhouette(
    model: Turntable,
    lo: float,
    hi: float,
    hull_points: np.ndarray,
    voxel: float,
    intrinsics: Intrinsics,
    mask: np.ndarray,
) -> tuple[float, float]:
    """The angle in [lo, hi] whose view of the hull best matches ``mask``, and its IoU.

    A grid search at 1/4 degree, then at 1/64 degree around the best: the IoU is
    not smooth enough in the angle for a gradient method."""
    splat = splat_radius(voxel, intrinsics, np.linalg.norm(model.c_fixed - hull_points.mean(axis=0)))

    def best(candidates: np.ndarray) -> tuple[float, float]:
        scores = [silhouette_iou(hull_points, splat, model.pose(a), intrinsics, mask) for a in candidates]
        i = int(np.argmax(scores))
        return float(candidates[i]), float(scores[i])

    coarse_step = np.radians(0.25)
    angle, _ = best(np.arange(lo, hi + coarse_step / 2, coarse_step))
    fine = np.radians(1 / 64)
    return best(np.clip(np.arange(angle - coarse_step, angle + coarse_step + fine / 2, fine), lo, hi))
