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

from pathlib import Path

import cv2
import numpy as np
import pycolmap
import trimesh

from pipeline import logger
from pipeline.camera.model import Intrinsics, Pose, Similarity

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


def extract_and_match(
    photos: dict[str, dict],
    cameras: list[dict],
    mask_dir: Path | None,
    image_dir: Path,
    database: Path,
    max_features: int,
    matcher: str,
    sequential_overlap: int,
    ring_neighbours: int,
    still_camera: bool,
) -> None:
    """SIFT features of every photo (one SIMPLE_PINHOLE COLMAP camera per camera
    setting), matched ``matcher``-wise (exhaustive, sequential or ring) and verified
    with seeded RANSAC; ``still_camera`` drops matches that do not move (a
    turntable's room)."""
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = max_features
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
    device = pycolmap.Device.cpu
    if matcher == "exhaustive":
        pycolmap.match_exhaustive(database, verification_options=verification, device=device)
    elif matcher == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = sequential_overlap
        pycolmap.match_sequential(database, pairing_options=pairing, verification_options=verification, device=device)
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
        pycolmap.match_image_pairs(database, pairing_options=pairing, verification_options=verification, device=device)


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
    ``intrinsics`` take SfM's focal length and principal point when ``refine_focal``."""
    registered = {} if model is None else {name_of[im.name]: im for im in model.images.values() if im.has_pose}
    poses = {}
    for name, image in registered.items():
        rigid = image.cam_from_world()
        poses[name] = Pose(np.asarray(rigid.rotation.matrix()), np.asarray(rigid.translation))
        if refine_focal:
            focal, cx, cy = image.camera.params
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
