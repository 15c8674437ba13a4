"""Stage scene: a Mitsuba 3 scene of the specimen as photographed, ready to render and fit.

The scene holds one perspective sensor per registered photo (its pinhole
intrinsics, principal point included, and pose from sfm), the UV-mapped mesh
from uv with the chosen material model (pipeline.render.materials: only what that
model needs), the light rig from capture.toml's ``[light]``, and, when the world
frame is the board's, the printed board under the specimen, and the table
around it (they light the specimen from below and show through a translucent
one).

All in one folder, scene/ (exported to CAPTURE/output/scene/):

==================  =============================================================
file                content
==================  =============================================================
scene.xml           every sensor, the lights, the specimen (via specimen.xml)
specimen.xml        the specimen (mesh, BSDF, medium when volumetric) and the
                    board; included by the other files
view-NAME.xml       one file per photo (NAME without extension): its sensor and its
                    lights. A turntable's light rides with the camera, so only
                    these files light every view correctly; scene.xml then
                    carries the first photo's light
mesh.ply            the mesh with UVs (a copy of uv's)
board.png           the board's print, when the board is in the scene
scene.json          model, integrator, fitted parameters (Mitsuba key, value,
                    bounds, units) and per photo its view file and sensor id
preview.png         the first view rendered from its view file, cropped to the
                    specimen
==================  =============================================================

Everything renders as-is: ``mitsuba scene.xml`` (first sensor) or
``mitsuba view-NAME.xml``. Light positions are in metres in the board frame; in
a frame without a board they are taken as they are and the stage warns.

The table under the specimen, when sfm found its plane, is a diffuse disk of
``ground_radius`` times the specimen's horizontal radius; its albedo is measured:
photo radiance over that of a white table rendered in the same scene, median over
the table pixels of up to four photos.

Limitations: Mitsuba's perspective sensor has square pixels, so cameras must
have fx = fy (undistort and sfm ensure it). The table is one uniform, matte
colour and the room is the rig's environment: a patterned table or a room that
reflects in the specimen biases the fitted material. The board's print is
assumed laser toner on white paper (reflectance 0.04 and 0.80).
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np
import trimesh

from pipeline import logger
from pipeline.render import materials
from pipeline.render import mitsuba_variant
from pipeline.render import scene_xml
from pipeline.camera.board import board_image
from pipeline.camera.model import Intrinsics, Pose, resize_exact, scaled
from pipeline.formats.cameras import read_frame, read_views
from pipeline.core.config import Range
from pipeline.core.errors import PipelineError
from pipeline.imaging.photo_io import read_photo, to_uint8
from pipeline.core.sections import BoardSection, CaptureSection, LightSection
from pipeline.core.stage import Stage, StageInputs, StageResult
from pipeline.formats.masks import read_masks
from pipeline.formats.pinhole import linear_photos
from pipeline.formats.scene_folder import DESCRIPTION_JSON, MESH_PLY, SCENE_XML, SPECIMEN_XML, write_json

PAPER, TONER = 0.80, 0.04


@dataclass(frozen=True)
class Config:
    """The Mitsuba scene."""

    model: Literal["auto", "opaque", "principled", "volumetric"] = "auto"
    """Material model (pipeline.render.materials); auto takes capture.material, and principled
    when that is auto too (it covers opaque surfaces, with spec_trans at 0)."""
    max_depth: Annotated[int, Range(0, 1024)] = 0
    """Longest light path; 0 takes the model's (opaque 4, principled 8, volumetric 32)."""
    spp: Annotated[int, Range(1, None)] = 64
    """Samples per pixel written into the sensors (renders with the mitsuba command)."""
    board_plane: bool = True
    """Put the printed board under the specimen when the world frame is the board's."""
    ground: bool = True
    """Put the table under the specimen (a diffuse disk on the ground plane, albedo
    estimated from the photos) when sfm found the table plane: it lights the
    specimen from below and is seen through a translucent one."""
    ground_radius: Annotated[float, Range(1.0, None)] = 4.0
    """Radius of the ground disk, in multiples of the specimen's horizontal radius."""
    preview_spp: Annotated[int, Range(1, None)] = 32
    """Samples per pixel of preview.png."""


def choose_model(conf: Config, capture: CaptureSection) -> materials.MaterialModel:
    if conf.model != "auto":
        return conf.model
    return capture.material if capture.material != "auto" else "principled"


def _lights(parent, light: LightSection, pose: Pose, environment_file: str | None) -> None:
    """Environment and softbox of the rig seen from ``pose``: in the world, or riding
    with the camera (a turntable's light)."""
    to_world = np.eye(3) if light.frame == "world" else pose.R.T
    if environment_file:
        # An equirectangular map's up is its +y: the world's +z, or the camera's -y.
        map_up = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]) if light.frame == "world" else np.diag([1.0, -1, -1])
        emitter = scene_xml.plugin(parent, "emitter", {"type": "envmap", "id": "environment", "filename": environment_file})
        matrix = np.eye(4)
        matrix[:3, :3] = to_world @ map_up
        scene_xml.transform_matrix(emitter, matrix)
    else:
        scene_xml.plugin(parent, "emitter", {"type": "constant", "id": "environment",
                                             "radiance": tuple(light.environment_radiance)})  # fmt: skip
    if not light.area_light:
        return
    position, target = np.array(light.area_position), np.array(light.area_target)
    up = np.array([0.0, 0.0, 1.0])
    if light.frame == "camera":
        position, target, up = pose.R.T @ (position - pose.t), pose.R.T @ (target - pose.t), -pose.R[1]
    scene_xml.area_light(parent, "softbox", position, target, up, light.area_size, light.area_radiance)


def _specimen_file(path: Path, model: str, values: dict, board: BoardSection | None,
                   ground: tuple[float, tuple[float, float, float]] | None) -> None:  # fmt: skip
    """``ground`` = (radius, albedo) of the table disk, or None."""
    root = scene_xml.new_scene()
    shape = scene_xml.plugin(root, "shape", {"type": "ply", "id": materials.SPECIMEN, "filename": "mesh.ply"})
    bsdf, medium = materials.bsdf_and_medium(model, values)
    scene_xml.plugin(shape, "bsdf", bsdf)
    if medium is not None:
        scene_xml.plugin(shape, "medium", medium, name="interior")
    if board is not None:
        half = (board.squares_x * board.square_mm / 2000, board.squares_y * board.square_mm / 2000)
        plane = scene_xml.plugin(root, "shape", {"type": "rectangle", "id": "board"})
        matrix = np.diag([half[0], half[1], 1.0, 1.0])
        scene_xml.transform_matrix(plane, matrix)
        paper = scene_xml.plugin(plane, "bsdf", {"type": "diffuse", "id": "board_paper"})
        scene_xml.plugin(paper, "texture", {"type": "bitmap", "id": "board_print", "filename": "board.png",
                                            "raw": True}, name="reflectance")  # fmt: skip
    if ground is not None:
        radius, albedo = ground
        disk = scene_xml.plugin(root, "shape", {"type": "disk", "id": "ground"})
        # Just below the board, so that the two never fight over a pixel.
        scene_xml.transform_matrix(disk, _disk_matrix(radius))
        scene_xml.plugin(disk, "bsdf", {"type": "diffuse", "id": "ground_bsdf", "reflectance": tuple(albedo)})
    scene_xml.write(root, path, "the specimen and what it stands on; included by scene.xml and view-*.xml")


def _disk_matrix(radius: float) -> np.ndarray:
    matrix = np.diag([radius, radius, 1.0, 1.0])
    matrix[2, 3] = -1e-3 * radius
    return matrix


def _scene_file(path: Path, include: str, views: list[tuple[str, Intrinsics, Pose]], light: LightSection,
                environment: str | None, integrator: tuple[str, int], spp: int, near_clip: float,
                comment: str) -> Path:  # fmt: skip
    root = scene_xml.new_scene()
    scene_xml.plugin(root, "integrator", {"type": integrator[0], "id": "integrator", "max_depth": integrator[1]})
    for sensor_id, intrinsics, pose in views:
        scene_xml.sensor(root, sensor_id, scene_xml.sensor_properties(intrinsics, pose, spp, near_clip))
    _lights(root, light, views[0][2], environment)
    scene_xml.include(root, include)
    return scene_xml.write(root, path, comment)


def _ground_albedo(view_files: dict[str, Path], views: dict[str, tuple[Intrinsics, Pose]], linear: dict[str, Path],
                   masks: dict[str, Path], board: BoardSection | None, radius: float,
                   near_clip: float) -> tuple[float, float, float] | None:  # fmt: skip
    """The table's diffuse albedo: photo radiance over the radiance of a white table
    rendered in the same scene, median over the pixels that see the table (inside
    the disk, off the board, away from the specimen) in up to four photos."""
    import mitsuba as mi

    ratios = []
    for name in sorted(views)[:: max(1, len(views) // 4)][:4]:
        intrinsics, pose = views[name]
        scale = min(1.0, 160 / max(intrinsics.width, intrinsics.height))
        small = scaled(intrinsics, scale, exact=True)
        columns, rows = np.meshgrid(np.arange(small.width), np.arange(small.height))
        rays = np.stack([(columns - small.cx) / small.fx, (rows - small.cy) / small.fy, np.ones(columns.shape)], -1) @ pose.R
        with np.errstate(divide="ignore", invalid="ignore"):
            distance = -pose.center[2] / rays[..., 2]
        hits = pose.center + distance[..., None] * rays
        seen = (distance > 0) & (np.linalg.norm(hits[..., :2], axis=-1) < 0.9 * radius)
        if board is not None:
            half = np.array([board.squares_x, board.squares_y]) * board.square_mm / 2000 + 0.01
            seen &= np.any(np.abs(hits[..., :2]) > half, axis=-1)
        specimen = cv2.imread(str(masks[name]), cv2.IMREAD_GRAYSCALE) > 127
        specimen = cv2.dilate(specimen.astype(np.uint8), np.ones((15, 15), np.uint8))
        seen &= resize_exact(specimen.astype(np.float32), scale)[: small.height, : small.width] == 0
        if np.count_nonzero(seen) < 50:
            continue
        sensor = scene_xml.load_sensor(scene_xml.sensor_properties(small, pose, 64, near_clip))
        white = np.asarray(mi.render(mi.load_file(str(view_files[name])), sensor=sensor, spp=64), dtype=np.float32)
        photo = resize_exact(read_photo(linear[name]).pixels, scale)
        ratios.append(photo[: small.height, : small.width][seen] / np.maximum(white[seen], 1e-4))
    if not ratios:
        return None
    return tuple(float(v) for v in np.clip(np.median(np.vstack(ratios), axis=0), 0.01, 1.0))


def render_preview(view_xml: Path, intrinsics: Intrinsics, pose: Pose, near_clip: float, mesh: trimesh.Trimesh,
                   spp: int, path: Path) -> None:  # fmt: skip
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


def _environment_file(light: LightSection, capture_dir: Path, out_dir: Path) -> str | None:
    """The environment map copied into the scene folder, its name there; None for none."""
    if not light.environment_map:
        return None
    source = capture_dir / light.environment_map
    if not source.is_file():
        raise PipelineError(f"light.environment_map = '{light.environment_map}' is not a file in "
                            f"{capture_dir}: fix the path or set it to \"\"")
    environment = "environment" + source.suffix
    shutil.copy2(source, out_dir / environment)
    return environment


def _write_board_texture(board: BoardSection, out_dir: Path) -> None:
    # Rows flipped: Mitsuba's rectangle puts the bitmap's first row at local -y,
    # and the board's top edge is at +y (pipeline.camera.board.board_to_world).
    reflectance = TONER + (PAPER - TONER) * board_image(board)[::-1].astype(np.float32) / 255.0
    cv2.imwrite(str(out_dir / "board.png"), np.round(reflectance * 255).astype(np.uint8))


def _load_all(paths: list[Path]) -> None:
    """Prove that Mitsuba loads every file written."""
    import mitsuba as mi

    for path in paths:
        try:
            mi.load_file(str(path))
        except RuntimeError as error:
            raise PipelineError(f"Mitsuba cannot load the scene it was given, {path}: {error}") from error


def main(conf: Config, inputs: StageInputs, out_dir: Path) -> StageResult:
    # 1. Model, integrator and the world frame the light is placed in.
    capture: CaptureSection = inputs.shared["capture"]
    light: LightSection = inputs.shared["light"]
    cameras_json = inputs.upstream["sfm"]["cameras"]
    frame = read_frame(cameras_json)
    views = read_views(cameras_json)
    model = choose_model(conf, capture)
    integrator = materials.INTEGRATORS[model]
    if conf.max_depth:
        integrator = (integrator[0], conf.max_depth)
    if not frame.get("metric"):
        logger.warning("the world frame is not metric (%s): the light positions in [light] are used as they are",
                       frame.get("source", "unknown"))

    # 2. The specimen: mesh, material, and the board and ground it stands on.
    out_dir = out_dir / "scene"  # one self-contained folder, exported as it is
    out_dir.mkdir()
    mesh_ply = out_dir / MESH_PLY
    shutil.copy2(inputs.upstream["uv"]["mesh"], mesh_ply)
    mesh = trimesh.load(mesh_ply, force="mesh", process=False)
    board = inputs.shared["board"] if conf.board_plane and frame.get("source") == "board" else None
    if board is not None:
        _write_board_texture(board, out_dir)
    environment = _environment_file(light, inputs.capture_dir, out_dir)
    values = materials.initial_values(model)
    ground_radius = None
    if conf.ground and frame.get("ground_plane") is not None:
        ground_radius = conf.ground_radius * float(np.max(np.linalg.norm(mesh.vertices[:, :2], axis=1)))
    # The ground's albedo is measured against a white ground in the scene itself.
    _specimen_file(out_dir / SPECIMEN_XML, model, values, board,
                   (ground_radius, (1.0, 1.0, 1.0)) if ground_radius else None)

    # 3. scene.xml with every sensor, and one view-NAME.xml per photo with its light.
    # Near clip well inside the closest camera's distance to the specimen.
    centre = mesh.bounding_box.centroid
    near_clip = 0.01 * min(np.linalg.norm(pose.center - centre) for _, pose in views.values())
    sensors = [(Path(name).stem, intrinsics, pose) for name, (intrinsics, pose) in sorted(views.items())]
    riding = light.frame == "camera"
    scene = _scene_file(out_dir / SCENE_XML, SPECIMEN_XML, sensors, light, environment, integrator, conf.spp,
                        near_clip, "every registered photo; " + ("the light rides with the camera: this file has the "
                        "first photo's light, view-*.xml light each photo correctly" if riding else
                        "the light is fixed in the world"))
    # Beside specimen.xml: Mitsuba resolves paths in an included file relative to
    # the including one.
    view_files = {}
    for name, (intrinsics, pose) in sorted(views.items()):
        stem = Path(name).stem
        view_files[name] = _scene_file(out_dir / f"view-{stem}.xml", SPECIMEN_XML, [(stem, intrinsics, pose)], light,
                                       environment, integrator, conf.spp, near_clip, f"photo {name}")
    mitsuba_variant.activate(inputs.shared["mitsuba"].variant)
    _load_all([scene, *view_files.values()])

    # 4. The ground's albedo, measured in the photos.
    ground_albedo = None
    if ground_radius:
        linear = linear_photos(inputs.upstream["undistort"]["pinhole"])
        masks = read_masks(inputs.upstream["masks"]["masks_json"])
        ground_albedo = _ground_albedo(view_files, views, linear, masks, board, ground_radius, near_clip)
        if ground_albedo is None:
            logger.warning("too little of the table is seen to measure its albedo: no ground in the scene")
        _specimen_file(out_dir / SPECIMEN_XML, model, values, board,
                       (ground_radius, ground_albedo) if ground_albedo else None)

    # 5. A preview, and the description the fit stages read (pipeline.formats.scene_folder).
    first = sorted(views)[0]
    render_preview(view_files[first], *views[first], near_clip, mesh, conf.preview_spp, out_dir / "preview.png")
    scene_json = write_json(out_dir / DESCRIPTION_JSON, {
        "model": model,
        "integrator": {"type": integrator[0], "max_depth": integrator[1]},
        "light_frame": light.frame,
        "near_clip": near_clip,
        "board_in_scene": board is not None,
        "ground": {"radius": ground_radius, "albedo": ground_albedo} if ground_albedo else None,
        "parameters": {name: {"key": materials.PARAMETERS[name].key, "value": list(value),
                              "lower": materials.PARAMETERS[name].lower, "upper": materials.PARAMETERS[name].upper,
                              "units": materials.PARAMETERS[name].units} for name, value in values.items()},
        "views": {name: {"xml": str(path.relative_to(out_dir)), "sensor": Path(name).stem}
                  for name, path in view_files.items()},
    })
    outputs = {"scene_dir": out_dir, "scene": scene, "description": scene_json, "preview": out_dir / "preview.png"}
    return StageResult(outputs, {"model": model, "views": len(views), "integrator": f"{integrator[0]}/{integrator[1]}"})


STAGE = Stage(
    name="scene",
    version=1,
    config=Config,
    main=main,
    needs=("uv.mesh", "sfm.cameras", "undistort.pinhole", "masks.masks_json"),
    outputs=("scene_dir", "scene", "description", "preview"),
    shared=("capture", "light", "board", "mitsuba"),
    exports=("scene_dir",),
)
