"""COLMAP through pycolmap: features, matching, incremental mapping, the database's
verified matches, writing a model, and screened Poisson meshing.

pycolmap 4.2's CPU wheel: no dense stereo, no Delaunay meshing. Every call is
made deterministic: photos are imported in sorted order, RANSAC and the mapper
are seeded, and bundle adjustment and Poisson run on one thread (COLMAP's
defaults gave bird_volumetric rotation errors anywhere from 0.7 to 164 degrees
between reruns). COLMAP puts the first pixel's centre at (0.5, 0.5), OpenCV and
this package at (0, 0): ``COLMAP_PIXEL_OFFSET`` converts.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np
import pycolmap
import trimesh

from pipeline import logger
from pipeline.camera.model import Intrinsics, Pose, Similarity
from pipeline.camera.self_calibration import SelfCalibrationSettings, corner_radius, frame_coverage, radial_shift_px
from pipeline.core.config import Range
from pipeline.core.interrupts import after_native_import

after_native_import()  # glog's handlers, installed as pycolmap loads, print stack dumps
# COLMAP logs every step of every photo at INFO, hundreds of lines a run: only its
# warnings are shown, unless GLOG_minloglevel says otherwise (`pipeline -v` sets it to 0).
pycolmap.logging.minloglevel = int(os.environ.get("GLOG_minloglevel", pycolmap.logging.WARNING.value))

COLMAP_PIXEL_OFFSET = 0.5


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
            stack = np.stack([cv2.imread(str(photos[n]["srgb"]), cv2.IMREAD_GRAYSCALE) for n in names]).astype(
                np.float32
            )
            still = np.median(stack, axis=0)
            difference = np.abs(stack - still)
            noise = max(1.4826 * float(np.median(difference)), 1.0)
            for name, diff in zip(names, difference):
                moving[name] = cv2.GaussianBlur(diff, (0, 0), 2.0) > 4 * noise
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
    revolution). auto: ring for a turntable, else exhaustive up to exhaustive_max_images
    photos and sequential beyond (a ring rig's photos need not be in order). Exhaustive
    matching of a turntable finds false pairs between opposite sides of a repetitive set
    (a checkerboard from 180 degrees away)."""
    exhaustive_max_images: Annotated[int, Range(2, None)] = 150
    """Largest capture matched exhaustively (pairs grow with the square of the count)."""
    sequential_overlap: Annotated[int, Range(1, None)] = 20
    """Sequential matching: each photo is matched with this many following ones."""
    ring_neighbours: Annotated[int, Range(1, None)] = 6
    """Ring matching: each photo is matched with this many following ones, cyclically."""


def features_and_matches(
    settings: FeatureSettings,
    rig: str,
    photos: dict[str, dict],
    cameras: list[dict],
    masks: dict[str, Path],
    work: Path,
) -> Path:
    """SIFT features and verified matches of every photo (undistort's ``{"srgb": PNG}``)
    in a new COLMAP database in ``work``, the settings' "auto" choices made for ``rig``."""
    mode = settings.feature_mask
    if mode == "auto":
        mode = "moving" if rig == "turntable" else "everywhere"
    matcher = settings.matcher
    if matcher == "auto":
        exhaustive = len(photos) <= settings.exhaustive_max_images
        matcher = "ring" if rig == "turntable" else "exhaustive" if exhaustive else "sequential"
    longest = max(max(c["intrinsics"]["width"], c["intrinsics"]["height"]) for c in cameras)
    small = longest < settings.small_photo_px
    database = work / "database.db"
    _extract_and_match(
        photos,
        cameras,
        feature_masks(mode, settings.mask_dilation, photos, masks, work),
        next(iter(photos.values()))["srgb"].parent,
        database,
        settings.max_features,
        upsample=settings.upsample == "yes" or (settings.upsample == "auto" and small),
        domain_size_pooling=settings.dsp_sift == "yes" or (settings.dsp_sift == "auto" and small),
        matcher=matcher,
        sequential_overlap=settings.sequential_overlap,
        ring_neighbours=settings.ring_neighbours,
        still_camera=rig == "turntable",
    )
    return database


def _extract_and_match(
    photos: dict[str, dict],
    cameras: list[dict],
    mask_dir: Path | None,
    image_dir: Path,
    database: Path,
    max_features: int,
    upsample: bool,
    domain_size_pooling: bool,
    matcher: str,
    sequential_overlap: int,
    ring_neighbours: int,
    still_camera: bool,
) -> None:
    """SIFT features of every photo (one SIMPLE_RADIAL COLMAP camera per camera
    setting, its distortion 0 until self-calibration; ``upsample``: from twice the
    resolution; ``domain_size_pooling``: DSP-SIFT descriptors), matched
    ``matcher``-wise (exhaustive, sequential or ring) and verified with seeded RANSAC;
    ``still_camera`` drops matches that do not move (a turntable's room)."""
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = max_features
    extraction.sift.first_octave = -1 if upsample else 0
    extraction.sift.domain_size_pooling = domain_size_pooling
    extraction.num_threads = -1
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
        if mask_dir is not None:
            reader.mask_path = str(mask_dir)
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
    _match(photos, database, matcher, sequential_overlap, ring_neighbours, still_camera)


def _match(
    photos: dict[str, dict],
    database: Path,
    matcher: str,
    sequential_overlap: int,
    ring_neighbours: int,
    still_camera: bool,
) -> None:
    logger.info("%s matching of %d photos", matcher, len(photos))
    verification = pycolmap.TwoViewGeometryOptions()
    # A fixed camera sees the still room at the same pixels in every photo: matches
    # that do not move say nothing about the turning object.
    verification.filter_stationary_matches = still_camera
    # COLMAP seeds RANSAC from the clock by default: the same photos then give
    # different verified matches, and a different model, on every run.
    verification.ransac.random_seed = 0
    matching = pycolmap.FeatureMatchingOptions()
    # The CPU matcher's approximate nearest-neighbour search gives other matches when
    # its threads interleave differently (seen on a loaded machine): one thread keeps
    # reruns identical for about twice the matching time (3 s for the bird's 30 photos).
    matching.num_threads = 1
    device = pycolmap.Device.cpu
    if matcher == "exhaustive":
        pycolmap.match_exhaustive(database, matching, verification_options=verification, device=device)
    elif matcher == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = sequential_overlap
        pycolmap.match_sequential(
            database, matching, pairing_options=pairing, verification_options=verification, device=device
        )
    else:
        names = sorted(Path(p["srgb"]).name for p in photos.values())
        neighbours = min(ring_neighbours, len(names) // 2)
        pairs = {
            tuple(sorted((names[i], names[(i + k) % len(names)])))
            for i in range(len(names))
            for k in range(1, neighbours + 1)
        }
        pairs_file = database.with_name("pairs.txt")
        pairs_file.write_text("".join(f"{a} {b}\n" for a, b in sorted(pairs)))
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = pairs_file
        pycolmap.match_image_pairs(
            database, matching, pairing_options=pairing, verification_options=verification, device=device
        )


def incremental_map(
    database: Path, image_dir: Path, work_dir: Path, refine_focal: bool, min_pose_inliers: int
) -> pycolmap.Reconstruction | None:
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


def self_calibrate(model: pycolmap.Reconstruction, settings: SelfCalibrationSettings) -> dict:
    """Principal point and radial distortion (k1) of each camera of ``model`` adjusted
    in a global bundle adjustment, each kept only when the photos constrain it
    (pipeline.camera.self_calibration: COLMAP's covariance estimate for the standard
    deviation); what is not kept is reset and the adjustment run again without it.
    Returns the report per camera: coverage, what was tried, what was held and why,
    and each parameter's final value and standard deviation."""
    report = {}
    for camera_id, camera in model.cameras.items():
        images = [im for im in model.images.values() if im.has_pose and im.camera_id == camera_id]
        pixels = np.array([p.xy for im in images for p in im.points2D if p.has_point3D()]).reshape(-1, 2)
        coverage = frame_coverage(pixels, camera.width, camera.height)
        entry: dict = {"frame_coverage": round(coverage, 3)}
        free = {"principal_point": False, "k1": False}
        if coverage < settings.min_frame_coverage:
            entry["skipped"] = (
                f"observations cover {coverage:.0%} of the frame (< {settings.min_frame_coverage:.0%}): "
                "principal point and distortion are not constrained"
            )
        else:
            before = np.array(camera.params)
            std = _bundle_adjust(model, refine_principal_point=True, refine_extra=True)[camera_id]
            focal, cx, cy, k1 = camera.params
            radius = corner_radius(camera.width, camera.height, focal, cx, cy)
            displacement = {"principal_point": float(max(std[1], std[2])), "k1": radial_shift_px(std[3], focal, radius)}
            entry["tried"] = {"cx": float(cx - COLMAP_PIXEL_OFFSET), "cy": float(cy - COLMAP_PIXEL_OFFSET), "k1": k1}
            entry["std_px"] = {name: round(value, 3) for name, value in displacement.items()}
            free = {name: value <= settings.max_calibration_std_px for name, value in displacement.items()}
            entry["held"] = {
                name: f"its standard deviation moves points by {displacement[name]:.2f} px "
                f"(> sfm.max_calibration_std_px = {settings.max_calibration_std_px})"
                for name, adjusted in free.items()
                if not adjusted
            }
            if not all(free.values()):
                params = np.array(camera.params)
                params[1:3] = params[1:3] if free["principal_point"] else before[1:3]
                params[3] = params[3] if free["k1"] else 0.0
                camera.params = params
                _bundle_adjust(model, free["principal_point"], free["k1"])
        std = _bundle_adjust(model, free["principal_point"], free["k1"], solve=False)[camera_id]
        values = np.array(camera.params) - [0, COLMAP_PIXEL_OFFSET, COLMAP_PIXEL_OFFSET, 0]
        adjusted = [True, free["principal_point"], free["principal_point"], free["k1"]]
        entry["values"] = {
            name: {"value": float(values[i]), "std": float(std[i]) if adjusted[i] else None, "adjusted": adjusted[i]}
            for i, name in enumerate(("f", "cx", "cy", "k1"))
        }
        report[str(camera_id)] = entry
    return report


def _bundle_adjust(
    model: pycolmap.Reconstruction, refine_principal_point: bool, refine_extra: bool, solve: bool = True
) -> dict[int, np.ndarray]:
    """A global bundle adjustment (focal length always refined; on one thread, as the
    mapper's) and the standard deviation of each camera's parameters, in COLMAP's
    order, 0 for those held fixed."""
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = True
    options.refine_principal_point = refine_principal_point
    options.refine_extra_params = refine_extra
    options.print_summary = False
    options.ceres.solver_options.num_threads = 1
    config = pycolmap.BundleAdjustmentConfig()
    for image in model.images.values():
        if image.has_pose:
            config.add_image(image.image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.THREE_POINTS)
    adjuster = pycolmap.create_default_ceres_bundle_adjuster(options, config, model)
    if solve:
        adjuster.solve()
    covariance = pycolmap.estimate_ba_covariance(pycolmap.BACovarianceOptions(), model, adjuster)
    free = [True, refine_principal_point, refine_principal_point, refine_extra]
    std = {}
    for camera_id, camera in model.cameras.items():
        values = np.zeros(len(camera.params))
        block = covariance.get_other_params_cov(camera.params) if covariance is not None else None
        if block is not None:
            values[np.flatnonzero(free)] = np.sqrt(np.maximum(np.diag(block), 0))
        std[camera_id] = values
    return std


def model_metrics(model: pycolmap.Reconstruction | None) -> dict:
    """The model's mean reprojection error (pixels) and mean track length (None without a model)."""
    if model is None:
        return {"mean_reprojection_error_px": None, "mean_track_length": None}
    return {
        "mean_reprojection_error_px": model.compute_mean_reprojection_error(),
        "mean_track_length": model.compute_mean_track_length(),
    }


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


def write_model(
    model: pycolmap.Reconstruction | None,
    database: Path,
    to_world: Similarity,
    poses: dict[str, Pose],
    stem_of: dict[str, str],
    folder: Path,
) -> Path:
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


def model_from_poses(
    intrinsics: dict[str, Intrinsics], poses: dict[str, Pose], stem_of: dict[str, str], folder: Path
) -> Path:
    """A COLMAP model holding only cameras and poses (cameras another tool made), in
    COLMAP's binary format: one PINHOLE camera per distinct intrinsics."""
    model = pycolmap.Reconstruction()
    camera_ids: dict[tuple, int] = {}
    for image_id, (name, pose) in enumerate(sorted(poses.items()), start=1):
        K = intrinsics[name]
        params = (K.fx, K.fy, K.cx + COLMAP_PIXEL_OFFSET, K.cy + COLMAP_PIXEL_OFFSET)
        key = (K.width, K.height, *params)
        if key not in camera_ids:
            camera_ids[key] = len(camera_ids) + 1
            model.add_camera_with_trivial_rig(
                pycolmap.Camera(
                    model="PINHOLE", width=K.width, height=K.height, params=list(params), camera_id=camera_ids[key]
                )
            )
        image = pycolmap.Image(name=stem_of[name], camera_id=camera_ids[key], image_id=image_id)
        model.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(pose.R), pose.t))
    folder.mkdir()
    model.write_binary(folder)
    return folder


def model_from_tracks(
    database: Path,
    intrinsics: Intrinsics,
    poses: dict[str, Pose],
    points: np.ndarray,
    tracks: list[dict[str, int]],
    stem_of: dict[str, str],
    folder: Path,
) -> Path:
    """A COLMAP model of one camera (SIMPLE_RADIAL: the pinhole and k1 of
    ``intrinsics``), the posed photos with their keypoints from ``database``, and
    ``points`` with their ``tracks`` (photo name -> keypoint index), in COLMAP's binary
    format; every point's reprojection error is computed."""
    model = pycolmap.Reconstruction()
    K = intrinsics
    camera = pycolmap.Camera(
        model="SIMPLE_RADIAL",
        width=K.width,
        height=K.height,
        params=[K.fx, K.cx + COLMAP_PIXEL_OFFSET, K.cy + COLMAP_PIXEL_OFFSET, K.dist[0]],
        camera_id=1,
    )
    model.add_camera_with_trivial_rig(camera)
    image_ids = {}
    with pycolmap.Database.open(database) as db:
        for image_id, name in enumerate(sorted(poses), start=1):
            stored = db.read_image_with_name(stem_of[name])
            keypoints = db.read_keypoints(stored.image_id)[:, :2].astype(float)
            image = pycolmap.Image(name=stem_of[name], keypoints=keypoints, camera_id=1, image_id=image_id)
            pose = poses[name]
            model.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(pose.R), pose.t))
            image_ids[name] = image_id
    for xyz, track in zip(points, tracks):
        elements = pycolmap.Track()
        for name, keypoint in track.items():
            elements.add_element(image_ids[name], keypoint)
        model.add_point3D(np.asarray(xyz, float), elements)
    model.update_point_3d_errors()
    folder.mkdir()
    model.write_binary(folder)
    return folder


def trusted_points(sparse: Path, min_track_length: int, max_error_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The model's points seen by at least ``min_track_length`` photos with at most
    ``max_error_px`` reprojection error and, for each, the mean direction towards the
    cameras that saw it."""
    model = pycolmap.Reconstruction(sparse)
    centres = {image_id: image.projection_center() for image_id, image in model.images.items() if image.has_pose}
    points, towards = [], []
    for point in model.points3D.values():
        if point.track.length() < min_track_length or point.error > max_error_px:
            continue
        directions = [centres[e.image_id] - point.xyz for e in point.track.elements if e.image_id in centres]
        directions = [d / np.linalg.norm(d) for d in directions]
        points.append(point.xyz)
        towards.append(np.mean(directions, axis=0))
    return np.reshape(points, (-1, 3)), np.reshape(towards, (-1, 3))


def screened_poisson(
    points: np.ndarray, normals: np.ndarray, depth: int, point_weight: float, work_dir: Path
) -> trimesh.Trimesh:
    """COLMAP's screened Poisson reconstruction, untrimmed (so closed) and on one
    thread. Unlike pymeshlab's, it returns the same mesh, vertex for vertex, on
    every run: cleanup's decimation and the UV charts depend on that order."""
    cloud_ply, mesh_ply = work_dir / "poisson_input.ply", work_dir / "poisson_output.ply"
    oriented = np.hstack([points, normals]).astype("<f4")
    header = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {len(oriented)}\n"
        + "".join(f"property float {name}\n" for name in ("x", "y", "z", "nx", "ny", "nz"))
        + "end_header\n"
    )
    cloud_ply.write_bytes(header.encode() + oriented.tobytes())
    options = pycolmap.PoissonMeshingOptions()
    options.depth, options.point_weight, options.trim, options.num_threads = depth, point_weight, 0.0, 1
    pycolmap.poisson_meshing(cloud_ply, mesh_ply, options)
    mesh = trimesh.load(mesh_ply, force="mesh", process=True)
    cloud_ply.unlink()
    mesh_ply.unlink()
    return mesh


def registered_poses(model, name_of: dict[str, str], intrinsics: dict[str, Intrinsics], refine_focal: bool):
    """Registered photos' poses, by photo name (``name_of`` maps COLMAP's image names);
    ``intrinsics`` take SfM's focal length and principal point when ``refine_focal``
    (the pinhole part: the photos stay as undistort made them)."""
    registered = {} if model is None else {name_of[im.name]: im for im in model.images.values() if im.has_pose}
    poses = {}
    for name, image in registered.items():
        rigid = image.cam_from_world()
        poses[name] = Pose(np.asarray(rigid.rotation.matrix()), np.asarray(rigid.translation))
        if refine_focal:
            focal, cx, cy = image.camera.params[:3]
            K = intrinsics[name]
            intrinsics[name] = Intrinsics(
                K.width,
                K.height,
                float(focal),
                float(focal),
                float(cx) - COLMAP_PIXEL_OFFSET,
                float(cy) - COLMAP_PIXEL_OFFSET,
            )
    return poses
