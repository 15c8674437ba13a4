"""A synthetic turntable without rendering: a still camera, an object of random points
(a box of features on a plate of features) turned by uneven steps, the keypoints each
photo sees (with noise and a radial lens) and the matches between ring neighbours, a
tenth of them wrong. The exact poses and angles come with it, so the circular-motion
solver can be checked against them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.camera.model import Intrinsics, Pose

K = Intrinsics(128, 96, 120.0, 120.0, 64.8, 46.6, [-0.08, 0.0, 0.0, 0.0, 0.0])
"""The lens: a principal point off centre, barrel distortion."""
CAMERA = Pose.look_at([0.4 * np.cos(np.radians(25)), 0.0, 0.4 * np.sin(np.radians(25)) + 0.04], [0.0, 0.0, 0.04])


@dataclass
class TurntableViews:
    intrinsics: Intrinsics
    names: list[str]
    angles: np.ndarray
    """True angles, radians."""
    poses: dict[str, Pose]
    keypoints: dict[str, np.ndarray]
    matches: dict[tuple[str, str], dict[int, int]]
    visible: dict[str, dict[int, int]]
    """Per photo: point index -> keypoint index."""


def pose_at(angle: float) -> Pose:
    """The still camera's pose when the table has turned by ``angle`` about world z."""
    return Pose(CAMERA.R @ Rotation.from_rotvec([0, 0, angle]).as_matrix(), CAMERA.t)


def scaled(factor: float) -> Intrinsics:
    """The lens for photos ``factor`` times the size (256 px wide at 2)."""
    return Intrinsics(
        round(K.width * factor), round(K.height * factor), K.fx * factor, K.fy * factor,
        (K.cx + 0.5) * factor - 0.5, (K.cy + 0.5) * factor - 0.5, K.dist,
    )  # fmt: skip


def turntable_views(
    views: int = 20,
    points: int = 600,
    neighbours: int = 3,
    jitter: float = 0.3,
    seed: int = 0,
    alternation: float = 1.0,
    noise_px: float = 0.3,
    intrinsics: Intrinsics = K,
) -> TurntableViews:
    """``jitter``: the steps' unevenness, a fraction of the mean step (0: a timed table);
    ``alternation``: every second step that many times the one before (a table turned by
    hand in short and long steps); ``noise_px``: the keypoints' noise."""
    rng = np.random.default_rng(seed)
    steps = 1 + jitter * rng.uniform(-1, 1, views)
    steps[1::2] *= alternation
    angles = np.concatenate([[0.0], np.cumsum(steps[:-1])]) * 2 * np.pi / steps.sum()
    half = points // 2
    xyz = np.vstack(
        [
            rng.uniform([-0.04, -0.03, 0.0], [0.04, 0.03, 0.09], (half, 3)),
            np.column_stack([rng.uniform(-0.18, 0.18, (points - half, 2)), np.zeros(points - half)]),
        ]
    )
    normals = np.vstack([np.column_stack([xyz[:half, :2], np.zeros(half)]), np.tile([0, 0, 1.0], (points - half, 1))])
    names = [f"view_{i:03d}.jpg" for i in range(views)]
    keypoints, visible, poses = {}, {}, {}
    for name, angle in zip(names, angles):
        pose = poses[name] = pose_at(angle)
        camera = xyz @ pose.R.T + pose.t
        x, y = camera[:, 0] / camera[:, 2], camera[:, 1] / camera[:, 2]
        lens = intrinsics
        radial = 1 + lens.dist[0] * (x * x + y * y)
        pixels = np.column_stack([lens.fx * x * radial + lens.cx, lens.fy * y * radial + lens.cy])
        pixels += rng.normal(0, noise_px, (points, 2))
        facing = np.einsum("ij,ij->i", normals, pose.center - xyz) > 0
        inside = (pixels[:, 0] > 0) & (pixels[:, 0] < lens.width - 1) & (pixels[:, 1] > 0)
        inside &= pixels[:, 1] < lens.height - 1
        seen = np.flatnonzero(facing & inside & (rng.uniform(size=points) < 0.6))
        keypoints[name] = pixels[seen]
        visible[name] = {int(p): k for k, p in enumerate(seen)}
    matches: dict[tuple[str, str], dict[int, int]] = {}
    for i in range(views):
        for k in range(1, neighbours + 1):
            a, b = names[i], names[(i + k) % views]
            pairs = {visible[a][p]: visible[b][p] for p in sorted(set(visible[a]) & set(visible[b]))}
            for key in list(pairs)[: len(pairs) // 10]:
                pairs[key] = int(rng.integers(len(keypoints[b])))
            matches[a, b] = pairs
            matches[b, a] = {v: u for u, v in pairs.items()}
    return TurntableViews(intrinsics, names, angles, poses, keypoints, matches, visible)


def blob_mask(pose: Pose, spheres: list[tuple[tuple[float, float, float], float]], lens: Intrinsics = K) -> np.ndarray:
    """The exact silhouette, in the distorted photo, of a union of spheres ((centre,
    radius) in the table's frame) seen from ``pose``."""
    u, v = np.meshgrid(np.arange(lens.width, dtype=float), np.arange(lens.height, dtype=float))
    distorted = np.stack([(u - lens.cx) / lens.fx, (v - lens.cy) / lens.fy], axis=-1)
    undistorted = distorted.copy()
    for _ in range(10):
        undistorted = distorted / (1 + lens.dist[0] * np.sum(undistorted**2, axis=-1, keepdims=True))
    rays = np.concatenate([undistorted, np.ones(u.shape + (1,))], axis=-1) @ pose.R
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    mask = np.zeros(u.shape, bool)
    for centre, radius in spheres:
        offset = np.asarray(centre) - pose.center
        along = rays @ offset
        mask |= (along > 0) & (np.sum(offset**2) - along**2 < radius**2)
    return mask


SPECIMEN = [((0.0, 0.0, 0.03), 0.03), ((0.025, 0.01, 0.06), 0.018), ((-0.02, -0.015, 0.015), 0.015)]
"""A lumpy specimen of spheres ((centre, radius) in the table's frame, metres): its
outline changes shape as the table turns."""


def shaded_turntable_views(
    views: int = 16, shading: float = 0.2, shading_rate: float = 0.5, seed: int = 0, intrinsics: Intrinsics = K
) -> TurntableViews:
    """A plain specimen on a plain table: the only features are on the specimen
    (``SPECIMEN``'s surface), and a fraction ``shading`` of them are shading and
    highlights, which stay with the light and slide over the surface, turning at
    ``shading_rate`` times the table's turn. Steps a tenth uneven, keypoints 0.3 px off,
    matches between the three next photos round the ring. ``blob_mask(pose, SPECIMEN)``
    gives the outlines."""
    rng = np.random.default_rng(seed)
    steps = 1 + 0.1 * rng.uniform(-1, 1, views)
    angles = np.concatenate([[0.0], np.cumsum(steps[:-1])]) * 2 * np.pi / steps.sum()
    surface, normals = [], []
    for centre, radius in SPECIMEN:
        directions = rng.normal(size=(300, 3))
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        surface.append(np.asarray(centre) + radius * directions)
        normals.append(directions)
    xyz, normals = np.vstack(surface), np.vstack(normals)
    rate = np.where(rng.uniform(size=len(xyz)) < shading, shading_rate, 1.0)
    names = [f"view_{i:03d}.jpg" for i in range(views)]
    keypoints, visible, poses = {}, {}, {}
    for name, angle in zip(names, angles):
        poses[name] = pose_at(angle)
        turns = Rotation.from_rotvec(np.outer(rate * angle, [0.0, 0.0, 1.0])).as_matrix()
        world, facing_normals = np.einsum("nij,nj->ni", turns, xyz), np.einsum("nij,nj->ni", turns, normals)
        camera = world @ CAMERA.R.T + CAMERA.t
        x, y = camera[:, 0] / camera[:, 2], camera[:, 1] / camera[:, 2]
        radial = 1 + intrinsics.dist[0] * (x * x + y * y)
        pixels = np.column_stack(
            [intrinsics.fx * x * radial + intrinsics.cx, intrinsics.fy * y * radial + intrinsics.cy]
        )
        pixels += rng.normal(0, 0.3, pixels.shape)
        to_camera = CAMERA.center - world
        facing = np.einsum("ij,ij->i", facing_normals, to_camera) > 0.2 * np.linalg.norm(to_camera, axis=1)
        seen = np.flatnonzero(facing & (rng.uniform(size=len(xyz)) < 0.7))
        keypoints[name] = pixels[seen]
        visible[name] = {int(p): k for k, p in enumerate(seen)}
    matches: dict[tuple[str, str], dict[int, int]] = {}
    for i in range(views):
        for k in (1, 2, 3):
            a, b = names[i], names[(i + k) % views]
            matches[a, b] = {visible[a][p]: visible[b][p] for p in sorted(set(visible[a]) & set(visible[b]))}
            matches[b, a] = {v: u for u, v in matches[a, b].items()}
    return TurntableViews(intrinsics, names, angles, poses, keypoints, matches, visible)


def two_set_views(
    views: tuple[int, int] = (16, 14),
    elevation_change_deg: float = 6.0,
    distance_ratio: float = 1.1,
    restart_deg: float = 10.0,
    turned_over: bool = False,
    patterned_table: bool = False,
    across: int = 2,
    points: int = 600,
    seed: int = 0,
) -> TurntableViews:
    """A turntable capture shot in two sets: the first as ``turntable_views`` (file names
    view_000...), the second (set_000...) from a camera moved up by
    ``elevation_change_deg`` and ``distance_ratio`` times as far, starting
    ``restart_deg`` back from where the first began; ``turned_over``: the specimen
    turned upside down between the sets, on a plain plate, or with ``patterned_table``
    on the same plate of features, which turn with the table, not with the specimen
    (the matches of the plate then tie the sets where the specimen does not lie). Each
    photo of the second set is matched with its ``across`` photos of the first that
    share the most points (0: none), a tenth of those matches wrong. Poses are in the frame of the specimen as the first
    set stands it."""
    rng = np.random.default_rng(seed)
    xyz = rng.uniform([-0.04, -0.03, 0.0], [0.04, 0.03, 0.09], (points // 2, 3))
    if patterned_table or not turned_over:
        plate = np.column_stack([rng.uniform(-0.18, 0.18, (points - points // 2, 2)), np.zeros(points // 2)])
        xyz = np.vstack([xyz, plate])
    on_plate = np.arange(len(xyz)) >= points // 2
    outward = np.column_stack([xyz[:, :2], np.zeros(len(xyz))])
    normals = np.where((xyz[:, 2] == 0)[:, None], [0.0, 0.0, 1.0], outward)
    elevation = np.radians(25 + elevation_change_deg)
    distance = 0.4 * distance_ratio
    moved = Pose.look_at([distance * np.cos(elevation), 0.0, distance * np.sin(elevation) + 0.04], [0.0, 0.0, 0.04])
    # Turned over: upside down about the x axis, standing on its former top.
    flip = Rotation.from_rotvec([np.pi, 0, 0]).as_matrix() if turned_over else np.eye(3)
    lift = np.array([0.0, 0.0, 0.09]) if turned_over else np.zeros(3)
    names, angles, poses, keypoints, visible = [], [], {}, {}, {}
    for number, (count, camera, prefix, start) in enumerate(
        ((views[0], CAMERA, "view", 0.0), (views[1], moved, "set", -np.radians(restart_deg)))
    ):
        steps = 1 + 0.3 * rng.uniform(-1, 1, count)
        turns = start + np.concatenate([[0.0], np.cumsum(steps[:-1])]) * 2 * np.pi / steps.sum()
        for i, angle in enumerate(turns):
            name = f"{prefix}_{i:03d}.jpg"
            turn = Rotation.from_rotvec([0, 0, angle]).as_matrix()
            placed_R, placed_t = (flip, lift) if number else (np.eye(3), np.zeros(3))
            R = camera.R @ turn @ placed_R
            pose = poses[name] = Pose(R, camera.R @ turn @ placed_t + camera.t)
            table = Pose(camera.R @ turn, camera.t)  # the plate's points turn with the table
            camera_points = np.where(on_plate[:, None], xyz @ table.R.T + table.t, xyz @ pose.R.T + pose.t)
            x, y = camera_points[:, 0] / camera_points[:, 2], camera_points[:, 1] / camera_points[:, 2]
            radial = 1 + K.dist[0] * (x * x + y * y)
            pixels = np.column_stack([K.fx * x * radial + K.cx, K.fy * y * radial + K.cy])
            pixels += rng.normal(0, 0.3, pixels.shape)
            seen_from = np.where(on_plate[:, None], table.center, pose.center)
            facing = np.einsum("ij,ij->i", normals, seen_from - xyz) > 0
            inside = (pixels[:, 0] > 0) & (pixels[:, 0] < K.width - 1) & (pixels[:, 1] > 0)
            inside &= pixels[:, 1] < K.height - 1
            seen = np.flatnonzero(facing & inside & (rng.uniform(size=len(xyz)) < 0.6))
            keypoints[name], visible[name] = pixels[seen], {int(p): k for k, p in enumerate(seen)}
            names.append(name)
            angles.append(angle)
    matches: dict[tuple[str, str], dict[int, int]] = {}

    def match(a: str, b: str, wrong: float) -> None:
        pairs = {visible[a][p]: visible[b][p] for p in sorted(set(visible[a]) & set(visible[b]))}
        for key in list(pairs)[: int(len(pairs) * wrong)]:
            pairs[key] = int(rng.integers(len(keypoints[b])))
        matches[a, b], matches[b, a] = pairs, {v: u for u, v in pairs.items()}

    first, second = names[: views[0]], names[views[0] :]
    for members in (first, second):
        for i in range(len(members)):
            for k in (1, 2, 3):
                match(members[i], members[(i + k) % len(members)], 0.1)
    for b in second:
        shared = sorted(first, key=lambda a: -len(set(visible[a]) & set(visible[b])))
        for a in shared[:across]:
            match(a, b, 0.1)
    return TurntableViews(K, names, np.array(angles), poses, keypoints, matches, visible)
