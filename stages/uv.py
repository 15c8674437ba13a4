"""Stage uv: a texture atlas for the cleaned mesh (xatlas), and a checker preview.

xatlas cuts the mesh into charts and packs them into a square atlas of
``texture_size`` texels: at ``texel_density`` texels per world unit when given
(metres in a board-scaled frame), else at the highest density (tried in steps
of 15 % in area) at which every chart fits the one atlas. Charts must never
overflow onto a second atlas: its UVs cover the same square, so two parts of
the surface would share texels and no texture could match both.
Vertices on chart seams are split, so the UV mesh has more vertices than the
cleaned mesh but the same surface.

==================  =============================================================
output              content
==================  =============================================================
mesh.ply            mesh with per-vertex UVs (texture_u, texture_v)
mesh.obj, mesh.mtl   the same for other tools, textured with checker.png (all three published)
checker.png         a checker texture of texture_size, 16 texels per square
uv_layout.png       the charts drawn in UV space
preview.png         the checker-textured mesh rendered by Mitsuba from the first
                    registered camera: squares should look square and even
uv.json             charts, atlas utilisation, texel density, area distortion,
                    overlapping texels (surface points sharing a texel: 0)
==================  =============================================================

Area distortion is, per face, its share of the UV area over its share of the
surface area; 1 everywhere means every part of the surface gets the same texel
density. Limitations: xatlas does not minimise angle distortion explicitly;
charts are cut where the surface bends, which leaves seams that texture fitting
must keep consistent (padding of ``padding`` texels around each chart).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import cv2
import numpy as np
import trimesh
import xatlas

from pipeline.camera.model import scaled
from pipeline.core.config import Range
from pipeline.core.errors import PipelineError
from pipeline.core.stage import Stage, StageInputs, StageResult
from pipeline.formats.cameras import read_views
from pipeline.geometry.atlas import overlapping_texels
from pipeline.imaging.photo_io import to_uint8
from pipeline.render import mitsuba_variant, scene_xml

CHECKER_TEXELS = 16


@dataclass(frozen=True)
class Config:
    """UV unwrapping with xatlas."""

    texture_size: Annotated[int, Range(64, 16384)] = 1024
    """Side of the square texture atlas in texels."""
    texel_density: Annotated[float, Range(0.0, None)] = 0.0
    """Texels per world unit (per metre when the world frame is metric); 0 chooses the
    density that fills the atlas."""
    padding: Annotated[int, Range(0, 16)] = 2
    """Texels of padding around each chart, so that filtering does not bleed across seams."""


def unwrap(mesh: trimesh.Trimesh, conf: Config) -> tuple[trimesh.Trimesh, dict]:
    pack = xatlas.PackOptions()
    pack.resolution = conf.texture_size
    pack.padding = conf.padding
    pack.bilinear = True
    # Aim for ~70 % of the atlas, what packing typically reaches. Charts that do not
    # fit spill onto further pages with the same UV range, which the single bitmap
    # of a Mitsuba scene would share between unrelated parts of the surface: pack
    # again, at a lower density, until one page holds every chart.
    fill = 0.7
    positions, triangles = mesh.vertices.astype(np.float32), mesh.faces.astype(np.uint32)
    while True:
        atlas = xatlas.Atlas()
        atlas.add_mesh(positions, triangles)
        pack.texels_per_unit = conf.texel_density or conf.texture_size * float(np.sqrt(fill / mesh.area))
        atlas.generate(xatlas.ChartOptions(), pack)
        if atlas.atlas_count == 1:
            break
        if conf.texel_density:
            raise PipelineError(
                f"uv.texel_density = {conf.texel_density:g} puts the charts on {atlas.atlas_count} "
                f"atlases of {conf.texture_size} texels: lower it, raise uv.texture_size, or set it "
                "to 0 to choose the density that fits"
            )
        fill *= 0.85
        if fill < 0.01:
            raise PipelineError(
                f"the mesh's {atlas.chart_count} UV charts do not fit one atlas of "
                f"uv.texture_size = {conf.texture_size} texels with uv.padding = {conf.padding}: "
                "raise texture_size or lower padding"
            )
    mapping, faces, uvs = atlas[0]
    visual = trimesh.visual.TextureVisuals(uv=uvs)
    unwrapped = trimesh.Trimesh(mesh.vertices[mapping], faces, visual=visual, process=False)
    edges = uvs[faces[:, 1:]] - uvs[faces[:, :1]]
    uv_area = np.abs(edges[:, 0, 0] * edges[:, 1, 1] - edges[:, 0, 1] * edges[:, 1, 0]) / 2
    surface_area = unwrapped.area_faces
    distortion = (uv_area / uv_area.sum()) / np.maximum(surface_area / surface_area.sum(), 1e-30)
    spread = np.maximum(distortion, 1 / np.maximum(distortion, 1e-12))
    report = {
        "charts": int(atlas.chart_count),
        "atlas_size": [int(atlas.width), int(atlas.height)],
        "utilisation": float(np.mean(atlas.utilization)),
        "texel_density": float(atlas.texels_per_unit),
        "overlapping_texels": overlapping_texels(unwrapped, (int(atlas.height), int(atlas.width))),
        "area_distortion_median": float(np.median(spread)),
        "area_distortion_p95": float(np.percentile(spread, 95)),
        "vertices": int(len(unwrapped.vertices)),
        "faces": int(len(faces)),
    }
    return unwrapped, report


def checker(size: int) -> np.ndarray:
    squares = (np.indices((size, size)) // CHECKER_TEXELS).sum(axis=0) % 2
    return np.where(squares[..., None], [0.85, 0.85, 0.85], [0.15, 0.25, 0.6]).astype(np.float32)


def draw_layout(mesh: trimesh.Trimesh, path: Path, size: int = 1024) -> None:
    image = np.full((size, size, 3), 255, np.uint8)
    uv = mesh.visual.uv * (size - 1)
    polygons = np.round(np.stack([uv[:, 0], (size - 1) - uv[:, 1]], axis=-1)[mesh.faces]).astype(np.int32)
    cv2.polylines(image, list(polygons), True, (90, 60, 30), 1, cv2.LINE_AA)
    cv2.imwrite(str(path), image)


def render_preview(mesh_ply: Path, checker_png: Path, cameras_json: Path, path: Path, variant: str) -> None:
    """The checker-textured mesh from the first registered camera, under a uniform sky,
    cropped to the specimen at about 256 pixels."""
    mitsuba_variant.activate(variant)
    import mitsuba as mi

    _, (intrinsics, pose) = sorted(read_views(cameras_json).items())[0]
    corners = trimesh.load(mesh_ply, force="mesh").bounding_box.vertices @ pose.R.T + pose.t
    pixels = corners[:, :2] / corners[:, 2:] * [intrinsics.fx, intrinsics.fy] + [intrinsics.cx, intrinsics.cy]
    scale = 256 / max(np.ptp(pixels, axis=0))
    small = scaled(intrinsics, scale, exact=True)
    lo = np.clip(np.floor(pixels.min(axis=0) * scale).astype(int), 0, [small.width - 1, small.height - 1])
    hi = np.clip(np.ceil(pixels.max(axis=0) * scale).astype(int), lo + 1, [small.width, small.height])
    # The pipeline's one pinhole sensor (principal point included), near clip well
    # inside the camera's distance to the mesh.
    near_clip = 0.01 * float(np.min(corners[:, 2]))
    sensor = scene_xml.sensor_properties(small, pose, 16, max(near_clip, 1e-4), (*lo, *(hi - lo)))
    scene = mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "direct"},
            "sensor": {**sensor, "to_world": mi.ScalarTransform4f(sensor["to_world"])},
            "specimen": {
                "type": "ply",
                "id": "specimen",
                "filename": str(mesh_ply),
                "bsdf": {
                    "type": "diffuse",
                    "id": "checker",
                    "reflectance": {"type": "bitmap", "filename": str(checker_png), "filter_type": "nearest"},
                },
            },
            "sky": {"type": "constant", "radiance": 1.0},
        }
    )
    cv2.imwrite(str(path), cv2.cvtColor(to_uint8(np.asarray(mi.render(scene))), cv2.COLOR_RGB2BGR))


def main(conf: Config, inputs: StageInputs, out_dir: Path) -> StageResult:
    mesh = trimesh.load(inputs.upstream["cleanup"]["mesh"], force="mesh", process=False)
    unwrapped, report = unwrap(mesh, conf)
    checker_png = out_dir / "checker.png"
    cv2.imwrite(str(checker_png), cv2.cvtColor(to_uint8(checker(conf.texture_size)), cv2.COLOR_RGB2BGR))
    unwrapped.visual.material = trimesh.visual.material.SimpleMaterial(name="checker")
    mesh_ply = out_dir / "mesh.ply"
    unwrapped.export(mesh_ply)
    obj = out_dir / "mesh.obj"
    # trimesh writes the UVs only with a texture; its material file is replaced by ours.
    text, _ = trimesh.exchange.obj.export_obj(unwrapped, include_texture=True, mtl_name="mesh.mtl", return_texture=True)
    obj.write_text(text)
    (out_dir / "mesh.mtl").write_text("newmtl checker\nKd 1 1 1\nmap_Kd checker.png\n")
    draw_layout(unwrapped, out_dir / "uv_layout.png")
    render_preview(
        mesh_ply,
        checker_png,
        inputs.upstream["sfm"]["cameras"],
        out_dir / "preview.png",
        inputs.shared["mitsuba"].variant,
    )
    uv_json = out_dir / "uv.json"
    uv_json.write_text(json.dumps(report, indent=1))
    outputs = {
        "mesh": mesh_ply,
        "obj": obj,
        "mtl": out_dir / "mesh.mtl",
        "checker": checker_png,
        "preview": out_dir / "preview.png",
        "report": uv_json,
    }
    return StageResult(outputs, {k: report[k] for k in ("charts", "utilisation", "area_distortion_median")})


STAGE = Stage(
    name="uv",
    version=4,
    config=Config,
    main=main,
    needs=("cleanup.mesh", "sfm.cameras"),
    outputs=("mesh", "obj", "mtl", "checker", "preview", "report"),
    shared=("mitsuba",),
    exports=("mesh", "obj", "mtl", "checker"),
)
