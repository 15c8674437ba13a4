"""``pipeline score``: compare a capture's latest outputs with its ground_truth/.

Each metric is computed from the file a stage exports to ``CAPTURE/output/stages/``;
a missing file means that stage has not run, and the score says so instead of
failing. The files and their producers:

=========================  ===============  ==============================================
file in output/stages/     stage            scored as
=========================  ===============  ==============================================
calibrate/intrinsics.json  calibrate        focal and principal point error, distortion
sfm/cameras.json           sfm              registered fraction; rotation and centre error
                                            after a similarity alignment to the truth
STAGE/mesh.ply             uv (or cleanup,  Chamfer distance (% of the true bounding-box
                           mesh)            diagonal), normal consistency and the shading
                                            normals' mean angle from the truth's, in the
                                            aligned frame
fit_material/params.json   fit_material     absolute error per parameter (relative for
                                            sigma_t)
fit_texture/params.json    fit_texture      the same for the constants fit_texture
                                            refitted (a kept texture's mean for it)
fit_material/heldout/      fit_material     PSNR of NAME.render.exr against
                                            NAME.reference.exr on views held out from
                                            fitting
fit_material/              fit_material     environment.exr, an estimated light (params.json's light, a
                                            world-fixed one) against the true rig:
                                            irradiance at the specimen's centre on the
                                            true surface's normals, from above the table
fit_texture/base_color.exr fit_texture      a kept base-colour texture against the true
                                            mesh's vertex colours: mean and 90th percentile
                                            absolute error per channel at points on the
                                            true surface; for scale, the constant's and
                                            the truth baked into the same atlas; and all
                                            over the surface the training photos see
fit_geometry/              fit_geometry     base_color.exr: the same, after its material
                                            passes
fit_texture/heldout/       fit_texture      the same, with the texture (or the constant
                                            when fit_texture did not keep one)
fit_geometry/heldout/      fit_geometry     the same, for the scene the pipeline ends with
=========================  ===============  ==============================================
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import OpenImageIO as oiio
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree

from pipeline.camera.model import Intrinsics, Pose, Similarity, project, rotation_angle_deg, similarity_umeyama
from pipeline.core.errors import PipelineError
from pipeline.core.publish import OUTPUT, STAGES
from pipeline.fit.loop import matched_gain
from pipeline.formats.cameras import read_cameras
from pipeline.formats.scene_folder import heldout_files, heldout_names
from pipeline.geometry.atlas import chart_texels, occluder, unoccluded
from pipeline.render.mitsuba_variant import activate as activate_mitsuba

MESH_SAMPLES = 30000
RELATIVE_PARAMETERS = {"sigma_t"}


def score_intrinsics(estimate: Intrinsics, truth: Intrinsics) -> dict[str, float]:
    if (estimate.width, estimate.height) != (truth.width, truth.height):
        raise PipelineError(
            f"output/stages/calibrate/intrinsics.json is for {estimate.width}x{estimate.height} images but the "
            f"photos are {truth.width}x{truth.height}: score intrinsics at the photos' resolution"
        )
    return {
        "focal_error_pct": 100 * max(abs(estimate.fx / truth.fx - 1), abs(estimate.fy / truth.fy - 1)),
        "principal_point_error_px": float(np.hypot(estimate.cx - truth.cx, estimate.cy - truth.cy)),
        "distortion_max_abs_error": float(np.max(np.abs(np.subtract(estimate.dist, truth.dist)))),
    }


def score_cameras(estimate: dict[str, Pose], truth: dict[str, Pose]) -> tuple[dict[str, Any], Similarity]:
    """Registration and pose errors after aligning the estimate to the truth."""
    common = sorted(set(estimate) & set(truth))
    metrics: dict[str, Any] = {
        "registered": len(common),
        "images": len(truth),
        "registered_fraction": len(common) / len(truth),
        "unregistered": sorted(set(truth) - set(estimate)),
    }
    if len(common) < 3:
        return metrics, Similarity.identity()
    est_centres = np.array([estimate[n].center for n in common])
    true_centres = np.array([truth[n].center for n in common])
    scale, R, t = similarity_umeyama(est_centres, true_centres)
    similarity = Similarity(scale, R, t)
    rotation_errors = [
        # aligned camera-to-world rotation is R @ R_est^T; compare with the truth's
        rotation_angle_deg(truth[n].R @ R @ estimate[n].R.T)
        for n in common
    ]
    scene_size = float(np.linalg.norm(true_centres.max(0) - true_centres.min(0)))
    centre_errors = np.linalg.norm(similarity.points(est_centres) - true_centres, axis=1) / scene_size * 100
    metrics.update(
        rotation_error_deg_median=float(np.median(rotation_errors)),
        rotation_error_deg_max=float(np.max(rotation_errors)),
        centre_error_pct_median=float(np.median(centre_errors)),
        centre_error_pct_max=float(np.max(centre_errors)),
        per_image={
            n: {"rotation_deg": r, "centre_pct": float(c)} for n, r, c in zip(common, rotation_errors, centre_errors)
        },
    )
    return metrics, similarity


def score_mesh(estimate: trimesh.Trimesh, truth: trimesh.Trimesh, seed: int = 0) -> dict[str, float]:
    """Symmetric Chamfer distance and normal consistency from surface samples, and the
    shading normals' error: at each sample of ``estimate``, the angle between its
    normal interpolated from the vertex normals (as a renderer shades it) and the
    truth's at the nearest sample of the true surface. A material fitted on the mesh
    sees the shading normals: a rough dielectric's alpha is as far off as their error
    spreads its highlights."""
    # The same seed for both: identical surfaces then give identical samples, so a
    # perfect mesh scores exactly zero instead of the sampling noise floor.
    est_points, est_faces = trimesh.sample.sample_surface(estimate, MESH_SAMPLES, seed=seed)
    true_points, true_faces = trimesh.sample.sample_surface(truth, MESH_SAMPLES, seed=seed)
    est_normals, true_normals = estimate.face_normals[est_faces], truth.face_normals[true_faces]
    to_truth, nearest_true = cKDTree(true_points).query(est_points)
    to_estimate, nearest_est = cKDTree(est_points).query(true_points)
    diagonal = float(np.linalg.norm(truth.bounds[1] - truth.bounds[0]))
    chamfer = (to_truth.mean() + to_estimate.mean()) / 2
    consistency = (
        np.abs(np.sum(est_normals * true_normals[nearest_true], axis=1)).mean()
        + np.abs(np.sum(true_normals * est_normals[nearest_est], axis=1)).mean()
    ) / 2
    cosines = np.sum(
        shading_normals(estimate, est_points, est_faces)
        * shading_normals(truth, true_points, true_faces)[nearest_true],
        axis=1,
    )
    angles = np.degrees(np.arccos(np.clip(cosines, -1.0, 1.0)))
    return {
        "chamfer_pct_of_diagonal": float(100 * chamfer / diagonal),
        "normal_consistency": float(consistency),
        "shading_normal_error_deg": float(angles.mean()),
        "shading_normal_error_deg_median": float(np.median(angles)),
        "faces": int(len(estimate.faces)),
        "watertight": bool(estimate.is_watertight),
    }


def shading_normals(mesh: trimesh.Trimesh, points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit normals at ``points`` on ``faces`` of ``mesh``, interpolated from its vertex
    normals as a renderer interpolates them."""
    barycentric = trimesh.triangles.points_to_barycentric(mesh.triangles[faces], points)
    normals = np.einsum("nk,nkj->nj", barycentric, mesh.vertex_normals[mesh.faces[faces]])
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def score_masks(truth_dir: Path, pinhole_json: Path, masks_json: Path) -> dict[str, float]:
    """IoU of each mask of the masks stage against the true mask, which is brought into
    the undistorted frame by the same remap as the photos (a cache-side score: masks
    are not exported)."""
    import cv2

    from pipeline.camera.model import undistort
    from pipeline.imaging.segmentation import iou

    cameras = json.loads(pinhole_json.read_text())["cameras"]
    photos = json.loads(pinhole_json.read_text())["images"]
    masks = json.loads(masks_json.read_text())["images"]
    scores = {}
    for name, entry in masks.items():
        camera = cameras[photos[name]["camera"]]
        source, target = Intrinsics.from_json(camera["source"]), Intrinsics.from_json(camera["intrinsics"])
        truth = cv2.imread(str(truth_dir / "masks" / f"{Path(name).stem}.png"), cv2.IMREAD_GRAYSCALE) > 127
        mask = cv2.imread(str(masks_json.parent / entry["mask"]), cv2.IMREAD_GRAYSCALE) > 127
        scores[name] = iou(mask, undistort(truth.astype(np.float32), source, target) >= 0.5)
    return scores


def score_material(estimate: dict[str, Any], truth: dict[str, Any]) -> dict[str, Any]:
    if estimate.get("model") != truth["model"]:
        return {"model": estimate.get("model"), "true_model": truth["model"], "note": "different models"}
    errors: dict[str, Any] = {"model": truth["model"]}
    for name, value in estimate["params"].items():
        if name not in truth:
            continue
        est, true = np.asarray(value, dtype=float), np.asarray(truth[name], dtype=float)
        if name == "base_color" and "base_color_mean" in truth:
            # a constant fit to a textured specimen is compared with the texture's mean
            true = np.asarray(truth["base_color_mean"], dtype=float)
        if name in RELATIVE_PARAMETERS:
            errors[f"{name}_rel_error"] = float(np.max(np.abs(est / true - 1)))
        else:
            errors[f"{name}_abs_error"] = float(np.max(np.abs(est - true)))
    return errors


@dataclass(frozen=True)
class TrueSurface:
    """A textured specimen's true surface, sampled once for every texture scored
    against it: ``points`` and their ``colours`` (linear), a denser sampling to
    bake from, and how many of the training photos see each point (None without
    views)."""

    points: np.ndarray
    colours: np.ndarray
    dense: cKDTree
    dense_colours: np.ndarray
    views_seeing: np.ndarray | None
    view_count: int
    """Number of training views counted in ``views_seeing`` (0 without views)."""


def true_surface(
    truth: trimesh.Trimesh, views: list[tuple[Intrinsics, Pose]] = (), samples: int = 20000
) -> TrueSurface:
    """Sample ``truth`` (sRGB vertex colours); with the true cameras of the training
    ``views``, also count the views that see each sample (needs Mitsuba's variant set)."""
    from pipeline.imaging.photo_io import srgb_decode

    def colours_at(faces: np.ndarray, points: np.ndarray) -> np.ndarray:
        weights = trimesh.triangles.points_to_barycentric(truth.triangles[faces], points)
        return srgb_decode(
            np.einsum("ij,ijk->ik", weights, truth.visual.vertex_colors[truth.faces[faces]][..., :3] / 255)
        )

    points, faces = trimesh.sample.sample_surface(truth, samples, seed=0)
    dense, dense_faces = trimesh.sample.sample_surface(truth, 30 * samples, seed=2)
    seeing = views_seeing(truth, points, truth.face_normals[faces], views) if views else None
    return TrueSurface(
        points, colours_at(faces, points), cKDTree(dense), colours_at(dense_faces, dense), seeing, len(views)
    )


def score_texture(
    textured: trimesh.Trimesh, texture: np.ndarray, constant: np.ndarray, truth: TrueSurface
) -> dict[str, Any]:
    """Per-channel error of a UV texture (linear, row 0 at v = 0, Mitsuba's convention)
    on ``textured`` (aligned to the truth) at the true surface's points. Each point
    takes the UV of the nearest point of a dense sampling of the textured mesh and
    reads the texture there as Mitsuba's bitmap does (bilinear, repeating).

    For scale: ``constant``'s error; the ``bake``, the truth written into the same
    atlas at the same resolution (what a perfect fit on this mesh and these UVs
    would score: mesh error and texel size set it); and, when the truth knows which
    points the training photos see, the same errors over those (a texture cannot be
    recovered where no photo looks) and over the points at least a third of them
    see (``well_seen_``): seen once, at a grazing angle, a texel is barely fixed."""
    dense, dense_faces = trimesh.sample.sample_surface(textured, 15 * len(truth.points), seed=1)
    dense_weights = trimesh.triangles.points_to_barycentric(textured.triangles[dense_faces], dense)
    uv = np.einsum("ij,ijk->ik", dense_weights, textured.visual.uv[textured.faces[dense_faces]])
    uv = uv[cKDTree(dense).query(truth.points)[1]]
    bake = bake_into_atlas(textured, texture.shape[:2], truth.dense, truth.dense_colours)
    errors = {
        "": np.abs(bilinear(texture[..., :3], uv) - truth.colours),
        "bake_": np.abs(bilinear(bake, uv) - truth.colours),
    }
    report = {
        "mean_abs_error": errors[""].mean(axis=0).tolist(),
        "p90_abs_error": np.percentile(errors[""], 90, axis=0).tolist(),
        "constant_mean_abs_error": np.abs(constant - truth.colours).mean(axis=0).tolist(),
        "bake_mean_abs_error": errors["bake_"].mean(axis=0).tolist(),
    }
    if truth.views_seeing is not None:
        well_seen = max(1, int(np.ceil(truth.view_count / 3)))
        for subset, selected in (("seen", truth.views_seeing >= 1), ("well_seen", truth.views_seeing >= well_seen)):
            report[f"{subset}_fraction"] = float(selected.mean())
            for prefix, error in errors.items():
                report[f"{prefix}{subset}_mean_abs_error"] = error[selected].mean(axis=0).tolist()
        report["well_seen_views"] = well_seen
    return report


def bilinear(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Mitsuba's bitmap lookup: bilinear between texel centres, wrapping around
    (``wrap_mode = repeat``, its default); row 0 at v = 0."""
    height, width = texture.shape[:2]
    coordinates = [uv[:, 1] * height - 0.5, uv[:, 0] * width - 0.5]
    return np.stack(
        [
            ndimage.map_coordinates(texture[..., channel], coordinates, order=1, mode="grid-wrap")
            for channel in range(texture.shape[2])
        ],
        axis=-1,
    )


def bake_into_atlas(
    textured: trimesh.Trimesh, shape: tuple[int, int], truth_points: cKDTree, truth_colours: np.ndarray
) -> np.ndarray:
    """An (h, w, 3) texture on ``textured``'s UVs holding, at each texel centre inside
    a chart, the colour of the nearest of ``truth_points``; texels between charts
    copy the nearest chart texel."""
    texels = chart_texels(textured, shape)
    return texels.fill_between_charts(truth_colours[truth_points.query(texels.points)[1]])


def views_seeing(
    mesh: trimesh.Trimesh, points: np.ndarray, normals: np.ndarray, views: list[tuple[Intrinsics, Pose]]
) -> np.ndarray:
    """How many of ``views`` have each of ``points`` (on ``mesh``, facing ``normals``)
    inside the image, facing the camera and not hidden by ``mesh``."""
    scene = occluder(mesh)
    offset = 1e-4 * float(np.linalg.norm(mesh.extents))
    seen = np.zeros(len(points), dtype=int)
    for intrinsics, pose in views:
        pixels, depth = project(points, intrinsics, pose)
        in_image = (
            (depth > 0)
            & (pixels[:, 0] >= 0)
            & (pixels[:, 0] < intrinsics.width)
            & (pixels[:, 1] >= 0)
            & (pixels[:, 1] < intrinsics.height)
        )
        seen += in_image & unoccluded(scene, points, normals, pose.center, offset)
    return seen


def read_linear_image(path: Path) -> np.ndarray:
    image = oiio.ImageBuf(str(path))
    if image.has_error:
        raise PipelineError(f"cannot read {path}: {image.geterror()}")
    return image.get_pixels(oiio.FLOAT)


def psnr(render: np.ndarray, reference: np.ndarray, peak: float = 1.0) -> float:
    mse = float(np.mean((render - reference) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(peak**2 / mse)


def score_heldout(folder: Path) -> dict[str, Any]:
    """PSNR of each held-out render against its photo, over NAME.mask.png's pixels when
    there is one (the specimen), else over the whole image. ``psnr_gain_db_mean``: the
    same after each render is scaled by the RGB gain that matches it best to its photo
    (least squares): what a phone's automatic exposure and white balance of that photo,
    which a fit cannot know for a photo it never saw, would take."""
    per_view, per_view_gain = {}, {}
    for name in heldout_names(folder):
        render_path, reference_path, mask_path = heldout_files(folder, name)
        render, reference = read_linear_image(render_path), read_linear_image(reference_path)
        if mask_path.is_file():
            inside = read_linear_image(mask_path)[..., 0] > 0.5
            render, reference = render[inside], reference[inside]
        per_view[name] = psnr(render, reference)
        flat_render, flat_reference = render.reshape(-1, 3), reference.reshape(-1, 3)
        gain = matched_gain(flat_render, flat_render, flat_reference, 1.0, 3)
        per_view_gain[name] = psnr(flat_render * gain, flat_reference)
    values, gained = list(per_view.values()), list(per_view_gain.values())
    return {
        "views": len(values),
        "psnr_db_mean": float(np.mean(values)) if values else None,
        "psnr_gain_db_mean": float(np.mean(gained)) if gained else None,
        "per_view": per_view,
    }


TRUE_MAP_WIDTH = 128
"""A wider true map (the room's is 2048 x 1024) is box-filtered to this many texels
across for the irradiance sum: 2.8 degrees a texel, far finer than a cosine lobe."""


def score_light(capture: Path, chosen: dict, fitted_dir: Path, similarity: Similarity) -> dict[str, Any]:
    """An estimated light (``chosen``: fit_material's summary; its map in
    ``fitted_dir``) against the capture's true rig: the irradiance each vertex normal
    of the true mesh would receive at the mesh's centre from above the table (the
    table hides the rest in both), unoccluded. ``irradiance_rel_error``: the mean
    absolute luminance difference over the surface (area-weighted) relative to the
    mean true luminance; ``irradiance_ratio``: estimated over true mean, per channel."""
    from pipeline.core.sections import LightSection
    from pipeline.imaging.photo_io import read_photo
    from pipeline.render import light

    section = LightSection(**json.loads((capture / "ground_truth" / "light.json").read_text()))
    if section.frame != "world" or chosen["frame"] != "world":
        return {"model": chosen["model"], "note": "a light riding with the camera is not scored"}
    true_map = None
    if section.environment_map:
        true_map = read_photo(capture / section.environment_map).pixels
        if true_map.shape[1] > TRUE_MAP_WIDTH:
            true_map = cv2.resize(true_map, (TRUE_MAP_WIDTH, TRUE_MAP_WIDTH // 2), interpolation=cv2.INTER_AREA)
    truth = light.from_section(section, true_map)
    estimate = light.read(chosen, fitted_dir)
    mesh = trimesh.load(capture / "ground_truth" / "mesh.ply", force="mesh", process=False)
    weights = np.zeros(len(mesh.vertices))
    np.add.at(weights, mesh.faces.ravel(), np.repeat(mesh.area_faces / 3, 3))
    centre = mesh.bounding_box.centroid
    true_irradiance = light.irradiance(truth, mesh.vertex_normals, centre, above=True)
    # Into the estimate's frame: x_truth = s R x_est + t.
    estimated_irradiance = light.irradiance(
        estimate,
        mesh.vertex_normals @ similarity.R,
        similarity.R.T @ (centre - similarity.t) / similarity.scale,
        above=True,
    )
    luminance = np.array([0.2126, 0.7152, 0.0722])
    true_luminance, estimated_luminance = true_irradiance @ luminance, estimated_irradiance @ luminance
    return {
        "model": chosen["model"],
        "irradiance_rel_error": float(
            weights @ np.abs(estimated_luminance - true_luminance) / (weights @ true_luminance)
        ),
        "irradiance_ratio": (weights @ estimated_irradiance / (weights @ true_irradiance)).tolist(),
        "true_irradiance_mean": (weights @ true_irradiance / weights.sum()).tolist(),
    }


def score_capture(capture: Path) -> dict[str, Any]:
    """Score whatever the capture's output/ holds; missing parts are listed, not fatal."""
    truth_dir, out_dir = capture / "ground_truth", capture / OUTPUT / STAGES
    if not (truth_dir / "cameras.json").is_file():
        raise PipelineError(
            f"{capture} has no ground_truth/cameras.json: only synthetic captures "
            f"(made by `pipeline synth`) can be scored"
        )
    true_intrinsics, true_poses = read_cameras(truth_dir / "cameras.json")
    report: dict[str, Any] = {"missing": []}

    def present(*names: str) -> Path | None:
        """The first of ``names`` (paths in output/stages/) that exists."""
        for name in names:
            if (out_dir / name).exists():
                return out_dir / name
        report["missing"].append(f"{names[0]} ({names[0].split('/')[0]} has not run)")
        return None

    if path := present("calibrate/intrinsics.json"):
        report["intrinsics"] = score_intrinsics(Intrinsics.from_json(json.loads(path.read_text())), true_intrinsics)
    similarity = Similarity.identity()
    if path := present("sfm/cameras.json"):
        _, poses = read_cameras(path)
        report["cameras"], similarity = score_cameras(poses, true_poses)
    if path := present("uv/mesh.ply", "cleanup/mesh.ply", "mesh/mesh.ply"):
        estimate = trimesh.load(path, force="mesh")
        # uv's mesh splits vertices along chart seams; watertightness is about the surface.
        estimate.merge_vertices(merge_tex=True, merge_norm=True)
        estimate.apply_transform(similarity.matrix())
        report["mesh"] = score_mesh(estimate, trimesh.load(truth_dir / "mesh.ply", force="mesh"))
    if path := present("fit_material/params.json"):
        truth = json.loads((truth_dir / "material.json").read_text())
        report["material"] = score_material(json.loads(path.read_text()), truth)
        texture = out_dir / "fit_texture" / "params.json"
        kept = json.loads(texture.read_text()) if texture.is_file() else {}
        if "params" in kept:
            report["material_fit_texture"] = score_material(kept, truth)
        refined = out_dir / "fit_geometry" / "params.json"
        if refined.is_file() and "params" in (final := json.loads(refined.read_text())):
            report["material_fit_geometry"] = score_material(final, truth)
        if truth.get("texture") and kept.get("kept") and kept["kind"] == "bitmap":
            # fit_texture's texture, and fit_geometry's after its material passes.
            fitted = json.loads(path.read_text())
            constant = np.asarray(fitted["params"]["base_color"])
            activate_mitsuba()
            training = [
                (true_intrinsics, pose) for name, pose in sorted(true_poses.items()) if name not in fitted["held_out"]
            ]
            surface = true_surface(trimesh.load(truth_dir / "mesh.ply", process=False), training)
            for folder, part in (("fit_texture", "texture"), ("fit_geometry", "texture_fit_geometry")):
                if (out_dir / folder / "base_color.exr").is_file():
                    textured = trimesh.load(out_dir / folder / "mesh.ply", process=False)
                    textured.apply_transform(similarity.matrix())
                    report[part] = score_texture(
                        textured, read_linear_image(out_dir / folder / "base_color.exr"), constant, surface
                    )
    material = out_dir / "fit_material" / "params.json"
    fitted = json.loads(material.read_text()) if material.is_file() else {}
    if fitted.get("light", {}).get("chosen", {}).get("model", "given") != "given":
        report["light"] = score_light(capture, fitted["light"]["chosen"], out_dir / "fit_material", similarity)
    for folder, part in (
        ("fit_material/heldout", "heldout"),
        ("fit_texture/heldout", "heldout_textured"),
        ("fit_geometry/heldout", "heldout_geometry"),
    ):
        if path := present(folder):
            report[part] = score_heldout(path)
    return report


def summary_rows(report: dict[str, Any]) -> list[tuple[str, str, str]]:
    """(part, metric, value) rows for the table, skipping bulky per-item details."""
    rows = []
    for part, metrics in report.items():
        if part == "missing" or not isinstance(metrics, dict):
            continue
        for name, value in metrics.items():
            if name in ("per_image", "per_view", "unregistered"):
                continue
            if isinstance(value, float):
                text = f"{value:.4g}"
            elif isinstance(value, list) and all(isinstance(v, float) for v in value):
                text = " / ".join(f"{v:.3g}" for v in value)  # per channel
            else:
                text = str(value)
            rows.append((part, name, text))
    return rows
