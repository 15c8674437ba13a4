"""Features and matches: SIFT on masked photos, matching (exhaustive, sequential or
along a ring), the database's verified matches and why a photo stayed unregistered."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np
import pycolmap

from pipeline import logger
from pipeline.camera.model import Intrinsics
from pipeline.colmap import COLMAP_PIXEL_OFFSET
from pipeline.core.config import Range
from pipeline.imaging.segmentation import on_mask, still_pixels


def feature_masks(
    mode: str, mask_dilation: float, photos: dict[str, dict], masks: dict[str, Path], out_dir: Path
) -> Path | None:
    """Where features may come from, as masks in COLMAP's convention (IMAGE.png.png,
    0 = no features), or None for everywhere. ``mode``: everywhere; specimen (the
    specimen mask dilated by ``mask_dilation`` of the image diagonal); moving (that
    plus whatever changes between the photos of one camera setting: a turntable)."""
    if mode == "everywhere":
        return None
    folder = out_dir / "feature_masks"
    folder.mkdir()
    moving: dict[str, np.ndarray] = {}
    if mode == "moving":
        for camera in {photo["camera"] for photo in photos.values()}:
            names = [n for n, p in photos.items() if p["camera"] == camera]
            still = still_pixels(np.stack([cv2.imread(str(photos[n]["srgb"]), cv2.IMREAD_GRAYSCALE) for n in names]))
            moving |= {name: ~still_here for name, still_here in zip(names, still)}
    for name, photo in photos.items():
        specimen = cv2.imread(str(masks[name]), cv2.IMREAD_GRAYSCALE) > 127
        h, w = specimen.shape
        radius = max(int(mask_dilation * np.hypot(w, h)), 1)
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1,) * 2)
        allowed = cv2.dilate(specimen.astype(np.uint8), kernel) > 0
        if name in moving:
            allowed |= cv2.dilate(moving[name].astype(np.uint8), kernel) > 0
        cv2.imwrite(str(folder / f"{Path(photo['srgb']).name}.png"), allowed.astype(np.uint8) * 255)
    return folder


@dataclass(frozen=True)
class FeatureSettings:
    """Where features come from, how they are described, and which photos are matched."""

    max_features: Annotated[int, Range(256, 65536)] = 8192
    """Most SIFT features kept per photo."""
    upsample: Literal["auto", "yes", "no"] = "auto"
    """Extract SIFT from twice the photo's resolution (COLMAP's first_octave of -1): two
    to three times the features on small photos. auto: yes below small_photo_px."""
    dsp_sift: Literal["auto", "yes", "no"] = "auto"
    """Domain-size pooled SIFT descriptors: more matches across a change of viewpoint, about
    four times the extraction time. auto: yes below small_photo_px."""
    small_photo_px: Annotated[int, Range(0, None)] = 1000
    """Photos whose longer side is below this are small for upsample and dsp_sift."""
    feature_mask: Literal["auto", "everywhere", "specimen", "moving"] = "auto"
    """Where features are extracted. everywhere: the whole photo (a handheld capture,
    where the set is as still as the specimen); specimen: the dilated specimen mask;
    moving: the specimen plus whatever changes between photos of a fixed camera (the
    turning table and board), not the still room. auto: moving for a turntable, else
    everywhere."""
    mask_dilation: Annotated[float, Range(0.0, 0.5)] = 0.03
    """Margin added around the specimen mask, as a fraction of the image diagonal:
    features on the silhouette's edge are among the best."""
    matcher: Literal["auto", "exhaustive", "sequential", "ring"] = "auto"
    """exhaustive: every pair; sequential: each photo with the next sequential_overlap in
    file order; ring: with the next ring_neighbours, wrapping round (a turntable's
    revolution), and with the outline_neighbours whose outlines look alike. auto: ring
    for a turntable, else exhaustive up to exhaustive_max_images photos and sequential
    beyond (a ring rig's photos need not be in order). Exhaustive matching of a
    turntable finds false pairs between opposite sides of a repetitive set (a
    checkerboard from 180 degrees away)."""
    exhaustive_max_images: Annotated[int, Range(2, None)] = 150
    """Largest capture matched exhaustively (pairs grow with the square of the count)."""
    sequential_overlap: Annotated[int, Range(1, None)] = 20
    """Sequential matching: each photo is matched with this many following ones."""
    ring_neighbours: Annotated[int, Range(1, None)] = 6
    """Ring matching: each photo is matched with this many following ones, cyclically."""
    outline_neighbours: Annotated[int, Range(0, None)] = 3
    """Ring matching: each photo is also matched with up to this many others whose
    specimen outline looks more like its own than its neighbours' in file order do
    (outline_neighbours), wherever they are in file order: a turntable's camera is
    fixed, so a second turn's photo shows the outline of the first turn's photo at
    nearly the same angle."""
    descriptor_neighbours: Annotated[int, Range(0, None)] = 4
    """Ring matching: each photo is also matched with up to this many others that share
    the most SIFT descriptors with it (descriptor_neighbours), wherever they are in file
    order: a capture shot in sets has photos of the same side in another set, where the
    camera stood higher or the specimen lay turned over, whose outlines differ."""


@dataclass(frozen=True)
class FeaturePlan:
    """FeatureSettings with every "auto" choice made for one capture."""

    max_features: int
    """Most SIFT features kept per photo."""
    upsample: bool
    """SIFT from twice the resolution (COLMAP's first_octave of -1)."""
    domain_size_pooling: bool
    """DSP-SIFT descriptors."""
    mask_dir: Path | None
    """Where features may come from (feature_masks), or None for everywhere."""
    matcher: Literal["exhaustive", "sequential", "ring"]
    """Which pairs are matched."""
    sequential_overlap: int
    """Sequential matching: following photos each photo is matched with."""
    pairs: tuple[tuple[str, str], ...]
    """Ring matching: the pairs of photo file names to match (ring_pairs); empty for
    the other matchers."""
    descriptor_neighbours: int
    """Ring matching: partners per photo retrieved by their descriptors after extraction."""
    specimen_masks: dict[str, Path]
    """Ring matching: each photo's specimen mask by its file name, where descriptor_neighbours
    compares features (the specimen, not the table it may have been turned over on)."""
    still_camera: bool
    """Matches that do not move are dropped (a turntable's room)."""

    @classmethod
    def of(
        cls,
        settings: FeatureSettings,
        rig: str,
        photos: dict[str, dict],
        cameras: list[dict],
        masks: dict[str, Path],
        work: Path,
    ) -> FeaturePlan:
        """The plan for ``rig``'s photos; writes the feature masks into ``work``."""
        mode = settings.feature_mask
        if mode == "auto":
            mode = "moving" if rig == "turntable" else "everywhere"
        matcher = settings.matcher
        if matcher == "auto":
            exhaustive = len(photos) <= settings.exhaustive_max_images
            matcher = "ring" if rig == "turntable" else "exhaustive" if exhaustive else "sequential"
        longest = max(max(c["intrinsics"]["width"], c["intrinsics"]["height"]) for c in cameras)
        small = longest < settings.small_photo_px
        return cls(
            max_features=settings.max_features,
            upsample=settings.upsample == "yes" or (settings.upsample == "auto" and small),
            domain_size_pooling=settings.dsp_sift == "yes" or (settings.dsp_sift == "auto" and small),
            mask_dir=feature_masks(mode, settings.mask_dilation, photos, masks, work),
            matcher=matcher,
            sequential_overlap=settings.sequential_overlap,
            pairs=ring_pairs(photos, masks, settings.ring_neighbours, settings.outline_neighbours)
            if matcher == "ring"
            else (),
            descriptor_neighbours=settings.descriptor_neighbours,
            specimen_masks={Path(photo["srgb"]).name: masks[name] for name, photo in photos.items() if name in masks},
            still_camera=rig == "turntable",
        )


def features_and_matches(plan: FeaturePlan, photos: dict[str, dict], cameras: list[dict], work: Path) -> Path:
    """SIFT features and verified matches of every photo (undistort's ``{"srgb": PNG}``)
    in a new COLMAP database in ``work``, as ``plan`` says."""
    database = work / "database.db"
    _extract(plan, photos, cameras, database)
    _match(plan, photos, database)
    return database


def _extract(plan: FeaturePlan, photos: dict[str, dict], cameras: list[dict], database: Path) -> None:
    """SIFT features of every photo: one SIMPLE_RADIAL COLMAP camera per camera
    setting, its distortion 0 until self-calibration."""
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = plan.max_features
    extraction.sift.first_octave = -1 if plan.upsample else 0
    extraction.sift.domain_size_pooling = plan.domain_size_pooling
    extraction.num_threads = -1
    image_dir = next(iter(photos.values()))["srgb"].parent
    pycolmap.Database.open(database).close()  # import_images needs the file to exist
    for index, camera in enumerate(cameras):
        names = [Path(p["srgb"]).name for p in photos.values() if p["camera"] == index]
        if not names:
            continue
        K = Intrinsics.from_json(camera["intrinsics"])
        reader = pycolmap.ImageReaderOptions()
        # One focal length: undistort makes square pixels, and refining keeps them. The
        # radial term is what self-calibration may find left in the undistorted photos.
        reader.camera_model = "SIMPLE_RADIAL"
        # COLMAP puts the first pixel's centre at (0.5, 0.5), OpenCV and we at (0, 0).
        reader.camera_params = f"{K.fx},{K.cx + COLMAP_PIXEL_OFFSET},{K.cy + COLMAP_PIXEL_OFFSET},0"
        if plan.mask_dir is not None:
            reader.mask_path = str(plan.mask_dir)
        # Extraction numbers photos in the order its threads finish, and matching
        # and mapping follow those numbers: importing them first, sorted, makes a
        # rerun give the same model (it gave rotation errors of 0.7 to 164 degrees).
        pycolmap.import_images(
            database, image_dir, camera_mode=pycolmap.CameraMode.SINGLE, image_names=sorted(names), options=reader
        )
        pycolmap.extract_features(
            database,
            image_dir,
            image_names=names,
            camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=reader,
            extraction_options=extraction,
            device=pycolmap.Device.cpu,
        )


def _match(plan: FeaturePlan, photos: dict[str, dict], database: Path) -> None:
    """Matches of the plan's pairs, verified with seeded RANSAC."""
    logger.info("%s matching of %d photos", plan.matcher, len(photos))
    verification = pycolmap.TwoViewGeometryOptions()
    # A fixed camera sees the still room at the same pixels in every photo: matches
    # that do not move say nothing about the turning object.
    verification.filter_stationary_matches = plan.still_camera
    verification.stationary_matches_max_error = STATIONARY_PX
    # COLMAP seeds RANSAC from the clock by default: the same photos then give
    # different verified matches, and a different model, on every run.
    verification.ransac.random_seed = 0
    matching = pycolmap.FeatureMatchingOptions()
    # The CPU matcher's approximate nearest-neighbour search gives other matches when
    # its threads interleave differently (seen on a loaded machine): one thread keeps
    # reruns identical for about twice the matching time.
    matching.num_threads = 1
    device = pycolmap.Device.cpu
    if plan.matcher == "exhaustive":
        pycolmap.match_exhaustive(database, matching, verification_options=verification, device=device)
    elif plan.matcher == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = plan.sequential_overlap
        pycolmap.match_sequential(
            database, matching, pairing_options=pairing, verification_options=verification, device=device
        )
    else:
        retrieved = descriptor_neighbours(database, plan.descriptor_neighbours, set(plan.pairs), plan.specimen_masks)
        logger.info(
            "%d pairs in file order or alike in outline, %d more alike in descriptors", len(plan.pairs), len(retrieved)
        )
        pairs_file = database.with_name("pairs.txt")
        pairs_file.write_text("".join(f"{a} {b}\n" for a, b in sorted(set(plan.pairs) | retrieved)))
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = pairs_file
        pycolmap.match_image_pairs(
            database, matching, pairing_options=pairing, verification_options=verification, device=device
        )


RETRIEVAL_FEATURES = 512
"""Features per photo compared by descriptor_neighbours: its largest (the most repeatable
across a change of viewpoint), which keeps the comparison of every pair to seconds."""
RETRIEVAL_RATIO = 0.8
"""Lowe's ratio: a feature counts as shared with a photo where its nearest descriptor
there is this much nearer than the second nearest."""


def descriptor_neighbours(
    database: Path, count: int, excluded: set[tuple[str, str]], masks: dict[str, Path]
) -> set[tuple[str, str]]:
    """Pairs (sorted file names) of each photo with up to ``count`` others, not in
    ``excluded``, that share the most of its RETRIEVAL_FEATURES largest features on the
    specimen (within its mask, by file name; every feature where a photo has none)
    (Lowe's ratio test against each other photo's, both ways): a retrieval by local
    features, as a vocabulary tree gives, without one. On the specimen: turned over
    between sets, it shows the same side in photos where the table does not."""
    if count == 0:
        return set()
    with pycolmap.Database.open(database) as db:
        images = sorted(db.read_all_images(), key=lambda image: image.name)
        names = [image.name for image in images]
        sampled = []
        for image in images:
            shapes = np.asarray(db.read_keypoints(image.image_id), np.float64)
            descriptors = np.asarray(db.read_descriptors(image.image_id).data, np.float32)
            scale = np.abs(shapes[:, 2] * shapes[:, 5] - shapes[:, 3] * shapes[:, 4]) if len(shapes) else np.zeros(0)
            if image.name in masks and len(shapes):
                scale = np.where(on_mask(masks[image.name], shapes[:, :2] - COLMAP_PIXEL_OFFSET), scale, -1.0)
                descriptors = descriptors[scale >= 0]
                scale = scale[scale >= 0]
            kept = descriptors[np.argsort(-scale, kind="stable")[:RETRIEVAL_FEATURES]]
            sampled.append(kept / np.maximum(np.linalg.norm(kept, axis=1, keepdims=True), 1e-9))
    n = len(names)
    if n < 3:
        return set()
    width = max(len(d) for d in sampled)
    # Zero rows pad every photo to one width: their similarity 0 is never a nearest neighbour.
    padded = np.zeros((n, width, 128), np.float32)
    for i, d in enumerate(sampled):
        padded[i, : len(d)] = d
    stacked = padded.reshape(n * width, 128)
    shared = np.zeros((n, n))
    for i, d in enumerate(sampled):
        if not len(d):
            continue
        similarity = (d @ stacked.T).reshape(len(d), n, width)
        best = similarity.max(axis=2)
        np.put_along_axis(similarity, similarity.argmax(axis=2)[..., None], -1.0, axis=2)
        second = similarity.max(axis=2)
        # Unit descriptors: distance^2 = 2 - 2 similarity.
        passed = np.sqrt(np.maximum(2 - 2 * best, 0)) < RETRIEVAL_RATIO * np.sqrt(np.maximum(2 - 2 * second, 0))
        shared[i] = passed.sum(axis=0)
    shared += shared.T
    np.fill_diagonal(shared, -1)
    pairs: set[tuple[str, str]] = set()
    for i in range(n):
        partners = [j for j in np.argsort(-shared[i], kind="stable") if j != i]
        fresh = [j for j in partners if tuple(sorted((names[i], names[j]))) not in excluded]
        pairs |= {tuple(sorted((names[i], names[j]))) for j in fresh[:count] if shared[i, j] > 0}
    return pairs


STATIONARY_PX = 4.0
"""A still camera's matches that move this little (pixels) are of the still room or of
highlights that stay with the light, not of the turning specimen (COLMAP's default)."""

OUTLINE_SIZE = 64
"""Pixels along the longer side of the masks compared by outline_neighbours: the
outline's shape, not its pixel-level noise."""


def outline_neighbours(masks: list[Path], count: int, excluded: set[tuple[int, int]]) -> set[tuple[int, int]]:
    """Pairs (i, j), i < j, of each mask (in file order) with up to ``count`` others more
    like it than either of its neighbours in file order (by the mean difference of the
    masks shrunk to OUTLINE_SIZE), leaving out the ``excluded`` pairs. A retrieval by a
    global descriptor, as hloc's, for a fixed camera: another photo at the same angle
    shows the same outline, and the next photo's outline, one step of the turn away,
    says how alike is alike. A body that looks alike from opposite sides gives pairs
    whose matches no single turn explains, which the turntable's solver leaves out
    (pipeline.geometry.circular_motion)."""
    if count == 0 or len(masks) < 3:
        return set()
    shrunk = []
    for path in masks:
        mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255
        scale = OUTLINE_SIZE / max(mask.shape)
        size = (max(round(mask.shape[1] * scale), 1), max(round(mask.shape[0] * scale), 1))
        shrunk.append(cv2.resize(mask, size, interpolation=cv2.INTER_AREA).ravel())
    outlines = np.stack(shrunk)
    n = len(outlines)
    pairs: set[tuple[int, int]] = set()
    for i, outline in enumerate(outlines):
        difference = np.abs(outlines - outline).mean(axis=1)
        step = min(difference[(i - 1) % n], difference[(i + 1) % n])
        candidates = [
            j for j in np.argsort(difference, kind="stable") if j != i and (min(i, j), max(i, j)) not in excluded
        ]
        pairs |= {(min(i, int(j)), max(i, int(j))) for j in candidates[:count] if difference[j] < step}
    return pairs


def ring_pairs(
    photos: dict[str, dict], masks: dict[str, Path], neighbours: int, alike: int
) -> tuple[tuple[str, str], ...]:
    """A turntable's pairs to match: each photo with its ``neighbours`` following ones in
    file order, wrapping round, and with up to ``alike`` photos whose outlines look more
    like its own than its file-order neighbours' (outline_neighbours); as sorted pairs
    of the photos' file names."""
    order = sorted(photos, key=lambda name: Path(photos[name]["srgb"]).name)
    files = [Path(photos[name]["srgb"]).name for name in order]
    n = len(order)
    pairs = {tuple(sorted((i, (i + k) % n))) for i in range(n) for k in range(1, min(neighbours, n // 2) + 1)}
    pairs |= outline_neighbours([masks[name] for name in order], alike, pairs)
    return tuple(sorted(tuple(sorted((files[i], files[j]))) for i, j in pairs))


def unregistered_causes(database: Path, unregistered: list[str], stem_of: dict[str, str]) -> dict[str, str]:
    """Why each photo may have failed: few features, or few verified matches."""
    with pycolmap.Database.open(database) as db:
        images = {image.name: image.image_id for image in db.read_all_images()}
        best: dict[int, int] = {}
        for pair_id, geometry in zip(*db.read_two_view_geometries()):
            i, j = pycolmap.pair_id_to_image_pair(pair_id)
            inliers = len(geometry.inlier_matches)
            best[i], best[j] = max(best.get(i, 0), inliers), max(best.get(j, 0), inliers)
        causes = {}
        for name in unregistered:
            image_id = images[stem_of[name]]
            keypoints = db.num_keypoints_for_image(image_id)
            matches = best.get(image_id, 0)
            if keypoints < 300:
                causes[name] = f"{keypoints} features: blurred, low-texture or masked out"
            elif matches < 30:
                causes[name] = (
                    f"{keypoints} features but at most {matches} verified matches with any photo: "
                    "too little overlap, another scene, or a background that moved"
                )
            else:
                causes[name] = f"{matches} verified matches but no consistent pose: a repeated or moving pattern"
    return causes


def unverified_matches(
    database: Path, order: list[str], stem_of: dict[str, str], min_motion_px: float
) -> dict[tuple[str, str], dict[int, int]]:
    """The matches of each pair (a < b in ``order``) that two-view verification left
    without a geometry, those that moved ``min_motion_px`` or less left out (a still
    camera's highlights and room): a few dozen matches between photos of a plain specimen
    can fail a five-degree-of-freedom model and still fit a turntable's one turn, which
    pipeline.geometry.circular_motion tests them for."""
    index = {name: i for i, name in enumerate(order)}
    found = {}
    with pycolmap.Database.open(database) as db:
        name_of = {db.read_image_with_name(stem_of[name]).image_id: name for name in order}
        keypoints = {image_id: db.read_keypoints(image_id)[:, :2] for image_id in name_of}
        verified = {
            int(pair_id) for pair_id, geometry in zip(*db.read_two_view_geometries()) if len(geometry.inlier_matches)
        }
        for pair_id, pairs in zip(*db.read_all_matches()):
            if int(pair_id) in verified or len(pairs) == 0:
                continue
            ids = pycolmap.pair_id_to_image_pair(pair_id)
            pairs = np.asarray(pairs)
            moved = np.linalg.norm(keypoints[ids[0]][pairs[:, 0]] - keypoints[ids[1]][pairs[:, 1]], axis=1)
            pairs = pairs[moved > min_motion_px]
            a, b = (name_of[i] for i in ids)
            if index[a] > index[b]:
                a, b, pairs = b, a, pairs[:, ::-1]
            found[a, b] = dict(zip(pairs[:, 0].tolist(), pairs[:, 1].tolist()))
    return found


def verified_matches(database: Path, order: list[str], stem_of: dict[str, str]):
    """Keypoints per photo (our pixel convention) and the verified inlier matches per
    ordered photo pair, as {(a, b): {keypoint in a: keypoint in b}}."""
    keypoints, matches = {}, {}
    with pycolmap.Database.open(database) as db:
        name_of = {}
        for name in order:
            image_id = db.read_image_with_name(stem_of[name]).image_id
            name_of[image_id] = name
            keypoints[name] = db.read_keypoints(image_id)[:, :2] - COLMAP_PIXEL_OFFSET
        for pair_id, geometry in zip(*db.read_two_view_geometries()):
            pairs = np.asarray(geometry.inlier_matches)
            if len(pairs) == 0:
                continue
            a, b = (name_of[i] for i in pycolmap.pair_id_to_image_pair(pair_id))
            matches[a, b] = dict(zip(pairs[:, 0].tolist(), pairs[:, 1].tolist()))
            matches[b, a] = dict(zip(pairs[:, 1].tolist(), pairs[:, 0].tolist()))
    return keypoints, matches
