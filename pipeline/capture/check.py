"""``pipeline check``: quality control of a capture before the expensive stages.

Looks at the photos the way the later stages will and reports, one line per
problem, what is wrong with which file and what to do about it. Errors (the run
would fail or be spoilt) make the command exit with 1; warnings do not.

==================  =============================================================
check               flagged when
==================  =============================================================
count               fewer than MIN_PHOTOS photos (error) or fewer than ENOUGH_PHOTOS
readable            OpenImageIO cannot decode a file (error)
camera settings     photos differ in camera, zoom or size (each setting gets its
                    own intrinsics, so each needs enough photos)
exposure            more than CLIPPED_FRACTION of the specimen's pixels clipped; the
                    specimen more than EXPOSURE_STOPS stops off the set's median
                    (exposure not locked); the whole photo where no mask was found
                    (a photo cut out on white is not overexposed, and a specimen
                    filling more of a dark set's frame is not a brighter exposure)
blur                variance of the Laplacian below BLUR_RATIO x the set's median
near-duplicates     thumbnails of the specimen's box (of the photo without a mask)
                    correlate above DUPLICATE_CORRELATION
strays              a photo shares fewer verified SIFT matches with every other
                    photo than max(MIN_SHARED_MATCHES, STRAY_RATIO x the set's
                    median): a photo of something else (error)
board               calibration shots in which the board is not found
masks               the specimen mask (user's, or segmented as the masks stage
                    would) covers almost nothing (error) or almost everything,
                    or touches the border
==================  =============================================================
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from itertools import combinations
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from pipeline.camera.board import BoardDetector, found_in_any
from pipeline.core import progress
from pipeline.core.config import Config
from pipeline.core.errors import PipelineError
from pipeline.imaging.photo_io import (
    PHOTO_SUFFIXES,
    UNREAD_NAMED,
    camera_setting,
    gray_uint8,
    list_photos,
    read_photo,
    to_uint8,
    unsupported_files,
)
from pipeline.imaging.segmentation import (
    FixedSet,
    clean,
    learn_fixed_sets,
    read_user_mask,
    resolve_segmenter,
    segment,
)

MIN_PHOTOS = 3
ENOUGH_PHOTOS = 20
CLIPPED_FRACTION = 0.05
EXPOSURE_STOPS = 1.0
BLUR_RATIO = 0.3
DUPLICATE_CORRELATION = 0.995
CORRELATION_BLOCK = 512
ALL_PAIRS_UP_TO = 150
"""Photos up to which the stray check matches every pair (11,175 pairs at most)."""
STRAY_NEIGHBOURS = 8
"""Beyond that, each photo is matched with this many neighbours in file order and as
many look-alikes."""
"""Rows of the thumbnails' correlation matrix computed at once (512 x N floats)."""
MIN_SHARED_MATCHES = 12
STRAY_RATIO = 0.3
FEATURE_SIZE = (256, 640)
"""Photos are resized for SIFT so that the longer side falls in this range."""
MASK_WORKING_SIZE = 256
MASK_CHECK_PHOTOS = 300
"""Photos whose masks are segmented to check them, evenly spread over a larger set (a
segmentation takes about a quarter of a second: 10,000 would take 45 minutes, and
`pipeline run --until masks` segments every one anyway)."""
MIN_MASK_COVERAGE = 0.005
"""A mask covering less of the photo has not found the specimen."""


@dataclass
class Problem:
    severity: Literal["error", "warning", "note"]
    check: str
    file: str
    """Photo or folder the problem is about, relative to the capture."""
    message: str
    advice: str

    def line(self) -> str:
        return f"{self.severity:7} {self.file}: {self.message}; {self.advice}"


@dataclass
class PhotoSummary:
    name: str
    gray: np.ndarray
    """8-bit, resized for feature extraction."""
    srgb: np.ndarray
    """8-bit RGB at full size."""
    setting: str


def _feature_copy(gray: np.ndarray) -> np.ndarray:
    longest = max(gray.shape)
    factor = min(max(1.0, FEATURE_SIZE[0] / longest), FEATURE_SIZE[1] / longest)
    if factor == 1.0:
        return gray
    interpolation = cv2.INTER_AREA if factor < 1 else cv2.INTER_CUBIC
    return cv2.resize(gray, None, fx=factor, fy=factor, interpolation=interpolation)


def _specimen(photo: PhotoSummary, masks: dict[str, np.ndarray | None]) -> np.ndarray | None:
    """The photo's specimen mask when one was found (at least MIN_MASK_COVERAGE)."""
    mask = masks.get(photo.name)
    return mask if mask is not None and mask.mean() >= MIN_MASK_COVERAGE else None


def check_exposure(photos: list[PhotoSummary], masks: dict[str, np.ndarray | None]) -> list[Problem]:
    problems = []
    brightness = {}
    for photo in photos:
        specimen = _specimen(photo, masks)
        clipped_pixels = photo.srgb.max(axis=-1) >= 250
        clipped = float(clipped_pixels[specimen].mean() if specimen is not None else clipped_pixels.mean())
        if clipped > CLIPPED_FRACTION:
            where = "the specimen's pixels" if specimen is not None else "the pixels (no specimen mask found)"
            problems.append(
                Problem(
                    "warning",
                    "exposure",
                    f"images/{photo.name}",
                    f"overexposed: {100 * clipped:.1f} % of {where} are clipped",
                    "retake it with a shorter exposure; clipped pixels carry no radiance",
                )
            )
        gray = cv2.cvtColor(photo.srgb, cv2.COLOR_RGB2GRAY)
        brightness[photo.name] = float(np.median(gray[specimen] if specimen is not None else gray)) + 1.0
    median = np.median(list(brightness.values()))
    for name, value in brightness.items():
        # 8-bit sRGB is roughly gamma 2.2: a stop is a factor 2 ** (1 / 2.2) in encoded values.
        stops = 2.2 * np.log2(value / median)
        if abs(stops) > EXPOSURE_STOPS:
            problems.append(
                Problem(
                    "warning",
                    "exposure",
                    f"images/{name}",
                    f"{abs(stops):.1f} stops {'brighter' if stops > 0 else 'darker'} than the set",
                    "lock exposure and white balance for the whole session",
                )
            )
    return problems


def check_blur(photos: list[PhotoSummary]) -> list[Problem]:
    sharpness = {p.name: float(cv2.Laplacian(p.gray, cv2.CV_64F).var()) for p in photos}
    median = np.median(list(sharpness.values()))
    return [
        Problem(
            "warning",
            "blur",
            f"images/{name}",
            f"blurred: sharpness {value / median:.2f} of the set's median",
            "retake it (tripod, shorter exposure, focus on the specimen) or remove it",
        )
        for name, value in sharpness.items()
        if value < BLUR_RATIO * median
    ]


def thumbnails(photos: list[PhotoSummary], masks: dict[str, np.ndarray | None]) -> np.ndarray:
    """Each photo's 32x32 grey thumbnail of the specimen's box (the whole photo without a
    mask), normalised to zero mean and unit deviation: one row per photo."""
    rows = np.zeros((len(photos), 32 * 32))
    for row, photo in zip(rows, photos):
        gray = cv2.cvtColor(photo.srgb, cv2.COLOR_RGB2GRAY)
        specimen = _specimen(photo, masks)
        if specimen is not None:
            x, y, w, h = cv2.boundingRect(specimen.astype(np.uint8))
            gray = gray[y : y + h, x : x + w]
        small = cv2.resize(gray, (32, 32), interpolation=cv2.INTER_AREA).astype(np.float64).ravel()
        row[:] = (small - small.mean()) / (small.std() + 1e-9)
    return rows


def check_duplicates(photos: list[PhotoSummary], masks: dict[str, np.ndarray | None]) -> list[Problem]:
    """Thumbnails of the specimen's box: photos cut out on white, or of a turntable, are
    alike around the specimen whatever the specimen shows."""
    problems = []
    for i, j, correlation in _correlated_pairs(thumbnails(photos, masks), DUPLICATE_CORRELATION):
        problems.append(
            Problem(
                "warning",
                "duplicates",
                f"images/{photos[j].name}",
                f"near-duplicate of {photos[i].name} (correlation {correlation:.4f})",
                "it adds no viewpoint; remove one of the two",
            )
        )
    return problems


def _correlated_pairs(thumbnails: np.ndarray, threshold: float) -> list[tuple[int, int, float]]:
    """Pairs (i < j, in that order) of normalised thumbnails (rows) whose correlation
    exceeds ``threshold``: one matrix product a block of rows at a time, so that 10,000
    photos take seconds and a bounded block of memory, not 50 million Python steps."""
    found = []
    count, size = thumbnails.shape
    for start in range(0, count, CORRELATION_BLOCK):
        block = thumbnails[start : start + CORRELATION_BLOCK] @ thumbnails.T / size
        rows, columns = np.nonzero(block > threshold)
        for row, column in zip(rows, columns):
            if column > start + row:
                found.append((int(start + row), int(column), float(block[row, column])))
    return sorted(found)


def verified_count(points_i: np.ndarray, points_j: np.ndarray) -> int:
    """Matches consistent with one fundamental matrix; 0 where none can be fitted."""
    try:
        _, verified = cv2.findFundamentalMat(points_i, points_j, cv2.USAC_MAGSAC, 1.5, 0.999)
    except cv2.error:
        # USAC asserts (`!model.empty()`) on degenerate matches, e.g. all on a few
        # repeated table dots of a low-resolution turntable photo: no geometry, no match.
        return 0
    return 0 if verified is None else int(verified.sum())


def candidate_pairs(photos: list[PhotoSummary], similar: np.ndarray | None = None) -> list[tuple[int, int]]:
    """The photo pairs to match: every pair up to ALL_PAIRS_UP_TO photos; beyond, each
    photo with its STRAY_NEIGHBOURS neighbours in file order and the STRAY_NEIGHBOURS
    whose thumbnails (rows of ``similar``) are most alike, as a vocabulary tree would
    propose them: a stray matches none of either, and the work grows with the count,
    not its square."""
    count = len(photos)
    if count <= ALL_PAIRS_UP_TO or similar is None:
        return list(combinations(range(count), 2))
    pairs = {(i, j) for i in range(count) for j in range(i + 1, min(i + 1 + STRAY_NEIGHBOURS, count))}
    for start in range(0, count, CORRELATION_BLOCK):
        block = similar[start : start + CORRELATION_BLOCK] @ similar.T
        for row, scores in enumerate(block):
            scores[start + row] = -np.inf
            for column in np.argpartition(-scores, STRAY_NEIGHBOURS)[:STRAY_NEIGHBOURS]:
                pairs.add((min(start + row, int(column)), max(start + row, int(column))))
    return sorted(pairs)


def shared_matches(photos: list[PhotoSummary], pairs: list[tuple[int, int]] | None = None) -> np.ndarray:
    """Matrix of SIFT matches between photo pairs (``pairs``; None: all) that survive a
    fundamental-matrix RANSAC."""
    sift = cv2.SIFT_create(nfeatures=1500)
    features = []
    for photo in progress.track(photos, "finding features"):
        keypoints, descriptors = sift.detectAndCompute(photo.gray, None)
        features.append((np.float32([k.pt for k in keypoints]), descriptors))
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    inliers = np.zeros((len(photos), len(photos)), int)
    pairs = pairs if pairs is not None else list(combinations(range(len(photos)), 2))
    for i, j in progress.track(pairs, "matching photo pairs"):
        (points_i, descriptors_i), (points_j, descriptors_j) = features[i], features[j]
        if descriptors_i is None or descriptors_j is None or min(len(points_i), len(points_j)) < 8:
            continue
        pairs = [m for m, n in matcher.knnMatch(descriptors_i, descriptors_j, k=2) if m.distance < 0.8 * n.distance]
        if len(pairs) < 8:
            continue
        inliers[i, j] = inliers[j, i] = verified_count(
            points_i[[m.queryIdx for m in pairs]], points_j[[m.trainIdx for m in pairs]]
        )
    return inliers


def check_strays(photos: list[PhotoSummary], blurred: set[str], similar: np.ndarray | None = None) -> list[Problem]:
    """Photos that match no other; blurred photos match poorly too, but their problem is
    blur. ``similar``: the photos' thumbnails, which pick the pairs to match in a large
    set (candidate_pairs)."""
    if len(photos) < MIN_PHOTOS:
        return []
    best = shared_matches(photos, candidate_pairs(photos, similar)).max(axis=1)
    limit = max(MIN_SHARED_MATCHES, STRAY_RATIO * float(np.median(best)))
    return [
        Problem(
            "error",
            "strays",
            f"images/{photo.name}",
            f"shares only {count} verified feature matches with any other photo (the set: "
            f"{np.median(best):.0f}); a photo of something else, or a gap in the orbit",
            "remove it from images/, or add photos between it and its neighbours",
        )
        for photo, count in zip(photos, best)
        if count < limit and f"images/{photo.name}" not in blurred
    ]


def check_board(capture_dir: Path, config: Config) -> list[Problem]:
    shots = list_photos(capture_dir / "calibration")
    board = config["board"]
    if not shots:
        return [
            Problem(
                "warning",
                "board",
                "calibration/",
                "no board shots",
                "calibration will use EXIF or self-calibration; shoot 10-20 board photos "
                "(`pipeline board` prints one) for accurate intrinsics",
            )
        ]
    if board.kind == "none":
        return [
            Problem(
                "warning",
                "board",
                "calibration/",
                "board shots but board.kind = 'none'",
                "set the [board] section of capture.toml to the printed board",
            )
        ]
    detector = BoardDetector(board, min_corners=config["calibrate"].min_corners)
    problems, found = [], 0
    for shot in progress.track(shots, "detecting the board"):
        try:
            pixels = read_photo(shot).pixels
        except PipelineError as error:
            problems.append(Problem("error", "board", f"calibration/{shot.name}", str(error), "remove or replace it"))
            continue
        if detector.detect(gray_uint8(pixels)) is None:
            problems.append(
                Problem(
                    "warning",
                    "board",
                    f"calibration/{shot.name}",
                    "board not found (or too few corners)",
                    "check that the [board] section matches the print, and that the "
                    "board is sharp, evenly lit and fills much of the frame",
                )
            )
        else:
            found += 1
    if found < config["calibrate"].min_shots:
        problems.append(
            Problem(
                "warning",
                "board",
                "calibration/",
                f"only {found} usable board shots (calibrate.min_shots = {config['calibrate'].min_shots})",
                "calibration will fall back to EXIF; add shots from varied angles",
            )
        )
    return problems


def _fixed_sets(photos: list[PhotoSummary], config: Config) -> dict[str, tuple[FixedSet, int]]:
    """The set of each camera setting, as the masks stage learns it (set_colours)."""
    settings = []
    for setting in sorted({photo.setting for photo in photos}):
        group = [photo for photo in photos if photo.setting == setting]
        settings.append(([photo.name for photo in group], [photo.srgb for photo in group]))
    return learn_fixed_sets(settings, MASK_WORKING_SIZE, camera_fixed=config["capture"].rig == "turntable")


def check_masks(
    capture_dir: Path, photos: list[PhotoSummary], config: Config
) -> tuple[list[Problem], dict[str, np.ndarray | None]]:
    """Problems with the specimen masks (the user's, or segmented as the masks stage
    would), and the masks by photo name (None where a user's mask is missing)."""
    conf = config["masks"]
    user_masks = {p.stem: p for p in list_photos(capture_dir / "masks")}
    problems: list[Problem] = []
    masks: dict[str, np.ndarray | None] = {}
    segmenter = resolve_segmenter(
        conf.segmenter,
        config["capture"].rig,
        lambda: found_in_any(config["board"], (cv2.cvtColor(p.srgb, cv2.COLOR_RGB2GRAY) for p in photos)),
    )
    fixed_sets = _fixed_sets(photos, config) if segmenter == "set_colours" and not user_masks else {}
    checked = photos
    if not user_masks and len(photos) > MASK_CHECK_PHOTOS:
        checked = [photos[i] for i in np.linspace(0, len(photos) - 1, MASK_CHECK_PHOTOS).round().astype(int)]
        problems.append(
            Problem(
                "note",
                "masks",
                "images/",
                f"masks segmented for {len(checked)} of {len(photos)} photos, evenly spread",
                "`pipeline run CAPTURE --until masks` segments every photo",
            )
        )
    for photo in progress.track(checked, "checking masks"):
        if user_masks:
            if Path(photo.name).stem not in user_masks:
                problems.append(
                    Problem(
                        "error",
                        "masks",
                        f"images/{photo.name}",
                        "no mask in masks/",
                        "add a PNG named like the photo, or empty masks/",
                    )
                )
                continue
            mask = read_user_mask(user_masks[Path(photo.name).stem])
        else:
            mask = segment(
                photo.srgb,
                segmenter,
                conf.backdrop_chroma,
                conf.centre_fraction,
                conf.grabcut_iterations,
                MASK_WORKING_SIZE,
                fixed_sets.get(photo.name),
            )
        mask = masks[photo.name] = clean(mask, conf.min_component_fraction, conf.max_hole_fraction)
        coverage = float(mask.mean())
        file = f"images/{photo.name}"
        if coverage < MIN_MASK_COVERAGE:
            problems.append(
                Problem(
                    "error",
                    "masks",
                    file,
                    f"the specimen mask covers {100 * coverage:.1f} % of the photo",
                    "the specimen was not found: provide masks/ or background/ plates, "
                    "or try masks.segmenter = 'centre_prior'",
                )
            )
        elif coverage > 0.9:
            problems.append(
                Problem(
                    "warning",
                    "masks",
                    file,
                    f"the specimen mask covers {100 * coverage:.0f} % of the photo",
                    "step back so that the whole specimen and some set are in view",
                )
            )
        elif np.concatenate([mask[0], mask[-1], mask[:, 0], mask[:, -1]]).any():
            problems.append(
                Problem(
                    "warning",
                    "masks",
                    file,
                    "the specimen touches the image border",
                    "keep the whole specimen in frame: a cut-off part is lost from the visual hull",
                )
            )
    return problems, masks


def check_capture(capture_dir: Path, config: Config, features: bool = True) -> list[Problem]:
    """Every check on ``capture_dir``; ``features=False`` skips the pairwise matching."""
    paths = list_photos(capture_dir / "images")
    unread = unsupported_files(capture_dir / "images")
    unsupported = [
        Problem(
            "warning",
            "unsupported",
            f"images/{path.name}",
            "not a photo the pipeline reads, left out",
            f"convert it to {', '.join(PHOTO_SUFFIXES)} or move it out of images/",
        )
        for path in unread[:UNREAD_NAMED]
    ]
    if len(unread) > UNREAD_NAMED:
        unsupported.append(
            Problem(
                "warning",
                "unsupported",
                "images/",
                f"{len(unread) - UNREAD_NAMED} more files are not photos the pipeline reads, left out",
                f"convert them to {', '.join(PHOTO_SUFFIXES)} or move them out of images/",
            )
        )
    if len(paths) < MIN_PHOTOS:
        return unsupported + [
            Problem(
                "error",
                "count",
                "images/",
                f"{len(paths)} photos",
                f"structure-from-motion needs at least {MIN_PHOTOS}; {ENOUGH_PHOTOS}+ from all sides is better",
            )
        ]
    problems, photos = unsupported, []
    for path in progress.track(paths, "reading photos"):
        try:
            photo = read_photo(path)
        except PipelineError as e:
            problems.append(
                Problem(
                    "error", "readable", f"images/{path.name}", str(e).split(": ", 1)[-1], "remove or replace the file"
                )
            )
            continue
        srgb = to_uint8(photo.pixels)
        gray = _feature_copy(cv2.cvtColor(srgb, cv2.COLOR_RGB2GRAY))
        photos.append(PhotoSummary(path.name, gray, srgb, camera_setting(photo.metadata, photo.size)))
    if len(photos) < ENOUGH_PHOTOS:
        problems.append(
            Problem(
                "warning",
                "count",
                "images/",
                f"only {len(photos)} photos",
                f"shoot {ENOUGH_PHOTOS}+ from all sides with 60-80 % overlap between neighbours",
            )
        )
    settings = sorted({p.setting for p in photos})
    if len(settings) > 1:
        for setting in settings:
            members = [p.name for p in photos if p.setting == setting]
            problems.append(
                Problem(
                    "warning",
                    "camera settings",
                    f"images/{members[0]}",
                    f"{len(members)} photos taken with {setting}",
                    "each camera/zoom setting is calibrated on its own; keep the zoom fixed",
                )
            )
    mask_problems, masks = check_masks(capture_dir, photos, config)
    for same_size_group in _by_setting(photos).values():
        problems += check_exposure(same_size_group, masks) + check_blur(same_size_group)
        problems += check_duplicates(same_size_group, masks)
    if features:
        blurred = {p.file for p in problems if p.check == "blur"}
        problems += check_strays(photos, blurred, thumbnails(photos, masks) / np.sqrt(32 * 32))
    return problems + check_board(capture_dir, config) + mask_problems


def _by_setting(photos: list[PhotoSummary]) -> dict[str, list[PhotoSummary]]:
    groups: dict[str, list[PhotoSummary]] = {}
    for photo in photos:
        groups.setdefault(photo.setting, []).append(photo)
    return groups


def as_json(problems: list[Problem]) -> list[dict]:
    return [asdict(p) for p in problems]
