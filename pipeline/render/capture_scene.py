"""The Mitsuba scene files of a capture: the light rig (in the world or riding
with the camera), the specimen file (mesh, material, board, ground disk), one
scene file per sensor set, the board's printed texture, the ground's albedo
measured in the photos, and a preview render."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import trimesh

from pipeline.camera.board import board_image
from pipeline.camera.model import Intrinsics, Pose, ground_hits, resize_exact, scaled
from pipeline.core.sections import BoardSection, LightSection
from pipeline.formats.scene_description import Integrator
from pipeline.imaging.photo_io import read_photo, to_uint8
from pipeline.render import materials, scene_xml

PAPER, TONER = 0.80, 0.04
"""Reflectance of the board's paper and of laser toner."""

GROUND_BSDF = "ground_bsdf"
"""Id of the table disk's BSDF (its albedo changes with an estimated light's level)."""


SPECIMEN_COMMENT = "the specimen and what it stands on; included by scene.xml and view-*.xml"


def environment_to_world(frame: str, pose: Pose) -> np.ndarray:
    """The 4x4 ``to_world`` of an equirectangular environment map in the light's
    ``frame`` (world, or camera: riding with the camera of ``pose``). The map's up
    is its +y: the world's +z, or the camera's -y."""
    to_world = np.eye(3) if frame == "world" else pose.R.T
    map_up = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]) if frame == "world" else np.diag([1.0, -1, -1])
    matrix = np.eye(4)
    matrix[:3, :3] = to_world @ map_up
    return matrix


def lights(parent, light: LightSection, pose: Pose, environment_file: str | None) -> None:
    """Environment and softbox of the rig seen from ``pose``: in the world, or riding
    with the camera (a turntable's light)."""
    if environment_file:
        emitter = scene_xml.plugin(
            parent, "emitter", {"type": "envmap", "id": "environment", "filename": environment_file}
        )
        scene_xml.transform_matrix(emitter, environment_to_world(light.frame, pose))
    else:
        scene_xml.plugin(
            parent, "emitter", {"type": "constant", "id": "environment", "radiance": tuple(light.environment_radiance)}
        )
    if not light.area_light:
        return
    position, target = np.array(light.area_position), np.array(light.area_target)
    up = np.array([0.0, 0.0, 1.0])
    if light.frame == "camera":
        position, target, up = pose.R.T @ (position - pose.t), pose.R.T @ (target - pose.t), -pose.R[1]
    scene_xml.area_light(parent, "softbox", position, target, up, light.area_size, light.area_radiance)


def write_specimen_file(
    path: Path,
    model: str,
    values: dict,
    board: BoardSection | None,
    ground: tuple[float, tuple[float, float, float]] | None,
) -> None:
    """``ground`` = (radius, albedo) of the table disk, or None."""
    root = scene_xml.new_scene()
    shape = scene_xml.plugin(root, "shape", {"type": "ply", "id": materials.SPECIMEN, "filename": "mesh.ply"})
    _add_material(shape, model, values)
    if board is not None:
        half = (board.squares_x * board.square_mm / 2000, board.squares_y * board.square_mm / 2000)
        plane = scene_xml.plugin(root, "shape", {"type": "rectangle", "id": "board"})
        matrix = np.diag([half[0], half[1], 1.0, 1.0])
        scene_xml.transform_matrix(plane, matrix)
        paper = scene_xml.plugin(plane, "bsdf", {"type": "diffuse", "id": "board_paper"})
        scene_xml.plugin(
            paper,
            "texture",
            {"type": "bitmap", "id": "board_print", "filename": "board.png", "raw": True},
            name="reflectance",
        )
    if ground is not None:
        radius, albedo = ground
        disk = scene_xml.plugin(root, "shape", {"type": "disk", "id": "ground"})
        # Just below the board, so that the two never fight over a pixel.
        scene_xml.transform_matrix(disk, _disk_matrix(radius))
        scene_xml.plugin(disk, "bsdf", {"type": "diffuse", "id": GROUND_BSDF, "reflectance": tuple(albedo)})
    scene_xml.write(root, path, SPECIMEN_COMMENT)


def rewrite_specimen_material(path: Path, model: str, values: dict) -> None:
    """The specimen file's BSDF (and interior medium) replaced by ``model``'s, with ``values``."""
    tree = ET.parse(path)
    shape = next(e for e in tree.getroot().iter("shape") if e.get("id") == materials.SPECIMEN)
    for child in [c for c in shape if c.tag in ("bsdf", "medium")]:
        shape.remove(child)
    _add_material(shape, model, values)
    scene_xml.write(tree.getroot(), path, SPECIMEN_COMMENT)


def rewrite_integrator(folder: Path, integrator: Integrator) -> None:
    """Every scene file in ``folder`` made to render with ``integrator`` (its render
    type and max_depth), comments kept."""
    for path in sorted(folder.glob("*.xml")):
        root = ET.parse(path, ET.XMLParser(target=ET.TreeBuilder(insert_comments=True))).getroot()
        old = root.find("integrator")
        if old is None:
            continue
        properties = {"type": integrator.type, "id": "integrator", "max_depth": integrator.max_depth}
        new = scene_xml.plugin(root, "integrator", properties)
        root.remove(new)
        root.insert(list(root).index(old), new)
        root.remove(old)
        scene_xml.write(root, path)


def _add_material(shape, model: str, values: dict) -> None:
    bsdf, medium = materials.bsdf_and_medium(model, values)
    scene_xml.plugin(shape, "bsdf", bsdf)
    if medium is not None:
        scene_xml.plugin(shape, "medium", medium, name="interior")


def _disk_matrix(radius: float) -> np.ndarray:
    matrix = np.diag([radius, radius, 1.0, 1.0])
    matrix[2, 3] = -1e-3 * radius
    return matrix


def write_scene_file(
    path: Path,
    include: str,
    views: list[tuple[str, Intrinsics, Pose]],
    light: LightSection,
    environment: str | None,
    integrator: Integrator,
    spp: int,
    near_clip: float,
    comment: str,
) -> Path:
    root = scene_xml.new_scene()
    properties = {"type": integrator.type, "id": "integrator", "max_depth": integrator.max_depth}
    scene_xml.plugin(root, "integrator", properties)
    for sensor_id, intrinsics, pose in views:
        scene_xml.sensor(root, sensor_id, scene_xml.sensor_properties(intrinsics, pose, spp, near_clip))
    lights(root, light, views[0][2], environment)
    scene_xml.include(root, include)
    return scene_xml.write(root, path, comment)


Region = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]
"""Pixels to compare, from (hits on the ground plane (h, w, 3), ray reaches the plane
(h, w), specimen mask (h, w)): a boolean image."""


def table_region(radius: float, board_half: np.ndarray | None) -> Region:
    """The table: inside the ground disk, off the board (its print's half width and
    height, metres, centred at the origin), away from the specimen."""

    def region(hits, reached, specimen):
        seen = reached & (np.linalg.norm(hits[..., :2], axis=-1) < 0.9 * radius)
        if board_half is not None:
            seen &= np.any(np.abs(hits[..., :2]) > np.asarray(board_half) + 0.01, axis=-1)
        return seen & ~_dilated(specimen)

    return region


def board_region(board: BoardSection) -> Region:
    """The board's print, away from its edges and the specimen."""

    def region(hits, reached, specimen):
        return reached & np.all(np.abs(hits[..., :2]) < board_half_extent(board) - 0.005, axis=-1) & ~_dilated(specimen)

    return region


def specimen_region(hits, reached, specimen) -> np.ndarray:
    """The specimen, eroded off its silhouette."""
    return cv2.erode(specimen.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0


def board_half_extent(board: BoardSection) -> np.ndarray:
    """Half the print's width and height, metres."""
    return np.array([board.squares_x, board.squares_y]) * board.square_mm / 2000


def _dilated(mask: np.ndarray) -> np.ndarray:
    return cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0


def photo_at_most(
    intrinsics: Intrinsics, photo: Path, mask: Path, longest: int
) -> tuple[Intrinsics, np.ndarray, np.ndarray]:
    """The camera, the linear ``photo`` and its specimen ``mask`` (boolean) scaled
    down (never up) to ``longest`` pixels on the longer side."""
    scale = min(1.0, longest / max(intrinsics.width, intrinsics.height))
    small = scaled(intrinsics, scale, exact=True)
    pixels = resize_exact(read_photo(photo).pixels, scale)[: small.height, : small.width]
    specimen = cv2.imread(str(mask), cv2.IMREAD_GRAYSCALE) > 127
    specimen = resize_exact(specimen.astype(np.float32), scale)[: small.height, : small.width] > 0.5
    return small, pixels, specimen


def photo_ratios(
    load_scene: Callable[[str], object],
    intrinsics: Intrinsics,
    pose: Pose,
    photo: Path,
    mask: Path,
    region: Region,
    near_clip: float,
    name: str,
    below: float = np.inf,
) -> np.ndarray | None:
    """(n, 3) photo radiance over rendered radiance (``load_scene(name)`` from the photo's
    camera, at most 160 px) at each of ``region``'s pixels whose photo radiance is below
    ``below`` in every channel; None when the photo shows fewer than 50 of them."""
    import mitsuba as mi

    small, pixels, specimen = photo_at_most(intrinsics, photo, mask, 160)
    hits, distance = ground_hits(small, pose)
    seen = region(hits, distance > 0, specimen)
    if np.count_nonzero(seen) < 50:
        return None
    sensor = scene_xml.load_sensor(scene_xml.sensor_properties(small, pose, 64, near_clip))
    rendered = np.asarray(mi.render(load_scene(name), sensor=sensor, spp=64), dtype=np.float32)
    seen &= np.all(pixels < below, axis=-1)
    if np.count_nonzero(seen) < 50:
        return None
    return pixels[seen] / np.maximum(rendered[seen], 1e-4)


def measure_ratio(
    load_scene: Callable[[str], object],
    views: dict[str, tuple[Intrinsics, Pose]],
    linear: dict[str, Path],
    masks: dict[str, Path],
    region: Region,
    near_clip: float,
) -> tuple[float, float, float] | None:
    """Photo radiance over rendered radiance (photo_ratios), median over ``region``'s
    pixels in up to four photos; None when they show fewer than 50 of them."""
    ratios = []
    for name in sorted(views)[:: max(1, len(views) // 4)][:4]:
        found = photo_ratios(load_scene, *views[name], linear[name], masks[name], region, near_clip, name)
        if found is not None:
            ratios.append(found)
    if not ratios:
        return None
    return tuple(float(v) for v in np.median(np.vstack(ratios), axis=0))


def render_preview(
    view_xml: Path, intrinsics: Intrinsics, pose: Pose, near_clip: float, mesh: trimesh.Trimesh, spp: int, path: Path
) -> None:
    """The view's scene rendered in a window around the specimen (at most 256 px)."""
    import mitsuba as mi

    corners = mesh.bounding_box.vertices @ pose.R.T + pose.t
    pixels = corners[:, :2] / corners[:, 2:] * [intrinsics.fx, intrinsics.fy] + [intrinsics.cx, intrinsics.cy]
    lo = np.clip(np.floor(pixels.min(axis=0)).astype(int) - 4, 0, [intrinsics.width - 1, intrinsics.height - 1])
    hi = np.clip(np.ceil(pixels.max(axis=0)).astype(int) + 4, lo + 1, [intrinsics.width, intrinsics.height])
    window = scene_xml.load_sensor(scene_xml.sensor_properties(intrinsics, pose, spp, near_clip, (*lo, *(hi - lo))))
    image = np.asarray(mi.render(mi.load_file(str(view_xml)), sensor=window, spp=spp))
    scale = min(1.0, 256 / max(image.shape[:2]))
    image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1 else image
    cv2.imwrite(str(path), cv2.cvtColor(to_uint8(image), cv2.COLOR_RGB2BGR))


def write_board_texture(board: BoardSection, out_dir: Path) -> None:
    # Rows flipped: Mitsuba's rectangle puts the bitmap's first row at local -y,
    # and the board's top edge is at +y (pipeline.camera.board.board_to_world).
    reflectance = TONER + (PAPER - TONER) * board_image(board)[::-1].astype(np.float32) / 255.0
    cv2.imwrite(str(out_dir / "board.png"), np.round(reflectance * 255).astype(np.uint8))
