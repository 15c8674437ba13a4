"""The passes fit_geometry alternates on a scene folder: the shape with the material
frozen, and the material with the shape frozen (no Mitsuba integrator
differentiates geometry through a medium, so the two never share a render)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import trimesh

from pipeline.camera.model import Intrinsics, Pose, ground_hits
from pipeline.fit import engine
from pipeline.fit.outputs import write_texture_files
from pipeline.fit.views import CapturePhotos, Window, Windowing, load_views
from pipeline.formats.scene_description import SceneDescription
from pipeline.formats.scene_folder import MESH_PLY, SPECIMEN_XML
from pipeline.render import materials, scene_xml


def silhouette_views(
    views: list[tuple[engine.FitView, Window]], mesh_file: Path, masks: dict[str, Path]
) -> list[engine.FitView]:
    """The same windows, with a scene holding only the specimen (black, under a white
    sky) and the mask's complement as reference: coverage, material-free."""
    import mitsuba as mi

    scene = mi.load_dict(
        {
            "type": "scene",
            "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
            "specimen": {
                "type": "ply",
                "id": "specimen",
                "filename": str(mesh_file),
                "bsdf": {"type": "diffuse", "id": "specimen_bsdf", "reflectance": {"type": "rgb", "value": 0.0}},
            },
        }
    )
    result = []
    for view, window in views:
        reference = np.repeat(1.0 - _mask_cover(window, masks[view.name])[..., None], 3, axis=2).astype(np.float32)
        result.append(engine.FitView(view.name, scene, view.sensor, reference, window.inside()))
    return result


BACKDROP_SPP = 64
"""Samples per pixel of the backdrop the photometric pass compares outside the masks."""


def backdrop_views(
    views: list[tuple[engine.FitView, Window]],
    masks: dict[str, Path],
    cameras: dict[str, tuple[Intrinsics, Pose]],
    description: SceneDescription,
    spp: int = BACKDROP_SPP,
) -> list[engine.FitView]:
    """The same windows, every pixel weighted, each reference the photo inside its
    specimen mask and on the scene's set (its table disk, the board's print), and
    elsewhere the scene as it renders there without the specimen (its environment,
    softbox), blended by the mask's cover of each pixel.

    Beyond the set the photo shows what the scene does not hold (a black cloth, the
    room): where an estimated environment is seen instead, an outline compared with
    the photo there moves to make the specimen look like that cloth (an estimated map
    far brighter than the cloth behind the specimen gave a pass error four times the
    backdrop's, and a worse mesh). Against the scene's own backdrop an outline pixel there
    costs what its mask says. The set keeps its photo: the scene holds it, with the
    specimen's shadow on it."""
    import mitsuba as mi

    backdrops: dict[int, Any] = {}
    result = []
    for view, window in views:
        if id(view.scene) not in backdrops:
            parts = {s.id(): s for s in view.scene.shapes() if s.id() != materials.SPECIMEN}
            if view.scene.environment() is not None:
                parts["environment"] = view.scene.environment()
            backdrops[id(view.scene)] = mi.load_dict({"type": "scene", "integrator": {"type": "path"}, **parts})
        backdrop = np.asarray(mi.render(backdrops[id(view.scene)], sensor=view.sensor, spp=spp), np.float32)[..., :3]
        if view.gain is not None:
            backdrop = backdrop * np.asarray(view.gain, np.float32)
        intrinsics, pose = cameras[view.name]
        photo = np.maximum(
            _mask_cover(window, masks[view.name]), _on_set(window.intrinsics(intrinsics), pose, description)
        )
        reference = photo[..., None] * view.reference + (1 - photo[..., None]) * backdrop
        result.append(replace(view, reference=np.ascontiguousarray(reference, np.float32), weight=window.inside()))
    return result


def _mask_cover(window: Window, mask_file: Path) -> np.ndarray:
    """(h, w) float: the share of each window pixel the photo's mask covers."""
    return window.cut((cv2.imread(str(mask_file), cv2.IMREAD_GRAYSCALE) > 127).astype(np.float32))


def _on_set(camera: Intrinsics, pose: Pose, description: SceneDescription) -> np.ndarray:
    """(h, w) float: 1 where a pixel centre's ray meets the scene's table disk or the
    board's print (scene.json's ``ground`` and ``board_print``), else 0."""
    hits, distance = ground_hits(camera, pose)
    reached, on = distance > 0, np.zeros(distance.shape, bool)
    if description.ground:
        on |= reached & (np.linalg.norm(hits[..., :2], axis=-1) < description.ground.radius)
    if description.board_print:
        on |= reached & np.all(np.abs(hits[..., :2]) < np.asarray(description.board_print), axis=-1)
    return on.astype(np.float32)


def shape_pass(
    geometry: Path,
    description: SceneDescription,
    loss: str,
    photos: CapturePhotos,
    held: set[str],
    max_size: int,
    settings: engine.ShapeSettings,
    min_improvement: float,
) -> tuple[engine.ShapeResult, bool]:
    """Vertices of the scene folder's mesh.ply refined with the scene's material
    frozen, compared by ``loss`` (photometric or silhouette) in windows of at most
    ``max_size`` px; the mesh written back when the held-out error drops by
    ``min_improvement`` (relative). Returns the fit and whether its mesh was kept."""
    import mitsuba as mi

    windowed = load_views(geometry, description, photos, Windowing(max_size, 0, settings.spp, sample_border=True))
    if loss == "silhouette":
        views = silhouette_views(windowed, geometry / MESH_PLY, photos.masks)
        integrator = {"type": "direct_projective", "sppi": 0}
    else:
        # The silhouette and its surroundings carry the shape: every window pixel counts.
        views = backdrop_views(windowed, photos.masks, photos.cameras, description)
        kind, depth = description.integrator.differentiable, description.integrator.max_depth
        integrator = (
            {"type": "prb_projective", "max_depth": depth, "sppi": 0}
            if kind == "prb"
            else {"type": kind, "max_depth": depth}
        )
    settings = replace(settings, symbolic_loops=integrator["type"] != "prbvolpath")
    result = engine.fit_shape(
        "specimen",
        [v for v in views if v.name not in held],
        [v for v in views if v.name in held],
        settings,
        mi.load_dict(integrator),
    )
    if not improved(result, min_improvement):
        return result, False
    next(s for s in views[0].scene.shapes() if s.id() == "specimen").write_ply(str(geometry / MESH_PLY))
    return result, True


def improved(result, min_improvement: float) -> bool:
    """Whether a pass's best held-out error is ``min_improvement`` (relative) below its start's."""
    return result.validation_error <= (1 - min_improvement) * result.start_validation_error


def material_pass(
    geometry: Path,
    description: SceneDescription,
    photos: CapturePhotos,
    held: set[str],
    parameters: list[engine.FitParameter],
    windowing: Windowing,
    settings: engine.FitSettings,
    min_improvement: float,
) -> tuple[engine.FitResult, bool]:
    """The material ``parameters`` fitted again on the scene folder's mesh, the
    geometry frozen; written back into specimen.xml (and the texture's files) when the
    held-out error drops by ``min_improvement`` (relative). Returns the fit and
    whether it was kept."""
    views = [v for v, _ in load_views(geometry, description, photos, windowing)]
    result = engine.fit(
        parameters, [v for v in views if v.name not in held], [v for v in views if v.name in held], settings
    )
    if not improved(result, min_improvement):
        return result, False
    slot = materials.TEXTURE_SLOTS[description.model]
    constants = {p.name: result.values[p.name] for p in parameters if p.key != slot.key}
    specimen = geometry / SPECIMEN_XML
    scene_xml.set_values(specimen, {materials.PARAMETERS[n].key: v for n, v in constants.items()}, specimen)
    if slot.parameter in result.textures:
        write_texture_files(geometry, slot, result.textures[slot.parameter])
    return result, True


def sphere_in_box(bounds: np.ndarray, subdivisions: int) -> trimesh.Trimesh:
    """An icosphere stretched to fill the axis-aligned box ``bounds`` (2, 3)."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    sphere.apply_scale((bounds[1] - bounds[0]) / 2)
    sphere.apply_translation(bounds.mean(axis=0))
    return sphere


def specimen_error(
    geometry: Path, description: SceneDescription, photos: CapturePhotos, held: set[str], windowing: Windowing
) -> float:
    """The held-out error of the scene folder as it stands, as fit_material and
    fit_texture measure it: the held-out photos' eroded specimen masks in their
    windows, their matched gains, each view's own integrator."""
    windowed = load_views(geometry, description, photos, windowing, names=held)
    return engine.heldout_error([v for v, _ in windowed], windowing.spp, None)


def pass_summary(result: engine.ShapeResult | engine.FitResult) -> dict:
    """A pass's figures for params.json: steps, best step, held-out error before and after."""
    return {
        "iterations": len(result.log),
        "best_iteration": result.best_iteration,
        "averaged": result.averaged,
        "validation_start": result.start_validation_error,
        "validation": result.validation_error,
        "skipped_gradients": result.skipped_gradients,
    }
