"""Stage scene: a Mitsuba 3 scene of the specimen as photographed, ready to render and fit.

The scene holds one perspective sensor per registered photo (its pinhole
intrinsics, principal point included, and pose from sfm), the UV-mapped mesh
from uv with the chosen material model (pipeline.render.materials: only what that
model needs), the light rig from capture.toml's ``[light]`` (or, when fit_material
estimates the light, a uniform start at the level measured in the photos, on the
board's print when they show it), and, when the world
frame is the board's, the printed board under the specimen, and the table
around it (they light the specimen from below and show through a translucent
one).

All in one folder, scene/ (exported to CAPTURE/output/stages/scene/):

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
scene.json          model, model_choice (the models fit_material chooses between),
                    integrator (the render one the files name, its depth,
                    and the differentiable one the fit uses; integrators: one per
                    model of model_choice), fitted parameters
                    (Mitsuba key, value, bounds, units) and per photo its view
                    file and sensor id
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

import numpy as np
import trimesh

from pipeline import logger
from pipeline.core.config import Range, input_file_path
from pipeline.core.errors import PipelineError
from pipeline.core.sections import LightSection
from pipeline.core.stage import Stage, StageInputs, StageResult
from pipeline.formats.cameras import read_frame, read_views
from pipeline.formats.masks import read_masks
from pipeline.formats.pinhole import linear_photos
from pipeline.formats.scene_description import (
    Ground,
    Integrator,
    LightStart,
    MaterialParameter,
    SceneDescription,
    ViewFiles,
)
from pipeline.formats.scene_folder import DESCRIPTION_JSON, MESH_PLY, SCENE_XML, SPECIMEN_XML
from pipeline.render import light as estimated_light
from pipeline.render import materials, mitsuba_variant
from pipeline.render.capture_scene import (
    board_half_extent,
    board_region,
    measure_ratio,
    render_preview,
    specimen_region,
    table_region,
    write_board_texture,
    write_scene_file,
    write_specimen_file,
)
from pipeline.render.samples import check_samples


@dataclass(frozen=True)
class Config:
    """The Mitsuba scene."""

    model: Literal["auto", "opaque", "principled", "volumetric"] = "auto"
    """Material model (pipeline.render.materials); auto takes capture.material. When that is
    auto too, the scene starts principled and fit_material chooses opaque, principled or
    volumetric by held-out error (scene.json's model_choice; fit_material.model_margin)."""
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


def model_choice(conf: Config, capture_material: str) -> list[materials.MaterialModel]:
    """The models fit_material chooses between, simplest first: materials.MODEL_LADDER
    when neither the stage nor the capture (``capture.material``) names one."""
    named = conf.model if conf.model != "auto" else capture_material
    return list(materials.MODEL_LADDER) if named == "auto" else [named]


def _environment_file(light: LightSection, capture_dir: Path, out_dir: Path) -> str | None:
    """The environment map copied into the scene folder, its name there; None for none."""
    if not light.environment_map:
        return None
    source = input_file_path(capture_dir, light.environment_map)  # checked by the config: exists, may be read
    estimated_light.check_environment_map(source, f"light.environment_map = {light.environment_map!r}")
    environment = "environment" + source.suffix
    shutil.copy2(source, out_dir / environment)
    return environment


def _load_all(paths: list[Path]) -> None:
    """Prove that Mitsuba loads every file written."""
    import mitsuba as mi

    for path in paths:
        try:
            mi.load_file(str(path))
        except RuntimeError as error:
            raise PipelineError(f"Mitsuba cannot load the scene it was given, {path}: {error}") from error


def _write_scene_files(
    out_dir: Path,
    views: dict,
    light: LightSection,
    environment: str | None,
    integrator: Integrator,
    spp: int,
    near_clip: float,
) -> tuple[Path, dict[str, Path]]:
    """scene.xml with every sensor, and one view-NAME.xml per photo with its own light."""
    sensors = [(Path(name).stem, intrinsics, pose) for name, (intrinsics, pose) in sorted(views.items())]
    riding = (
        "the light rides with the camera: this file has the first photo's light, view-*.xml light each photo correctly"
    )
    about = "every registered photo; " + (riding if light.frame == "camera" else "the light is fixed in the world")
    scene = write_scene_file(
        out_dir / SCENE_XML, SPECIMEN_XML, sensors, light, environment, integrator, spp, near_clip, about
    )
    # Beside specimen.xml: Mitsuba resolves paths in an included file relative to
    # the including one.
    view_files = {}
    for name, (intrinsics, pose) in sorted(views.items()):
        stem = Path(name).stem
        view_files[name] = write_scene_file(
            out_dir / f"view-{stem}.xml",
            SPECIMEN_XML,
            [(stem, intrinsics, pose)],
            light,
            environment,
            integrator,
            spp,
            near_clip,
            f"photo {name}",
        )
    return scene, view_files


def _light_level(view_files, views, linear, masks, board, near_clip) -> tuple[tuple[float, ...], str]:
    """The uniform radiance at which the scene renders like the photos, measured on the
    board's print (known reflectance: absolute) when the photos show it, else on the
    specimen with its starting material (relative)."""
    unit = {}

    def load(name: str):
        if name not in unit:
            unit[name] = estimated_light.render_unit_light(view_files[name])
        return unit[name]

    if board is not None:
        level = measure_ratio(load, views, linear, masks, board_region(board), near_clip)
        if level is not None:
            return level, "board"
    level = measure_ratio(load, views, linear, masks, specimen_region, near_clip)
    if level is None:
        raise PipelineError("the masks show too little of the specimen to measure the light's level: check the masks")
    return (float(np.mean(level)),) * 3, estimated_light.SPECIMEN_LEVEL


def _relative(view_files: dict[str, Path], out_dir: Path) -> dict[str, str]:
    return {name: str(path.relative_to(out_dir)) for name, path in view_files.items()}


def _poses(views: dict) -> dict:
    return {name: pose for name, (_, pose) in views.items()}


def _description(
    model: str,
    integrators: dict[str, Integrator],
    light: LightSection,
    near_clip: float,
    board,
    ground: Ground | None,
    values: dict,
    view_files: dict[str, str],
    light_start: LightStart,
) -> SceneDescription:
    """scene.json's content (pipeline.formats.scene_description), what the fit stages read."""
    parameters = {
        name: MaterialParameter(
            key=materials.PARAMETERS[name].key,
            value=list(value),
            lower=materials.PARAMETERS[name].lower,
            upper=materials.PARAMETERS[name].upper,
            units=materials.PARAMETERS[name].units,
        )
        for name, value in values.items()
    }
    return SceneDescription(
        model=model,
        integrator=integrators[model],
        light_frame=light.frame,
        near_clip=near_clip,
        # the print's half width and height (metres, at the world's origin): its
        # reflectance is known, so fit_material counts its pixels for the light's level
        board_print=None if board is None else board_half_extent(board).tolist(),
        ground=ground,
        parameters=parameters,
        views={name: ViewFiles(xml=xml, sensor=Path(name).stem) for name, xml in view_files.items()},
        model_choice=list(integrators),
        integrators=integrators,
        light=light_start,
    )


def main(conf: Config, inputs: StageInputs, out_dir: Path) -> StageResult:
    # 1. Model, integrator and the world frame the light is placed in.
    light: LightSection = inputs.shared["light"]
    cameras_json = inputs.upstream["sfm"]["cameras"]
    frame, views = read_frame(cameras_json), read_views(cameras_json)
    largest = max((intrinsics for intrinsics, _ in views.values()), key=lambda k: k.width * k.height)
    for setting, spp in (("scene.spp", conf.spp), ("scene.preview_spp", conf.preview_spp)):
        # the view files render the photos' size: a scene Mitsuba cannot render is refused
        check_samples(largest.width * largest.height, spp, setting, f"photos of {largest.width}x{largest.height} px")
    choice = model_choice(conf, inputs.shared["capture.material"])
    model = materials.OPEN_SCENE_MODEL if len(choice) > 1 else choice[0]
    integrators = {m: materials.model_integrator(m, conf.max_depth) for m in choice}
    integrator = integrators[model]
    if not frame.get("metric") and not light.estimated and light.area_light:
        logger.warning(
            "the world frame is not metric (%s): the light positions in [light] are used as they are",
            frame.get("source", "unknown"),
        )

    # 2. The specimen: mesh, material, and the board and ground it stands on.
    out_dir = out_dir / "scene"  # one self-contained folder, exported as it is
    out_dir.mkdir()
    shutil.copy2(inputs.upstream["uv"]["mesh"], out_dir / MESH_PLY)
    mesh = trimesh.load(out_dir / MESH_PLY, force="mesh", process=False)
    board = inputs.shared["board"] if conf.board_plane and frame.get("source") == "board" else None
    if board is not None:
        write_board_texture(board, out_dir)
    environment = _environment_file(light, inputs.capture_dir, out_dir)
    values = materials.initial_values(model)
    ground_radius = None
    if conf.ground and frame.get("ground_plane") is not None:
        ground_radius = conf.ground_radius * float(np.max(np.linalg.norm(mesh.vertices[:, :2], axis=1)))
    # The ground's albedo is measured against a white ground in the scene itself.
    white_ground = (ground_radius, (1.0, 1.0, 1.0)) if ground_radius else None
    write_specimen_file(out_dir / SPECIMEN_XML, model, values, board, white_ground)

    # 3. The scene files, near clip well inside the closest camera's distance to the specimen.
    centre = mesh.bounding_box.centroid
    near_clip = 0.01 * min(np.linalg.norm(pose.center - centre) for _, pose in views.values())
    scene, view_files = _write_scene_files(out_dir, views, light, environment, integrator, conf.spp, near_clip)
    mitsuba_variant.activate(inputs.shared["mitsuba"].variant)
    _load_all([scene, *view_files.values()])

    # 4. An estimated light's start: uniform, at the level the photos show.
    linear = linear_photos(inputs.upstream["undistort"]["pinhole"])
    masks = read_masks(inputs.upstream["masks"]["masks_json"])
    light_start = LightStart(model=light.model if light.estimated else "given")
    if light.estimated:
        level, source = _light_level(view_files, views, linear, masks, board, near_clip)
        start = estimated_light.start("constant", light.frame, np.array(level), 1)
        estimated_light.write(start, out_dir, _relative(view_files, out_dir), _poses(views))
        light_start = LightStart(model=light.model, level=list(level), level_from=source)
        logger.info("light: starts uniform at %s, measured on the %s", np.round(level, 3).tolist(), source)

    # 5. The ground's albedo, measured in the photos under that light.
    import mitsuba as mi

    ground_albedo = None
    if ground_radius:
        region = table_region(ground_radius, None if board is None else board_half_extent(board))
        ratio = measure_ratio(lambda n: mi.load_file(str(view_files[n])), views, linear, masks, region, near_clip)
        ground_albedo = None if ratio is None else tuple(float(v) for v in np.clip(ratio, 0.01, 1.0))
        if ground_albedo is None:
            logger.warning("too little of the table is seen to measure its albedo: no ground in the scene")
        measured = (ground_radius, ground_albedo) if ground_albedo else None
        write_specimen_file(out_dir / SPECIMEN_XML, model, values, board, measured)

    # 6. A preview, and the description the fit stages read.
    first = sorted(views)[0]
    render_preview(view_files[first], *views[first], near_clip, mesh, conf.preview_spp, out_dir / "preview.png")
    ground = Ground(radius=ground_radius, albedo=list(ground_albedo)) if ground_albedo else None
    files = _relative(view_files, out_dir)
    description = _description(model, integrators, light, near_clip, board, ground, values, files, light_start)
    scene_json = description.write(out_dir / DESCRIPTION_JSON)
    outputs = {"scene_dir": out_dir, "scene": scene, "description": scene_json, "preview": out_dir / "preview.png"}
    return StageResult(
        outputs,
        {"model": model, "views": len(views), "integrator": f"{integrator.differentiable}/{integrator.max_depth}"},
    )


STAGE = Stage(
    name="scene",
    version=8,
    config=Config,
    main=main,
    needs=("uv.mesh", "sfm.cameras", "undistort.pinhole", "masks.masks_json"),
    outputs=("scene_dir", "scene", "description", "preview"),
    shared=("capture.material", "light", "board", "mitsuba"),
    exports=("scene_dir",),
    result=("scene", "scene_dir"),
)
