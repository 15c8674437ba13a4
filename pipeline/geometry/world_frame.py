"""The world frame of a reconstruction: from the calibration board (metric), else
from a turntable's axis, a ground plane or the cameras alone (scale normalised),
and the checks that tie SfM's poses to the board's."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline import logger
from pipeline.camera.model import Pose, Similarity, rotation_angle_deg, similarity_umeyama
from pipeline.core.errors import PipelineError
from pipeline.geometry import turntable
from pipeline.geometry.visual_hull import convergence_point


def board_frame(**details) -> dict:
    """The description of the board's frame (cameras.json's ``frame``), with ``details``."""
    return {
        "source": "board",
        "metric": True,
        "units": "metres",
        "up": "+z, normal to the board",
        "ground_plane": [0.0, 0.0, 1.0, 0.0],
        **details,
    }


def robust_similarity(source: dict[str, np.ndarray], target: dict[str, np.ndarray]) -> tuple[Similarity, dict]:
    """Similarity taking SfM centres to board centres; photos whose residual exceeds
    three times the median (a misdetected board) are dropped once and it is refitted."""
    names = sorted(set(source) & set(target))
    for _ in range(2):
        s, R, t = similarity_umeyama(np.array([source[n] for n in names]), np.array([target[n] for n in names]))
        similarity = Similarity(s, R, t)
        residuals = {n: float(np.linalg.norm(similarity.points(source[n][None])[0] - target[n])) for n in names}
        limit = max(3 * np.median(list(residuals.values())), 1e-4)
        kept = [n for n in names if residuals[n] <= limit]
        if len(kept) == len(names) or len(kept) < 3:
            break
        names = kept
    return similarity, {
        "photos": len(names),
        "centre_residual_mm_median": 1000 * float(np.median([residuals[n] for n in names])),
    }


def ground_plane(points: np.ndarray, centres: np.ndarray, looked_at: np.ndarray, scale: float, seed: int = 0):
    """The plane the scene stands on, as (unit normal towards the cameras, offset)
    with normal . x + offset = 0, or None.

    Its normal is that of the dominant plane of the sparse points (RANSAC; the
    cameras must be on one side of it). Its level is where the points near the
    specimen bottom out (their 1st percentile of height): a textured specimen on a
    plain table gives its top face more points than the table gets (a cube: most
    of 23k points on its faces, few on the white table), and the top face is
    parallel to the table."""
    if len(points) < 50:
        return None
    rng = np.random.default_rng(seed)
    threshold = 0.005 * scale
    best, best_count = None, 0
    for _ in range(500):
        sample = points[rng.choice(len(points), 3, replace=False)]
        normal = np.cross(sample[1] - sample[0], sample[2] - sample[0])
        if np.linalg.norm(normal) < 1e-12:
            continue
        normal /= np.linalg.norm(normal)
        count = int(np.count_nonzero(np.abs((points - sample[0]) @ normal) < threshold))
        if count > best_count:
            best, best_count = (normal, -normal @ sample[0]), count
    if best is None or best_count < 0.25 * len(points):
        return None
    normal, offset = best
    inliers = points[np.abs(points @ normal + offset) < threshold]
    centroid = inliers.mean(axis=0)
    normal = np.linalg.svd(inliers - centroid)[2][2]
    side = np.sign(centres @ normal - normal @ centroid)
    if abs(side.sum()) < 0.9 * len(side):
        return None  # cameras on both sides: not a table
    normal = normal * np.sign(side.sum())
    # Near the specimen only: a floor seen past the table's edge is lower still.
    near = points[np.linalg.norm(points - looked_at, axis=1) < 0.75 * scale]
    heights = (near if len(near) >= 50 else points) @ normal - normal @ centroid
    return normal, float(-normal @ centroid - min(np.percentile(heights, 1), 0.0))


def frame_rotation(up: np.ndarray, forward_hint: np.ndarray) -> np.ndarray:
    """Rotation taking ``up`` to +z, with ``forward_hint`` (projected) to +x."""
    z = up / np.linalg.norm(up)
    x = forward_hint - z * (forward_hint @ z)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [1.0, 0, 0]) if abs(z[0]) < 0.9 else np.cross(z, [0, 1.0, 0])
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def level_frame(origin: np.ndarray, up: np.ndarray, poses: dict[str, Pose]) -> Similarity:
    """Up to +z, origin to 0, median camera distance to 1."""
    centres = np.array([p.center for p in poses.values()])
    R = frame_rotation(up, centres[0] - origin)
    scale = 1.0 / float(np.median(np.linalg.norm(centres - origin, axis=1)))
    return Similarity(scale, R, -scale * R @ origin)


def frame_from_board(
    source: str, max_disagreement: float, board_poses: dict[str, Pose], poses: dict[str, Pose]
) -> tuple[Similarity, dict] | None:
    """The similarity taking SfM's frame to the board's, with the frame's record, when
    ``source`` allows the board and SfM's camera centres agree with three or more board
    poses to ``max_disagreement`` of their distance."""
    common = set(board_poses) & set(poses)
    if source not in ("auto", "board") or len(common) < 3:
        return None
    frame, fit = robust_similarity({n: poses[n].center for n in common}, {n: board_poses[n].center for n in common})
    distance = float(np.median([np.linalg.norm(board_poses[n].center) for n in common]))
    if fit["centre_residual_mm_median"] / 1000 > max_disagreement * distance:
        # SfM and the board tell different stories: SfM joined photos wrongly
        # (a repetitive set) or the board moved against the specimen.
        logger.warning(
            "SfM's camera centres and the board's disagree by %.1f mm (median; %.0f mm from the board): "
            "not aligning SfM to the board",
            fit["centre_residual_mm_median"],
            1000 * distance,
        )
        return None
    logger.info(
        "world frame from the board in %d photos (centres agree to %.2f mm)",
        fit["photos"],
        fit["centre_residual_mm_median"],
    )
    return frame, board_frame(**fit)


@dataclass(frozen=True)
class BoardTie:
    """What tying SfM's poses to the board gave."""

    frame: Similarity | None
    """SfM's frame to the board's; None when the board gave no frame."""
    poses: dict[str, Pose]
    points: np.ndarray
    dropped: bool
    """SfM's poses were dropped for the board poses alone."""
    record: dict | None
    """The world frame's description (cameras.json's frame), when the board gave it."""
    replaced_by_board: list[str] | None = None
    """Photos whose SfM pose contradicted their board pose and took the latter."""


def tie_to_board(
    source: str,
    max_disagreement: float,
    board_poses: dict[str, Pose],
    poses: dict[str, Pose],
    points: np.ndarray,
    model_is_circle: bool,
) -> BoardTie:
    """The poses and points moved into the board's frame when they agree with the board
    (``frame_from_board``); when they do not but the board is seen in three photos, the
    board poses alone (the poses, not tied to them, are dropped; not for a circular
    motion, whose circle is the model); else unchanged."""
    found = frame_from_board(source, max_disagreement, board_poses, poses)
    if found is not None:
        frame, record = found
        poses = {n: frame.pose(p) for n, p in poses.items()}
        points = frame.points(points) if len(points) else points
        replaced = None if model_is_circle else replace_by_board(max_disagreement, poses, board_poses)
        return BoardTie(frame, poses, points, False, record, replaced)
    if len(board_poses) >= 3 and source in ("auto", "board") and not model_is_circle:
        logger.warning("SfM's %d photos could not be tied to the board: using the board poses alone", len(poses))
        return BoardTie(Similarity.identity(), {}, np.zeros((0, 3)), True, board_frame(photos=len(board_poses)))
    return BoardTie(None, poses, points, False, None)


def replace_by_board(max_disagreement: float, poses: dict[str, Pose], board_poses: dict[str, Pose]) -> list[str]:
    """Photos whose SfM pose, in the board frame, contradicts their own board pose
    (SfM placed them wrongly on a plain or symmetric specimen: a view from behind
    registered as one from the front) take the board pose. Returns their names."""
    replaced = []
    for name in sorted(set(poses) & set(board_poses)):
        sfm, board = poses[name], board_poses[name]
        rotation = rotation_angle_deg(sfm.R @ board.R.T)
        distance = np.linalg.norm(sfm.center - board.center) / np.linalg.norm(board.center)
        if rotation > 2.0 or distance > max_disagreement:
            logger.warning(
                "%s: SfM's pose is %.1f degrees and %.1f %% of the distance from its board pose; using the board pose",
                name,
                rotation,
                100 * distance,
            )
            poses[name] = board
            replaced.append(name)
    return replaced


def frame_without_board(
    requested: str, poses: dict[str, Pose], points: np.ndarray, table: turntable.Turntable | None
) -> tuple[Similarity, dict]:
    """The world frame when the board gives none: the turntable's axis (and the table
    plane), else the ground plane, else the cameras alone, as ``requested`` allows
    (sfm.frame); scaled to a median camera distance of 1. Returns it and its record."""
    if requested == "board":
        raise PipelineError(
            "sfm.frame = 'board' but the board was not found in three registered photos, or SfM "
            "disagrees with it (see the log): check [board], or set sfm.frame = 'auto'"
        )
    centres = np.array([p.center for p in poses.values()])
    spread = float(np.median(np.linalg.norm(centres - centres.mean(axis=0), axis=1)))
    looked_at = convergence_point(poses.values())
    plane = ground_plane(points, centres, looked_at, spread) if requested != "normalised" else None
    if table is not None and requested in ("auto", "turntable"):
        # Up is the axis' sense that the table plane's normal (towards the cameras) or,
        # without a plane, the photos' own up (their image's -y) points along: a camera
        # level with the table leaves the centres' height above the axis' point no sign.
        towards = plane[0] if plane is not None else -np.mean([p.R[1] for p in poses.values()], axis=0)
        up = table.axis if towards @ table.axis >= 0 else -table.axis
        if plane is not None and abs(plane[0] @ up) > np.cos(np.radians(10)):
            # The axis meets the table plane: the natural origin.
            origin = table.point - up * ((plane[0] @ table.point + plane[1]) / (plane[0] @ up))
        else:
            plane = None
            origin = table.point
        source = "turntable"
    elif plane is not None and requested in ("auto", "ground_plane"):
        up = plane[0]
        origin = looked_at - up * (up @ looked_at + plane[1])
        source = "ground_plane"
    elif requested in ("auto", "normalised"):
        up = -np.mean([p.R[1] for p in poses.values()], axis=0)
        origin = convergence_point(poses.values())
        plane = None
        source = "normalised"
    else:
        raise PipelineError(f"sfm.frame = '{requested}' could not be established: set sfm.frame = 'auto'")
    level = level_frame(origin, up, poses)
    # The origin was put on the table plane when there is one: it becomes z = 0.
    ground = [0.0, 0.0, 1.0, 0.0] if plane is not None else None
    logger.warning("no board seen: world frame from %s, scale normalised (not metric)", source.replace("_", " "))
    record = {
        "source": source,
        "metric": False,
        "units": "median camera distance = 1",
        "up": "+z",
        "ground_plane": ground,
    }
    return level, record
