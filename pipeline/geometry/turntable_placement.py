"""Poses of a turntable or ring capture: the circular motion solved from the photos'
feature matches (pipeline.geometry.circular_motion), then the photos the features
could not place put on the circle by their board pose, each group of photos the
features tie together but not to the ring by the group's silhouettes at once, the
rest by even steps (a timed turntable, when asked for) or by their own silhouette
(epipolar tangency with placed photos); a photo none of these places reliably is
left out with the reason. Two photos are never put at one angle by anything but
their features."""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
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
from pipeline.geometry.circular_motion import GROUP_OUTLINES, CircularMotion, CircularSettings
from pipeline.geometry.turntable import Turntable
from pipeline.geometry.world_frame import robust_similarity


@dataclass(frozen=True)
class RigSettings:
    """How a turntable's or ring's photos are placed on their circle (sfm's section)."""

    turntable_steps: Literal["free", "even"] = "free"
    """Turntable: free, any angle per photo; even, the table turned by equal steps (a
    timed table): a prior holds the steps equal (even_step_std_deg), and photos without
    features are put at their step."""
    even_step_std_deg: Annotated[float, Range(0.0, None, exclusive_lo=True)] = 0.2
    """How far a step may differ from the others when turntable_steps is even."""
    silhouette_noise_factor: Annotated[float, Range(1.0, None)] = 2.0
    """Turntable or ring: a photo placed by its silhouette needs its outline's epipolar
    tangents to meet the placed photos' within this many times as well as those of the
    photos the features placed meet each other at their own angles (the masks' and the
    model's own error, measured on every capture)."""
    silhouette_ambiguity: Annotated[float, Range(1.0, None)] = 2.0
    """... and every angle more than 5 degrees away must fit this many times worse (and,
    for an arc of the ring that matching left apart to be joined to it by its outlines,
    every other minimum of their error)."""
    silhouette_coherence: bool = True
    """Turntable or ring: fit the specimen's outlines with its features (the epipolar
    tangency of pairs of photos, each cue weighted by its own measured noise): features on
    a plain or glossy specimen are shading that stays with the light, and the outlines
    decide what they leave loose. Off: the features alone."""


@dataclass(frozen=True)
class PlacementSettings:
    """How photos are placed on the circle (the sfm stage's settings)."""

    circular: CircularSettings
    """The circular-motion solver's settings."""
    in_file_order: bool
    """The photos are named in the order the table turned (a turntable): a photo placed
    by its silhouette is searched for between its placed neighbours."""
    silhouette_noise_factor: float
    """A silhouette placement's tangency error may be this many times the feature-placed photos'."""
    silhouette_ambiguity: float
    """... and every angle more than 5 degrees away must do this many times worse."""
    silhouette_coherence: bool
    """The outlines are fitted with the features."""
    max_partners: int = 16
    """Placed photos a silhouette is compared with, spread round the circle."""

    @classmethod
    def of(
        cls,
        rig: RigSettings,
        calibration: SelfCalibrationSettings,
        turntable: bool,
        min_observations: int,
        weak_min_observations: int,
        refine_focal: bool,
    ) -> "PlacementSettings":
        """The settings for a turntable (photos in turning order) or a ring."""
        circular = CircularSettings(
            min_observations=min_observations,
            weak_min_observations=weak_min_observations,
            refine_focal=refine_focal,
            self_calibrate=refine_focal and calibration.self_calibrate,
            max_calibration_std_px=calibration.max_calibration_std_px,
            min_frame_coverage=calibration.min_frame_coverage,
            even_steps_deg=rig.even_step_std_deg if turntable and rig.turntable_steps == "even" else 0.0,
            silhouette_ambiguity=rig.silhouette_ambiguity,
        )
        return cls(circular, turntable, rig.silhouette_noise_factor, rig.silhouette_ambiguity, rig.silhouette_coherence)


def circular_poses(
    settings: PlacementSettings,
    order: list[str],
    intrinsics: dict[str, Intrinsics],
    masks: dict[str, Path],
    keypoints: dict[str, np.ndarray],
    matches: dict[tuple[str, str], dict[int, int]],
    board_poses: dict[str, Pose],
    unverified: dict[tuple[str, str], dict[int, int]] | None = None,
) -> tuple[Turntable, dict[str, Pose], CircularMotion, dict]:
    """The circle in the frame of the photo at angle 0, a pose for every photo that
    could be placed, the solver's solution (its points and tracks those of the ring and
    the groups placed, in the ring's frame), and the report (sfm.json's "circular").
    ``unverified``: matches of pairs two-view verification found no geometry for, which
    the solver tests against one turn each."""
    if len({json.dumps(k.to_json(), sort_keys=True) for k in intrinsics.values()}) > 1:
        raise PipelineError(
            "a turntable or ring needs one camera setting, but the photos were taken with several (see "
            "calibration.json): shoot it with one camera, zoom and image size"
        )
    hulls = _hulls(masks)
    try:
        first = intrinsics[order[0]]
        solution = circular_motion.solve(
            settings.circular,
            order,
            first,
            keypoints,
            matches,
            board_poses,
            outlines=hulls if settings.silhouette_coherence else None,
            unverified=unverified,
        )
    except ValueError as error:
        raise PipelineError(
            f"the photos' features do not determine the turning: {error}. Check the photos with "
            "`pipeline check`; give the table texture (a printed board or a patterned mat) or shoot more "
            "photos per turn"
        ) from error
    table = Turntable(solution.axis, solution.point, np.eye(3), np.zeros(3), dict(solution.angles))
    unplaced = dict(solution.unplaced)
    if any(solution.partners.get(n, 0) < 2 for n in solution.angles):
        for name, reason in _unchecked(settings, _Outlines(settings, table, solution, hulls), solution).items():
            del table.angles[name]
            unplaced[name] = reason
    source = {name: "features" for name in table.angles}
    details: dict[str, dict] = {}
    for name, angle in _by_board(table, solution, board_poses, unplaced).items():
        table.angles[name], source[name] = angle, "board"
    # Silhouettes are compared with the photos the features placed (and kept).
    outlines = _Outlines(settings, table, solution, hulls) if solution.groups or unplaced else None
    offsets, grouped = _groups_by_silhouette(settings, outlines, solution.groups, order, unplaced)
    for name, found in grouped.items():
        table.angles[name], source[name], details[name] = found["angle"], "group_silhouette", found
    points, tracks = circular_motion.place_group(solution, offsets)
    # Tracks of the photos placed; a point its placed photos see fewer than twice is dropped.
    tracks = [{n: k for n, k in track.items() if n in table.angles} for track in tracks]
    seen = np.array([len(track) >= 2 for track in tracks], bool)
    points, tracks = points[seen], [track for track, kept in zip(tracks, seen) if kept]
    solution = replace(solution, points=points, tracks=tracks, point_groups=np.zeros(len(points), int))
    if settings.circular.even_steps_deg > 0:
        for name, angle in _by_even_steps(table, order, unplaced).items():
            table.angles[name], source[name] = angle, "even_steps"
    for name, found in _by_silhouette(settings, outlines, order, unplaced).items():
        table.angles[name], source[name], details[name] = found["angle"], "silhouette", found
    for name, reason in unplaced.items():
        logger.warning("%s cannot be placed on the circle and is left out: %s", name, reason)
    placed = [name for name in order if name in table.angles]
    poses = {name: table.pose(table.angles[name]) for name in placed}
    report = {
        "pose_source": {kind: sorted(n for n in source if source[n] == kind) for kind in _SOURCES},
        "unplaced": unplaced,
        "reprojection_error_px_median": solution.reprojection_px,
        "points": len(solution.points),
        "observations": solution.observations,
        # Unwrapped in file order: a turntable's angles then grow as the table turned.
        "angle_deg": dict(zip(placed, np.degrees(np.unwrap([table.angles[n] for n in placed])).tolist())),
        "angle_std_deg": solution.angle_std_deg,
        "silhouette": details,
        "self_calibration": solution.calibration,
        "silhouette_coherence": solution.silhouette_coherence,
        "weak_pairs": solution.weak_pairs,
        "joined_groups": solution.joined_groups,
    }
    return table, poses, solution, report


_SOURCES = ("features", "board", "group_silhouette", "even_steps", "silhouette")


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


def _hulls(masks: dict[str, Path]) -> dict[str, np.ndarray]:
    """Each photo's outline (convex hull, pixels); photos with an empty mask have none."""
    hulls = {}
    for name, path in masks.items():
        hull = silhouette_tangency.outline(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 127)
        if hull is not None:
            hulls[name] = hull
    return hulls


class _Outlines:
    """The photos' outlines in normalised camera coordinates, the circle's poses, and the
    partners a silhouette is compared with: photos placed by features, spread round it."""

    def __init__(
        self, settings: PlacementSettings, table: Turntable, solution: CircularMotion, hulls: dict[str, np.ndarray]
    ):
        K = solution.intrinsics
        self.focal = K.fx
        self.table = table
        self.hulls = hulls
        self.model = circular_motion.Model(table.axis)
        self.g = np.array([0, 0, 0, K.fx, K.cx, K.cy, K.dist[0]], float)
        feature_placed = sorted((n for n in solution.angles if n in table.angles), key=table.angles.get)
        spread = feature_placed[:: max(1, len(feature_placed) // settings.max_partners)]
        self.partners = [(hull, self.pose_at(table.angles[n])) for n in spread if (hull := self.of(n)) is not None]
        steps = np.diff(np.sort(np.mod([table.angles[n] for n in feature_placed], 2 * np.pi)))
        self.typical_step = float(np.median(steps)) if len(steps) else np.radians(5)
        # The masks' own tangency error: the partners at the angles their features gave.
        own = [
            self.place([(hull, 0.0)], np.array([table.angles[n]])) for n in spread if (hull := self.of(n)) is not None
        ]
        errors = [placement.error_px for placement in own if placement is not None]
        self.noise_px = float(np.median(errors)) if errors else np.inf

    def of(self, name: str) -> np.ndarray | None:
        hull = self.hulls.get(name)
        return None if hull is None else self.model.undistorted_rays(self.g, hull)

    def pose_at(self, angle: float) -> tuple[np.ndarray, np.ndarray]:
        pose = self.table.pose(angle)
        return pose.R, pose.t

    def place(self, members: list[tuple[np.ndarray, float]], candidates: np.ndarray):
        if not len(candidates):
            return None
        return silhouette_tangency.place(members, self.pose_at, self.partners, candidates, self.focal)


def _unchecked(settings: PlacementSettings, outlines: _Outlines, solution: CircularMotion) -> dict[str, str]:
    """Photos of the ring that one pair of matches alone placed (a false pair can place a
    photo anywhere, and nothing else contradicts it) and whose silhouette disagrees with
    that angle as the placement of a silhouette would be refused; with the reason."""
    refused = {}
    for name in (n for n in solution.angles if solution.partners.get(n, 0) < 2):
        hull = outlines.of(name)
        angle = outlines.table.angles[name]
        placement = outlines.place([(hull, 0.0)], np.array([angle])) if hull is not None else None
        if placement is None or placement.error_px > settings.silhouette_noise_factor * outlines.noise_px:
            error = f"{placement.error_px:.2f} px" if placement is not None else "no constraint"
            refused[name] = (
                f"one pair of matches alone places it, and its silhouette disagrees there ({error} against the "
                f"{outlines.noise_px:.2f} px by which the photos placed by features miss each other)"
            )
            logger.info("%s: %s", name, refused[name])
    return refused


def _groups_by_silhouette(
    settings: PlacementSettings,
    outlines: _Outlines | None,
    groups: list[dict[str, float]],
    order: list[str],
    unplaced: dict[str, str],
) -> tuple[dict[int, float], dict[str, dict]]:
    """Angles of the photos of each group the features tie together but not to the ring:
    the group's offset from the epipolar tangency of its outlines (a spread of at most
    ``GROUP_OUTLINES`` of them) with those of the ring's photos (on a turntable between
    the placed photos around its first in file order, where file order holds there),
    kept only when reliable and no member is stacked; a group not placed leaves its
    photos to be placed alone.
    Returns the offsets (group number, from 1, -> its first photo's angle) and the angles."""
    offsets: dict[int, float] = {}
    found: dict[str, dict] = {}
    for number, group in enumerate(groups, start=1):
        names = sorted(group, key=group.get)
        spread = names[:: max(1, len(names) // GROUP_OUTLINES)]
        members = [(hull, group[n]) for n in spread if (hull := outlines.of(n)) is not None]
        first = min(group, key=order.index)
        bracket = _bracket(outlines.table, order, first, outlines.typical_step) if settings.in_file_order else None
        low, high = bracket or (-np.pi, np.pi)
        candidates = np.arange(low, high, np.radians(0.5)) - group[first]
        placement = outlines.place(members, candidates) if members else None
        taken = list(outlines.table.angles.values()) + [f["angle"] for f in found.values()]
        reason = _unreliable(settings, placement, taken, outlines, list(group.values()))
        if reason:
            for name in names:
                unplaced[name] = (
                    f"in a group of {len(names)} photos not matched into the ring; the group's silhouettes: {reason}"
                )
            continue
        offsets[number] = placement.angle
        for name in names:
            angle = placement.angle + group[name]
            found[name] = {
                "angle": angle,
                "angle_deg": float(np.degrees(angle)),
                "error_px": placement.error_px,
                "runner_up_px": placement.runner_up_px,
                "partners": placement.partners,
                "group": len(names),
            }
        logger.info(
            "a group of %d photos not matched into the ring placed by their silhouettes (tangency error %.2f px, "
            "next best %.2f px): %s",
            len(names),
            placement.error_px,
            placement.runner_up_px,
            ", ".join(names),
        )
    return offsets, found


def _by_silhouette(
    settings: PlacementSettings, outlines: _Outlines | None, order: list[str], unplaced: dict[str, str]
) -> dict[str, dict]:
    """Angles of unplaced photos from the epipolar tangency of their outlines with
    those of photos placed by features, kept only when reliable and not stacked."""
    if not unplaced:
        return {}
    table = outlines.table
    found: dict[str, dict] = {}
    for name in list(unplaced):
        hull = outlines.of(name)
        if hull is None:
            unplaced[name] += "; its mask is empty"
            continue
        bracket = _bracket(table, order, name, outlines.typical_step) if settings.in_file_order else None
        low, high = bracket or (-np.pi, np.pi)
        # Inside a bracket, not at its ends: photos are never stacked on their neighbours.
        margin = min(0.25 * outlines.typical_step, 0.25 * (high - low)) if bracket else 0.0
        placement = outlines.place([(hull, 0.0)], np.arange(low + margin, high - margin, np.radians(0.25)))
        taken = list(table.angles.values()) + [f["angle"] for f in found.values()]
        reason = _unreliable(settings, placement, taken, outlines, [0.0])
        if reason:
            unplaced[name] += f"; its own silhouette: {reason}"
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


def _unreliable(
    settings: PlacementSettings, placement, taken: list[float], outlines: _Outlines, offsets: list[float]
) -> str:
    """Why a silhouette placement is not trusted ('' when it is): ``taken`` are the angles
    already placed, ``offsets`` the placed photos' angles relative to the placement's."""
    noise_px, typical_step = outlines.noise_px, outlines.typical_step
    if placement is None:
        return "no placed photo sees it from a constraining angle"
    limit = settings.silhouette_noise_factor * noise_px
    if placement.error_px > limit:
        return (
            f"its outline's tangents miss those of the placed photos by {placement.error_px:.2f} px, more than "
            f"sfm.silhouette_noise_factor = {settings.silhouette_noise_factor} times the {noise_px:.2f} px by which "
            "the photos placed by features miss each other"
        )
    if placement.runner_up_px < settings.silhouette_ambiguity * placement.error_px:
        return (
            f"ambiguous: an angle more than 5 degrees away fits almost as well ({placement.runner_up_px:.2f} px "
            f"against {placement.error_px:.2f} px)"
        )
    nearest = min(
        (abs(np.angle(np.exp(1j * (placement.angle + offset - a)))) for a in taken for offset in offsets),
        default=np.inf,
    )
    if nearest < 0.2 * typical_step:
        return f"its angle is {np.degrees(nearest):.2f} degrees from a placed photo's: photos are never stacked"
    return ""


def _bracket(table: Turntable, order: list[str], name: str, typical_step: float) -> tuple[float, float] | None:
    """Angles between which an unplaced photo of a turntable lies when file order holds
    there: from the nearest placed photo before it in file order to the nearest after
    (wrapping round once), when the turn between those two is forward and no more than
    three typical steps for each photo in between; None where file order does not hold
    (a restart, a second turn, photos out of order), so the whole circle is searched."""
    placed = [n for n in order if n in table.angles]
    index = order.index(name)
    before = [n for n in order[:index] if n in table.angles] or placed[-1:]
    after = [n for n in order[index + 1 :] if n in table.angles] or placed[:1]
    if not before or not after:
        return None
    low = table.angles[before[-1]]
    gap = float(np.mod(table.angles[after[0]] - low, 2 * np.pi))
    between = (order.index(after[0]) - order.index(before[-1])) % len(order)
    if gap == 0 or gap > 3 * typical_step * between:
        return None
    return float(low), float(low + gap)
