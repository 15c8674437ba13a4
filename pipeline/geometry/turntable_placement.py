"""Poses of a turntable or ring capture: the circular motion solved from the photos'
feature matches (pipeline.geometry.circular_motion); each other set of the capture
(a group of photos whose matches with the ring one circle does not explain: the
camera moved or the specimen was re-placed) solved alone and joined to the ring by
those matches, or left out with a warning naming its photos
(pipeline.geometry.turntable_sets), the joined sets adjusted together with the ring
(pipeline.geometry.sets_adjustment); then the photos the features could not place put
on the circle by their board pose, each group of photos the features tie together
but not to the ring (an arc matching left apart, no pair across) by the group's
silhouettes at once, the rest by even steps (a timed turntable, when asked for) or
by their own silhouette (epipolar tangency with placed photos); a photo none of
these places reliably is left out with the reason. Two photos are never put at one
angle by anything but their features. A photo that outlines alone placed is marked
uncertain, with a warning naming it: a near-symmetric specimen has several angles
its outline fits.

Every photo's record (report ``photos``): its set, what placed it (``placed_by``:
features, features across sets, board, even steps, outline), its angle uncertainty and
whether it is certain; ``summary`` says it in one line."""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np

from pipeline import logger
from pipeline.camera.model import Intrinsics, Pose
from pipeline.camera.self_calibration import SelfCalibrationSettings
from pipeline.core.config import Range
from pipeline.core.errors import PipelineError
from pipeline.geometry import circular_motion, sets_adjustment, silhouette_tangency, turntable_sets
from pipeline.geometry.circular_motion import GROUP_OUTLINES, CircularMotion, CircularSettings, matched_pairs
from pipeline.geometry.turntable import Turntable
from pipeline.geometry.world_frame import robust_similarity
from pipeline.imaging.segmentation import on_mask


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
    set_separation: Annotated[float, Range(2.0, None)] = 6.0
    """Turntable or ring: the photos are taken as several sets (the camera moved up or
    down, nearer or farther between turns) where, each posed freely on the circle's
    points, they fall into groups whose elevations (or distances from the axis) lie
    this many robust standard deviations apart; one set's photos scatter about one
    height, and the best split of such a scatter lies about three apart."""
    join_noise_factor: Annotated[float, Range(1.0, None)] = 4.0
    """Turntable or ring with several sets (the camera moved or the specimen re-placed
    between turns): an observation across two sets fits their join when it reprojects
    within this many times the larger median reprojection error of the two sets' own
    features (about 3.4 standard deviations of a Gaussian noise at 4)."""


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
    join_noise_factor: float = 4.0
    """An observation across two sets fits their join within this many times their features' noise."""
    set_separation: float = 6.0
    """Groups of free cameras this many robust standard deviations apart are sets."""
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
        return cls(
            circular,
            turntable,
            rig.silhouette_noise_factor,
            rig.silhouette_ambiguity,
            rig.silhouette_coherence,
            rig.join_noise_factor,
            rig.set_separation,
        )


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
    solution = _solve(settings, order, intrinsics[order[0]], keypoints, matches, board_poses, hulls, unverified)
    on_specimen = {name: on_mask(masks[name], keypoints[name]) for name in order if name in masks}
    other_sets = _other_sets(settings, order, solution, keypoints, matches, board_poses)
    # The first set solved alone; a photo its own circle poses freely at another
    # elevation belongs to another set (a few stood wrong on the one circle of all).
    for _ in range(MAX_SET_ROUNDS if other_sets else 0):
        apart = {n for found in other_sets for n in found}
        solution = _solve(
            settings,
            [n for n in order if n not in apart],
            intrinsics[order[0]],
            keypoints,
            {pair: m for pair, m in matches.items() if pair[0] not in apart and pair[1] not in apart},
            {n: p for n, p in board_poses.items() if n not in apart},
            hulls,
            {pair: m for pair, m in (unverified or {}).items() if pair[0] not in apart and pair[1] not in apart},
        )
        strays = turntable_sets.strays(
            turntable_sets.free_cameras(solution, keypoints, matches), settings.set_separation
        )
        if not strays:
            break
        logger.info(
            "circular motion: %d photo(s) of the first set stand at another elevation: %s",
            len(strays),
            ", ".join(strays),
        )
        other_sets = [
            [n for n in order if n in found]
            for found in turntable_sets.with_the_rest(
                other_sets, strays, {k: v for k, v in matches.items() if k[1] in apart}
            )
        ]
    table = Turntable(solution.axis, solution.point, np.eye(3), np.zeros(3), dict(solution.angles))
    unplaced = dict(solution.unplaced)
    if any(solution.partners.get(n, 0) < 2 for n in solution.angles):
        for name, reason in _unchecked(settings, _Outlines(settings, table, solution, hulls), solution).items():
            del table.angles[name]
            unplaced[name] = reason
    source = {name: "features" for name in table.angles}
    for group in solution.joined_groups:  # an arc whose offset its outlines gave
        for name in group["photos"] if group.get("joined") else ():
            if name in source:
                source[name] = "joined_by_outline"
    details: dict[str, dict] = {}
    sets = _join_sets(settings, order, solution, table, keypoints, matches, on_specimen, hulls, other_sets)
    solution, table, undetermined = _adjust_together(settings, solution, table, sets, keypoints, hulls)
    unplaced |= undetermined
    for name, pose in sets.poses.items():
        source[name] = "features_across_sets"
    for name, angle in _by_board(table, solution, board_poses, unplaced).items():
        table.angles[name], source[name] = angle, "board"
    # Silhouettes are compared with the photos the features placed (and kept).
    outlines = _Outlines(settings, table, solution, hulls) if solution.groups or unplaced else None
    arcs = {number: group for number, group in enumerate(solution.groups, start=1) if number not in sets.numbers}
    offsets, grouped = _groups_by_silhouette(settings, outlines, arcs, order, unplaced)
    for name, found in grouped.items():
        table.angles[name], source[name], details[name] = found["angle"], "group_silhouette", found
    points, tracks = circular_motion.place_group(solution, offsets)
    # Tracks of the photos placed; a point its placed photos see fewer than twice is dropped.
    tracks = [{n: k for n, k in track.items() if n in table.angles or n in sets.poses} for track in tracks]
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
    unplaced |= sets.left_out  # each set left out was warned about once, naming its photos
    poses = {name: table.pose(table.angles[name]) for name in order if name in table.angles} | sets.poses
    placed = [name for name in order if name in poses]
    angles = {name: table.angles[name] for name in placed if name in table.angles} | sets.angles
    photos = _photo_records(order, poses, source, solution.angle_std_deg, sets)
    summary = _summary(order, photos, sets.reports)
    logger.info("circular motion: %s", summary)
    outline_only = [name for name, record in photos.items() if record["placed_by"] == "outline"]
    if outline_only:
        logger.warning(
            "%d photo(s) placed by their outlines alone, uncertain (a near-symmetric specimen has several angles "
            "its outline fits; matches would prove one): %s",
            len(outline_only),
            ", ".join(outline_only),
        )
    report = {
        "summary": summary,
        "photos": photos,
        "sets": sets.reports,
        "sets_adjustment": sets.adjustment,
        "pose_source": {kind: sorted(n for n in placed if source[n] == kind) for kind in _SOURCES},
        "unplaced": unplaced,
        "reprojection_error_px_median": solution.reprojection_px,
        "points": len(solution.points),
        "observations": solution.observations,
        # Unwrapped in file order within each set: a turntable's angles then grow as the table turned.
        "angle_deg": {
            name: value
            for members in _by_set(placed, photos)
            for name, value in zip(members, np.degrees(np.unwrap([angles[n] for n in members])).tolist())
        },
        "angle_std_deg": solution.angle_std_deg,
        "silhouette": details,
        "self_calibration": solution.calibration,
        "silhouette_coherence": solution.silhouette_coherence,
        "weak_pairs": solution.weak_pairs,
        "joined_groups": solution.joined_groups,
    }
    return table, poses, solution, report


def _other_sets(
    settings: PlacementSettings,
    order: list[str],
    solution: CircularMotion,
    keypoints: dict[str, np.ndarray],
    matches: dict[tuple[str, str], dict[int, int]],
    board_poses: dict[str, Pose],
) -> list[list[str]]:
    """The sets after the first (the largest), in file order; none for one set. Sets
    shot from different heights or distances: one circle puts them all between, and
    posed freely on its points each set's photos stand at their own
    (pipeline.geometry.turntable_sets). Where the board on the table is seen in most
    photos, their cameras stand where its poses put them, over the board's plane."""
    min_photos = max(3, len(order) // 10)
    if len(board_poses) > len(order) / 2:
        cameras = turntable_sets.over_the_board(board_poses)
    else:
        cameras = turntable_sets.free_cameras(solution, keypoints, matches)
    found_sets = turntable_sets.split_by_camera(cameras, settings.set_separation, min_photos)
    if len(found_sets) == 1:
        return []
    found_sets = sorted(turntable_sets.with_the_rest(found_sets, order, matches), key=len, reverse=True)
    logger.info(
        "circular motion: %d sets by where their cameras stand (%s): the first solved alone, the others joined",
        len(found_sets),
        ", ".join(str(len(found)) for found in found_sets),
    )
    return [[n for n in order if n in found] for found in found_sets[1:]]


def _solve(
    settings: PlacementSettings,
    order: list[str],
    start: Intrinsics,
    keypoints: dict[str, np.ndarray],
    matches: dict[tuple[str, str], dict[int, int]],
    board_poses: dict[str, Pose],
    hulls: dict[str, np.ndarray],
    unverified: dict[tuple[str, str], dict[int, int]] | None,
) -> CircularMotion:
    try:
        return circular_motion.solve(
            settings.circular,
            order,
            start,
            keypoints,
            matches,
            board_poses,
            outlines={n: hulls[n] for n in order if n in hulls} if settings.silhouette_coherence else None,
            unverified=unverified,
        )
    except ValueError as error:
        raise PipelineError(
            f"the photos' features do not determine the turning: {error}. Check the photos with "
            "`pipeline check`; give the table texture (a printed board or a patterned mat) or shoot more "
            "photos per turn"
        ) from error


@dataclass
class _Sets:
    """The capture's other sets: the group numbers that were sets, the joined sets'
    photos' poses and angles (in their own set) in the ring's frame, the photos of sets
    left out (with the reason), and a report per set."""

    numbers: set[int] = field(default_factory=set)
    poses: dict[str, Pose] = field(default_factory=dict)
    angles: dict[str, float] = field(default_factory=dict)
    angle_std_deg: dict[str, float] = field(default_factory=dict)
    set_of: dict[str, int] = field(default_factory=dict)
    left_out: dict[str, str] = field(default_factory=dict)
    reports: list[dict] = field(default_factory=list)
    joined: list[sets_adjustment.JoinedSet] = field(default_factory=list)
    """Each joined set as solved alone, for the adjustment of all together."""
    adjustment: dict = field(default_factory=dict)
    """The adjustment of all together: observations, matches across shared, residual,
    each set's turn uncertainty, the intrinsics."""


def _join_sets(
    settings: PlacementSettings,
    order: list[str],
    solution: CircularMotion,
    table: Turntable,
    keypoints: dict[str, np.ndarray],
    matches: dict[tuple[str, str], dict[int, int]],
    on_specimen: dict[str, np.ndarray],
    hulls: dict[str, np.ndarray],
    other_sets: list[list[str]],
) -> _Sets:
    """Each of ``other_sets`` (found where their cameras stand), and each group that
    strong pairs of matches tie to the ring, is another set: solved alone at the ring's
    intrinsics and joined by its matches with the ring on the specimen (``on_specimen``:
    per photo, which keypoints lie on its mask) (pipeline.geometry.turntable_sets), or
    left out with one warning naming its photos. On the specimen: one turned over
    between sets no longer turns with the table, and matches of the table would join
    the table, not the specimen."""
    sets = _Sets()
    ring_names = set(table.angles)
    ring_poses = {name: table.pose(angle) for name, angle in table.angles.items()}
    held = replace(settings.circular, refine_focal=False, self_calibrate=False, even_steps_deg=0.0)
    candidates = [(None, names) for names in other_sets] + [
        (number, [name for name in order if name in group]) for number, group in enumerate(solution.groups, start=1)
    ]
    for number, names in candidates:
        group = set(names)
        crossing = matched_pairs(matches, ring_names, group, settings.circular.min_observations)
        if number is not None and not crossing:
            continue  # an arc of the ring that matching left apart: its outlines place it
        if number is not None:
            sets.numbers.add(number)
        report: dict = {"set": len(sets.reports) + 2, "photos": names, "pairs_across": crossing}
        sets.reports.append(report)
        own_matches = {pair: found for pair, found in matches.items() if pair[0] in group and pair[1] in group}
        try:
            own = circular_motion.solve(
                held,
                names,
                solution.intrinsics,
                keypoints,
                own_matches,
                outlines={n: hulls[n] for n in names if n in hulls} if settings.silhouette_coherence else None,
            )
        except ValueError as error:
            joined, why = None, f"its own turn cannot be solved: {error}"
        else:
            own_table = Turntable(own.axis, own.point, np.eye(3), np.zeros(3), dict(own.angles))
            own_poses = {name: own_table.pose(angle) for name, angle in own.angles.items()}
            across = _across_on_specimen(matches, ring_names, group, on_specimen)
            joined, found = turntable_sets.join(
                turntable_sets.Solved(solution, ring_poses),
                turntable_sets.Solved(own, own_poses),
                keypoints,
                across,
                settings.circular.min_observations,
                settings.join_noise_factor,
                solution.axis,
            )
            report.update(found)
            why = found["decision"]
        report["joined"] = joined is not None
        if joined is None:
            reason = f"in set {report['set']} of {len(names)} photos, left out: {why}"
            sets.left_out |= {name: reason for name in names}
            logger.warning(
                "set %d of %d photos (%s) is left out: %s. Its matches with the first set do not prove where it "
                "lies; shoot photos between the sets, or a board the sets both see",
                report["set"],
                len(names),
                ", ".join(names),
                why,
            )
            continue
        for name in names:
            if name in own_poses:
                sets.poses[name] = joined.pose(own_poses[name])
                sets.angles[name] = own.angles[name]
                sets.set_of[name] = report["set"]
                sets.angle_std_deg[name] = float(np.hypot(own.angle_std_deg.get(name, 0.0), found["angle_std_deg"]))
            else:
                sets.left_out[name] = f"in set {report['set']}, not placed within it: {own.unplaced.get(name, '')}"
        sets.joined.append(
            sets_adjustment.JoinedSet(turntable_sets.Solved(own, own_poses), joined, across, found["inlier_limit_px"])
        )
        logger.info("set %d of %d photos %s", report["set"], len(names), why)
    return sets


def _adjust_together(
    settings: PlacementSettings,
    solution: CircularMotion,
    table: Turntable,
    sets: _Sets,
    keypoints: dict[str, np.ndarray],
    hulls: dict[str, np.ndarray],
) -> tuple[CircularMotion, Turntable, dict[str, str]]:
    """The ring and the joined sets adjusted together (pipeline.geometry.sets_adjustment):
    the solution and table with the ring's adjusted circle, angles, intrinsics and the
    points of all sets (the groups' kept as they were), and the ring's photos whose
    angle it leaves undetermined, with the reason (their outlines may still place
    them); the sets' poses, angle uncertainties and the join reports updated in
    ``sets``, a set's photo left undetermined left out."""
    if not sets.joined:
        return solution, table, {}
    ring_poses = {name: table.pose(angle) for name, angle in table.angles.items()}
    values = solution.calibration.get("values", {})
    adjusted = sets_adjustment.adjust_sets(
        turntable_sets.Solved(solution, ring_poses),
        sets.joined,
        keypoints,
        {name: bool(values.get(name, {}).get("adjusted")) for name in ("f", "k1")},
        settings.circular.outlier_px,
        hulls if settings.silhouette_coherence else None,
    )
    sets.adjustment = adjusted.report
    joined_reports = [report for report in sets.reports if report["joined"]]
    for report, turn_std in zip(joined_reports, adjusted.report["set_turn_std_deg"]):
        report["angle_std_deg"] = turn_std
    reason = "its features leave its angle undetermined when the sets are adjusted together (outliers there)"
    unplaced = {name: reason for name in adjusted.undetermined if name in table.angles}
    for name in list(sets.poses):
        if name in adjusted.undetermined:
            for record in (sets.poses, sets.angles, sets.angle_std_deg, sets.set_of):
                del record[name]
            sets.left_out[name] = reason
            logger.warning("%s is left out: %s", name, reason)
            continue
        sets.poses[name], sets.angle_std_deg[name] = adjusted.poses[name], adjusted.angle_std_deg[name]
        sets.angles[name] = adjusted.angles[name]
    logger.info(
        "circular motion: %d sets adjusted together, %d matches across them shared, %.2f px median residual",
        1 + len(sets.joined),
        adjusted.report["matches_across_shared"],
        adjusted.report["reprojection_px_median"],
    )
    groups = solution.point_groups != 0
    solution = replace(
        solution,
        axis=adjusted.axis,
        point=adjusted.point,
        intrinsics=adjusted.intrinsics,
        angles=solution.angles | {name: adjusted.angles[name] for name in adjusted.poses if name in table.angles},
        angle_std_deg={n: std for n, std in solution.angle_std_deg.items() if n not in unplaced}
        | {name: adjusted.angle_std_deg[name] for name in adjusted.poses if name in table.angles},
        points=np.vstack([adjusted.points, solution.points[groups]]),
        tracks=adjusted.tracks + [track for track, group in zip(solution.tracks, groups) if group],
        point_groups=np.concatenate([np.zeros(len(adjusted.points), int), solution.point_groups[groups]]),
        reprojection_px=adjusted.report["reprojection_px_median"],
        calibration=solution.calibration | {"values": adjusted.report["intrinsics"]},
    )
    angles = {name: adjusted.angles[name] for name in adjusted.poses if name in table.angles}
    return solution, Turntable(solution.axis, solution.point, np.eye(3), np.zeros(3), angles), unplaced


def _across_on_specimen(
    matches: dict[tuple[str, str], dict[int, int]], ring: set[str], group: set[str], on_specimen: dict[str, np.ndarray]
) -> dict[tuple[str, str], dict[int, int]]:
    """The matches from the ring's photos to the group's whose keypoints both lie on the
    specimen's masks."""
    return {
        (a, b): {ka: kb for ka, kb in found.items() if on_specimen[a][ka] and on_specimen[b][kb]}
        for (a, b), found in matches.items()
        if a in ring and b in group and a in on_specimen and b in on_specimen
    }


MAX_SET_ROUNDS = 3
"""The first set is solved again at most this many times, each time without the photos
its own circle poses at another elevation."""


_PLACED_BY = {
    "features": "features",
    "features_across_sets": "features across sets",
    "board": "board",
    "even_steps": "even steps",
    "joined_by_outline": "outline",
    "group_silhouette": "outline",
    "silhouette": "outline",
}


def _photo_records(
    order: list[str], poses: dict[str, Pose], source: dict[str, str], angle_std: dict[str, float], sets: _Sets
) -> dict[str, dict]:
    """Per placed photo: its set (1: the ring's), what placed it, its angle's standard
    deviation (None where no covariance gives one: a board's, even steps', an outline's)
    and whether it is certain (not by outlines alone)."""
    records = {}
    for name in (n for n in order if n in poses):
        placed_by = _PLACED_BY[source[name]]
        if name in sets.poses:
            std = sets.angle_std_deg[name]
        else:
            std = angle_std.get(name) if placed_by == "features" else None
        records[name] = {
            "set": sets.set_of.get(name, 1),
            "placed_by": placed_by,
            "angle_std_deg": std,
            "certain": placed_by != "outline",
        }
    return records


def _by_set(placed: list[str], photos: dict[str, dict]) -> list[list[str]]:
    numbers = sorted({photos[name]["set"] for name in placed})
    return [[name for name in placed if photos[name]["set"] == number] for number in numbers]


def _summary(order: list[str], photos: dict[str, dict], reports: list[dict]) -> str:
    """One line: how many photos were placed, in how many sets, joined by how many
    verified observations, how many by outline alone, how many left out."""
    joined = [r for r in reports if r["joined"]]
    parts = [f"{len(photos)} of {len(order)} placed"]
    if reports:
        parts.append(
            f"{1 + len(reports)} sets, {1 + len(joined)} joined"
            + (f" by {sum(r['inliers'] for r in joined)} verified observations" if joined else "")
        )
    outline = sum(1 for record in photos.values() if record["placed_by"] == "outline")
    if outline:
        parts.append(f"{outline} by outline alone (uncertain)")
    if len(photos) < len(order):
        parts.append(f"{len(order) - len(photos)} left out")
    return "; ".join(parts)


_SOURCES = tuple(_PLACED_BY)


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
    groups: dict[int, dict[str, float]],
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
    for number, group in groups.items():
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
