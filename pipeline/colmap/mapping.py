"""Incremental mapping, self-calibration of the lens, and the registered poses."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap

from pipeline.camera.model import Intrinsics, Pose
from pipeline.camera.self_calibration import SelfCalibrationSettings, corner_radius, frame_coverage, radial_shift_px
from pipeline.colmap import COLMAP_PIXEL_OFFSET


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
