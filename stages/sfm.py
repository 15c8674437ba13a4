"""Stage sfm: camera poses of the undistorted photos, in a metric, upright world frame.

1. **Features**: SIFT (pycolmap, CPU) on undistort's 8-bit photos, each camera
   setting one COLMAP camera (SIMPLE_PINHOLE: undistorted, square pixels). Where
   features may come from is ``sfm.feature_mask``: for a turntable, only pixels
   that change between photos (what turns) plus the dilated specimen mask, so a
   still room cannot pull every pose towards "nothing moved".
2. **Matching**: exhaustive up to ``exhaustive_max_images`` photos, else sequential
   in file order with loop detection off (no vocabulary tree ships with pycolmap).
3. **Mapping**: incremental; a calibrated camera (board) stays fixed, a guessed
   one (EXIF, prior) has its focal length refined. The largest model is kept.
   Fewer than ``min_registered_fraction`` registered photos is an error that
   names the unregistered photos and the likely cause for each. A rerun gives
   the same model: photos are numbered in sorted order, RANSAC and the mapper
   are seeded, and bundle adjustment runs on one thread (COLMAP's defaults gave
   bird_volumetric rotation errors anywhere from 0.7 to 164 degrees).
4. **Turntable** (``capture.rig = "turntable"``): the poses are explained by one
   circle about one axis (pipeline.geometry.turntable), fitted to each photo's board pose
   (the board turns with the specimen) or else its SfM pose, poses off the circle
   dropped. SfM poses that disagree with the board's are not used at all: a plain
   specimen on a repetitive set makes COLMAP join photos wrongly. Photos without a
   pose get their angle from their verified feature matches with posed photos,
   else from their silhouette.
5. **World frame** (``frame``): from the ChArUco board when it is seen in at least
   three registered photos whose SfM centres agree with it (PnP per photo,
   similarity to the SfM centres; on a turntable the board poses alone do; metres,
   z up, origin at the board's centre as pipeline.camera.board.board_to_world); else from
   the turntable axis (up) and the table plane if one is found; else from a ground
   plane (the sparse points' dominant plane, lowered to where the points near the
   specimen end); else centred on where the cameras look, scaled to
   a median camera distance of 1, with z along the cameras' average up. Only the
   board gives metric scale; the stage says which frame it used.
6. **Silhouette check** (not on a turntable): a registered photo whose mask
   does not match the visual hull of the others seen from its pose is left out
   (``min_silhouette_iou``), as is a camera below the ground plane.

==================  =============================================================
output              content
==================  =============================================================
sparse/             the model in COLMAP's binary format (cameras.bin, images.bin,
                    points3D.bin, frames.bin, rigs.bin), in the world frame
cameras.json        pinhole intrinsics and pose per photo (pipeline.camera.model), with
                    the world frame's description; keyed by the original photo name
sfm.json            registered and unregistered photos (with causes), metrics,
                    board and turntable residuals
==================  =============================================================

Limitations: SIFT needs texture. A plain specimen on a plain set registers only
through the board (or, on a turntable, its matches on the table and silhouette;
the board's markers need about 10 px to decode, so below ~384 px wide a turntable
capture loses its board poses and accuracy: 0.5-2.4 degrees at 256x192). Without a board the scale
is arbitrary. A handheld photo SfM cannot register is dropped.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np
import pycolmap

from pipeline import logger
from pipeline.geometry import turntable
from pipeline.camera.board import BoardDetector, board_to_world
from pipeline.camera.model import Intrinsics, Pose, Similarity, rotation_angle_deg, similarity_umeyama, write_cameras
from pipeline.core.config import Range
from pipeline.core.errors import PipelineError
from pipeline.core.sections import BoardSection, CaptureSection
from pipeline.core.stage import Stage, StageInputs, StageResult
from pipeline.geometry.visual_hull import Grid, View, bounds, convergence_point, hull_field
from stages.masks import mask_files
from stages.undistort import photo_files

COLMAP_PIXEL_OFFSET = 0.5


@dataclass(frozen=True)
class Config:
    """Structure from motion with pycolmap, and the world frame."""

    max_features: Annotated[int, Range(256, 65536)] = 8192
    """Most SIFT features kept per photo."""
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
    revolution). auto: ring for a turntable, else exhaustive up to exhaustive_max_images
    photos and sequential beyond. Exhaustive matching of a turntable finds false pairs
    between opposite sides of a repetitive set (a checkerboard from 180 degrees away)."""
    exhaustive_max_images: Annotated[int, Range(2, None)] = 150
    """Largest capture matched exhaustively (pairs grow with the square of the count)."""
    sequential_overlap: Annotated[int, Range(1, None)] = 20
    """Sequential matching: each photo is matched with this many following ones."""
    ring_neighbours: Annotated[int, Range(1, None)] = 4
    """Ring matching: each photo is matched with this many following ones, cyclically."""
    min_pose_inliers: Annotated[int, Range(6, None)] = 15
    """2D-3D inliers a photo needs to be registered (COLMAP's default, 30, leaves out
    photos of low-texture specimens that share only a few dozen points)."""
    turntable_poses: Literal["model", "measured"] = "model"
    """Turntable: model puts every photo exactly on the fitted circle (the rig allows one
    angle per photo, so per-photo noise averages out); measured keeps the board or SfM
    pose of each photo that has one."""
    min_registered_fraction: Annotated[float, Range(0.0, 1.0)] = 0.5
    """Below this fraction of registered photos the stage fails; above, it warns."""
    frame: Literal["auto", "board", "turntable", "ground_plane", "normalised"] = "auto"
    """World frame source; auto tries them in this order. Forcing one that cannot be
    found is an error."""
    board_min_corners: Annotated[int, Range(4, None)] = 8
    """Board corners a photo needs for its board pose to count."""
    board_max_error_px: Annotated[float, Range(0.0, None, exclusive_lo=True)] = 2.0
    """Board poses with a larger RMS reprojection error are ignored (a misdetection)."""
    board_max_disagreement: Annotated[float, Range(0.0, 1.0, exclusive_lo=True)] = 0.02
    """SfM is aligned to the board only when their camera centres agree to this fraction
    of the camera's distance from the board (median over photos)."""
    min_silhouette_iou: Annotated[float, Range(0.0, 1.0)] = 0.2
    """A registered photo whose mask overlaps the visual hull of the consistent photos,
    seen from its pose, by less than this (IoU) is left out: SfM posed it wrongly. Wrong poses
    score near 0 (0.00-0.04 on bird_volumetric); right poses with masks that take in
    some of the table score 0.37-0.48 (porous cube), so the default sits between."""
    silhouette_resolution: Annotated[int, Range(16, 256)] = 64
    """Voxels along the hull's longest side used to place turntable photos by silhouette."""


def _feature_masks(
    conf: Config, rig: str, photos: dict[str, dict], masks: dict[str, Path], out_dir: Path
) -> Path | None:
    """Masks in COLMAP's convention (IMAGE.png.png, 0 = no features), or None."""
    mode = conf.feature_mask if conf.feature_mask != "auto" else ("moving" if rig == "turntable" else "everywhere")
    if mode == "everywhere":
        return None
    folder = out_dir / "feature_masks"
    folder.mkdir()
    moving: dict[str, np.ndarray] = {}
    if mode == "moving":
        for camera in {photo["camera"] for photo in photos.values()}:
            names = [n for n, p in photos.items() if p["camera"] == camera]
            stack = np.stack([cv2.imread(str(photos[n]["srgb"]), cv2.IMREAD_GRAYSCALE) for n in names]).astype(np.float32)
            still = np.median(stack, axis=0)
            difference = np.abs(stack - still)
            noise = max(1.4826 * float(np.median(difference)), 1.0)
            for name, diff in zip(names, difference):
                moving[name] = cv2.GaussianBlur(diff, (0, 0), 2.0) > 4 * noise
    for name, photo in photos.items():
        specimen = cv2.imread(str(masks[name]), cv2.IMREAD_GRAYSCALE) > 127
        h, w = specimen.shape
        radius = max(int(conf.mask_dilation * np.hypot(w, h)), 1)
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1,) * 2)
        allowed = cv2.dilate(specimen.astype(np.uint8), kernel) > 0
        if name in moving:
            allowed |= cv2.dilate(moving[name].astype(np.uint8), kernel) > 0
        cv2.imwrite(str(folder / f"{Path(photo['srgb']).name}.png"), allowed.astype(np.uint8) * 255)
    return folder


def _extract_and_match(conf: Config, rig: str, photos: dict[str, dict], cameras: list[dict],
                       mask_dir: Path | None, image_dir: Path, database: Path) -> None:  # fmt: skip
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = conf.max_features
    extraction.num_threads = -1
    pycolmap.Database.open(database).close()  # import_images needs the file to exist
    for index, camera in enumerate(cameras):
        names = [Path(p["srgb"]).name for p in photos.values() if p["camera"] == index]
        if not names:
            continue
        K = Intrinsics.from_json(camera["intrinsics"])
        reader = pycolmap.ImageReaderOptions()
        # One focal length: undistort makes square pixels, and refining keeps them.
        reader.camera_model = "SIMPLE_PINHOLE"
        # COLMAP puts the first pixel's centre at (0.5, 0.5), OpenCV and we at (0, 0).
        reader.camera_params = f"{K.fx},{K.cx + COLMAP_PIXEL_OFFSET},{K.cy + COLMAP_PIXEL_OFFSET}"
        if mask_dir is not None:
            reader.mask_path = str(mask_dir)
        # Extraction numbers photos in the order its threads finish, and matching
        # and mapping follow those numbers: importing them first, sorted, makes a
        # rerun give the same model (it gave rotation errors of 0.7 to 164 degrees).
        pycolmap.import_images(database, image_dir, camera_mode=pycolmap.CameraMode.SINGLE,
                               image_names=sorted(names), options=reader)  # fmt: skip
        pycolmap.extract_features(database, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction,
                                  device=pycolmap.Device.cpu)  # fmt: skip
    matcher = conf.matcher
    if matcher == "auto":
        matcher = "ring" if rig == "turntable" else "exhaustive" if len(photos) <= conf.exhaustive_max_images else "sequential"
    logger.info("%s matching of %d photos", matcher, len(photos))
    verification = pycolmap.TwoViewGeometryOptions()
    # A fixed camera sees the still room at the same pixels in every photo: matches
    # that do not move say nothing about the turning object.
    verification.filter_stationary_matches = rig == "turntable"
    # COLMAP seeds RANSAC from the clock by default: the same photos then give
    # different verified matches, and a different model, on every run.
    verification.ransac.random_seed = 0
    device = pycolmap.Device.cpu
    if matcher == "exhaustive":
        pycolmap.match_exhaustive(database, verification_options=verification, device=device)
    elif matcher == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = conf.sequential_overlap
        pycolmap.match_sequential(database, pairing_options=pairing, verification_options=verification, device=device)
    else:
        names = sorted(Path(p["srgb"]).name for p in photos.values())
        neighbours = min(conf.ring_neighbours, len(names) // 2)
        pairs = {tuple(sorted((names[i], names[(i + k) % len(names)])))
                 for i in range(len(names)) for k in range(1, neighbours + 1)}  # fmt: skip
        pairs_file = database.with_name("pairs.txt")
        pairs_file.write_text("".join(f"{a} {b}\n" for a, b in sorted(pairs)))
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = pairs_file
        pycolmap.match_image_pairs(database, pairing_options=pairing, verification_options=verification, device=device)


def _map(database: Path, image_dir: Path, work_dir: Path, refine_focal: bool,
         min_pose_inliers: int) -> pycolmap.Reconstruction | None:  # fmt: skip
    options = pycolmap.IncrementalPipelineOptions()
    options.mapper.abs_pose_min_num_inliers = min_pose_inliers
    options.ba_refine_focal_length = refine_focal
    options.ba_refine_principal_point = False
    options.ba_refine_extra_params = False
    options.random_seed = 0
    options.mapper.random_seed = 0
    # Ceres' threaded bundle adjustment sums in a varying order: poses then differ
    # between reruns by hundredths of a degree, enough to change every later stage.
    options.num_threads = 1
    models = pycolmap.incremental_mapping(database, image_dir, work_dir, options=options)
    return max(models.values(), key=lambda m: m.num_reg_images()) if models else None


def _unregistered_causes(database: Path, unregistered: list[str], stem_of: dict[str, str]) -> dict[str, str]:
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
                causes[name] = (f"{keypoints} features but at most {matches} verified matches with any photo: "
                                "too little overlap, another scene, or a background that moved")  # fmt: skip
            else:
                causes[name] = f"{matches} verified matches but no consistent pose: a repeated or moving pattern"
    return causes


def _board_poses(conf: Config, board: BoardSection, photos: dict[str, dict], intrinsics: dict[str, Intrinsics]):
    """World pose of every photo in which the board is found (pipeline.camera.board's frame)."""
    if board.kind == "none":
        return {}, {}
    detector = BoardDetector(board, conf.board_min_corners)
    B = board_to_world(board)
    poses, errors = {}, {}
    for name, photo in photos.items():
        gray = cv2.imread(str(photo["srgb"]), cv2.IMREAD_GRAYSCALE)
        detection = detector.detect(gray)
        if detection is None:
            continue
        K = intrinsics[name].K
        found, rvec, tvec = cv2.solvePnP(detection.object_points, detection.image_points, K, None,
                                         flags=cv2.SOLVEPNP_IPPE)  # fmt: skip
        if not found:
            continue
        rvec, tvec = cv2.solvePnPRefineLM(detection.object_points, detection.image_points, K, None, rvec, tvec)
        projected = cv2.projectPoints(detection.object_points, rvec, tvec, K, None)[0].reshape(-1, 2)
        rms = float(np.sqrt(np.mean(np.sum((projected - detection.image_points) ** 2, axis=1))))
        if rms > conf.board_max_error_px:
            continue
        R_board = cv2.Rodrigues(rvec)[0]
        R = R_board @ B[:3, :3].T
        poses[name] = Pose(R, tvec.ravel() - R @ B[:3, 3])
        errors[name] = rms
    return poses, errors


def _robust_similarity(source: dict[str, np.ndarray], target: dict[str, np.ndarray]) -> tuple[Similarity, dict]:
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
    return similarity, {"photos": len(names), "centre_residual_mm_median": 1000 * float(np.median([residuals[n] for n in names]))}


def _ground_plane(points: np.ndarray, centres: np.ndarray, looked_at: np.ndarray, scale: float,
                  rng=np.random.default_rng(0)):  # fmt: skip
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


def _frame_rotation(up: np.ndarray, forward_hint: np.ndarray) -> np.ndarray:
    """Rotation taking ``up`` to +z, with ``forward_hint`` (projected) to +x."""
    z = up / np.linalg.norm(up)
    x = forward_hint - z * (forward_hint @ z)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [1.0, 0, 0]) if abs(z[0]) < 0.9 else np.cross(z, [0, 1.0, 0])
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def _level_frame(origin: np.ndarray, up: np.ndarray, poses: dict[str, Pose]) -> Similarity:
    """Up to +z, origin to 0, median camera distance to 1."""
    centres = np.array([p.center for p in poses.values()])
    R = _frame_rotation(up, centres[0] - origin)
    scale = 1.0 / float(np.median(np.linalg.norm(centres - origin, axis=1)))
    return Similarity(scale, R, -scale * R @ origin)


def main(conf: Config, inputs: StageInputs, out_dir: Path) -> StageResult:
    capture: CaptureSection = inputs.shared["capture"]
    board: BoardSection = inputs.shared["board"]
    pinhole_json = inputs.upstream["undistort"]["pinhole"]
    cameras = json.loads(pinhole_json.read_text())["cameras"]
    photos = json.loads(pinhole_json.read_text())["images"]
    photo_paths = photo_files(pinhole_json, "images")
    masks = mask_files(inputs.upstream["masks"]["masks_json"])
    order = sorted(photos)
    stem_of = {name: Path(photo_paths[name]["srgb"]).name for name in order}
    name_of = {stem: name for name, stem in stem_of.items()}
    intrinsics = {name: Intrinsics.from_json(cameras[photos[name]["camera"]]["intrinsics"]) for name in order}
    image_dir = photo_paths[order[0]]["srgb"].parent

    work = out_dir / "colmap"
    work.mkdir()
    mask_dir = _feature_masks(conf, capture.rig, photo_paths, masks, work)
    database = work / "database.db"
    _extract_and_match(conf, capture.rig, photo_paths, cameras, mask_dir, image_dir, database)
    refine_focal = any(c["source"] != "board" for c in cameras)
    model = _map(database, image_dir, work / "models", refine_focal, conf.min_pose_inliers)
    registered = {} if model is None else {name_of[im.name]: im for im in model.images.values() if im.has_pose}
    unregistered = [n for n in order if n not in registered]
    causes = _unregistered_causes(database, unregistered, stem_of) if unregistered else {}
    board_poses, board_errors = _board_poses(conf, board, photo_paths, intrinsics)
    # On a turntable the board turns with the specimen, so a board pose is as good
    # as a registration, and SfM may fail on a plain specimen.
    # A board pose is as good as a registration (in the board frame), and SfM may
    # fail on a plain specimen.
    posed = set(registered) | set(board_poses)
    if len(posed) < conf.min_registered_fraction * len(order):
        _too_few(conf, posed, order, causes)
    poses = {}
    for name, image in registered.items():
        rigid = image.cam_from_world()
        poses[name] = Pose(np.asarray(rigid.rotation.matrix()), np.asarray(rigid.translation))
        if refine_focal:
            focal, cx, cy = image.camera.params
            K = intrinsics[name]
            intrinsics[name] = Intrinsics(K.width, K.height, float(focal), float(focal),
                                          float(cx) - COLMAP_PIXEL_OFFSET, float(cy) - COLMAP_PIXEL_OFFSET)  # fmt: skip
    points = np.array([p.xyz for p in model.points3D.values()]) if model is not None else np.zeros((0, 3))
    report: dict = {"registered": len(registered), "photos": len(order), "unregistered": causes,
                    "mean_reprojection_error_px": model.compute_mean_reprojection_error() if model else None,
                    "mean_track_length": model.compute_mean_track_length() if model else None,
                    "points": len(points)}  # fmt: skip

    frame = _frame_from_board(conf, board_poses, poses, report)
    if frame is not None:
        poses = {n: frame.pose(p) for n, p in poses.items()}
        points = frame.points(points) if len(points) else points
        report["replaced_by_board"] = _replace_by_board(conf, poses, board_poses)
    elif len(board_poses) >= 3 and conf.frame in ("auto", "board"):
        # The board poses alone define the world; SfM's model, not tied to them, is dropped.
        logger.warning("SfM's %d photos could not be tied to the board: using the board poses alone", len(poses))
        frame, model, poses, points = Similarity.identity(), None, {}, np.zeros((0, 3))
        report["frame"] = {"source": "board", "metric": True, "units": "metres", "up": "+z, normal to the board",
                           "ground_plane": [0.0, 0.0, 1.0, 0.0], "photos": len(board_poses)}  # fmt: skip
    to_world = frame or Similarity.identity()
    if frame is not None and capture.rig != "turntable":
        report["posed_by_board"] = sorted(set(board_poses) - set(poses))
        poses |= {n: board_poses[n] for n in report["posed_by_board"]}

    table = None
    if capture.rig == "turntable":
        measured = {"board": board_poses if frame is not None else {}, "sfm": poses}
        table, poses, report["turntable"] = _turntable_poses(conf, order, measured, intrinsics, masks, database,
                                                             stem_of)  # fmt: skip
    if frame is None:
        level = _frame_without_board(conf, poses, points, table, report)
        poses = {n: level.pose(p) for n, p in poses.items()}
        points = level.points(points) if len(points) else points
        to_world = to_world.then(level)
    if capture.rig != "turntable" and len(poses) >= 3:
        mask_of = {n: cv2.imread(str(masks[n]), cv2.IMREAD_GRAYSCALE) > 127 for n in poses}
        report["silhouette_iou"], off = silhouette_check(conf, poses, intrinsics, mask_of)
        for name in off:
            logger.warning("%s: its silhouette does not match the hull of the other photos at SfM's pose (IoU %.2f "
                           "< sfm.min_silhouette_iou = %.2f); leaving the photo out", name,
                           report["silhouette_iou"][name], conf.min_silhouette_iou)  # fmt: skip
            del poses[name]
    if report["frame"].get("ground_plane") is not None:
        # The world's z = 0 is the table: a camera below it cannot see the specimen on
        # it. SfM does this to a view of a plain, symmetric specimen it mirrors.
        report["below_ground"] = sorted(n for n, p in poses.items() if p.center[2] < 0)
        for name in report["below_ground"]:
            logger.warning("%s: SfM put the camera below the table (z = %.3f); leaving the photo out", name,
                           poses.pop(name).center[2])  # fmt: skip
    if len(poses) < conf.min_registered_fraction * len(order):
        _too_few(conf, set(poses), order, causes)
    if len(poses) < len(order):
        logger.warning("%d of %d photos are not registered and are left out: %s", len(order) - len(poses),
                       len(order), ", ".join(n for n in order if n not in poses))  # fmt: skip

    sparse = _write_colmap(model, database, to_world, poses, stem_of, out_dir / "sparse")
    cameras_json = out_dir / "cameras.json"
    write_cameras(cameras_json, {n: intrinsics[n] for n in poses}, poses, frame=report["frame"])
    report["board_reprojection_px"] = board_errors
    sfm_json = out_dir / "sfm.json"
    sfm_json.write_text(json.dumps(report, indent=1))
    shutil.rmtree(work / "models")
    metrics = {k: report[k] for k in ("registered", "photos", "mean_reprojection_error_px", "mean_track_length")}
    metrics["frame"] = report["frame"]["source"]
    return StageResult({"cameras": cameras_json, "sparse": sparse, "report": sfm_json}, metrics)


def _turntable_poses(conf: Config, order: list[str], measured: dict[str, dict[str, Pose]],
                     intrinsics: dict[str, Intrinsics], masks: dict[str, Path], database: Path,
                     stem_of: dict[str, str]):  # fmt: skip
    """The turntable fitted to the measured poses (per photo its board pose, else its
    SfM pose; a board turns with the specimen and does not depend on SfM's luck with
    a plain specimen), and a pose for every photo: a measured one the model agrees
    with, else its angle from feature matches with posed photos, else from its
    silhouette. Returns (model, poses, report)."""
    first_choice = measured["sfm"] | measured["board"]
    if len(first_choice) < 3:
        raise PipelineError(f"only {len(first_choice)} photos registered: a turntable needs three to find its axis")
    table, off_circle = turntable.fit_robust(first_choice, order)
    fitted = {n: p for n, p in first_choice.items() if n not in off_circle}
    limit = max(3 * float(np.median([r for r, _ in table.residuals(fitted).values()])), 1.0)
    method = {n: "board" if n in measured["board"] else "sfm" for n in fitted}
    poses = dict(fitted)
    for name in order:
        for source in ("board", "sfm"):
            pose = measured[source].get(name)
            if name in poses or pose is None:
                continue
            angle = table.angle_of(pose)
            rotation, centre = table.residuals_at(pose, angle)
            if rotation <= limit and centre <= 0.1:
                table.angles[name], poses[name], method[name] = angle, pose, source
    for name in off_circle:
        logger.warning("%s: its measured pose is off the turntable's circle", name)
    missing = [n for n in order if n not in poses]
    by_matches = _place_by_matches(conf, table, order, missing, poses, intrinsics, database, stem_of)
    missing = [n for n in missing if n not in by_matches]
    by_silhouette = _place_by_silhouette(conf, table, order, missing, poses, intrinsics, masks) if missing else {}
    placed = by_matches | by_silhouette
    method |= {n: "matches" for n in by_matches} | {n: "silhouette" for n in by_silhouette}
    report = {
        "off_circle": off_circle,
        "pose_source": {source: sorted(n for n in method if method[n] == source)
                        for source in ("board", "sfm", "matches", "silhouette")},  # fmt: skip
        "rotation_residual_deg_max": max(r for r, _ in table.residuals(fitted).values()),
        "centre_residual_of_radius_max": max(c for _, c in table.residuals(fitted).values()),
        "placed": placed,
    }
    poses |= {n: table.pose(table.angles[n]) for n in placed}
    if conf.turntable_poses == "model":
        poses = {n: table.pose(table.angles[n]) for n in poses}
    return table, poses, report


def _verified_matches(database: Path, order: list[str], stem_of: dict[str, str]):
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


def _place_by_matches(conf: Config, table: turntable.Turntable, order: list[str], missing: list[str],
                      poses: dict[str, Pose], intrinsics: dict[str, Intrinsics], database: Path,
                      stem_of: dict[str, str]) -> dict[str, dict]:  # fmt: skip
    """Angles for photos with at least ``min_pose_inliers`` verified matches with
    posed photos that agree on one angle (recorded in ``table.angles``)."""
    keypoints, matches = _verified_matches(database, order, stem_of)
    placed = {}
    for name in missing:
        partners = []
        for partner in poses:
            pairs = matches.get((name, partner))
            if pairs:
                mine, theirs = (np.array(side) for side in zip(*pairs.items()))
                partners.append(turntable.Matches(poses[partner], intrinsics[partner], keypoints[name][mine],
                                                  keypoints[partner][theirs]))  # fmt: skip
        if sum(len(m.points) for m in partners) < conf.min_pose_inliers:
            continue
        low, high = turntable.bracket(table, order, name)
        angle, agreeing = turntable.angle_from_matches(table, low, high, intrinsics[name], partners)
        supporting = sum(len(m.points) for m in agreeing)
        if supporting < conf.min_pose_inliers:
            logger.info("%s: no posed photo's matches agree on an angle; trying its silhouette", name)
            continue
        table.angles[name] = angle
        placed[name] = {"method": "matches", "angle_deg": float(np.degrees(angle)), "matches": supporting,
                        "partners": len(agreeing), "partners_dropped": len(partners) - len(agreeing)}  # fmt: skip
        logger.info("%s placed on the turntable at %.2f degrees by its feature matches (posed photos: %d agree, "
                    "%d disagree)", name, placed[name]["angle_deg"], len(agreeing),
                    placed[name]["partners_dropped"])  # fmt: skip
    return placed


def _place_by_silhouette(conf: Config, table: turntable.Turntable, order: list[str], missing: list[str],
                         poses: dict[str, Pose], intrinsics: dict[str, Intrinsics],
                         masks: dict[str, Path]) -> dict[str, dict]:  # fmt: skip
    """Angles for the ``missing`` photos from their silhouettes against the hull of
    the posed photos (recorded in ``table.angles``)."""
    placed: dict[str, dict] = {}
    mask_of = {n: cv2.imread(str(masks[n]), cv2.IMREAD_GRAYSCALE) > 127 for n in order}
    try:
        hull_points, voxel = _hull_points(conf, [n for n in order if n in poses], poses, intrinsics, mask_of)
    except ValueError as error:
        raise PipelineError(f"cannot place {', '.join(missing)} on the turntable by silhouette: {error}") from error
    for name in missing:
        low, high = turntable.bracket(table, order, name)
        angle, iou = turntable.angle_from_silhouette(table, low, high, hull_points, voxel,
                                                     intrinsics[name], mask_of[name])  # fmt: skip
        table.angles[name] = angle
        placed[name] = {"method": "silhouette", "angle_deg": float(np.degrees(angle)), "silhouette_iou": iou}
        log = logger.warning if iou < 0.8 else logger.info
        log("%s placed on the turntable by its silhouette at %.2f degrees (IoU %.3f%s)", name,
            placed[name]["angle_deg"], iou, ", unreliable" if iou < 0.8 else "")  # fmt: skip
    return placed


def _write_colmap(model: pycolmap.Reconstruction | None, database: Path, to_world: Similarity, poses: dict[str, Pose],
                  stem_of: dict[str, str], folder: Path) -> Path:  # fmt: skip
    """The model in the world frame with the final poses (turntable-placed photos
    registered too, without observations), in COLMAP's binary format. The points
    stay where SfM triangulated them."""
    if model is None:  # SfM failed or disagreed with the board: cameras and poses only
        model = pycolmap.Reconstruction()
    model.transform(pycolmap.Sim3d(to_world.scale, pycolmap.Rotation3d(to_world.R), to_world.t))
    with pycolmap.Database.open(database) as db:
        for name, pose in poses.items():
            rigid = pycolmap.Rigid3d(pycolmap.Rotation3d(pose.R), pose.t)
            image = model.find_image_with_name(stem_of[name])
            if image is not None:
                model.frame(image.frame_id).rig_from_world = rigid
                continue
            stored = db.read_image_with_name(stem_of[name])
            if not model.exists_camera(stored.camera_id):
                model.add_camera_with_trivial_rig(db.read_camera(stored.camera_id))
            model.add_image_with_trivial_frame(
                pycolmap.Image(name=stored.name, camera_id=stored.camera_id, image_id=stored.image_id), rigid
            )
    folder.mkdir()
    model.write_binary(folder)
    return folder


def _frame_from_board(conf: Config, board_poses: dict[str, Pose], poses: dict[str, Pose], report: dict):
    common = set(board_poses) & set(poses)
    if conf.frame not in ("auto", "board") or len(common) < 3:
        return None
    frame, fit = _robust_similarity({n: poses[n].center for n in common}, {n: board_poses[n].center for n in common})
    distance = float(np.median([np.linalg.norm(board_poses[n].center) for n in common]))
    if fit["centre_residual_mm_median"] / 1000 > conf.board_max_disagreement * distance:
        # SfM and the board tell different stories: SfM joined photos wrongly
        # (a repetitive set) or the board moved against the specimen.
        logger.warning("SfM's camera centres and the board's disagree by %.1f mm (median; %.0f mm from the board): "
                       "not aligning SfM to the board", fit["centre_residual_mm_median"], 1000 * distance)  # fmt: skip
        return None
    report["frame"] = {"source": "board", "metric": True, "units": "metres", "up": "+z, normal to the board",
                       "ground_plane": [0.0, 0.0, 1.0, 0.0], **fit}  # fmt: skip
    logger.info("world frame from the board in %d photos (centres agree to %.2f mm)", fit["photos"],
                fit["centre_residual_mm_median"])  # fmt: skip
    return frame


def _too_few(conf: Config, posed: set[str], order: list[str], causes: dict[str, str]) -> None:
    listing = "; ".join(f"{n}: {causes.get(n, 'a pose SfM got wrong (see the warnings above)')}"
                        for n in order if n not in posed)  # fmt: skip
    raise PipelineError(
        f"only {len(posed)} of {len(order)} photos registered (sfm.min_registered_fraction = "
        f"{conf.min_registered_fraction}). Unregistered: {listing}. "
        "Check them with `pipeline check`; add texture or a board near the specimen, or reshoot with more overlap"
    )


def _hull_points(conf: Config, names: list[str], poses: dict[str, Pose], intrinsics: dict[str, Intrinsics],
                 mask_of: dict[str, np.ndarray], tolerance: int = 1) -> tuple[np.ndarray, float]:  # fmt: skip
    """Voxel centres inside the visual hull of the posed ``names`` (``tolerance``
    photos may disagree), and the voxel size. ValueError when the silhouettes do not meet."""
    views = [View(intrinsics[n], poses[n], mask_of[n]) for n in names]
    lo, hi = bounds(views, tolerance)
    grid = Grid.around(lo, hi, conf.silhouette_resolution)
    centres = grid.centres()
    return centres[hull_field(centres, views, tolerance) > 0], grid.voxel


def silhouette_check(conf: Config, poses: dict[str, Pose], intrinsics: dict[str, Intrinsics],
                     mask_of: dict[str, np.ndarray]) -> tuple[dict[str, float], list[str]]:  # fmt: skip
    """Each photo's mask against the visual hull of the posed photos seen from its pose
    (IoU), and the photos below ``min_silhouette_iou``: a pose SfM got wrong shows the
    specimen where it is not.

    Two passes. The first hull lets a fifth of the photos disagree, so that several
    wrong poses neither carve it away nor leave no hull at all (two photos posed 164
    and 42 degrees off did that to the strict hull on bird_volumetric); it finds the
    outliers. The second, the hull of the rest letting one disagree, gives the
    scores. Returns ({}, []) when even the first has no inside (the mesh stage then
    says so)."""
    names = sorted(poses)
    consistent = names
    for tolerance in (max(1, len(names) // 5), 1):
        try:
            hull_points, voxel = _hull_points(conf, consistent, poses, intrinsics, mask_of, tolerance)
        except ValueError as error:
            logger.warning("cannot check the poses against the silhouettes: %s", error)
            return {}, []
        scores = {}
        for name in names:
            depth = np.linalg.norm(poses[name].center - hull_points.mean(axis=0))
            radius = turntable.splat_radius(voxel, intrinsics[name], depth)
            scores[name] = turntable.silhouette_iou(hull_points, radius, poses[name], intrinsics[name], mask_of[name])
        consistent = [n for n in names if scores[n] >= conf.min_silhouette_iou]
        if len(consistent) < 3:
            logger.warning("fewer than three photos agree with the visual hull: not checking the poses")
            return scores, []
    return scores, [n for n in names if scores[n] < conf.min_silhouette_iou]


def _replace_by_board(conf: Config, poses: dict[str, Pose], board_poses: dict[str, Pose]) -> list[str]:
    """Photos whose SfM pose, in the board frame, contradicts their own board pose
    (SfM placed them wrongly on a plain or symmetric specimen: a view from behind
    registered as one from the front) take the board pose. Returns their names."""
    replaced = []
    for name in sorted(set(poses) & set(board_poses)):
        sfm, board = poses[name], board_poses[name]
        rotation = rotation_angle_deg(sfm.R @ board.R.T)
        distance = np.linalg.norm(sfm.center - board.center) / np.linalg.norm(board.center)
        if rotation > 2.0 or distance > conf.board_max_disagreement:
            logger.warning("%s: SfM's pose is %.1f degrees and %.1f %% of the distance from its board pose; "
                           "using the board pose", name, rotation, 100 * distance)  # fmt: skip
            poses[name] = board
            replaced.append(name)
    return replaced


def _frame_without_board(conf: Config, poses: dict[str, Pose], points: np.ndarray,
                         table: turntable.Turntable | None, report: dict) -> Similarity:  # fmt: skip
    if conf.frame == "board":
        raise PipelineError("sfm.frame = 'board' but the board was not found in three registered photos, or SfM "
                            "disagrees with it (see the log): check [board], or set sfm.frame = 'auto'")  # fmt: skip
    centres = np.array([p.center for p in poses.values()])
    spread = float(np.median(np.linalg.norm(centres - centres.mean(axis=0), axis=1)))
    looked_at = convergence_point(poses.values())
    plane = _ground_plane(points, centres, looked_at, spread) if conf.frame != "normalised" else None
    if table is not None and conf.frame in ("auto", "turntable"):
        up = table.axis if (centres.mean(axis=0) - table.point) @ table.axis >= 0 else -table.axis
        if plane is not None and abs(plane[0] @ up) > np.cos(np.radians(10)):
            # The axis meets the table plane: the natural origin.
            origin = table.point - up * ((plane[0] @ table.point + plane[1]) / (plane[0] @ up))
        else:
            plane = None
            origin = table.point
        source = "turntable"
    elif plane is not None and conf.frame in ("auto", "ground_plane"):
        up = plane[0]
        origin = looked_at - up * (up @ looked_at + plane[1])
        source = "ground_plane"
    elif conf.frame in ("auto", "normalised"):
        up = -np.mean([p.R[1] for p in poses.values()], axis=0)
        origin = convergence_point(poses.values())
        plane = None
        source = "normalised"
    else:
        raise PipelineError(f"sfm.frame = '{conf.frame}' could not be established: set sfm.frame = 'auto'")
    level = _level_frame(origin, up, poses)
    # The origin was put on the table plane when there is one: it becomes z = 0.
    ground = [0.0, 0.0, 1.0, 0.0] if plane is not None else None
    report["frame"] = {"source": source, "metric": False, "units": "median camera distance = 1",
                       "up": "+z", "ground_plane": ground}  # fmt: skip
    logger.warning("no board seen: world frame from %s, scale normalised (not metric)", source.replace("_", " "))
    return level


STAGE = Stage(
    name="sfm",
    version=5,
    config=Config,
    main=main,
    upstream=("undistort", "masks"),
    shared=("capture", "board"),
    exports=("cameras",),
)
