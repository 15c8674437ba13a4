"""Stage mesh: one watertight surface of the specimen, from silhouettes, refined by
the sparse points or by stereo.

The pycolmap wheel has no dense stereo and no Delaunay meshing (both need CUDA or
CGAL), so the dense shape starts from the masks:

1. **Visual hull** (pipeline.geometry.visual_hull): a box around the specimen is found by a
   coarse carve, then a grid of ``resolution`` voxels along its longest side holds
   each voxel's distance to the nearest silhouette edge; marching cubes at 0 gives
   a closed surface. Voxels below the ground plane (the table, when the sfm stage
   found it) are cut off: cameras above a table cannot carve underneath the
   specimen, and the table and board never enter the hull as the masks exclude them.
2. **Sparse points** (``refine = "poisson"``): a visual hull bridges concavities
   that no silhouette shows; SfM points inside the hull lie on the true surface
   there. Hull samples near such interior points are dropped, the points join
   the rest with normals estimated from their neighbours and turned towards the
   cameras that saw them, and a screened Poisson reconstruction (COLMAP's)
   makes the surface watertight again. Points outside the hull contradict the
   silhouettes and are discarded as outliers. A refined surface that is not
   watertight or has more handles than the hull (noisy points on a porous
   surface) is rejected, and the hull kept (mesh.json says which).
3. **Stereo** (``refine = "stereo"``, pipeline.geometry.stereo): each photo's depth
   by plane-sweep stereo against its nearest viewpoints, searched between where its
   rays enter and leave the hull; depths that neighbouring depth maps confirm (to a
   voxel) carve away the hull in front of them. The carved field stays a field, so
   marching cubes closes the surface as before; concavities open where the photos
   show texture.

==================  =============================================================
output              content
==================  =============================================================
mesh.ply            the specimen's surface in the world frame of cameras.json
mesh.json           faces, watertightness, volume, points used, timings
==================  =============================================================

Limitations: concavities need texture (sparse points or stereo) to be recovered; a
specimen cut off by the frame in many photos, or masks that include the table,
inflate the hull. The resolution bounds the detail: the voxel size is the
specimen's largest extent divided by ``resolution``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree

from pipeline import logger
from pipeline.camera.model import Similarity, mesh_coverage
from pipeline.colmap import meshing, model_io
from pipeline.core.config import InputFile, Range, input_file_path
from pipeline.core.errors import PipelineError
from pipeline.core.stage import Stage, StageInputs, StageResult
from pipeline.formats.cameras import read_frame, read_views
from pipeline.formats.masks import read_masks
from pipeline.formats.pinhole import read_photos
from pipeline.geometry import stereo
from pipeline.geometry.visual_hull import View, bounds, hull_field, sample_hull, surface
from pipeline.imaging.segmentation import iou


@dataclass(frozen=True)
class Config:
    """Dense geometry on CPU: visual hull, refined with the sparse points."""

    resolution: Annotated[int, Range(16, 512)] = 128
    """Voxels along the specimen's longest side; time and memory grow with its cube."""
    carve_tolerance: Annotated[int, Range(0, None)] = 0
    """Views allowed to disagree before a voxel is carved away. 0: every mask carves
    (on the samples the hull is 2-6 % too large; with 1, 7-14 %: whatever a single
    view alone carves stays, and with 20-30 views that is much). 1 or more when a
    mask may have lost part of the specimen (a leg, a pale rim), which would
    otherwise be cut off."""
    close_voxels: Annotated[int, Range(0, 8)] = 1
    """Tunnels and gaps through the hull up to twice this many voxels wide are filled
    (a stray gap in one mask would otherwise give the hull a handle)."""
    clip_to_ground: bool = True
    """Cut the hull at the ground plane found by the sfm stage (the table or board)."""
    refine: Literal["poisson", "stereo", "none"] = "poisson"
    """poisson: add the sparse points inside the hull and rebuild with screened Poisson;
    stereo: carve the hull where plane-sweep depth maps see past it (the photos'
    texture; 1.6 s a photo at 640 px on 2 cores); none: the visual hull as it is."""
    poisson_depth: Annotated[int, Range(5, 12)] = 8
    """Octree depth of the Poisson reconstruction (2^depth cells along the longest side)."""
    poisson_point_weight: Annotated[float, Range(0.0, None)] = 4.0
    """Screening weight: how closely the surface keeps to the points (0: unscreened)."""
    min_track_length: Annotated[int, Range(2, None)] = 3
    """Sparse points seen in fewer photos are not trusted."""
    max_point_error_px: Annotated[float, Range(0.0, None, exclusive_lo=True)] = 2.0
    """Sparse points with a larger mean reprojection error are not trusted."""
    stereo_max_size: Annotated[int, Range(64, None)] = 640
    """Longer side, in pixels, of the photos stereo compares (time grows with its square)."""
    stereo_planes: Annotated[int, Range(8, 1024)] = 96
    """Depth planes swept per photo between the hull's near and far side."""
    stereo_window: Annotated[int, Range(3, 31)] = 7
    """Side of the square window compared between photos, pixels (odd)."""
    stereo_neighbours: Annotated[int, Range(1, 12)] = 4
    """Photos each is compared with: the nearest viewpoints 3-45 degrees away; per
    pixel the better half of them counts (one may see the point occluded)."""
    stereo_min_score: Annotated[float, Range(-1.0, 1.0)] = 0.5
    """Normalised cross-correlation below which a depth is not trusted."""
    stereo_min_votes: Annotated[int, Range(1, None)] = 2
    """Photos that must see past a voxel before it is carved."""
    source: Annotated[str, InputFile(suffixes=(".ply", ".obj"))] = ""
    """A PLY or OBJ of the specimen made by another tool, used instead of the visual
    hull (the settings above then do nothing), relative to the capture folder. It is
    in the frame of `[cameras] source` when that is set, else in the world frame of
    the sfm stage's cameras.json (output/stages/sfm/cameras.json)."""
    min_silhouette_iou: Annotated[float, Range(0.0, 1.0)] = 0.5
    """A given mesh whose outline overlaps the masks less than this (median over the
    photos, intersection over union) is refused: it is not in the cameras' frame."""


def _views(cameras_json: Path, masks_json: Path) -> dict[str, View]:
    masks = read_masks(masks_json)
    views = {}
    for name, (intrinsics, pose) in sorted(read_views(cameras_json).items()):
        mask = cv2.imread(str(masks[name]), cv2.IMREAD_GRAYSCALE) > 127
        if mask.shape != (intrinsics.height, intrinsics.width):
            raise PipelineError(
                f"the mask of {name} is {mask.shape[::-1]} but its camera is "
                f"{intrinsics.width}x{intrinsics.height}: rerun the masks and sfm stages"
            )
        views[name] = View(intrinsics, pose, mask)
    return views


def _ground_height(cameras_json: Path) -> float | None:
    """Height of the ground plane z = h in the world frame, if the sfm stage found one."""
    plane = read_frame(cameras_json).get("ground_plane")
    return None if plane is None else float(-plane[3] / plane[2])


def _refine_with_points(
    hull: trimesh.Trimesh,
    views: list[View],
    points: np.ndarray,
    towards: np.ndarray,
    conf: Config,
    voxel: float,
    work_dir: Path,
) -> tuple[trimesh.Trimesh, dict]:
    depth_in_hull = hull_field(points, views, conf.carve_tolerance)
    consistent = depth_in_hull > -voxel
    # A concavity the hull cannot carve: inside and further than two voxels from its
    # surface. (The hull field is no measure of that: a point mid-face of a cube is
    # far from every silhouette's edge, yet on the surface.)
    to_surface = cKDTree(hull.vertices).query(points)[0]
    interior = (depth_in_hull > 0) & (to_surface > 2 * voxel)
    points, towards, interior = points[consistent], towards[consistent], interior[consistent]
    samples, normals = hull.vertices, hull.vertex_normals
    if interior.any():
        near_interior = cKDTree(points[interior]).query(samples, distance_upper_bound=2 * voxel)[0] < np.inf
        samples, normals = samples[~near_interior], normals[~near_interior]
    cloud = np.vstack([samples, points])
    # Normals of the sparse points from their neighbours in the joint cloud, turned
    # towards the cameras that saw them.
    tree = cKDTree(cloud)
    _, neighbours = tree.query(points, k=min(12, len(cloud)))
    local = cloud[neighbours] - cloud[neighbours].mean(axis=1, keepdims=True)
    # The smallest-eigenvalue eigenvector of each neighbourhood's scatter, all at once.
    point_normals = np.linalg.eigh(np.einsum("nki,nkj->nij", local, local))[1][:, :, 0]
    point_normals *= np.where(np.sum(point_normals * towards, axis=1) >= 0, 1.0, -1.0)[:, None]
    mesh = meshing.screened_poisson(
        cloud, np.vstack([normals, point_normals]), conf.poisson_depth, conf.poisson_point_weight, work_dir
    )
    parts = mesh.split(only_watertight=False)
    mesh = max(parts, key=lambda part: len(part.faces)) if len(parts) > 1 else mesh
    if mesh.volume < 0:
        mesh.invert()
    report = {
        "sparse_points_used": int(len(points)),
        "sparse_points_inside": int(interior.sum()),
        "sparse_points_rejected": int((~consistent).sum()),
    }
    return mesh, report


def _genus(mesh: trimesh.Trimesh) -> int:
    return round(1 - mesh.euler_number / 2) if mesh.is_watertight else -1


def _check_given_mesh(setting: str, path: Path, mesh: trimesh.Trimesh) -> None:
    """Refuse a mesh no later step can use: corners that are not numbers, faces that
    name corners it lacks, or no area at all."""
    problem = None
    bad_vertices = int(np.count_nonzero(~np.isfinite(mesh.vertices).all(axis=1)))
    if bad_vertices:
        problem = f"{bad_vertices} of its {len(mesh.vertices)} vertices are NaN or infinite"
    elif mesh.faces.min() < 0 or mesh.faces.max() >= len(mesh.vertices):
        problem = f"its faces name vertices it does not have (0-{len(mesh.vertices) - 1})"
    elif not np.any(mesh.area_faces > 0):
        problem = "every triangle has zero area"
    if problem:
        raise PipelineError(f"mesh.source = {setting!r}: {path}: {problem}; repair or re-export the mesh")


def _given_mesh(conf: Config, capture_dir: Path, cameras_json: Path, views: list[View]) -> tuple[trimesh.Trimesh, dict]:
    """``mesh.source`` in the world frame, refused when its outlines miss the masks."""
    path = input_file_path(capture_dir, conf.source)
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except (ValueError, OSError, KeyError, IndexError) as error:
        raise PipelineError(f"mesh.source = {conf.source!r}: cannot read {path} as a mesh ({error})") from error
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise PipelineError(f"mesh.source = {conf.source!r}: {path} holds no triangles")
    _check_given_mesh(conf.source, path, mesh)
    from_source = read_frame(cameras_json).get("from_source")
    if from_source is not None:
        mesh.apply_transform(Similarity.from_json(from_source).matrix())
    overlaps = [iou(mesh_coverage(mesh.vertices, mesh.faces, v.intrinsics, v.pose, 1) >= 0.5, v.mask) for v in views]
    median = float(np.median(overlaps))
    if median < conf.min_silhouette_iou:
        frame = "[cameras] source" if from_source is not None else "the cameras in output/stages/sfm/cameras.json"
        raise PipelineError(
            f"mesh.source = {conf.source!r}: its outline overlaps the masks by {median:.2f} (median IoU over "
            f"{len(views)} photos; mesh.min_silhouette_iou = {conf.min_silhouette_iou}): it is not in the frame of "
            f"{frame}. Export the mesh and the cameras from the same project, in the same coordinate system"
        )
    logger.info("mesh from %s: %d faces, outline IoU with the masks %.2f (median)", path, len(mesh.faces), median)
    return mesh, {"source": conf.source, "silhouette_iou_median": median, "silhouette_iou_min": float(min(overlaps))}


def main(conf: Config, inputs: StageInputs, out_dir: Path) -> StageResult:
    cameras_json = inputs.upstream["sfm"]["cameras"]
    named_views = _views(cameras_json, inputs.upstream["masks"]["masks_json"])
    views = list(named_views.values())
    if conf.source:
        mesh, report = _given_mesh(conf, inputs.capture_dir, cameras_json, views)
        return _write(mesh, report, out_dir)
    started = time.perf_counter()
    try:
        lo, hi = bounds(views, conf.carve_tolerance)
    except ValueError as error:
        masks_folder = inputs.upstream["masks"]["masks_json"].parent / "masks"
        raise PipelineError(f"no visual hull: {error}. Look at the masks in {masks_folder}") from error
    ground = _ground_height(cameras_json) if conf.clip_to_ground else None
    if ground is not None:
        lo[2] = max(lo[2], ground)
    grid, centres, field = sample_hull(views, lo, hi, conf.resolution, conf.carve_tolerance)
    if ground is not None:
        field = np.minimum(field, centres[:, 2] - ground)
    report: dict = {}
    if conf.refine == "stereo":
        photos = read_photos(inputs.upstream["undistort"]["pinhole"])
        greys = [cv2.imread(str(photos[name]["srgb"]), cv2.IMREAD_GRAYSCALE) for name in named_views]
        settings = stereo.StereoSettings(
            conf.stereo_max_size,
            conf.stereo_planes,
            conf.stereo_window,
            conf.stereo_neighbours,
            conf.stereo_min_score,
            conf.stereo_min_votes,
        )
        field, report = stereo.carve(field, grid, centres, views, greys, settings)
    if conf.close_voxels:
        # A tunnel a voxel or two wide is a mask's stray gap, not a handle of the
        # specimen: a grey closing of the inside field fills it.
        size = 2 * conf.close_voxels + 1
        field = ndimage.grey_closing(field.reshape(grid.shape), size=(size,) * 3).ravel()
    mesh = surface(field, grid)
    report |= {
        "views": len(views),
        "voxel": grid.voxel,
        "grid": list(grid.shape),
        "hull_seconds": time.perf_counter() - started - report.get("stereo_seconds", 0.0),
        "ground_clipped": ground is not None,
    }
    if conf.refine == "poisson":
        points, towards = model_io.trusted_points(
            inputs.upstream["sfm"]["sparse"], conf.min_track_length, conf.max_point_error_px
        )
        if len(points) >= 10:
            refined, details = _refine_with_points(mesh, views, points, towards, conf, grid.voxel, out_dir)
            report.update(details)
            # Noisy points (a porous surface, pores deeper than the hull) can give
            # Poisson handles and holes; the hull is closed by construction.
            if refined.is_watertight and _genus(refined) <= _genus(mesh):
                mesh, report["refinement"] = refined, "kept"
            else:
                report["refinement"] = (
                    f"rejected: genus {_genus(refined)}, watertight {refined.is_watertight} "
                    f"against the hull's genus {_genus(mesh)}"
                )
                logger.warning("Poisson refinement %s; keeping the visual hull", report["refinement"])
        else:
            logger.warning("only %d trusted sparse points: keeping the visual hull as it is", len(points))
    report["seconds"] = time.perf_counter() - started
    return _write(mesh, report, out_dir)


def _write(mesh: trimesh.Trimesh, report: dict, out_dir: Path) -> StageResult:
    report.update(
        faces=int(len(mesh.faces)),
        watertight=bool(mesh.is_watertight),
        volume=float(mesh.volume) if mesh.is_watertight else None,
        extent=(mesh.bounds[1] - mesh.bounds[0]).tolist(),
    )
    if not mesh.is_watertight:
        logger.warning("the mesh is not watertight; the cleanup stage closes its holes")
    mesh_ply = out_dir / "mesh.ply"
    mesh.export(mesh_ply)
    mesh_json = out_dir / "mesh.json"
    mesh_json.write_text(json.dumps(report, indent=1))
    metrics = {k: report[k] for k in ("faces", "watertight", "voxel") if k in report}
    return StageResult({"mesh": mesh_ply, "report": mesh_json}, metrics)


STAGE = Stage(
    name="mesh",
    version=8,
    config=Config,
    main=main,
    needs=("sfm.cameras", "sfm.sparse", "masks.masks_json", "undistort.pinhole"),
    outputs=("mesh", "report"),
    exports=("mesh",),
)
