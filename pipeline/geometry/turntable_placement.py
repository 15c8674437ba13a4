"""Poses of a turntable or ring capture: the circular motion solved from the photos'
feature matches (pipeline.geometry.circular_motion), then the photos the features
could not place put on the circle by their board pose, by even steps (a timed
turntable, when asked for) or by their silhouette (epipolar tangency with placed
photos); a photo none of these places reliably is left out with the reason.
Two photos are never put at one angle by anything but their features."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np

from pipeline import logger
from pipeline.camera.model import Intrinsics, Pose
from pipeline.camera.self_calibration import SelfCalibrationSettings
from pipeline.core.config import Range
from pipeline.core.errors import PipelineError
from pipeline.geometry import circular_motion, silhouette_tangency
from pipeline.geometry.circular_motion import CircularMotion, CircularSettings
from pipeline.geometry.turntable import Turntable
from pipeline.geometry.world_frame import robust_similarity


@dataclass(frozen=True)
class RigSettings:
    """How a turntable's or ring's photos are placed on their circle (sfm's section)."""

    max_angle_std_deg: Annotated[float, Range(0.0, None, exclusive_lo=True)] = 0.5
    """Turntable or ring: a photo whose angle its features leave more uncertain than this
    (one standard deviation, degrees) is placed by other means or left out."""
    turntable_steps: Literal["free", "even"] = "free"
    """Turntable: free, any angle per photo; even, the table turned by equal steps (a
    timed table): a prior holds the steps equal (even_step_std_deg), and photos without
    features are put at their step."""
    even_step_std_deg: Annotated[float, Range(0.0, None, exclusive_lo=True)] = 0.2
    """How far a step may differ from the others when turntable_steps is even."""
    max_silhouette_error_px: Annotated[float, Range(0.0, None, exclusive_lo=True)] = 1.5
    """Turntable or ring: a photo placed by its silhouette needs its outline's epipolar
    tangents within this of the placed photos' (RMS, pixels)."""
    silhouette_ambiguity: Annotated[float, Range(1.0, None)] = 2.0
    """... and every angle more than 5 degrees away must fit this many times worse."""


@dataclass(frozen=True)
class PlacementSettings:
    """How photos are placed on the circle (the sfm stage's settings)."""

    circular: CircularSettings
    """The circular-motion solver's settings."""
    in_file_order: bool
    """The photos are named in the order the table turned (a turntable): a photo placed
    by its silhouette is searched for between its placed neighbours."""
    max_silhouette_error_px: float
    """A silhouette placement needs its outline's tangents within this of its partners' (RMS)."""
    silhouette_ambiguity: float
    """... and every angle more than 5 degrees away must do this many times worse."""
    max_partners: int = 16
    """Placed photos a silhouette is compared with, spread round the circle."""

    @classmethod
    def of(
        cls,
        rig: RigSettings,
        calibration: SelfCalibrationSettings,
        turntable: bool,
        min_observations: int,
        refine_focal: bool,
    ) -> "PlacementSettings":
        """The settings for a turntable (photos in turning order) or a ring."""
        circular = CircularSettings(
            min_observations=min_observations,
            max_angle_std_deg=rig.max_angle_std_deg,
            refine_focal=refine_focal,
            self_calibrate=refine_focal and calibration.self_calibrate,
            max_calibration_std_px=calibration.max_calibration_std_px,
            min_frame_coverage=calibration.min_frame_coverage,
            in_file_order=turntable,
            even_steps_deg=rig.even_step_std_deg if turntable and rig.turntable_steps == "even" else 0.0,
        )
        return cls(circular, turntable, rig.max_silhouette_error_px, rig.silhouette_ambiguity)


def circular_poses(
    settings: PlacementSettings,
    order: list[str],
    intrinsics: dict[str, Intrinsics],
    masks: dict[str, Path],
    keypoints: dict[str, np.ndarray],
    matches: dict[tuple[str, str], dict[int, int]],
    board_poses: dict[str, Pose],
) -> tuple[Turntable, dict[str, Pose], CircularMotion, dict]:
    """The circle in the frame of the photo at angle 0, a pose for every photo that
    could be placed, the solver's solution, and the report (sfm.json's "circular")."""
    if len({json.dumps(k.to_json(), sort_keys=True) for k in intrinsics.values()}) > 1:
        raise PipelineError(
            "a turntable or ring needs one camera setting, but the photos were taken with several (see "
            "calibration.json): shoot it with one camera, zoom and image size"
        )
    try:
        first = intrinsics[order[0]]
        solution = circular_motion.solve(settings.circular, order, first, keypoints, matches, board_poses)
    except ValueError as error:
        raise PipelineError(
            f"the photos' features do not determine the turning: {error}. Check the photos with "
            "`pipeline check`; give the table texture (a printed board or a patterned mat) or shoot more "
            "photos per turn"
        ) from error
    table = Turntable(solution.axis, solution.point, np.eye(3), np.zeros(3), dict(solution.angles))
    source = {name: "features" for name in solution.angles}
    unplaced = dict(solution.unplaced)
    details: dict[str, dict] = {}
    for name, angle in _by_board(table, solution, board_poses, unplaced).items():
        table.angles[name], source[name] = angle, "board"
    if settings.circular.even_steps_deg > 0:
        for name, angle in _by_even_steps(table, order, unplaced).items():
            table.angles[name], source[name] = angle, "even_steps"
    for name, found in _by_silhouette(settings, table, solution, order, masks, unplaced).items():
        table.angles[name], source[name], details[name] = found["angle"], "silhouette", found
    for name, reason in unplaced.items():
        logger.warning("%s cannot be placed on the circle and is left out: %s", name, reason)
    poses = {name: table.pose(table.angles[name]) for name in order if name in table.angles}
    report = {
        "pose_source": {kind: sorted(n for n in source if source[n] == kind) for kind in _SOURCES},
        "unplaced": unplaced,
        "reprojection_error_px_median": solution.reprojection_px,
        "points": len(solution.points),
        "observations": solution.observations,
        "angle_deg": {n: float(np.degrees(a)) for n, a in sorted(table.angles.items())},
        "angle_std_deg": solution.angle_std_deg,
        "silhouette": details,
        "self_calibration": solution.calibration,
    }
    return table, poses, solution, report


_SOURCES = ("features", "board", "even_steps", "silhouette")


def _by_board(
    table: Turntable, solution: CircularMotion, board_poses: dict[str, Pose], unplaced: dict[str, str]
) -> dict[str, float]:
    """Angles of unplaced photos from their board pose (the board turns with the
    specimen), once three placed photos tie the board's frame to the solution's."""
    common = [n for n in board_poses if n in solution.angles]
    candidates = [n for n in unplaced if n in board_poses]
    if len(common) < 3 or not candidates:
        return {}
    to_board, _ = robust_similarity(
        {n: table.pose(solution.angles[n]).center for n in common}, {n: board_poses[n].center for n in common}
    )
    placed = {}
    for name in candidates:
        board = board_poses[name]
        # The board pose in the solution's frame: the inverse similarity.
        R = board.R @ to_board.R
        centre = to_board.R.T @ (board.center - to_board.t) / to_board.scale
        pose = Pose(R, -R @ centre)
        angle = table.angle_of(pose)
        rotation, offset = table.residuals_at(pose, angle)
        if rotation <= 2.0 and offset <= 0.05:
            placed[name] = angle
            del unplaced[name]
            logger.info("%s placed on the circle by its board pose at %.2f degrees", name, np.degrees(angle))
    return placed


def _by_even_steps(table: Turntable, order: list[str], unplaced: dict[str, str]) -> dict[str, float]:
    """Angles of unplaced photos between placed ones, in file order, at the mean step."""
    placed = [i for i, n in enumerate(order) if n in table.angles]
    angles = np.unwrap([table.angles[order[i]] for i in placed])
    step = (angles[-1] - angles[0]) / (placed[-1] - placed[0])
    found = {}
    for name in list(unplaced):
        i = order.index(name)
        before = [k for k in placed if k < i]
        if before:
            found[name] = table.angles[order[before[-1]]] + (i - before[-1]) * step
            del unplaced[name]
            logger.info("%s placed on the circle by even steps at %.2f degrees", name, np.degrees(found[name]))
    return found


def _by_silhouette(
    settings: PlacementSettings,
    table: Turntable,
    solution: CircularMotion,
    order: list[str],
    masks: dict[str, Path],
    unplaced: dict[str, str],
) -> dict[str, dict]:
    """Angles of unplaced photos from the epipolar tangency of their outlines with
    those of photos placed by features, kept only when reliable and not stacked."""
    if not unplaced:
        return {}
    K = solution.intrinsics
    model = circular_motion.Model(table.axis)
    g = np.array([0, 0, 0, K.fx, K.cx, K.cy, K.dist[0]], float)

    def normalised_outline(name: str) -> np.ndarray | None:
        hull = silhouette_tangency.outline(cv2.imread(str(masks[name]), cv2.IMREAD_GRAYSCALE) > 127)
        return None if hull is None else model.undistorted_rays(g, hull)

    def pose_at(angle: float) -> tuple[np.ndarray, np.ndarray]:
        pose = table.pose(angle)
        return pose.R, pose.t

    feature_placed = sorted(solution.angles, key=solution.angles.get)
    spread = feature_placed[:: max(1, len(feature_placed) // settings.max_partners)]
    partners = [(hull, pose_at(table.angles[n])) for n in spread if (hull := normalised_outline(n)) is not None]
    monotonic = settings.in_file_order and _monotonic(table, order)
    steps = np.abs(np.diff(np.unwrap([table.angles[n] for n in order if n in table.angles])))
    typical_step = float(np.median(steps)) if len(steps) else np.radians(5)
    found: dict[str, dict] = {}
    for name in list(unplaced):
        hull = normalised_outline(name)
        if hull is None:
            unplaced[name] += "; its mask is empty"
            continue
        low, high = _bracket(table, order, name) if monotonic else (-np.pi, np.pi)
        margin = min(0.25 * typical_step, 0.25 * (high - low))
        candidates = np.arange(low + margin, high - margin, np.radians(0.25))
        placement = silhouette_tangency.place(hull, pose_at, partners, candidates, K.fx) if len(candidates) else None
        reason = _unreliable(settings, placement, table, found, typical_step)
        if reason:
            unplaced[name] += f"; silhouette: {reason}"
            continue
        found[name] = {
            "angle": placement.angle,
            "angle_deg": float(np.degrees(placement.angle)),
            "error_px": placement.error_px,
            "runner_up_px": placement.runner_up_px,
            "partners": placement.partners,
        }
        del unplaced[name]
        logger.info(
            "%s placed on the circle by its silhouette at %.2f degrees (tangency error %.2f px, next best %.2f px)",
            name,
            found[name]["angle_deg"],
            placement.error_px,
            placement.runner_up_px,
        )
    return found


def _unreliable(settings: PlacementSettings, placement, table: Turntable, found: dict, typical_step: float) -> str:
    """Why a silhouette placement is not trusted ('' when it is)."""
    if placement is None:
        return "no placed photo sees it from a constraining angle"
    if placement.error_px > settings.max_silhouette_error_px:
        return (
            f"its outline's tangents miss those of the placed photos by {placement.error_px:.2f} px "
            f"(> sfm.max_silhouette_error_px = {settings.max_silhouette_error_px})"
        )
    if placement.runner_up_px < settings.silhouette_ambiguity * placement.error_px:
        return (
            f"ambiguous: an angle more than 5 degrees away fits almost as well ({placement.runner_up_px:.2f} px "
            f"against {placement.error_px:.2f} px)"
        )
    taken = [a for a in list(table.angles.values()) + [f["angle"] for f in found.values()]]
    nearest = min((abs(np.angle(np.exp(1j * (placement.angle - a)))) for a in taken), default=np.inf)
    if nearest < 0.2 * typical_step:
        return f"its angle is {np.degrees(nearest):.2f} degrees from a placed photo's: photos are never stacked"
    return ""


def _monotonic(table: Turntable, order: list[str]) -> bool:
    """Whether the placed photos' angles increase in file order (within one turn)."""
    angles = np.unwrap([table.angles[n] for n in order if n in table.angles])
    return bool(np.all(np.diff(angles) > 0) and angles[-1] - angles[0] < 2 * np.pi)


def _bracket(table: Turntable, order: list[str], name: str) -> tuple[float, float]:
    """Angles between which an unplaced photo must lie: those of the nearest placed
    photos before and after it in file order (wrapping round once)."""
    placed = [n for n in order if n in table.angles]
    angles = dict(zip(placed, np.unwrap([table.angles[n] for n in placed])))
    index = order.index(name)
    before = [n for n in order[:index] if n in angles]
    after = [n for n in order[index + 1 :] if n in angles]
    low = angles[before[-1]] if before else angles[placed[-1]] - 2 * np.pi
    high = angles[after[0]] if after else angles[placed[0]] + 2 * np.pi
    return float(low), float(high)
